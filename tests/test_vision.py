"""Colour-marker extraction (flightstack.vision.markers) on frames of the simulated camera
(flightstack.sim_backend.scene.render).

References that do not share code with the module under test: the pinhole/Brown–Conrady formula written
out here, the disc area π r² (f/z)², flightstack.paper.projection for the target's feature points, and the
coverage map recovered from the image by linear unmixing against the known paint and floor colours.
"""

from __future__ import annotations

import dataclasses
import math
import re

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from flightstack.paper.geometry import Pose
from flightstack.paper.projection import CameraModel, points_in_camera, project
from flightstack.sim_backend.scene.render import RenderOptions, render_markers
from flightstack.vision.camera_file import CameraCalibration, MarkerColour, load_calibration
from flightstack.vision.markers import MarkerDetection, extract_markers, features_from_detection
from tests.conftest import MISSIONS

CAL_TELLO = load_calibration(MISSIONS / "cameras" / "tello_down_sim.yaml")
# a 960x720 forward camera: fx ≈ 920 px (about 55° horizontal field of view), mild barrel distortion
CAL_FWD = CameraCalibration(
    width=960,
    height=720,
    camera_matrix=np.array([[921.5, 0.0, 480.7], [0.0, 918.2, 359.4], [0.0, 0.0, 1.0]]),
    dist_coeffs=np.array([-0.05, 0.012, 0.0003, -0.0002, 0.0]),
    markers=CAL_TELLO.markers,
    device="forward-960-test",
)
CALS = {"tello_down_320": CAL_TELLO, "forward_960": CAL_FWD}
# the target's four feature points p0^j (metres, target frame Σ0): a 0.2 m square, one marker per corner
P0 = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]])
RADIUS = 0.03
BG = np.array([90.0, 90.0, 90.0])
FACING = np.tile([0.0, 0.0, -1.0], (4, 1))  # fronto-parallel discs
_M = "'(red|green|blue|yellow)'"
REASON = re.compile(
    rf"^(marker {_M}(: \d+ blobs| touches the image border)|marker sizes: {_M} vs {_M}"
    rf"|marker spacing: {_M} and {_M} overlap)$"
)


def random_target(rng: np.random.Generator, cal: CameraCalibration, max_tilt_deg: float = 8.0):
    """Marker centres and normals (4, 3) in Σc for a random target pose seen by the camera.

    The target pose g_i0 = (p, yaw) in the camera-aligned drone frame Σi (rotation about the optical axis
    only, as in the paper) at depth 0.6–2.5 m, any yaw; the physical camera is tilted against Σi by up
    to max_tilt_deg about a random axis in the image plane (the drone's roll/pitch).
    """
    z = rng.uniform(0.6, 2.5)
    x = rng.uniform(-0.5, 0.5) * z * cal.width / cal.fx
    y = rng.uniform(-0.5, 0.5) * z * cal.height / cal.fy
    axis_angle = rng.uniform(0.0, 2.0 * math.pi)
    tilt = math.radians(rng.uniform(0.0, max_tilt_deg))
    R_ic = Rotation.from_rotvec(
        tilt * np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0])
    ).as_matrix()
    cam = CameraModel(R_ic=R_ic)
    g_i0 = Pose.make([x, y, z], rng.uniform(-math.pi, math.pi))
    centres = points_in_camera(g_i0, P0, cam)
    normals = np.tile(R_ic.T @ np.array([0.0, 0.0, 1.0]), (4, 1))  # the target plane's z axis in Σc
    return centres, normals


def render_visible(rng, cal, opts, margin_px: float = 4.0):
    """Render random poses until all four discs are in view with a margin to the border."""
    for _ in range(1000):
        centres, normals = random_target(rng, cal)
        img, true_px, in_view = render_markers(cal, centres, normals, opts, rng)
        r_px = 1.15 * max(cal.fx, cal.fy) * RADIUS / centres[:, 2].min() + margin_px
        lo, hi = true_px.min(axis=0), true_px.max(axis=0)
        if (
            in_view.all()
            and lo.min() > r_px
            and hi[0] < cal.width - 1 - r_px
            and hi[1] < cal.height - 1 - r_px
        ):
            return img, true_px, centres
    raise AssertionError("no visible pose found")


def coverage(img: np.ndarray, rgb, bg=BG) -> np.ndarray:
    """Per-pixel covered fraction α of a disc of colour rgb over the floor colour bg (linear unmixing)."""
    d = np.asarray(rgb, float) - bg
    return ((img.astype(float) - bg) @ d) / (d @ d)


# ------------------------------------------------------------------------------------------------------
# centroid accuracy on rendered frames


@pytest.mark.parametrize("cal_name", list(CALS))
@pytest.mark.parametrize(
    ("noisy", "spec_mean_limit"), [(False, 0.5), (True, 1.0)], ids=["clean", "noise5_blur3"]
)
def test_centroid_accuracy_and_features(cal_name, noisy, spec_mean_limit):
    cal = CALS[cal_name]
    rng = np.random.default_rng(2026 + 7 * noisy + len(cal_name))
    lam = 0.9  # a non-unit λ, to check the scaling of the features
    errs = []
    for _ in range(60):
        blur_dir = rng.uniform(0.0, math.pi)
        opts = RenderOptions(noise_std=5.0, blur_px=3.0, blur_dir_rad=blur_dir) if noisy else RenderOptions()
        img, true_px, centres = render_visible(rng, cal, opts)
        det = extract_markers(img, cal)
        assert det.ok, f"{cal_name}: rejected: {det.reason}"
        e = np.linalg.norm(det.pixels - true_px, axis=1)
        # marker order: every detected centre is nearest to its own true projection
        d_all = np.linalg.norm(det.pixels[:, None, :] - true_px[None, :, :], axis=2)
        assert np.array_equal(d_all.argmin(axis=1), np.arange(4))
        # features: λ·(undistorted normalised true points), i.e. flightstack.paper.projection of the centres;
        # a pixel error δ maps to ≤ 1.5 δ / f in normalised units for these lenses
        f_true = project(centres, CameraModel(focal_length=lam))
        f = features_from_detection(det, focal_length=lam)
        assert f is not None and f.shape == (8,)
        tol = lam * (1.5 * np.repeat(e, 2) / min(cal.fx, cal.fy) + 1e-7)
        assert np.all(np.abs(f - f_true) <= tol), (f - f_true, tol)
        assert np.allclose(features_from_detection(det), det.normalized.reshape(-1))
        errs.append(e)
    e = np.concatenate(errs)
    kind = "noisy" if noisy else "clean"
    msg = f"{cal_name} {kind}: centroid error mean {e.mean():.3f} px, max {e.max():.3f} px"
    print(msg)
    assert e.mean() < spec_mean_limit, msg  # the requirement
    # regression bounds, about 2.5x the measured values (mean 0.025-0.037 px, max 0.11-0.15 px); a
    # binary-mask centroid gives mean 0.11-0.16 px, max 0.5 px on the same frames
    assert e.mean() < 0.08, msg
    assert e.max() < 0.4, msg


def test_downscaled_detection_matches_full_resolution():
    rng = np.random.default_rng(5)
    for _ in range(10):
        img, _, _ = render_visible(rng, CAL_FWD, RenderOptions(noise_std=3.0), margin_px=8.0)
        a = extract_markers(img, CAL_FWD)  # default: found at half resolution, measured at full
        b = extract_markers(img, CAL_FWD, downscale=1)
        assert a.ok and b.ok, (a.reason, b.reason)
        assert np.abs(a.pixels - b.pixels).max() < 0.05
        assert np.abs(a.areas - b.areas).max() < 0.03 * b.areas.max()


def test_soft_area_and_touching_foreign_colour():
    # red and yellow discs touching: the hue gate keeps yellow out of red's centroid and vice versa
    for cal in CALS.values():
        z = 1.0
        centres = np.array([[0.0, 0.0, z], [0.15, 0.1, z], [-0.15, 0.1, z], [2 * RADIUS, 0.0, z]])
        img, true_px, in_view = render_markers(cal, centres, FACING, RenderOptions())
        assert in_view.all()
        det = extract_markers(img, cal)
        assert det.ok, det.reason
        assert np.linalg.norm(det.pixels - true_px, axis=1).max() < 0.15
        expected_area = math.pi * RADIUS**2 * cal.fx * cal.fy / z**2
        assert np.allclose(det.areas, expected_area, rtol=0.04), (det.areas, expected_area)


@pytest.mark.parametrize("rgb", [(225, 25, 60), (225, 50, 25)], ids=["hue175", "hue4"])
def test_hue_wraps_both_sides(rgb):
    # the red threshold wraps (hsv_lo 170 > hsv_hi 8): a red on either side of hue 0 is found
    markers = (dataclasses.replace(CAL_TELLO.markers[0], rgb=rgb), *CAL_TELLO.markers[1:])
    cal = dataclasses.replace(CAL_TELLO, markers=markers)
    hue = cv2.cvtColor(np.array([[rgb]], np.uint8), cv2.COLOR_RGB2HSV)[0, 0, 0]
    assert hue >= 170 or hue <= 8
    centres = np.array([[0.0, 0.0, 1.0], [0.15, 0.1, 1.0], [-0.15, 0.1, 1.0], [0.1, -0.1, 1.0]])
    img, true_px, _ = render_markers(cal, centres, None, RenderOptions())
    det = extract_markers(img, cal)
    assert det.ok, det.reason
    assert np.linalg.norm(det.pixels - true_px, axis=1).max() < 0.2


# ------------------------------------------------------------------------------------------------------
# rejections


def square_at(z: float = 1.0) -> np.ndarray:
    return P0 + np.array([0.0, 0.0, z])


@pytest.mark.parametrize("cal_name", list(CALS))
def test_marker_out_of_view_rejected(cal_name):
    cal = CALS[cal_name]
    centres = square_at()
    centres[3] = [2.0, 0.0, 1.0]  # yellow far to the right, outside the field of view
    img, true_px, in_view = render_markers(cal, centres, None, RenderOptions())
    assert in_view.tolist() == [True, True, True, False]
    assert true_px[3, 0] > cal.width
    det = extract_markers(img, cal)
    assert not det.ok and det.reason == "marker 'yellow': 0 blobs"
    assert det.pixels is None and det.normalized is None and det.areas is None
    assert features_from_detection(det) is None


@pytest.mark.parametrize("cal_name", list(CALS))
def test_marker_partly_outside_touches_border(cal_name):
    cal = CALS[cal_name]
    centres = square_at()
    # blue's centre exactly on the left image edge (undistorted normalised x of pixel u = 0, v = cy)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
    edge = cv2.undistortPoints(
        np.array([[[0.0, cal.cy]]]), cal.camera_matrix, cal.dist_coeffs, criteria=criteria
    )
    centres[2] = [edge[0, 0, 0], edge[0, 0, 1], 1.0]
    img, true_px, in_view = render_markers(cal, centres, FACING, RenderOptions())
    assert not in_view[2] and in_view[[0, 1, 3]].all()
    assert np.allclose(true_px[2], [0.0, cal.cy], atol=1e-3)
    det = extract_markers(img, cal)
    assert det.reason == "marker 'blue' touches the image border"


@pytest.mark.parametrize("cal_name", list(CALS))
def test_marker_behind_camera_rejected(cal_name):
    cal = CALS[cal_name]
    centres = square_at()
    centres[1] = [0.0, 0.0, -1.0]  # green behind the camera, on the optical axis
    img, true_px, in_view = render_markers(cal, centres, None, RenderOptions())
    assert not in_view[1] and np.isnan(true_px[1]).all()
    assert np.isfinite(true_px[[0, 2, 3]]).all()
    det = extract_markers(img, cal)
    assert det.reason == "marker 'green': 0 blobs"


def test_two_blobs_of_one_colour_rejected_or_largest_taken():
    cal = CAL_FWD
    cal5 = dataclasses.replace(cal, markers=(*cal.markers, cal.markers[0]))  # a second red disc
    centres = np.vstack([square_at(1.0), [[0.0, 0.05, 1.6]]])  # the extra red disc is farther (smaller)
    img, true_px, in_view = render_markers(cal5, centres, None, RenderOptions())
    assert in_view.all()
    det = extract_markers(img, cal)
    assert det.reason == "marker 'red': 2 blobs"
    det2 = extract_markers(img, cal, max_blobs_per_colour=2)
    assert det2.ok and np.linalg.norm(det2.pixels - true_px[:4], axis=1).max() < 0.2


@pytest.mark.parametrize("cal_name", list(CALS))
def test_blobs_that_cannot_be_the_target_are_rejected(cal_name):
    """One marker much nearer than the others (a reflection, a smear): sizes; two markers on top of each
    other: spacing. The same square at a steep tilt still passes."""
    cal = CALS[cal_name]
    centres = square_at(1.0)
    centres[2] = [-0.02, -0.02, 0.2]  # blue five times nearer: 25 times the area
    img, _, in_view = render_markers(cal, centres, None, RenderOptions())
    assert in_view.all()
    assert (extract_markers(img, cal).reason or "").startswith("marker sizes: 'blue' vs ")
    assert extract_markers(img, cal, max_area_ratio=30.0).ok
    centres = square_at(1.0)
    centres[1] = centres[0] + [1.5 * RADIUS, 0.0, 0.0]  # green over red, their discs overlapping
    img, _, _ = render_markers(cal, centres, FACING, RenderOptions())
    det = extract_markers(img, cal)
    assert det.reason == "marker spacing: 'red' and 'green' overlap", det.reason
    tilt = Rotation.from_euler("x", 70, degrees=True).as_matrix()  # seen at 70° from its normal
    centres = P0 @ tilt.T + [0.0, 0.0, 1.0]
    normals = np.tile(tilt @ [0.0, 0.0, -1.0], (4, 1))
    img, _, in_view = render_markers(cal, centres, normals, RenderOptions())
    assert in_view.all()
    assert extract_markers(img, cal).ok


@pytest.mark.parametrize("cal_name", list(CALS))
def test_empty_and_noise_images_rejected(cal_name):
    cal = CALS[cal_name]
    shape = (cal.height, cal.width, 3)
    grey, _, in_view = render_markers(cal, -square_at(), None, RenderOptions())  # all behind the camera
    assert not in_view.any() and (grey == 90).all()
    for img in (grey, np.zeros(shape, np.uint8), np.full(shape, 255, np.uint8)):
        det = extract_markers(img, cal)
        assert det.reason == "marker 'red': 0 blobs"
    rng = np.random.default_rng(0)
    for _ in range(3):
        det = extract_markers(rng.integers(0, 256, shape, dtype=np.uint8), cal)
        assert not det.ok and REASON.match(det.reason), det.reason
    # a strongly noisy frame that still contains the markers must not raise either
    img, _, _ = render_markers(cal, square_at(), None, RenderOptions(noise_std=60.0), rng)
    det = extract_markers(img, cal)
    assert det.ok or det.reason.startswith("marker '")


def test_bad_inputs_raise_value_error():
    img = np.zeros((240, 320, 3), np.uint8)
    with pytest.raises(ValueError, match="uint8"):
        extract_markers(img.astype(np.float32), CAL_TELLO)
    with pytest.raises(ValueError, match="shape"):
        extract_markers(img[:, :, 0], CAL_TELLO)
    with pytest.raises(ValueError, match="calibration is for"):
        extract_markers(np.zeros((720, 960, 3), np.uint8), CAL_TELLO)
    with pytest.raises(ValueError, match="no markers"):
        extract_markers(img, dataclasses.replace(CAL_TELLO, markers=()))


def small_calibration(w: int, h: int) -> CameraCalibration:
    f = 0.8 * max(w, h)
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    return CameraCalibration(w, h, K, np.array([-0.1, 0.02, 0.0, 0.0, 0.0]), CAL_TELLO.markers)


@st.composite
def odd_images(draw: st.DrawFn) -> np.ndarray:
    """Small frames: random bytes, random coloured rectangles, or four marker patches plus clutter."""
    mode = draw(st.sampled_from(["bytes", "rectangles", "markers"]))
    h = draw(st.integers(1 if mode != "markers" else 12, 40))
    w = draw(st.integers(1 if mode != "markers" else 12, 48))
    if mode == "bytes":
        return draw(arrays(np.uint8, (h, w, 3)))
    img = np.empty((h, w, 3), np.uint8)
    if mode == "markers":
        img[:] = draw(st.integers(0, 255))  # a grey floor
    else:
        img[:] = draw(st.tuples(*[st.integers(0, 255)] * 3))
    marker_rgb = [mk.rgb for mk in CAL_TELLO.markers]
    clutter = [*marker_rgb, (255, 255, 255), (0, 0, 0)]
    if mode == "markers":  # a patch per marker colour, one per quadrant, mostly away from the border
        for j, rgb in enumerate(marker_rgb):
            qx, qy = (j % 2) * (w // 2), (j // 2) * (h // 2)
            x0, y0 = qx + draw(st.integers(0, 3)), qy + draw(st.integers(0, 3))
            img[y0 : y0 + draw(st.integers(2, 9)), x0 : x0 + draw(st.integers(2, 9))] = rgb
    for _ in range(draw(st.integers(0, 4))):
        x0, y0 = draw(st.integers(0, w - 1)), draw(st.integers(0, h - 1))
        x1, y1 = draw(st.integers(x0, w)), draw(st.integers(y0, h))
        img[y0:y1, x0:x1] = draw(st.sampled_from(clutter))
    return img


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(img=odd_images())
def test_extract_never_raises_on_small_images(img):
    h, w = img.shape[:2]
    det = extract_markers(img, small_calibration(w, h))
    assert isinstance(det, MarkerDetection)
    if det.ok:
        assert det.pixels.shape == (4, 2) and det.normalized.shape == (4, 2) and det.areas.shape == (4,)
        assert np.all((det.pixels >= 0) & (det.pixels <= [w - 1, h - 1]))
        assert np.all(np.isfinite(det.normalized)) and np.all(det.areas > 0)
    else:
        assert det.reason and det.pixels is None and features_from_detection(det) is None


# ------------------------------------------------------------------------------------------------------
# the renderer against independent references


@pytest.mark.parametrize("z", [0.4, 1.0, 2.5])
@pytest.mark.parametrize("fy", [900.0, 870.0])
def test_rendered_disc_area_and_centre(z, fy):
    """A fronto-parallel disc on the optical axis, no distortion: area π r² fx fy / z², centre (cx, cy)."""
    fx, cx, cy = 900.0, 480.3, 359.6
    cal = CameraCalibration(
        960, 720, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.zeros(5), CAL_TELLO.markers
    )
    # the other three markers are far out of view
    centres = np.array([[0.0, 0.0, z], [5.0, 0.0, 1.0], [-5.0, 0.0, 1.0], [0.0, 5.0, 1.0]])
    img, true_px, in_view = render_markers(cal, centres, FACING, RenderOptions())
    assert in_view.tolist() == [True, False, False, False]
    assert np.allclose(true_px[0], [cx, cy], atol=1e-9)
    a = coverage(img, CAL_TELLO.markers[0].rgb)
    v, u = np.mgrid[0 : cal.height, 0 : cal.width]
    area = a.sum()
    expected = math.pi * RADIUS**2 * fx * fy / z**2
    assert area == pytest.approx(expected, rel=0.02)
    assert (a * u).sum() / area == pytest.approx(cx, abs=0.05)
    assert (a * v).sum() / area == pytest.approx(cy, abs=0.05)


def brown_conrady(points_c: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """Independent reference for cv2.projectPoints with (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = cal.dist_coeffs
    x, y = points_c[:, 0] / points_c[:, 2], points_c[:, 1] / points_c[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.c_[cal.fx * xd + cal.cx, cal.fy * yd + cal.cy]


@pytest.mark.parametrize("cal_name", list(CALS))
def test_true_px_is_the_distorted_projection(cal_name):
    cal = CALS[cal_name]
    rng = np.random.default_rng(11)
    for _ in range(20):
        centres, normals = random_target(rng, cal)
        _, true_px, _ = render_markers(cal, centres, normals, RenderOptions())
        assert np.allclose(true_px, brown_conrady(centres, cal), atol=1e-6)


def test_blur_keeps_mass_and_centre_noise_is_seeded():
    cal = CAL_FWD
    centres = square_at(1.2)
    sharp, true_px, _ = render_markers(cal, centres, FACING, RenderOptions())
    blurred, _, _ = render_markers(cal, centres, FACING, RenderOptions(blur_px=6.0, blur_dir_rad=0.7))
    v, u = np.mgrid[0 : cal.height, 0 : cal.width]
    for j, mk in enumerate(cal.markers):
        near = (u - true_px[j, 0]) ** 2 + (v - true_px[j, 1]) ** 2 < 40**2
        a0, a1 = coverage(sharp, mk.rgb) * near, coverage(blurred, mk.rgb) * near
        assert a1.sum() == pytest.approx(a0.sum(), rel=0.01)
        assert (a1 * u).sum() / a1.sum() == pytest.approx((a0 * u).sum() / a0.sum(), abs=0.05)
        assert (a1 * v).sum() / a1.sum() == pytest.approx((a0 * v).sum() / a0.sum(), abs=0.05)
        partial0 = np.count_nonzero((a0 > 0.05) & (a0 < 0.95))
        assert np.count_nonzero((a1 > 0.05) & (a1 < 0.95)) > 1.5 * partial0  # blur widens the edges
    assert not np.array_equal(sharp, blurred)
    opts = RenderOptions(noise_std=5.0)
    n1, _, _ = render_markers(cal, centres, FACING, opts, np.random.default_rng(3))
    n2, _, _ = render_markers(cal, centres, FACING, opts, np.random.default_rng(3))
    assert np.array_equal(n1, n2)
    floor = n1[:100, :100].astype(float)
    assert floor.mean() == pytest.approx(90.0, abs=0.2)
    assert floor.std() == pytest.approx(5.0, rel=0.1)


def test_render_clips_outside_the_monotone_distortion_range():
    # with k1 = −0.05 alone, cv2.projectPoints folds a point at x/z = 4.2 (77° off-axis) back into the
    # image; the renderer must not paint such a disc
    cal = dataclasses.replace(CAL_FWD, dist_coeffs=np.array([-0.05, 0.0, 0.0, 0.0, 0.0]))
    far = np.array([[4.2, 0.0, 1.0]])
    folded, _ = cv2.projectPoints(far, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
    assert 0 <= folded[0, 0, 0] < cal.width  # the fold is real
    centres = np.vstack([far, [[0.0, 0.0, -1.0]] * 3])
    img, _, in_view = render_markers(cal, centres, None, RenderOptions())
    assert not in_view.any()
    assert (img == 90).all()
    # a disc straddling the camera plane is clipped, not mirrored, and never raises
    centres = np.array([[0.0, 0.0, 0.01], [0.1, 0.0, -0.02], [0.2, 0.1, 0.0], [0.0, 0.2, 1e-4]])
    normals = np.tile([1.0, 0.0, 0.0], (4, 1))
    img, _, in_view = render_markers(cal, centres, normals, RenderOptions())
    assert img.shape == (720, 960, 3) and not in_view.any()


def test_render_validates_markers():
    centres = square_at()
    no_rgb = dataclasses.replace(CAL_TELLO, markers=(MarkerColour("red", (170, 120, 80), (8, 255, 255)),) * 4)
    with pytest.raises(ValueError, match="rgb"):
        render_markers(no_rgb, centres, None, RenderOptions())
    with pytest.raises(ValueError, match="expected shape"):
        render_markers(CAL_TELLO, centres[:3], None, RenderOptions())
    with pytest.raises(ValueError, match="normals_c"):
        render_markers(CAL_TELLO, centres, np.zeros((4, 3)), RenderOptions())


def test_painters_order_near_disc_on_top():
    cal = CAL_TELLO
    # red on the optical axis at 2 m, green in front of it at 1 m
    centres = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.5, 0.4, 1.0], [-0.5, 0.4, 1.0]])
    img, true_px, _ = render_markers(cal, centres, FACING, RenderOptions())
    u, v = np.round(true_px[0]).astype(int)
    assert tuple(img[v, u]) == cal.markers[1].rgb
