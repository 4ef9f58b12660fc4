"""Check a calibration on a sample image: what undistortion does to it, and (optionally) how well the
calibration explains a pattern seen in it.

Reported (pixels unless stated):
* the distortion's displacement: distance between each pixel of the image's outline and where the
  undistortion (same K) moves it, max and mean; 0 for a distortion-free camera;
* the field of view (degrees) between the undistorted edge midpoints;
* the valid region: the fraction of the image that cv2.getOptimalNewCameraMatrix(alpha=0) keeps;
* with a pattern found in the sample: its reprojection RMS after cv2.solvePnP with the calibration (an
  independent view, not used in the fit), and the straightness of the pattern's rows before and after
  undistortion (RMS distance of the points to each row's fitted line, px).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.calibration.patterns import PatternDetector, PatternSpec
from flightstack.vision.camera_file import CameraCalibration

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass
class CheckReport:
    max_shift_px: float
    mean_shift_px: float
    fov_deg: tuple[float, float]
    valid_fraction: float
    undistorted: np.ndarray  # RGB uint8, same size, same K (cv2.undistort)
    pattern_rms_px: float | None = None
    straightness_px: tuple[float, float] | None = None  # (before, after) undistortion
    pattern_note: str | None = None

    def lines(self) -> list[str]:
        out = [
            f"distortion displacement on the image outline: max {self.max_shift_px:.2f} px, "
            f"mean {self.mean_shift_px:.2f} px",
            f"field of view: {self.fov_deg[0]:.1f} deg horizontal, {self.fov_deg[1]:.1f} deg vertical",
            f"valid region after undistortion (alpha=0): {self.valid_fraction:.0%} of the image",
        ]
        if self.pattern_rms_px is not None:
            out.append(f"pattern in the sample: reprojection RMS {self.pattern_rms_px:.3f} px (solvePnP)")
        if self.straightness_px is not None:
            b, a = self.straightness_px
            out.append(
                f"pattern rows, RMS distance to a straight line: {b:.3f} px raw -> {a:.3f} px undistorted"
            )
        if self.pattern_note:
            out.append(self.pattern_note)
        return out


def _outline(W: int, H: int, step: int = 8) -> np.ndarray:
    xs = np.arange(0, W, step, dtype=float)
    ys = np.arange(0, H, step, dtype=float)
    return np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], 1),
            np.stack([xs, np.full_like(xs, H - 1)], 1),
            np.stack([np.zeros_like(ys), ys], 1),
            np.stack([np.full_like(ys, W - 1), ys], 1),
        ]
    )


def _undistort_px(pts: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(
        pts.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K, criteria=_CRITERIA
    ).reshape(-1, 2)


def _line_rms(points: np.ndarray, obj: np.ndarray) -> float:
    """RMS distance (px) of image points to the best line through each pattern row (same object y)."""
    res = []
    for y in np.unique(np.round(obj[:, 1], 9)):
        row = points[np.abs(obj[:, 1] - y) < 1e-9]
        if len(row) < 3:
            continue
        c = row - row.mean(axis=0)
        res.append(np.linalg.svd(c, full_matrices=False)[1][-1] ** 2 / len(row))
    return float(math.sqrt(np.mean(res))) if res else float("nan")


def check_calibration(
    cal: CameraCalibration, image_rgb: np.ndarray, spec: PatternSpec | None = None
) -> CheckReport:
    """Report on `cal` with one RGB uint8 sample of the calibrated size (ValueError if the size differs)."""
    H, W = image_rgb.shape[:2]
    if (cal.width, cal.height) != (W, H):
        raise ValueError(f"the sample is {W}x{H} but the calibration is for {cal.width}x{cal.height}")
    K = np.asarray(cal.camera_matrix, dtype=float)
    dist = np.asarray(cal.dist_coeffs, dtype=float)
    outline = _outline(W, H)
    shift = np.linalg.norm(_undistort_px(outline, K, dist) - outline, axis=1)
    mids = np.array([[0, cal.cy], [W - 1, cal.cy], [cal.cx, 0], [cal.cx, H - 1]], dtype=float)
    n = cv2.undistortPoints(mids.reshape(-1, 1, 2), K, dist, criteria=_CRITERIA).reshape(-1, 2)
    fov = (
        math.degrees(math.atan(-n[0, 0]) + math.atan(n[1, 0])),
        math.degrees(math.atan(-n[2, 1]) + math.atan(n[3, 1])),
    )
    _, roi = cv2.getOptimalNewCameraMatrix(K, dist, (W, H), 0.0)
    valid = roi[2] * roi[3] / float(W * H)
    undist = cv2.undistort(image_rgb, K, dist)
    rep = CheckReport(float(shift.max()), float(shift.mean()), fov, valid, undist)
    if spec is not None:
        det = PatternDetector(spec).detect(cv2.cvtColor(image_rgb, cv2.COLOR_RGB2GRAY))
        if isinstance(det, str):
            rep.pattern_note = f"pattern not found in the sample: {det}"
            return rep
        obj = det.object_points.astype(np.float64)
        img = det.image_points.astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist)
        if ok:
            proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
            rep.pattern_rms_px = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
        rep.straightness_px = (_line_rms(img, obj), _line_rms(_undistort_px(img, K, dist), obj))
    return rep
