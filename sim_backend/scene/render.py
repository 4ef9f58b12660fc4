"""The simulated camera image: the target's coloured discs or its ArUco fiducial, through a calibrated lens.

Frames and units: marker centres and normals are given in the physical camera frame Σc (metres; z = optical
axis, x right, y down, as in OpenCV and flightstack.paper.projection). Pixel coordinates follow OpenCV: u to
the
right, v down, the origin at the centre of the top-left pixel, so pixel (row i, column j) covers
[j − ½, j + ½] × [i − ½, i + ½].

Each disc is the projection of a polygon of its 3-D boundary circle through `cv2.projectPoints` with the
calibration's K and distortion coefficients (so lens distortion bends the outline exactly as it bends
the ground-truth centre), rasterised at `supersample`× resolution inside the disc's bounding box only and
area-averaged back (cv2.INTER_AREA), which gives each edge pixel its covered fraction of the marker
colour. Then motion blur (a centred line kernel, so it moves no centroid), integer-rounded Gaussian noise and
rounding/clipping to uint8.

Polygons that leave the field of view are clipped in 3-D against a near plane and in the undistorted
normalised image plane against a rectangle slightly larger than the image before distortion is
applied: OpenCV's polynomial distortion folds back far outside the field of view (k1 < 0), and without
the clip a disc 77° off-axis (x/z = 4.2, k1 = −0.05) would be painted inside the image.

A calibration with a `fiducial` gets its ArUco board instead (flightstack.vision.fiducial): the marker's
black and white cells and its white quiet zone on the plane of the four feature points (its corners, in
the calibration's corner order). Each pixel of the board's box is sampled `supersample`² times at
sub-pixel centres; a sample's ray (its undistorted normalised coordinates, interpolated from the
calibration's per-pixel ones) meets the board's plane through a homography, and the sample takes the
colour of the cell it lands in; the samples are area-averaged (cv2.INTER_AREA), as the discs' masks are.
A grey camera (`image: grey`) is rendered as one channel (H × W). The floor is plain
(`RenderOptions.background_rgb`) or, with `floor="tiles"` and the camera's pose given, the tiled pattern
of flightstack.sim_backend.scene.floor.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.paper.geometry import Pose, rot_z
from flightstack.sim_backend.scene.floor import FloorView, floor_image, grey_range
from flightstack.vision.camera_file import CameraCalibration, Fiducial

#: Discs closer than this to the camera plane (metres along z) are clipped away.
NEAR_PLANE_M = 1e-3
#: A centre nearer than this (metres along z) is not "in view" (see render_markers).
MIN_IN_VIEW_DEPTH_M = 0.05

_SHIFT = 8  # fixed-point fractional bits for cv2.fillPoly
# cv2.fillPoly fills every pixel whose centre lies within about half a pixel *outside* the polygon
# (it rasterises edges inclusively). Insetting the polygon by this much (in supersampled pixels) makes
# the filled area an unbiased estimate of the polygon area (measured: residual < 0.03 px per unit
# perimeter for circles and ellipses of radius 10..60 px).
_FILL_INSET_PX = 0.48
_MAX_MASK_SAMPLES = 1 << 22  # largest supersampled mask (16 MB of float32)
_MASK_MARGIN = 8  # supersamples
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)


#: Where the simulated camera adds its pixel noise (RenderOptions.region).
REGIONS = ("full", "markers")
#: What the floor shows (RenderOptions.floor): one grey, or flightstack.sim_backend.scene.floor's tiles.
FLOORS = ("plain", "tiles")
#: Grey levels of a printed matte fiducial board's white paper and black cells as the camera sees them.
BOARD_WHITE = 225
BOARD_BLACK = 25
#: Points per edge of a fiducial board's outline (its edges bend under lens distortion).
_BOARD_EDGE_POINTS = 32
#: Pixels by which the noisy rectangle of region "markers" extends beyond the painted markers: more than
#: marker extraction's window around a blob (flightstack.vision.markers: dilation 3 + ring 2, + 1 when
#: it searches a frame shrunk by 2, + 1 for the shrunk pixel's size).
ROI_MARGIN_PX = 10


@dataclass(frozen=True)
class RenderOptions:
    """How the simulated camera paints the markers.

    marker_radius_m: physical disc radius (metres).
    background_rgb: the floor colour; grey (low saturation) so that no marker threshold fires.
    noise_std: standard deviation of additive Gaussian pixel noise, on the 0..255 scale.
    blur_px: motion-blur length in pixels along blur_dir_rad (0 = none).
    blur_dir_rad: blur direction in the image, radians from the +u axis towards +v.
    supersample: anti-aliasing factor (samples per pixel per axis).
    floor: "plain" (background_rgb) or "tiles" (flightstack.sim_backend.scene.floor; needs the camera's pose,
        `render_markers_region`'s floor argument, else the floor is plain).
    region: where the pixel noise is added. "full": every pixel. "markers": only in the rectangle
        around the painted markers (grown by ROI_MARGIN_PX and the blur), with exactly the random
        numbers the full frame would have drawn there (the generator is advanced past the rest); the
        rest of the frame is the plain background and the frame says so (`render_markers_region`'s
        roi), so marker extraction gives the same bits as on the fully noisy frame, faster.
    """

    marker_radius_m: float = 0.03
    background_rgb: tuple[int, int, int] = (90, 90, 90)
    noise_std: float = 0.0
    blur_px: float = 0.0
    blur_dir_rad: float = 0.0
    supersample: int = 4
    region: str = "full"
    floor: str = "plain"

    def __post_init__(self) -> None:
        if self.region not in REGIONS:
            raise ValueError(f"region must be one of {', '.join(REGIONS)}, got {self.region!r}")
        if self.floor not in FLOORS:
            raise ValueError(f"floor must be one of {', '.join(FLOORS)}, got {self.floor!r}")
        if not (self.marker_radius_m > 0 and math.isfinite(self.marker_radius_m)):
            raise ValueError(f"marker_radius_m must be > 0, got {self.marker_radius_m}")
        if not (self.noise_std >= 0 and self.blur_px >= 0):
            raise ValueError("noise_std and blur_px must be >= 0")
        if not (isinstance(self.supersample, int) and 1 <= self.supersample <= 16):
            raise ValueError(f"supersample must be an integer in 1..16, got {self.supersample}")


def _clip_polygon(P: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Sutherland–Hodgman step: keep the part of the closed polygon P (n, d) where the signed value s ≥ 0."""
    inside = s >= 0.0
    if inside.all():
        return P
    if not inside.any():
        return P[:0]
    Pn = np.roll(P, -1, axis=0)
    sn = np.roll(s, -1)
    cross = inside != (sn >= 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, s / (s - sn), 0.0)
    n, d = P.shape
    out = np.empty((2 * n, d))
    keep = np.empty(2 * n, dtype=bool)
    out[0::2] = P
    keep[0::2] = inside
    out[1::2] = P + t[:, None] * (Pn - P)
    keep[1::2] = cross
    return out[keep]


def _densify(P: np.ndarray, max_step: float) -> np.ndarray:
    """Insert points on the edges of the closed polygon P (n, 2) so that no edge is longer than max_step."""
    Pn = np.roll(P, -1, axis=0)
    k = np.maximum(1, np.ceil(np.linalg.norm(Pn - P, axis=1) / max_step).astype(int))
    if (k == 1).all():
        return P
    idx = np.repeat(np.arange(len(P)), k)
    start = np.cumsum(k) - k
    t = (np.arange(idx.size) - start[idx]) / k[idx]
    return P[idx] + t[:, None] * (Pn[idx] - P[idx])


def _distort(xy: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """Pixels (n, 2) of normalised undistorted points xy (n, 2) (x/z, y/z) through K and the distortion."""
    pts = np.empty((len(xy), 3))
    pts[:, :2] = xy
    pts[:, 2] = 1.0
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
    return px.reshape(-1, 2)


_CLIP_RECT_CACHE: dict[tuple[object, ...], tuple[float, float, float, float]] = {}


def _normalised_clip_rect(cal: CameraCalibration) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) in the undistorted normalised plane, enclosing the whole image.

    The image outline (pixel area [−½, W − ½] × [−½, H − ½]) is undistorted and its bounding box widened
    by a margin; the margin shrinks until the distorted rectangle lies entirely outside the image, so
    anything clipped away is invisible and distortion is only evaluated where it is well behaved.
    """
    K = np.asarray(cal.camera_matrix, dtype=float)
    dist = np.asarray(cal.dist_coeffs, dtype=float).reshape(-1)
    key = (cal.width, cal.height, K.tobytes(), dist.tobytes())
    rect = _CLIP_RECT_CACHE.get(key)
    if rect is not None:
        return rect
    W, H = cal.width, cal.height
    us = np.linspace(-0.5, W - 0.5, 65)
    vs = np.linspace(-0.5, H - 0.5, 49)
    border = np.concatenate(
        [
            np.c_[us, np.full_like(us, -0.5)],
            np.c_[us, np.full_like(us, H - 0.5)],
            np.c_[np.full_like(vs, -0.5), vs],
            np.c_[np.full_like(vs, W - 0.5), vs],
        ]
    )
    xy = cv2.undistortPoints(border.reshape(-1, 1, 2), K, dist, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = hi - lo
    rect = (lo[0] - span[0], hi[0] + span[0], lo[1] - span[1], hi[1] + span[1])  # last resort, see below
    for margin in (0.25, 0.15, 0.08, 0.04, 0.02, 0.01):
        x0, y0 = lo - margin * span
        x1, y1 = hi + margin * span
        outline = _densify(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), 0.005 * span.max())
        px = _distort(outline, cal)
        outside = (px[:, 0] < -0.5) | (px[:, 0] > W - 0.5) | (px[:, 1] < -0.5) | (px[:, 1] > H - 0.5)
        if outside.all():
            rect = (float(x0), float(x1), float(y0), float(y1))
            break
    else:  # pathological distortion: clip at the undistorted image outline itself
        rect = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    _CLIP_RECT_CACHE[key] = rect
    return rect


def _line_kernel(length_px: float, direction_rad: float) -> np.ndarray:
    """Normalised motion-blur kernel: a segment of the given length (pixels) centred on the kernel centre."""
    half = math.ceil(length_px / 2.0) + 1
    k = 2 * half + 1
    kern = np.zeros((k, k), dtype=np.float64)
    n = max(32, int(16 * math.ceil(length_px)))
    t = (np.arange(n) + 0.5) / n * length_px - length_px / 2.0
    x = half + t * math.cos(direction_rad)
    y = half + t * math.sin(direction_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, w in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        np.add.at(kern, (y0 + dy, x0 + dx), w)
    return (kern / kern.sum()).astype(np.float32)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _disc_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to the unit vector `normal`."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _cross(normal, helper)
    e1 /= math.sqrt(float(e1 @ e1))
    return e1, _cross(normal, e1)


def _blur_boxes(image: np.ndarray, kern: np.ndarray, boxes: list[tuple[int, int, int, int]]) -> np.ndarray:
    """cv2.filter2D of the whole image (BORDER_REPLICATE), in place, only where it can differ from the input.

    Outside the painted boxes the frame is the uniform background, which a normalised kernel leaves
    unchanged, so each box grown by the kernel radius is filtered from a source grown by another radius.
    """
    H, W = image.shape[:2]
    h = kern.shape[0] // 2
    patches = []
    for x0, y0, x1, y1 in boxes:  # all patches from the unblurred image first (boxes may overlap)
        ox0, oy0, ox1, oy1 = max(0, x0 - h), max(0, y0 - h), min(W, x1 + h), min(H, y1 + h)
        sx0, sy0, sx1, sy1 = max(0, ox0 - h), max(0, oy0 - h), min(W, ox1 + h), min(H, oy1 + h)
        blurred = cv2.filter2D(image[sy0:sy1, sx0:sx1], -1, kern, borderType=cv2.BORDER_REPLICATE)
        patches.append((oy0, oy1, ox0, ox1, blurred[oy0 - sy0 : oy1 - sy0, ox0 - sx0 : ox1 - sx0]))
    for oy0, oy1, ox0, ox1, patch in patches:
        image[oy0:oy1, ox0:ox1] = patch
    return image


_GAUSS_QUANTILES: np.ndarray | None = None
_NOISE_TABLES: dict[float, np.ndarray] = {}


def _noise_table(std: float) -> np.ndarray:
    """(65536,) int16: round(std · Φ⁻¹((k + ½)/65536)), the noise of the 16-bit random value k."""
    global _GAUSS_QUANTILES
    table = _NOISE_TABLES.get(std)
    if table is None:
        if _GAUSS_QUANTILES is None:
            from scipy.special import ndtri

            _GAUSS_QUANTILES = ndtri((np.arange(65536) + 0.5) / 65536.0)
        table = np.clip(np.round(std * _GAUSS_QUANTILES), -32768, 32767).astype(np.int16)
        if len(_NOISE_TABLES) < 16:
            _NOISE_TABLES[std] = table
    return table


def _gaussian_noise_int16(rng: np.random.Generator, n: int, std: float) -> np.ndarray:
    """n samples of round(N(0, std²)) as int16, from 16 random bits each through a table of 65536 quantiles.

    Exact Gaussian quantiles (truncated at ±4.2σ), about 4× faster than rng.standard_normal; the integer
    rounding is exact for an integer image: round(I + ε) = I + round(ε).
    """
    idx = rng.bit_generator.random_raw((n + 3) // 4).view(np.uint16)[:n]
    return np.take(_noise_table(std), idx)


def _noise_span(rng: np.random.Generator, n: int, e0: int, e1: int, std: float) -> np.ndarray:
    """Elements e0 .. e1 − 1 of `_gaussian_noise_int16(rng, n, std)`, leaving `rng` where that call
    leaves it: the words before and after the span are skipped with the bit generator's `advance`
    (PCG64's, O(log n)) when it has one, else drawn and dropped."""
    bits = rng.bit_generator
    w0, w1, total = e0 // 4, (e1 + 3) // 4, (n + 3) // 4
    advance = getattr(bits, "advance", None)
    if advance is None:
        return _gaussian_noise_int16(rng, n, std)[e0:e1]
    if w0 > 0:
        advance(w0)
    raw = bits.random_raw(w1 - w0).view(np.uint16)[e0 - 4 * w0 : e1 - 4 * w0]
    if total > w1:
        advance(total - w1)
    return np.take(_noise_table(std), raw)


_QUIET_CACHE: dict[tuple[object, ...], bool] = {}


def _noise_never_fires(
    cal: CameraCalibration, backgrounds: tuple[tuple[int, int, int], ...], amplitude: int
) -> bool:
    """Whether no background pixel (any of `backgrounds`, RGB) with noise of at most `amplitude` grey levels
    per channel is inside any marker's colour box (flightstack.vision.markers.fires): checked on every
    such pixel, cached."""
    key = (tuple(cal.markers), backgrounds, amplitude)
    quiet = _QUIET_CACHE.get(key)
    if quiet is None:
        from flightstack.vision.markers import fires

        d = np.arange(-amplitude, amplitude + 1)
        cube = np.stack(np.meshgrid(d, d, d, indexing="ij"), axis=-1).reshape(-1, 3)
        grid = (cube[None, :, :] + np.array(backgrounds)[:, None, :]).reshape(-1, 3)
        quiet = not fires(np.clip(grid, 0, 255).astype(np.uint8), cal)
        _QUIET_CACHE[key] = quiet
    return quiet


@dataclass(frozen=True)
class NormalisedGrid:
    """The undistorted normalised coordinates (x/z, y/z) in Σc of a calibration's pixel centres, float32.

    padded: (H + 2, W + 2, 2), of every pixel centre from −1 to W (columns) and −1 to H (rows): entry
    [i + 1, j + 1] is pixel (row i, column j); pixels: (H, W, 2), the image's own (a contiguous copy);
    bounds: (x_min, x_max, y_min, y_max) of `pixels`; coarse: (H/2, W/2, 2) for an image of even size
    at least FLOOR_COARSE_PX, at pixels (2i + ½, 2j + ½), where cv2.resize (INTER_LINEAR) by 2 puts the
    centres of its samples; else None.
    """

    padded: np.ndarray
    pixels: np.ndarray
    bounds: tuple[float, float, float, float]
    coarse: np.ndarray | None = None


FLOOR_COARSE_PX = 640 * 480
"""A frame of at least this many pixels (and of even size) has its floor sampled on every second pixel and
interpolated (cv2.resize, bilinear): the floor's finest detail is about 1 cm, a forward camera 960 × 720 px
wide sees 1 cm over 7 px at 1 m; the downward 320 × 240 camera samples every pixel."""

_GRID_CACHE: dict[tuple[object, ...], NormalisedGrid] = {}


def normalised_grid(cal: CameraCalibration) -> NormalisedGrid:
    """The calibration's NormalisedGrid, computed once (cv2.undistortPoints, iterated to 1e-12); read-only."""
    K = np.asarray(cal.camera_matrix, dtype=float)
    dist = np.asarray(cal.dist_coeffs, dtype=float).reshape(-1)
    key = (cal.width, cal.height, K.tobytes(), dist.tobytes())
    grid = _GRID_CACHE.get(key)
    if grid is None:
        us, vs = np.meshgrid(
            np.arange(-1, cal.width + 1, dtype=float), np.arange(-1, cal.height + 1, dtype=float)
        )
        px = np.stack([us, vs], axis=-1).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(px, K, dist, criteria=_UNDISTORT_CRITERIA).reshape((*us.shape, 2))
        padded = np.ascontiguousarray(xy, dtype=np.float32)
        pixels = np.ascontiguousarray(padded[1:-1, 1:-1])
        padded.setflags(write=False)
        pixels.setflags(write=False)
        x, y = pixels[:, :, 0], pixels[:, :, 1]
        coarse = None
        W, H = cal.width, cal.height
        if W * H >= FLOOR_COARSE_PX and W % 2 == 0 and H % 2 == 0:
            cu, cv = np.meshgrid(np.arange(W // 2) * 2.0 + 0.5, np.arange(H // 2) * 2.0 + 0.5)
            cpx = np.stack([cu, cv], axis=-1).reshape(-1, 1, 2)
            cxy = cv2.undistortPoints(cpx, K, dist, criteria=_UNDISTORT_CRITERIA).reshape((*cu.shape, 2))
            coarse = np.ascontiguousarray(cxy, dtype=np.float32)
            coarse.setflags(write=False)
        grid = NormalisedGrid(
            padded, pixels, (float(x.min()), float(x.max()), float(y.min()), float(y.max())), coarse
        )
        if len(_GRID_CACHE) >= 8:
            _GRID_CACHE.clear()
        _GRID_CACHE[key] = grid
    return grid


def _background(
    cal: CameraCalibration, opts: RenderOptions, floor: FloorView | None
) -> tuple[np.ndarray, tuple[tuple[int, int, int], ...]]:
    """The frame before anything is painted on it, (H, W) grey or (H, W, 3) RGB uint8, and the RGB colours
    it can hold (for the `markers` region's promise)."""
    W, H = int(cal.width), int(cal.height)
    if opts.floor == "tiles" and floor is not None:
        grid = normalised_grid(cal)
        if grid.coarse is None:
            grey = floor_image(grid.pixels, floor, grid.bounds)
        else:
            grey = cv2.resize(
                floor_image(grid.coarse, floor, grid.bounds), (W, H), interpolation=cv2.INTER_LINEAR
            )
        lo, hi = grey_range()
        colours = tuple((g, g, g) for g in range(max(0, lo), min(255, hi) + 1))
        image = grey if cal.grey else np.ascontiguousarray(np.repeat(grey[:, :, None], 3, axis=2))
        return image, colours
    if cal.grey:
        r, g, b = opts.background_rgb
        level = round(0.299 * r + 0.587 * g + 0.114 * b)
        return np.full((H, W), level, dtype=np.uint8), ((level, level, level),)
    row = np.tile(np.asarray(opts.background_rgb, dtype=np.uint8), W)
    image = np.ascontiguousarray(np.broadcast_to(row, (H, 3 * W))).reshape(H, W, 3)
    return image, (tuple(int(c) for c in opts.background_rgb),)  # type: ignore[return-value]


def markers_in_camera(
    g_i0: Pose, P0: np.ndarray, R_ic: np.ndarray, t_ic: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(centres_c, normals_c), both (m, 3), of the target's markers in the camera frame Σc (metres).

    g_i0: the target's pose in the drone's body frame (FLU, metres, radians); P0: (m, 3) marker centres
    in the target's frame; R_ic, t_ic: the camera's mount (columns = Σc axes in the body frame) and its
    offset (m, body frame). The discs lie flat on the target (normal = the target's z axis).
    """
    centres_c = marker_centres_in_camera(g_i0, P0, R_ic, t_ic)
    normals_c = np.tile(R_ic.T @ rot_z(g_i0.theta) @ np.array([0.0, 0.0, 1.0]), (len(P0), 1))
    return centres_c, normals_c


def marker_centres_in_camera(g_i0: Pose, P0: np.ndarray, R_ic: np.ndarray, t_ic: np.ndarray) -> np.ndarray:
    """The centres_c of `markers_in_camera` alone (m, 3): the markers' centres in Σc (metres)."""
    return ((P0 @ rot_z(g_i0.theta).T + g_i0.p) - t_ic) @ R_ic


def render_markers(
    cal: CameraCalibration,
    centres_c: np.ndarray,
    normals_c: np.ndarray | None,
    opts: RenderOptions,
    rng: np.random.Generator | None = None,
    floor: FloorView | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, true_px, in_view) of `render_markers_region` (its documentation)."""
    image, true_px, in_view, _ = render_markers_region(cal, centres_c, normals_c, opts, rng, floor)
    return image, true_px, in_view


def render_markers_region(
    cal: CameraCalibration,
    centres_c: np.ndarray,
    normals_c: np.ndarray | None,
    opts: RenderOptions,
    rng: np.random.Generator | None = None,
    floor: FloorView | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int, int] | None]:
    """Paint the target's disc markers, or its fiducial board, into a simulated camera frame.

    centres_c: (m, 3) the feature points in the camera frame Σc (metres), in the calibration's order: the
        disc centres (cal.markers), or the fiducial's corners (m = 4, cal.fiducial.corners).
    normals_c: (m, 3) disc normals in Σc (any length, either sign), or None: each disc faces the camera
        (normal along the line of sight to its centre). Unused for a fiducial (its corners span its plane).
    opts: radius, background, floor, blur, noise, supersampling.
    rng: source of the pixel noise (only used when opts.noise_std > 0; None: a fresh default_rng()).
    floor: the camera's pose over the floor (flightstack.sim_backend.scene.floor.floor_view), for opts.floor
        "tiles"; None: a plain floor.

    Returns
        image: (H, W, 3) uint8 RGB, or (H, W) uint8 for a grey camera (cal.grey).
        true_px: (m, 2) ground truth, cv2.projectPoints of each centre (corner) with K and the distortion
            (pixels, OpenCV convention); NaN for a point on or behind the camera plane (z ≤ 0).
        in_view: (m,) bool, the point is in front of the camera (z > 0.05 m) AND the whole disc (the
            whole board with its quiet zone) is inside the image without reaching its outermost
            row/column of pixels (every outline point in [½, W − 3/2] × [½, H − 3/2]), so an unblurred
            in-view marker never touches the border.
        roi: with opts.region "markers", the rectangle (x0, y0, x1, y1) (pixels, end exclusive; empty
            when nothing was painted) outside which the frame shows no marker: for discs, only floor,
            which no marker's colour box accepts, with or without the noise
            (flightstack.vision.markers.extract_markers' `roi`); for a fiducial, the board and its quiet
            zone lie inside it, ROI_MARGIN_PX from its edges (its detector searches the whole frame). None
            with region "full" or when that cannot be promised (then the whole frame is noisy, as with
            "full").

    Discs are drawn far to near (painter's order by centre depth); discs behind the camera are not drawn,
    discs partly outside the image are drawn clipped; so is the board. Raises ValueError when the shapes
    do not match the calibration's feature points or a marker has no `rgb` paint colour.
    """
    m = cal.feature_count
    centres = np.asarray(centres_c, dtype=float)
    if centres.shape != (m, 3):
        raise ValueError(
            f"centres_c: expected shape ({m}, 3) for {m} calibration feature points, got {centres.shape}"
        )
    if not np.all(np.isfinite(centres)):
        raise ValueError("centres_c must be finite")
    W, H = int(cal.width), int(cal.height)
    K = np.asarray(cal.camera_matrix, dtype=float)
    dist = np.asarray(cal.dist_coeffs, dtype=float).reshape(-1)
    image, backgrounds = _background(cal, opts, floor)

    true_px = np.full((m, 2), np.nan)
    front = centres[:, 2] > 0.0
    if front.any():
        px, _ = cv2.projectPoints(centres[front], np.zeros(3), np.zeros(3), K, dist)
        true_px[front] = px.reshape(-1, 2)
    if cal.fiducial is not None:
        in_view, boxes = _paint_board(image, cal, centres, opts)
    else:
        in_view, boxes = _paint_discs(image, cal, centres, normals_c, opts)

    grow = ROI_MARGIN_PX
    if opts.blur_px > 0.0 and boxes:
        kern = _line_kernel(opts.blur_px, opts.blur_dir_rad)
        image = _blur_boxes(image, kern, boxes)
        grow += kern.shape[0] // 2
    roi: tuple[int, int, int, int] | None = None
    if opts.region == "markers":
        amplitude = int(np.abs(_noise_table(opts.noise_std)).max()) if opts.noise_std > 0.0 else 0
        if cal.fiducial is not None or _noise_never_fires(cal, backgrounds, amplitude):
            if boxes:
                b = np.array(boxes)
                roi = (
                    max(0, int(b[:, 0].min()) - grow),
                    max(0, int(b[:, 1].min()) - grow),
                    min(W, int(b[:, 2].max()) + grow),
                    min(H, int(b[:, 3].max()) + grow),
                )
            else:
                roi = (0, 0, 0, 0)
    if opts.noise_std > 0.0:
        gen = rng if rng is not None else np.random.default_rng()
        if roi is None:
            noisy = _gaussian_noise_int16(gen, image.size, opts.noise_std).reshape(image.shape)
            noisy += image
            np.clip(noisy, 0, 255, out=noisy)
            image = noisy.astype(np.uint8)
        else:  # the rows of the rectangle drawn, the rest of the frame's draws skipped
            x0, y0, x1, y1 = roi
            y1 = max(y0, y1)
            ch = 1 if image.ndim == 2 else 3
            band = _noise_span(gen, image.size, y0 * W * ch, y1 * W * ch, opts.noise_std)
            if x1 > x0 and y1 > y0:
                view = image.reshape(H, W, ch)
                patch = band.reshape(y1 - y0, W, ch)[:, x0:x1] + view[y0:y1, x0:x1]
                np.clip(patch, 0, 255, out=patch)
                view[y0:y1, x0:x1] = patch
    return image, true_px, in_view, roi


def _project_outline(
    P: np.ndarray, cal: CameraCalibration, rect: tuple[float, float, float, float]
) -> tuple[np.ndarray | None, bool]:
    """The pixels (n, 2) of the closed 3-D outline P (n, 3) in Σc, clipped against the near plane and the
    normalised rectangle `rect` (x0, x1, y0, y1) before distortion, and whether it was clipped; None when
    nothing of it is left or the distortion gives non-finite pixels."""
    rx0, rx1, ry0, ry1 = rect
    clipped = False
    if P[:, 2].min() < NEAR_PLANE_M:
        P = _clip_polygon(P, P[:, 2] - NEAR_PLANE_M)
        clipped = True
        if len(P) < 3:
            return None, clipped
    xy = P[:, :2] / P[:, 2:3]
    for axis, bound, sign in ((0, rx0, 1.0), (0, rx1, -1.0), (1, ry0, 1.0), (1, ry1, -1.0)):
        vals = sign * (xy[:, axis] - bound)
        if vals.min() < 0.0:
            xy = _clip_polygon(xy, vals)
            clipped = True
            if len(xy) < 3:
                break
    if len(xy) < 3:
        return None, clipped
    if clipped:  # straight clip edges must stay straight-ish after distortion
        xy = _densify(xy, 0.01 * max(rx1 - rx0, ry1 - ry0))
    poly = _distort(xy, cal)
    if not np.all(np.isfinite(poly)):
        return None, clipped
    return poly, clipped


def _pixel_box(poly: np.ndarray, W: int, H: int) -> tuple[int, int, int, int] | None:
    """The pixel box (x0, y0, x1, y1), end exclusive, that can receive any coverage from the polygon
    (pixel k covers [k − ½, k + ½]); None when it is empty."""
    lo = poly.min(axis=0)
    hi = poly.max(axis=0)
    bx0 = max(0, math.floor(lo[0] + 0.5))
    by0 = max(0, math.floor(lo[1] + 0.5))
    bx1 = min(W, math.floor(hi[0] + 0.5) + 1)
    by1 = min(H, math.floor(hi[1] + 0.5) + 1)
    if bx1 <= bx0 or by1 <= by0:
        return None
    return bx0, by0, bx1, by1


def _inside(poly: np.ndarray, W: int, H: int) -> bool:
    """Every outline point in [½, W − 3/2] × [½, H − 3/2] (pixels)."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    return bool(lo[0] >= 0.5 and lo[1] >= 0.5 and hi[0] <= W - 1.5 and hi[1] <= H - 1.5)


def _paint_discs(
    image: np.ndarray,
    cal: CameraCalibration,
    centres: np.ndarray,
    normals_c: np.ndarray | None,
    opts: RenderOptions,
) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """Paint the colour discs into the RGB `image` in place: (in_view (m,), the painted pixel boxes)."""
    markers = cal.markers
    m = len(markers)
    missing = [mk.name for mk in markers if mk.rgb is None]
    if missing:
        raise ValueError(f"markers without an rgb paint colour: {', '.join(missing)}")
    if m and image.ndim != 3:
        raise ValueError("colour markers need a colour camera (the calibration's image is grey)")
    if normals_c is None:
        normals = -centres
    else:
        normals = np.asarray(normals_c, dtype=float)
        if normals.shape != (m, 3):
            raise ValueError(f"normals_c: expected shape ({m}, 3), got {normals.shape}")
    norms = np.linalg.norm(normals, axis=1)
    if not np.all(np.isfinite(norms)) or np.any(norms < 1e-12):
        raise ValueError(
            "normals_c must be finite and non-zero (and centres_c non-zero when normals_c is None)"
        )
    normals = normals / norms[:, None]
    W, H = int(cal.width), int(cal.height)
    in_view = np.zeros(m, dtype=bool)
    boxes: list[tuple[int, int, int, int]] = []
    s = opts.supersample
    rect = _normalised_clip_rect(cal)
    r = opts.marker_radius_m
    for j in np.argsort(-centres[:, 2], kind="stable"):  # far first
        c = centres[j]
        # boundary polygon of the circle; its vertices sit on a slightly larger circle so that the
        # polygon has exactly the disc's area (an inscribed polygon would be (2π/N)²/6 too small)
        z_ref = max(float(c[2]), r)
        n_pts = int(min(512, max(64, 2.0 * math.pi * math.sqrt(max(cal.fx, cal.fy) * r / z_ref) * 4)))
        dphi = 2.0 * math.pi / n_pts
        r_eq = r * math.sqrt(dphi / math.sin(dphi))
        phi = np.arange(n_pts) * dphi
        e1, e2 = _disc_basis(normals[j])
        P = c + r_eq * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        poly, clipped = _project_outline(P, cal, rect)
        if poly is None:
            continue
        if not clipped and c[2] > MIN_IN_VIEW_DEPTH_M:
            in_view[j] = _inside(poly, W, H)
        pbox = _pixel_box(poly, W, H)
        if pbox is None:
            continue
        bx0, by0, bx1, by1 = pbox
        # supersampling factor, lowered for a disc so near that its box would need a huge mask (its edge
        # pixels are then a negligible part of its area)
        ss = min(s, max(1, math.isqrt(_MAX_MASK_SAMPLES // ((bx1 - bx0) * (by1 - by0)))))
        # supersampled coordinates: sub-pixel k of the box has its centre at pixel bx0 − ½ + (k + ½)/ss
        q = (poly - (bx0, by0) + 0.5) * ss - 0.5
        # inset by the fill rule's half-pixel inflation; (d_y, −d_x) is the outward vertex normal of a
        # polygon with positive signed area 2A = Σ x_i y_{i+1} − y_i x_{i+1}
        d = np.roll(q, -1, axis=0) - np.roll(q, 1, axis=0)
        nrm = np.c_[d[:, 1], -d[:, 0]]
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-12)[:, None]
        area2 = np.dot(q[:, 0], np.roll(q[:, 1], -1)) - np.dot(q[:, 1], np.roll(q[:, 0], -1))
        q = q - (_FILL_INSET_PX if area2 > 0 else -_FILL_INSET_PX) * nrm
        bw, bh = bx1 - bx0, by1 - by0
        qi = np.round(q * (1 << _SHIFT)).astype(np.int32)
        # fillPoly rasterises the edges it clips slightly differently within ~3 samples of the mask
        # edge, so the mask gets _MASK_MARGIN extra samples on every side, cropped after the fill (the
        # offset is in the same fixed-point units as the points)
        mask = np.zeros((bh * ss + 2 * _MASK_MARGIN, bw * ss + 2 * _MASK_MARGIN), dtype=np.float32)
        cv2.fillPoly(mask, [qi], 1.0, cv2.LINE_8, _SHIFT, (_MASK_MARGIN << _SHIFT, _MASK_MARGIN << _SHIFT))
        mask = mask[_MASK_MARGIN:-_MASK_MARGIN, _MASK_MARGIN:-_MASK_MARGIN]
        alpha = mask if ss == 1 else cv2.resize(mask, (bw, bh), interpolation=cv2.INTER_AREA)
        box = image[by0:by1, bx0:bx1].astype(np.float32)
        box += alpha[:, :, None] * (np.asarray(markers[j].rgb, dtype=np.float32) - box)
        image[by0:by1, bx0:bx1] = np.clip(box + 0.5, 0.0, 255.0).astype(np.uint8)
        boxes.append(pbox)
    return in_view, boxes


_BOARD_TEXELS_PER_CELL = 16
"""Resolution of the board's texture (texels per marker cell): the cells' edges fall on texel edges."""
_MAX_BOARD_SAMPLES = 1 << 18
"""The board's supersampling is lowered towards 2 × 2 a pixel to keep its samples at most this many (a board
250 px wide, a forward camera's at 0.85 m, gets 2 × 2; its cells are then 25 px); below 2 × 2 only for a
box so large that its mask would exceed _MAX_MASK_SAMPLES (its edges alias then)."""


@functools.lru_cache(maxsize=8)
def _board_texture(fid: Fiducial) -> tuple[np.ndarray, int, int]:
    """(texture, quiet zone in texels, texels per cell): the board as (N, N, 2) float32 texels holding
    (grey level, 1), BOARD_WHITE paper around the marker's cells (BOARD_BLACK / BOARD_WHITE)."""
    from flightstack.vision.fiducial import marker_cells

    k = _BOARD_TEXELS_PER_CELL
    cells = marker_cells(fid)
    n = cells.shape[0]
    quiet = round(fid.quiet_zone_m / fid.side_m * n * k)
    grey = np.where(cells > 127, np.float32(BOARD_WHITE), np.float32(BOARD_BLACK))
    tex = np.full((n * k + 2 * quiet, n * k + 2 * quiet, 2), 1.0, dtype=np.float32)
    tex[:, :, 0] = BOARD_WHITE
    tex[quiet : quiet + n * k, quiet : quiet + n * k, 0] = np.kron(grey, np.ones((k, k), dtype=np.float32))
    tex.setflags(write=False)
    return tex, quiet, k * n


def _paint_board(
    image: np.ndarray, cal: CameraCalibration, corners: np.ndarray, opts: RenderOptions
) -> tuple[np.ndarray, list[tuple[int, int, int, int]]]:
    """Paint the fiducial board (marker and quiet zone) whose marker corners are `corners` (4, 3) (Σc, m;
    feature-point order) into `image` in place: (in_view (4,), [its pixel box] or [])."""
    from flightstack.vision.fiducial import corner_points

    fid = cal.fiducial
    assert fid is not None
    W, H = int(cal.width), int(cal.height)
    A = corner_points(fid, corners)  # row k: ArUco corner k (0 top-left, clockwise)
    e_u, e_v = A[1] - A[0], A[3] - A[0]  # along the top edge, down the left edge
    tex, quiet, per_unit = _board_texture(fid)
    lo_, hi_ = -quiet / per_unit, 1.0 + quiet / per_unit  # the board's extent in (u, v)
    t = np.linspace(0.0, 1.0, _BOARD_EDGE_POINTS, endpoint=False)
    span = hi_ - lo_
    uv = np.concatenate(
        [
            np.c_[lo_ + span * t, np.full_like(t, lo_)],
            np.c_[np.full_like(t, hi_), lo_ + span * t],
            np.c_[hi_ - span * t, np.full_like(t, hi_)],
            np.c_[np.full_like(t, lo_), hi_ - span * t],
        ]
    )
    outline = A[0] + uv[:, :1] * e_u + uv[:, 1:] * e_v
    poly, clipped = _project_outline(outline, cal, _normalised_clip_rect(cal))
    in_view = np.zeros(4, dtype=bool)
    if poly is None:
        return in_view, []
    if not clipped and corners[:, 2].min() > MIN_IN_VIEW_DEPTH_M:
        in_view[:] = _inside(poly, W, H)
    pbox = _pixel_box(poly, W, H)
    if pbox is None:
        return in_view, []
    bx0, by0, bx1, by1 = pbox
    bw, bh = bx1 - bx0, by1 - by0
    ss = min(opts.supersample, max(2, math.isqrt(_MAX_BOARD_SAMPLES // (bw * bh))))
    ss = min(ss, max(1, math.isqrt(_MAX_MASK_SAMPLES // (bw * bh))))
    # the box's sub-samples: cv2.resize (INTER_LINEAR, half-pixel centres) of the padded grid's pixels
    # bx0 − 1 .. bx1 puts sample d at bx0 − 1 + (d + ½)/ss − ½; dropping ss on each side leaves pixel k's
    # ss samples at k − ½ + (i + ½)/ss
    padded = normalised_grid(cal).padded[by0 : by1 + 2, bx0 : bx1 + 2]
    samples = cv2.resize(padded, ((bw + 2) * ss, (bh + 2) * ss), interpolation=cv2.INTER_LINEAR)
    samples = np.ascontiguousarray(samples[ss:-ss, ss:-ss])
    # (x, y, 1) ∝ M (u, v, 1) with M = [e_u | e_v | A0]; texel t = quiet + u · per_unit − ½ (cv2.remap's
    # nearest texel j covers t ∈ (j − ½, j + ½], so texel j covers u ∈ [(j − quiet)/per_unit, … + 1/per_unit))
    M = np.column_stack([e_u, e_v, A[0]])
    to_texel = np.array([[per_unit, 0.0, quiet - 0.5], [0.0, per_unit, quiet - 0.5], [0.0, 0.0, 1.0]])
    G = to_texel @ np.linalg.inv(M)
    texels = cv2.perspectiveTransform(samples, G)
    sampled = cv2.remap(tex, texels, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if outline[:, 2].min() <= NEAR_PLANE_M:  # rays that meet the board's plane behind the camera see nothing
        depth = cv2.transform(samples, np.linalg.inv(M)[2:, :2].astype(np.float32)).reshape(samples.shape[:2])
        sampled[depth + np.float32(np.linalg.inv(M)[2, 2]) <= 0.0] = 0.0
    if ss > 1:
        sampled = cv2.resize(sampled, (bw, bh), interpolation=cv2.INTER_AREA)
    value, cover = sampled[:, :, 0] * sampled[:, :, 1], sampled[:, :, 1]
    box = image[by0:by1, bx0:bx1].astype(np.float32)
    if box.ndim == 3:
        cover, value = cover[:, :, None], value[:, :, None]
    box = box * (1.0 - cover) + value
    image[by0:by1, bx0:bx1] = np.clip(box + 0.5, 0.0, 255.0).astype(np.uint8)
    return in_view, [pbox]


def true_pixels(cal: CameraCalibration, points_c: np.ndarray) -> np.ndarray:
    """(m, 2) where the points points_c (m, 3) of Σc (metres) lie in the image of `cal` (its intrinsics
    and distortion, pixels, OpenCV convention); NaN for a point on or behind the camera plane. The truth
    a rendered frame carries (hal.Frame.truth_px)."""
    zero = np.zeros(3)
    pts = np.ascontiguousarray(points_c, dtype=float).reshape(-1, 1, 3)
    px, _ = cv2.projectPoints(pts, zero, zero, cal.camera_matrix, cal.dist_coeffs)
    out = px.reshape(-1, 2).astype(float)
    out[np.asarray(points_c)[:, 2] <= 1e-3] = np.nan
    return out
