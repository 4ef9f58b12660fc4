"""The target as a grey camera sees it: the calibration file's image kind, stream layout and ArUco fiducial,
the fiducial drawn by the renderer and found by the vision layer, and the Tello EDU's downward frame cut by
the driver.

The truth is never the code under test: corners are placed in the camera frame here, from the pose, the
mount and the experiment's feature points, and projected with cv2.projectPoints and the calibration.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.paper.geometry import Pose
from flightstack.sim_backend.scene.floor import PERIOD_TEXELS, floor_view, texture
from flightstack.sim_backend.scene.render import RenderOptions, render_markers_region
from flightstack.vision.camera_file import (
    CalibrationError,
    CameraCalibration,
    calibration_from_dict,
    load_calibration,
)
from flightstack.vision.detect import detect_markers
from flightstack.vision.fiducial import (
    cells_wrong,
    detect_fiducial,
    marker_cells,
    placement_problem,
    track_fiducial,
)
from flightstack.vision.markers import extract_markers
from flightstack.vision.picture import picture, picture_of
from tests.conftest import MISSIONS

CAMERAS = MISSIONS / "cameras"
EDU = load_calibration(CAMERAS / "tello_down_edu_sim.yaml")
COLOUR = load_calibration(CAMERAS / "tello_down_sim.yaml")
FRONT = load_calibration(CAMERAS / "tello_front_sim.yaml")
# paper_experiment's feature points (target frame: x forward, y left, z up; m), in their order
P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
DOWN = CAMERA_MOUNTS["down"]


def with_fiducial(cal: CameraCalibration, grey: bool = False) -> CameraCalibration:
    """`cal` (a colour file) with EDU's fiducial instead of its markers."""
    return dataclasses.replace(cal, markers=(), fiducial=EDU.fiducial, image="grey" if grey else "colour")


def corners_in_camera(drone: Pose, target: Pose) -> np.ndarray:
    """The feature points (4, 3) in the downward camera's frame (m), computed here: body frame FLU of the
    drone, then the camera's axes (the columns of the mount)."""
    c, s = np.cos(target.theta), np.sin(target.theta)
    world = P0 @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + target.p
    cd, sd = np.cos(drone.theta), np.sin(drone.theta)
    body = (world - drone.p) @ np.array([[cd, -sd, 0.0], [sd, cd, 0.0], [0.0, 0.0, 1.0]])
    return body @ DOWN


def truth_px(cal: CameraCalibration, corners_c: np.ndarray) -> np.ndarray:
    px, _ = cv2.projectPoints(corners_c, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
    return px.reshape(-1, 2)


def views(n: int, seed: int) -> list[tuple[Pose, Pose]]:
    """n (drone, target) pose pairs in Σw: the drone 0.9–1.2 m up, the target within its view, any yaws."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        drone = Pose.make([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.9, 1.2)], rng.uniform(-3, 3))
        off = rng.uniform(-0.12, 0.12, 2)
        target = Pose.make([drone.p[0] + off[0], drone.p[1] + off[1], 0.0], rng.uniform(-np.pi, np.pi))
        out.append((drone, target))
    return out


# ---- the calibration file ------------------------------------------------------------------------------
def test_the_camera_files_declare_what_their_cameras_see() -> None:
    assert EDU.grey and EDU.fiducial is not None and not EDU.markers and EDU.feature_count == 4
    assert EDU.stream is not None and EDU.frame_size == (320, 720) and (EDU.stream.x, EDU.stream.y) == (0, 0)
    assert (EDU.width, EDU.height) == (320, 240)
    template = load_calibration(CAMERAS / "tello_down_template.yaml")
    assert template.grey and template.fiducial == EDU.fiducial and template.stream == EDU.stream
    assert template.rms_px is None  # still never measured: preflight refuses it
    for name in ("tello_down_sim", "tello_front_sim", "tello_front_template"):
        cal = load_calibration(CAMERAS / f"{name}.yaml")
        assert cal.image == "colour" and cal.fiducial is None and cal.stream is None and len(cal.markers) == 4


def test_a_calibration_round_trips_through_its_file(tmp_path: Path) -> None:
    for suffix in ("yaml", "json"):
        EDU.save(tmp_path / f"c.{suffix}")
        back = load_calibration(tmp_path / f"c.{suffix}")
        assert (back.image, back.stream, back.fiducial) == (EDU.image, EDU.stream, EDU.fiducial)
    assert (
        "image" not in COLOUR.to_dict() and "fiducial" not in COLOUR.to_dict()
    )  # old files stay as they are


def test_a_grey_camera_with_colour_markers_is_refused_naming_the_fix() -> None:
    doc = {**COLOUR.to_dict(), "image": "grey"}
    with pytest.raises(CalibrationError) as err:
        calibration_from_dict(doc, "cam.yaml")
    text = str(err.value)
    assert "\n" not in text and text.startswith("cam.yaml: markers:") and "fiducial" in text


FID = {"dictionary": "DICT_4X4_50", "id": 0, "side_m": 0.2, "corners": [1, 0, 3, 2]}


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"fiducial": FID}, "markers"),  # both colour markers and a fiducial
        ({"markers": [], "fiducial": {**FID, "dictionary": "DICT_9X9_1"}}, "fiducial.dictionary"),
        ({"markers": [], "fiducial": {**FID, "id": 50}}, "fiducial.id"),
        ({"markers": [], "fiducial": {**FID, "corners": [0, 1, 2, 2]}}, "fiducial.corners"),
        ({"markers": [], "fiducial": {**FID, "side_m": 0}}, "fiducial.side_m"),
        ({"markers": [], "fiducial": {**FID, "colour": "red"}}, "fiducial"),
        ({"image": "infrared"}, "image"),
        ({"stream": {"width": 320, "height": 720, "picture": [0, 0, 320, 480]}}, "stream.picture"),
        ({"stream": {"width": 320, "height": 720, "picture": [0, 500, 320, 240]}}, "stream.picture"),
        ({"stream": {"width": 320, "height": 720}}, "stream"),
    ],
)
def test_invalid_keys_are_named(change: dict, key: str) -> None:
    with pytest.raises(CalibrationError, match=f"cam.yaml: {key}:"):
        calibration_from_dict({**COLOUR.to_dict(), **change}, "cam.yaml")


def test_the_fiducial_must_lie_face_up_on_the_feature_square() -> None:
    fid = EDU.fiducial
    assert fid is not None
    assert placement_problem(fid, P0) is None
    mirrored = dataclasses.replace(fid, corners=(0, 1, 2, 3))  # clockwise from below: printed side down
    assert "upside down" in str(placement_problem(mirrored, P0))
    assert "not a square of side 0.25 m" in str(placement_problem(dataclasses.replace(fid, side_m=0.25), P0))
    assert "4 feature points" in str(placement_problem(fid, P0[:3]))
    rotated = P0 @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T  # any yaw on the plate
    assert placement_problem(fid, rotated) is None


# ---- drawn and found -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("cal", "floor"),
    [(EDU, "plain"), (EDU, "tiles"), (with_fiducial(FRONT), "tiles")],
    ids=["edu_320_grey_plain", "edu_320_grey_tiles", "front_960_colour_tiles"],
)
def test_rendered_fiducial_corners_are_found_within_half_a_pixel(cal: CameraCalibration, floor: str) -> None:
    opts = RenderOptions(noise_std=2.0, region="markers", floor=floor)
    rng = np.random.default_rng(5)
    errors = []
    for drone, target in views(25, seed=11):
        corners = corners_in_camera(drone, target)
        fv = floor_view(drone, DOWN, np.zeros(3))
        img, px, in_view, roi = render_markers_region(cal, corners, None, opts, rng, fv)
        assert img.shape == ((cal.height, cal.width) if cal.grey else (cal.height, cal.width, 3))
        assert in_view.all() and roi is not None
        truth = truth_px(cal, corners)
        assert np.allclose(px, truth, atol=1e-9)  # the renderer's own truth is the projection
        det = detect_markers(img, cal, roi=roi)
        assert det.ok, det.reason
        errors.append(np.linalg.norm(det.pixels - truth, axis=1).max())
        assert det.normalized is not None and np.allclose(
            det.normalized,
            cv2.undistortPoints(det.pixels.reshape(-1, 1, 2), cal.camera_matrix, cal.dist_coeffs).reshape(
                -1, 2
            ),
            atol=1e-6,
        )
    print(f"corner error (px): median {np.median(errors):.3f}, max {max(errors):.3f}")
    assert max(errors) < 0.5


def test_grey_and_rgb_frames_of_one_view_give_the_same_corners() -> None:
    drone, target = views(1, seed=2)[0]
    corners = corners_in_camera(drone, target)
    grey, *_ = render_markers_region(EDU, corners, None, RenderOptions(), None)
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    a, b = detect_fiducial(grey, EDU), detect_markers(rgb, EDU)
    assert a.ok and b.ok and np.allclose(a.pixels, b.pixels)


def test_a_frame_without_the_fiducial_or_with_two_is_rejected_with_its_reason() -> None:
    blank = np.full((240, 320), 90, dtype=np.uint8)
    assert detect_fiducial(blank, EDU).reason == "fiducial 0 (DICT_4X4_50): not found"
    cells = marker_cells(EDU.fiducial)  # two boards: the marker's cells, 8 px each, on white
    board = np.full((72, 72), 255, dtype=np.uint8)
    board[12:60, 12:60] = np.kron(cells, np.ones((8, 8), dtype=np.uint8))
    twice = blank.copy()
    twice[40:112, 30:102] = board
    twice[120:192, 200:272] = board
    assert detect_fiducial(twice, EDU).reason == "fiducial 0 (DICT_4X4_50): seen 2 times"
    twice[120:192, 200:272] = 90
    assert detect_fiducial(twice, EDU).ok


def _darken_cells(img: np.ndarray, truth: np.ndarray, k: int) -> None:
    """Paint the first k white cells of the marker's code black in `img`, as concealment greys a board's
    cells (truth: its corners, feature-point order)."""
    fid = EDU.fiducial
    cells = marker_cells(fid)
    n = cells.shape[0]
    quad = np.empty((4, 2))
    quad[list(fid.corners)] = truth
    grid = np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(grid, quad.astype(np.float32))
    white = [(r, c) for r in range(1, n - 1) for c in range(1, n - 1) if cells[r, c] == 255][:k]
    for r, c in white:
        square = np.array([[[c, r]], [[c + 1, r]], [[c + 1, r + 1]], [[c, r + 1]]], dtype=np.float32)
        poly = cv2.perspectiveTransform(square, H).reshape(-1, 2)
        cv2.fillConvexPoly(img, np.round(poly * 16).astype(np.int32), 20, lineType=cv2.LINE_AA, shift=4)


def test_a_board_the_detector_misses_is_tracked_from_where_it_is_expected() -> None:
    """One code cell darkened (what concealment does to a board): ArUco cannot read the code (4x4_50
    corrects no bit at OpenCV's default rate), `track_fiducial` from corners 3 px off the truth finds it
    within 0.5 px and reads the code with that one cell wrong; with three cells dark, with the board
    absent, or expected 20 px away it refuses, naming why."""
    opts = RenderOptions(noise_std=2.0, region="markers", floor="tiles")
    rng = np.random.default_rng(7)
    errors, tried = [], 0
    for drone, target in views(25, seed=13):
        corners = corners_in_camera(drone, target)
        img, *_ = render_markers_region(EDU, corners, None, opts, rng, floor_view(drone, DOWN, np.zeros(3)))
        truth = truth_px(EDU, corners)
        one = img.copy()
        _darken_cells(one, truth, 1)
        if detect_fiducial(one, EDU).ok:
            continue  # ArUco read through the dark cell: nothing to track
        tried += 1
        off = truth + rng.normal(0.0, 3.0, 2) / np.sqrt(2)
        det = track_fiducial(one, off, EDU)
        assert det.ok, det.reason
        errors.append(float(np.linalg.norm(det.pixels - truth, axis=1).max()))
        quad = np.empty((4, 2))
        quad[list(EDU.fiducial.corners)] = det.pixels
        assert cells_wrong(one, quad, EDU.fiducial) == 1
        three = img.copy()
        _darken_cells(three, truth, 3)
        assert (
            track_fiducial(three, off, EDU).reason
            == "fiducial 0 (DICT_4X4_50): not found, nor its code where expected"
        )
        assert not track_fiducial(one, truth + 20.0, EDU).ok
    print(
        f"tracked {len(errors)} of {tried}: corner error median {np.median(errors):.3f}, "
        f"max {max(errors):.3f} px"
    )
    assert tried >= 10 and max(errors) < 0.5
    blank = np.full((240, 320), 90, dtype=np.uint8)
    assert not track_fiducial(blank, truth, EDU).ok


def test_the_dispatcher_finds_what_the_calibration_declares() -> None:
    drone, target = views(1, seed=4)[0]
    corners = corners_in_camera(drone, target)
    img, *_ = render_markers_region(COLOUR, corners, None, RenderOptions(marker_radius_m=0.025), None)
    a, b = detect_markers(img, COLOUR), extract_markers(img, COLOUR)
    assert a.ok and np.array_equal(a.pixels, b.pixels)
    with pytest.raises(ValueError, match="grey frame cannot show colour markers"):
        detect_markers(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), COLOUR)
    with pytest.raises(ValueError, match="calibration is for 320x240"):
        detect_markers(np.zeros((720, 320), dtype=np.uint8), EDU)


# ---- the floor ----------------------------------------------------------------------------------------
def test_the_tiled_floor_is_fixed_in_the_world_and_deterministic() -> None:
    tex = texture()
    assert tex.shape == (PERIOD_TEXELS, PERIOD_TEXELS) and tex.std() > 15  # structure, not a plain grey
    opts = RenderOptions(floor="tiles")
    far = Pose.make([3.0, 3.0, 0.0], 0.0)  # the target far out of view: only floor
    drone = Pose.make([0.3, -0.2, 1.0], 0.4)
    a, *_ = render_markers_region(
        EDU, corners_in_camera(drone, far), None, opts, None, floor_view(drone, DOWN, np.zeros(3))
    )
    b, *_ = render_markers_region(
        EDU, corners_in_camera(drone, far), None, opts, None, floor_view(drone, DOWN, np.zeros(3))
    )
    assert np.array_equal(a, b) and a.std() > 10
    # 1 m up the downward camera sees 260 px per m: moving the drone 0.1 m along its x (forward) moves
    # the floor 26 px down the image (the camera's y axis is the body's −x)
    ahead = Pose.make([*(drone.p[:2] + 0.1 * np.array([np.cos(0.4), np.sin(0.4)])), 1.0], 0.4)
    c, *_ = render_markers_region(
        EDU, corners_in_camera(ahead, far), None, opts, None, floor_view(ahead, DOWN, np.zeros(3))
    )
    centre, shifted = np.s_[95:145, 130:190], np.s_[121:171, 130:190]
    assert np.abs(c[shifted].astype(int) - a[centre].astype(int)).mean() < 3.0
    assert np.abs(c[centre].astype(int) - a[centre].astype(int)).mean() > 6.0
    colour, *_ = render_markers_region(
        COLOUR,
        corners_in_camera(drone, far),
        None,
        dataclasses.replace(opts, floor="tiles"),
        None,
        floor_view(drone, DOWN, np.zeros(3)),
    )
    assert np.array_equal(colour[:, :, 0], colour[:, :, 2])  # grey in a colour camera: no hue to fire on


def test_colour_markers_on_the_tiled_floor_keep_the_roi_promise() -> None:
    full = RenderOptions(marker_radius_m=0.025, noise_std=2.0, floor="tiles")
    roi_opts = dataclasses.replace(full, region="markers")
    accepted = 0
    for k, (drone, target) in enumerate(views(15, seed=8)):
        corners = corners_in_camera(drone, target)
        fv = floor_view(drone, DOWN, np.zeros(3))
        img_full, *_ = render_markers_region(COLOUR, corners, None, full, np.random.default_rng(k), fv)
        img, _, _, roi = render_markers_region(COLOUR, corners, None, roi_opts, np.random.default_rng(k), fv)
        assert roi is not None
        d_full, d = extract_markers(img_full, COLOUR), extract_markers(img, COLOUR, roi=roi)
        assert d.reason == d_full.reason
        if d.ok:
            accepted += 1
            assert np.array_equal(d.pixels, d_full.pixels)
    assert accepted >= 10


# ---- the EDU's downward stream ------------------------------------------------------------------------
def edu_spec(floor: str = "tiles") -> object:
    from flightstack.sim_backend.emulators.tello.view import CameraSpec

    return CameraSpec(
        calibration=EDU.to_dict(),
        R_ic=tuple(tuple(r) for r in DOWN.tolist()),
        t_ic=(0.0, 0.0, 0.0),
        feature_points=tuple(tuple(p) for p in P0.tolist()),
        start=(0.0, 0.0, 0.0, 0.0),
        floor=floor,
    )


def test_picture_cuts_the_stream_layout_and_makes_it_grey() -> None:
    frame = np.zeros((720, 320, 3), dtype=np.uint8)
    frame[:240, :, 0] = 200  # the picture: reddish, so that the grey conversion shows
    frame[240:] = 128
    pic = picture(frame, EDU)
    assert pic.shape == (240, 320) and pic.dtype == np.uint8
    assert np.all(pic == round(0.299 * 200))  # cv2's RGB → grey weights
    small = np.full((240, 320, 3), 77, dtype=np.uint8)  # already the picture: only made grey
    assert picture(small, EDU).shape == (240, 320)
    other = np.zeros((720, 960, 3), dtype=np.uint8)  # the forward camera's frame: left as it is, made grey
    assert picture(other, EDU).shape == (720, 960)
    assert picture(frame, COLOUR) is frame  # a colour camera without a stream layout: untouched


class Receiver:
    """What VideoReceiver.latest gives: the newest decoded frame (one, clean)."""

    def __init__(self, frame: np.ndarray) -> None:
        self.frame = frame

    def latest(self) -> object:
        from flightstack.drivers.tello.camera import DecodedFrame

        return DecodedFrame(1, 10.0, self.frame, False, None)


class Driver:
    """What TelloCamera.latest reads of its driver: the drone's address (no emulated truth registered)."""

    class cfg:  # noqa: N801
        host = "127.0.0.99"
        video_port = 1


def test_a_downward_frame_in_the_edu_layout_is_cut_by_the_driver_and_its_corners_found() -> None:
    """The acceptance test of the layout: the frame the emulator sends (320 × 720, grey picture on top,
    noise below), through TelloCamera.latest's cut, gives the corners within 0.5 px of the truth."""
    from flightstack.drivers.tello.camera import TelloCamera
    from flightstack.sim_backend.emulators.tello.view import DOWN_NOISE_MEAN, DOWN_NOISE_STD, CameraView

    view = CameraView(edu_spec())  # type: ignore[arg-type]
    assert view.spec.stream_size(True) == (320, 720) and view.spec.stream_size(False) == (320, 240)
    errors = []
    for drone, target in views(10, seed=21):
        frame = view.frame(drone, target, downvision=True)
        assert frame.shape == (720, 320, 3) and frame.dtype == np.uint8
        below = frame[240:, :, 0].astype(float)
        assert abs(below.mean() - DOWN_NOISE_MEAN) < 1.0 and abs(below.std() - DOWN_NOISE_STD) < 0.3
        assert np.array_equal(frame[:, :, 0], frame[:, :, 1])  # a grey picture in all three channels

        cam = TelloCamera(driver=Driver(), to_picture=picture_of(EDU))  # type: ignore[arg-type]
        cam._rx = Receiver(frame)  # type: ignore[assignment]
        got = cam.latest()
        assert got is not None and got.image is not None and got.image.shape == (240, 320)
        assert cam.latest() is not None and cam.frames_seen == 1  # one decoded frame, cut once
        det = detect_markers(got.image, EDU)
        assert det.ok, det.reason
        errors.append(
            np.linalg.norm(det.pixels - truth_px(EDU, corners_in_camera(drone, target)), axis=1).max()
        )
    assert max(errors) < 0.5, errors
    forward = view.frame(*views(1, seed=21)[0], downvision=False)  # the forward camera selected
    assert forward.shape == (240, 320, 3)


def test_the_stamp_goes_below_the_picture() -> None:
    from flightstack.sim_backend.emulators.tello.frames import (
        read_checked_frame_index,
        read_frame_index,
        stamp_frame_index,
    )
    from flightstack.sim_backend.emulators.tello.view import CameraView

    view = CameraView(edu_spec("plain"))  # type: ignore[arg-type]
    drone, target = views(1, seed=3)[0]
    frame = view.frame(drone, target, downvision=True)
    before = frame[:240].copy()
    area = view.stamp_area(frame)
    stamp_frame_index(area, 1234, checked=True)
    assert np.array_equal(frame[:240], before) and read_frame_index(frame[240:]) == 1234
    assert read_checked_frame_index(frame[240:]) == 1234


def test_a_smeared_or_mixed_bar_code_names_no_frame() -> None:
    """The check row: a code read whole names its frame; one whose index row is another frame's (a
    concealment that reached one row), or with one block smeared, names none."""
    from flightstack.sim_backend.emulators.tello.frames import read_checked_frame_index, stamp_frame_index

    def coded(index: int) -> np.ndarray:
        img = np.full((480, 320), 90, dtype=np.uint8)
        stamp_frame_index(img, index, checked=True)
        return img

    rng = np.random.default_rng(5)
    for index in rng.integers(0, 2**16, 200):
        assert read_checked_frame_index(coded(int(index))) == index
    now, older = coded(1235), coded(1234)
    mixed = now.copy()
    mixed[:30] = older[:30]  # the index row (rows 10-29) from the frame before, the check row current
    assert read_checked_frame_index(mixed) is None
    smeared = now.copy()
    smeared[10:30, 28:42] = 255 - smeared[10:30, 28:42]  # one block of the index row flipped
    assert read_checked_frame_index(smeared) is None


# ---- the served world carries grey frames --------------------------------------------------------------
def test_a_grey_frame_crosses_the_served_world() -> None:
    from flightstack.sim_backend.served import messages as wm

    img = np.arange(240 * 320, dtype=np.uint32).astype(np.uint8).reshape(240, 320)
    tick = wm.WorldTick(
        3, 0.15, wm.TickState(90.0, 1.0, True, True, "flying"), {}, wm.Truth((0.0,) * 4, (0.0,) * 4),
        wm.FrameHead(0.1, None, (240, 320, 1)),
    )  # fmt: skip
    back, image, reason = wm.decode_tick(wm.encode_tick(tick, img))
    assert reason is None and back is not None and image is not None
    assert back.frame is not None and back.frame.image_shape == (240, 320, 1)
    assert image.shape == (240, 320) and np.array_equal(image, img)
    bad = wm.FrameHead(0.1, None, (240, 320, 2))  # neither RGB nor grey
    assert wm.decode_tick(wm.encode_tick(dataclasses.replace(tick, frame=bad), img))[2] == "bad image"


# ---- the wizard: the printable board and a check on photos ----------------------------------------------
def test_the_board_prints_the_marker_at_its_true_size(tmp_path: Path) -> None:
    from PIL import Image

    from flightstack.calibration.board import write_board

    fid = EDU.fiducial
    assert fid is not None
    w, h = write_board(fid, tmp_path / "board.png", dpi=100.0)
    img = np.asarray(Image.open(tmp_path / "board.png").convert("L"))
    assert img.shape == (h, w)
    assert Image.open(tmp_path / "board.png").info["dpi"][0] == pytest.approx(100.0, abs=0.1)
    side = round(0.2 / 0.0254 * 100)  # 787 px: 200 mm at 100 dpi
    quiet = round(0.05 / 0.0254 * 100)
    dark = np.argwhere(img[:w, :] < 128)  # the marker's black cells, above the label
    assert dark.min(axis=0).tolist() == [quiet + 2, quiet + 2]
    assert dark.max(axis=0).tolist() == [quiet + 2 + side - 1, quiet + 2 + side - 1]
    small = cv2.resize(img[:w], (w // 4, w // 4), interpolation=cv2.INTER_AREA)
    calib = dataclasses.replace(EDU, width=w // 4, height=w // 4, stream=None)
    calib = dataclasses.replace(
        calib, camera_matrix=np.array([[100.0, 0, w / 8], [0, 100.0, w / 8], [0, 0, 1]])
    )
    assert detect_fiducial(small, calib).ok  # the print is the calibration's marker
    write_board(fid, tmp_path / "board.pdf", dpi=100.0)
    assert (tmp_path / "board.pdf").read_bytes().startswith(b"%PDF")


def test_calibrate_markers_writes_the_board_and_checks_photos(tmp_path: Path, capsys) -> None:
    from flightstack.cli.app import main
    from flightstack.sim_backend.emulators.tello.view import CameraView

    cal_path = tmp_path / "edu.yaml"
    EDU.save(cal_path)
    assert (
        main(["calibrate", "markers", "--calibration", str(cal_path), "--board", str(tmp_path / "b.png")])
        == 0
    )
    assert (tmp_path / "b.png").is_file()
    photos = tmp_path / "photos"
    photos.mkdir()
    view = CameraView(edu_spec())  # type: ignore[arg-type]
    for k, (drone, target) in enumerate(views(3, seed=9)):  # frames as the EDU streams them
        cv2.imwrite(str(photos / f"p{k}.png"), view.frame(drone, target, downvision=True))
    argv = ["calibrate", "markers", "--calibration", str(cal_path), "--images", str(photos)]
    assert main(argv) == 0
    assert "verified: the fiducial found in all 3 samples" in capsys.readouterr().out
    cv2.imwrite(str(photos / "p9.png"), np.full((720, 320), 90, dtype=np.uint8))
    assert main(argv) == 1
    assert "p9.png: fiducial 0 (DICT_4X4_50): not found" in capsys.readouterr().out
    colour = tmp_path / "colour.yaml"
    COLOUR.save(colour)
    assert (
        main(["calibrate", "markers", "--calibration", str(colour), "--board", str(tmp_path / "c.png")]) == 2
    )
    assert "declares no fiducial" in capsys.readouterr().err


# ---- validate and preflight ------------------------------------------------------------------------------
def test_validate_and_preflight_refuse_a_grey_camera_with_colour_markers_in_one_line(
    tmp_path: Path, capsys
) -> None:
    import yaml

    from flightstack.cli.app import main
    from flightstack.config.mission import load_mission
    from flightstack.drivers.lab.preflight import check_files

    bad = tmp_path / "grey_markers.yaml"
    bad.write_text(yaml.safe_dump({**COLOUR.to_dict(), "image": "grey"}))
    lab = yaml.safe_load((MISSIONS / "rigs" / "lab.yaml").read_text())
    lab["drones"][0]["camera"] = str(bad)
    lab["drones"][1]["camera"] = str(CAMERAS / "tello_front_template.yaml")
    rig = tmp_path / "lab.yaml"
    rig.write_text(yaml.safe_dump(lab))
    assert main(["validate", "paper_experiment", "--rig", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot tell colour markers apart" in err and "fiducial" in err
    mission = load_mission("paper_experiment", rig=str(rig), check_files=False)
    rows = [r for r in check_files(mission) if r.device == "drone 1"]
    assert [r.status for r in rows] == ["FAIL"] and "declare the target's ArUco `fiducial:`" in rows[0].detail
    assert "\n" not in rows[0].detail
    lab["drones"][0]["camera"] = str(CAMERAS / "tello_down_template.yaml")  # grey, with the fiducial
    rig.write_text(yaml.safe_dump(lab))
    mission = load_mission("paper_experiment", rig=str(rig), check_files=False)
    rows = {r.check: r for r in check_files(mission) if r.device == "drone 1"}
    assert rows["fiducial"].status == "PASS" and rows["camera calibration"].status == "FAIL"  # never measured
