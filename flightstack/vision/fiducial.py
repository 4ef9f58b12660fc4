"""The target's ArUco fiducial: its cells, where its corners sit on the target, and its detection.

A camera whose calibration declares a `fiducial` (flightstack.vision.camera_file.Fiducial) finds the target
by one OpenCV ArUco marker instead of colour discs: a grey, IR-sensitive camera (the Tello EDU's downward
one) sees black and white, not hue. The marker's four corners are the paper's m = 4 feature points p0^j.

Corners. OpenCV numbers a marker's corners 0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left of the
upright printed marker (clockwise as one looks at it). `Fiducial.corners[j]` names the corner that is
feature point j, so `detect_fiducial` returns pixels in feature-point order. The marker lies flat on the
target, printed side up (normal along the target's +z), its corner k at the feature point j with
corners[j] = k: with the marker's own axes x right (corner 0 → 1) and y up (corner 3 → 0), x × y is the
target's +z. `placement_problem` checks this of an experiment's feature points: the four must be the
corners of a square of side `side_m`, level, in that order. paper_experiment's square (0.1, 0.1),
(−0.1, 0.1), (−0.1, −0.1), (0.1, −0.1) at z = 0.15 m (x forward, y left) takes corners [1, 0, 3, 2]: the
marker's top edge faces the robot's left (+y), its corner 0 at the rear left.

Detection (`detect_fiducial`): cv2.aruco.ArucoDetector on the grey image (an RGB frame is converted with
cv2.COLOR_RGB2GRAY), corners refined to sub-pixel by cv2.cornerSubPix (CORNER_REFINE_SUBPIX). Pixels are in
the distorted image (OpenCV convention: u right, v down, origin at the centre of the top-left pixel);
`normalized` are the undistorted normalised coordinates in Σc (flightstack.vision.markers.normalise).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from flightstack.vision.camera_file import FIDUCIAL_CORNERS, CameraCalibration, Fiducial
from flightstack.vision.markers import MarkerDetection, normalise

BORDER_BITS = 1
"""Cells of the black border on each side of the marker's bits (OpenCV's default)."""
MIN_PERIMETER_PX = 40.0
"""Candidate quadrilaterals with a shorter perimeter (pixels) are ignored: below 10 px a side the cells
(6 across for a 4×4 dictionary) are under 2 px and cannot be read."""
REFINE_WIN_PX = 5
"""Half-width (pixels) of cv2.cornerSubPix's window (OpenCV caps it at 0.3 cell:
relativeCornerRefinmentWinSize)."""
REFINE_ACCURACY_PX = 0.01
"""cv2.cornerSubPix stops when a corner moves less than this (pixels), or after REFINE_ITERATIONS."""
REFINE_ITERATIONS = 50
NOT_FOUND = ": not found"
"""How `detect_fiducial`'s rejection of a frame without the marker ends (the agent then tracks it)."""
PLACEMENT_TOLERANCE_M = 1e-3
"""How far (m) the experiment's feature points may be from the fiducial's square (placement_problem)."""


@functools.lru_cache(maxsize=8)
def dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined ArUco dictionary `name` (e.g. "DICT_4X4_50")."""
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@functools.lru_cache(maxsize=8)
def _cells(name: str, ident: int) -> np.ndarray:
    d = dictionary(name)
    n = d.markerSize + 2 * BORDER_BITS
    cells = cv2.aruco.generateImageMarker(d, ident, n, borderBits=BORDER_BITS)
    cells.setflags(write=False)
    return cells


def marker_cells(fid: Fiducial) -> np.ndarray:
    """The marker's cells, border included: (n, n) uint8, 0 black and 255 white, row 0 at the top edge
    (corners 0 → 1) of the upright marker, column 0 at its left edge (corners 0 → 3); read-only."""
    return _cells(fid.dictionary, fid.id)


def corner_points(fid: Fiducial, feature_points: np.ndarray) -> np.ndarray:
    """(4, k) the feature points (4, k) in ArUco corner order: row c is the feature point of corner c."""
    pts = np.asarray(feature_points, dtype=float)
    out = np.empty_like(pts)
    out[list(fid.corners)] = pts
    return out


def placement_problem(fid: Fiducial, feature_points: np.ndarray) -> str | None:
    """Why the experiment's feature points (m, 3) (target frame, m) cannot be the corners of the fiducial
    lying flat, printed side up, its corner corners[j] at point j; None when they can (within
    PLACEMENT_TOLERANCE_M)."""
    pts = np.asarray(feature_points, dtype=float)
    if pts.shape != (FIDUCIAL_CORNERS, 3):
        return f"a fiducial's corners are {FIDUCIAL_CORNERS} feature points, the experiment has {len(pts)}"
    q = corner_points(fid, pts)
    side, tol = fid.side_m, PLACEMENT_TOLERANCE_M
    x_axis, y_axis = q[1] - q[0], q[0] - q[3]  # the marker's right and up
    ideal = q[0] + np.array([np.zeros(3), x_axis, x_axis - y_axis, -y_axis])
    edges = [float(np.linalg.norm(q[(k + 1) % 4] - q[k])) for k in range(4)]
    normal = np.cross(x_axis, y_axis)
    if (
        max(abs(e - side) for e in edges) > tol
        or float(np.linalg.norm(q - ideal, axis=1).max()) > tol
        or abs(float(x_axis @ y_axis)) > tol * side
    ):
        return (
            f"the feature points are not a square of side {side:g} m (edges "
            f"{', '.join(f'{e:.3f}' for e in edges)} m in the order of fiducial.corners): the fiducial's "
            "side_m or the experiment's target.feature_points is wrong"
        )
    if normal[2] < (1.0 - 1e-3) * side * side:
        return (
            "the fiducial's corners would put it upside down or not level on the target (its corner "
            "order must run clockwise seen from above: fix fiducial.corners)"
        )
    return None


def _detector(fid: Fiducial, image_side_px: int) -> cv2.aruco.ArucoDetector:
    """A detector for `fid` whose size limits are in pixels whatever the searched image's size (px)."""
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.cornerRefinementWinSize = REFINE_WIN_PX
    p.cornerRefinementMinAccuracy = REFINE_ACCURACY_PX
    p.cornerRefinementMaxIterations = REFINE_ITERATIONS
    p.markerBorderBits = BORDER_BITS
    p.minMarkerPerimeterRate = min(1.0, MIN_PERIMETER_PX / max(1, image_side_px))
    return cv2.aruco.ArucoDetector(dictionary(fid.dictionary), p)


def grey_image(image: np.ndarray) -> np.ndarray:
    """The image as grey H × W uint8: itself when grey, cv2.COLOR_RGB2GRAY of an RGB H × W × 3 one.
    Raises ValueError for another dtype or shape."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise ValueError(f"image must be a uint8 numpy array, got {getattr(image, 'dtype', type(image))}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    raise ValueError(f"image must have shape (H, W) or (H, W, 3), got {image.shape}")


def detect_fiducial(image: np.ndarray, cal: CameraCalibration) -> MarkerDetection:
    """Find the calibration's fiducial in a frame: its 4 corners in feature-point order, refined to sub-pixel.

    image: (cal.height, cal.width) grey or (cal.height, cal.width, 3) RGB, uint8. The whole frame is
    searched (0.3 ms at 320 × 240, 1.9 ms at 960 × 720); a renderer's roi (hal.Frame.roi) is not needed.
    Returns the corners' pixels and normalised coordinates (areas None), or a rejection naming why: the
    marker not found, or found more than once. Raises ValueError for a wrong dtype, shape or size, or a
    calibration without a fiducial.
    """
    fid = cal.fiducial
    if fid is None:
        raise ValueError("the calibration declares no fiducial")
    grey = grey_image(image)
    H, W = grey.shape
    if (cal.width, cal.height) != (W, H):
        raise ValueError(f"image is {W}x{H} but the calibration is for {cal.width}x{cal.height}")
    what = f"fiducial {fid.id} ({fid.dictionary})"
    corners, ids, _ = _detector(fid, max(W, H)).detectMarkers(grey)
    found = [] if ids is None else [k for k, i in enumerate(ids.reshape(-1)) if int(i) == fid.id]
    if not found:
        return MarkerDetection.rejected(f"{what}{NOT_FOUND}")
    if len(found) > 1:
        return MarkerDetection.rejected(f"{what}: seen {len(found)} times")
    quad = np.asarray(corners[found[0]], dtype=float).reshape(FIDUCIAL_CORNERS, 2)
    refined = refine_by_edges(grey, quad, cal, int(marker_cells(fid).shape[0]))
    pixels = (quad if refined is None else refined)[list(fid.corners)]
    if not np.all(np.isfinite(pixels)):
        return MarkerDetection.rejected(f"{what}: corner refinement failed")
    return MarkerDetection(pixels, normalise(pixels, cal), None, None)


EDGE_SPAN = (0.15, 0.85)
"""The part of each side (fractions of its length from its first corner) whose edge is measured: clear of
the corners, where the neighbouring side's edge would enter the profile."""
EDGE_STEP_PX = 0.25
"""Spacing of an edge profile's samples (pixels)."""
EDGE_REACH_CELLS = 0.45
"""An edge profile reaches this far (cells) to either side: within the black border cell inside, within the
quiet zone (≥ 1 cell wide) outside."""
EDGE_MAX_SHIFT_PX = 1.5
"""A corner the edge lines move farther than this (pixels) from ArUco's is not trusted: ArUco's is kept."""


def refine_by_edges(
    grey: np.ndarray,
    quad: np.ndarray,
    cal: CameraCalibration,
    cells: int,
    max_shift_px: float = EDGE_MAX_SHIFT_PX,
) -> np.ndarray | None:
    """The marker's corners (4, 2) (pixels, ArUco order) as the intersections of its four sides' edge lines.

    Why: cv2.cornerSubPix pulls the corner of a blurred square towards its inside (measured on rendered
    frames: 0.13 px on average at 10 px cells, up to 1 px at 25 px cells). A side is a straight line on the
    board's plane, so it is straight in the undistorted normalised image: along the middle of each side
    (EDGE_SPAN), profiles across the edge (± EDGE_REACH_CELLS, bilinear samples EDGE_STEP_PX apart) give the
    edge's position by the area under the normalised profile, (I − I_in)/(I_out − I_in), which a symmetric
    blur or anti-aliasing does not move; the edge points are undistorted and fitted with a line (total least
    squares); adjacent lines meet at the corners, which are distorted back to pixels (cv2.projectPoints).
    None when a side has too few usable profiles (low contrast, the marker cut by the image border), or a
    corner would move more than max_shift_px (px) from `quad`'s.
    """
    H, W = grey.shape
    centre = quad.mean(axis=0)
    side_px = float(np.mean([np.linalg.norm(quad[(k + 1) % 4] - quad[k]) for k in range(4)]))
    reach = EDGE_REACH_CELLS * side_px / cells
    if reach < 1.0:
        return None
    offsets = np.arange(-reach, reach + 1e-9, EDGE_STEP_PX)
    lo = np.maximum(np.floor(quad.min(axis=0) - reach - 2.0), 0).astype(int)  # the profiles' window
    hi = np.minimum(np.ceil(quad.max(axis=0) + reach + 3.0), (W, H)).astype(int)
    image = grey[lo[1] : hi[1], lo[0] : hi[0]].astype(np.float32)
    lines = []
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        direction = (b - a) / np.linalg.norm(b - a)
        normal = np.array([-direction[1], direction[0]])
        if normal @ ((a + b) / 2 - centre) < 0:
            normal = -normal  # outwards: from the black border into the white quiet zone
        n_pts = max(8, int(np.linalg.norm(b - a) * (EDGE_SPAN[1] - EDGE_SPAN[0])))
        t = np.linspace(*EDGE_SPAN, n_pts)
        base = a + t[:, None] * (b - a)
        pts = base[:, None, :] + offsets[None, :, None] * normal
        inside = (pts[..., 0] >= 0) & (pts[..., 0] <= W - 1) & (pts[..., 1] >= 0) & (pts[..., 1] <= H - 1)
        keep = inside.all(axis=1)
        if keep.sum() < 5:
            return None
        pts = (pts[keep] - lo).astype(np.float32)
        prof = cv2.remap(image, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR).astype(float)
        m = max(1, round(0.5 / EDGE_STEP_PX))
        lo_level, hi_level = prof[:, :m].mean(axis=1), prof[:, -m:].mean(axis=1)
        contrast = hi_level - lo_level
        ok = contrast > 20.0
        if ok.sum() < 5:
            return None
        frac = np.clip((prof[ok] - lo_level[ok, None]) / contrast[ok, None], 0.0, 1.0)
        area = np.trapezoid(frac, offsets, axis=1)
        edge = base[keep][ok] + (offsets[-1] - area)[:, None] * normal
        xy = normalise(edge, cal)
        mean = xy.mean(axis=0)
        _, vecs = np.linalg.eigh(np.cov((xy - mean).T))
        n_line = vecs[:, 0]  # the least-spread direction: the line is n_line · p = n_line · mean
        lines.append((n_line, float(n_line @ mean)))
    corners_n = np.empty((4, 2))
    for k in range(4):  # corner k is where side k − 1 (into it) meets side k (out of it)
        (n1, d1), (n2, d2) = lines[(k - 1) % 4], lines[k]
        A = np.array([n1, n2])
        if abs(np.linalg.det(A)) < 1e-9:
            return None
        corners_n[k] = np.linalg.solve(A, [d1, d2])
    refined = distorted_pixels(corners_n, cal)
    if not np.all(np.isfinite(refined)) or np.linalg.norm(refined - quad, axis=1).max() > max_shift_px:
        return None
    return refined


TRACK_MAX_SHIFT_PX = 6.0
"""How far (pixels) one pass of `track_fiducial` may move a corner: the edge profiles reach 0.45 cell to
either side of the expected side (4.5 px at 10 px cells), and a few passes walk farther."""
TRACK_PASSES = 4
"""Passes of `track_fiducial`'s side refinement at most; it stops once no corner moves TRACK_SETTLED_PX."""
TRACK_SETTLED_PX = 0.05
TRACK_MAX_CELLS_WRONG = 1
"""Cells of the marker (border included: 36 for a 4×4 dictionary) that may read wrong at the tracked
corners: concealment may grey a cell of the board; a square that is not the marker (a uniform floor tile)
reads about half of them wrong by chance."""
CELL_SAMPLES = 10
"""Pixels a cell spans in the marker warped upright for reading (`cells_wrong`); its middle 4 are read."""


def cells_wrong(grey: np.ndarray, quad: np.ndarray, fid: Fiducial) -> int:
    """How many of the marker's cells (border included) read wrong in `grey` with its corners at `quad`
    (4, 2 px, ArUco order): the marker warped upright, each cell's mean over its middle against the
    midpoint of the means of the cells that should be black and white."""
    cells = marker_cells(fid)
    n, c = cells.shape[0], CELL_SAMPLES
    square = np.array([[0, 0], [n * c, 0], [n * c, n * c], [0, n * c]], dtype=np.float32)
    H = cv2.getPerspectiveTransform(np.asarray(quad, dtype=np.float32), square)
    upright = cv2.warpPerspective(grey, H, (n * c, n * c), flags=cv2.INTER_LINEAR).astype(float)
    means = upright.reshape(n, c, n, c)[:, 3 : c - 3, :, 3 : c - 3].mean(axis=(1, 3))
    white = cells == 255
    threshold = (means[white].mean() + means[~white].mean()) / 2
    return int(np.sum((means > threshold) != white))


def distorted_pixels(normalized: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """(k, 2) pixels of the distorted image of undistorted normalised coordinates (k, 2) (x/z, y/z)."""
    pts3 = np.column_stack([np.asarray(normalized, dtype=float), np.ones(len(normalized))])
    px, _ = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
    return px.reshape(-1, 2)


def track_fiducial(image: np.ndarray, expected_px: np.ndarray, cal: CameraCalibration) -> MarkerDetection:
    """The fiducial found from where it is expected, when `detect_fiducial` did not find it.

    A frame decoded through a lost datagram often shows the board with its outline notched or a cell or two
    greyed: ArUco's candidate stage (a contour with four vertices) then misses a board whose sides are still
    straight (benchmarks/concealed_frames.py: most misses). From `expected_px` (4, 2: the feature points'
    pixels where the detection gate expects them, distorted image, feature-point order) the sides are
    measured as `refine_by_edges` measures them, up to TRACK_PASSES passes of at most TRACK_MAX_SHIFT_PX,
    and the result is kept only if the marker's own code reads at the new corners, in the orientation
    expected, with at most TRACK_MAX_CELLS_WRONG cells wrong. What it finds is a detection like any other:
    the caller gates it. Returns the corners (feature-point order) or a rejection naming why.
    """
    fid = cal.fiducial
    if fid is None:
        raise ValueError("the calibration declares no fiducial")
    grey = grey_image(image)
    what = f"fiducial {fid.id} ({fid.dictionary})"
    quad = np.empty((FIDUCIAL_CORNERS, 2))
    quad[list(fid.corners)] = np.asarray(expected_px, dtype=float).reshape(FIDUCIAL_CORNERS, 2)
    H, W = grey.shape
    if (
        not np.all(np.isfinite(quad))
        or quad.min() < 0
        or quad[:, 0].max() > W - 1
        or quad[:, 1].max() > H - 1
    ):
        return MarkerDetection.rejected(f"{what}{NOT_FOUND}")  # expected (partly) outside: nothing to look at
    cells = int(marker_cells(fid).shape[0])
    for _ in range(TRACK_PASSES):
        refined = refine_by_edges(grey, quad, cal, cells, TRACK_MAX_SHIFT_PX)
        if refined is None:
            return MarkerDetection.rejected(f"{what}: not found, nor its sides where expected")
        moved = float(np.linalg.norm(refined - quad, axis=1).max())
        quad = refined
        if moved < TRACK_SETTLED_PX:
            break
    if cells_wrong(grey, quad, fid) > TRACK_MAX_CELLS_WRONG:
        return MarkerDetection.rejected(f"{what}: not found, nor its code where expected")
    pixels = quad[list(fid.corners)]
    return MarkerDetection(pixels, normalise(pixels, cal), None, None)


__all__ = [
    "BORDER_BITS",
    "NOT_FOUND",
    "TRACK_MAX_CELLS_WRONG",
    "TRACK_MAX_SHIFT_PX",
    "cells_wrong",
    "corner_points",
    "detect_fiducial",
    "dictionary",
    "distorted_pixels",
    "grey_image",
    "marker_cells",
    "placement_problem",
    "refine_by_edges",
    "track_fiducial",
]
