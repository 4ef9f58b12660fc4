"""Intrinsics from detected views: OpenCV calibration, per-view errors, outlier views, the verdict.

Model: OpenCV's pinhole camera K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels) with distortion
(k1, k2, p1, p2, k3) (k3 fixed at 0 with `fix_k3`), fitted by cv2.calibrateCameraExtended to all views
at once. A view's error is the RMS (px) of its reprojection residuals; the calibration's RMS is over
all points of all kept views.

Outliers: while the worst view's error exceeds max(outlier_factor × median view error,
outlier_floor_px) and more than min_views remain, that view is dropped and the fit repeated.

Refusals (SolveError, nothing is written):
* fewer than min_views usable views (`kind` "input");
* degenerate geometry (`kind` "degenerate"): the board normals of all views lie within
  min_spread_deg of each other (boards seen from one direction only, e.g. all head-on: the focal
  length is then not observable, whatever the residuals say), or the fit's standard deviation of fx or
  fy exceeds max_rel_std of its value, or that of cx or cy exceeds max_rel_std of the image
  width/height (the views do not constrain the intrinsics);
* RMS above max_rms_px (`kind` "verdict").
RMS above warn_rms_px gives the verdict "warning" (written, with a warning), else "good".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class SolveOptions:
    min_views: int = 6
    outlier_factor: float = 3.0
    outlier_floor_px: float = 0.25
    warn_rms_px: float = 1.0
    max_rms_px: float = 3.0
    max_rel_std: float = 0.05
    min_spread_deg: float = 10.0
    fix_k3: bool = False


@dataclass(frozen=True)
class View:
    """One usable view: name, image points (n, 2) px, object points (n, 3) m (board frame)."""

    name: str
    image_points: np.ndarray
    object_points: np.ndarray


@dataclass
class SolveResult:
    rms_px: float
    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    std_intrinsics: np.ndarray  # (4,) standard deviations of fx, fy, cx, cy (px)
    used: list[tuple[str, float]]  # (view name, RMS px) of the views in the final fit
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (view name, reason)
    verdict: str = "good"  # good | warning
    message: str = ""


class SolveError(ValueError):
    """The views cannot give a trustworthy calibration; `kind` is input, degenerate or verdict."""

    def __init__(self, kind: str, message: str, rejected: list[tuple[str, str]] | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.rejected = rejected or []


def _fit(views: list[View], size: tuple[int, int], flags: int) -> tuple:
    obj = [v.object_points.reshape(-1, 1, 3).astype(np.float32) for v in views]
    img = [v.image_points.reshape(-1, 1, 2).astype(np.float32) for v in views]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    # the stubs require cameraMatrix/distCoeffs arrays; None lets OpenCV allocate them (no intrinsic guess)
    rms, K, dist, rvecs, _, std_in, _, per_view = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
        obj, img, size, None, None, flags=flags, criteria=criteria
    )
    normals = np.array([cv2.Rodrigues(np.asarray(r, dtype=float))[0][:, 2] for r in rvecs])
    return (
        float(rms),
        K,
        dist.reshape(-1),
        np.asarray(std_in).reshape(-1)[:4],
        np.asarray(per_view).reshape(-1),
        normals,
    )


def normal_spread_deg(normals: np.ndarray) -> float:
    """Largest angle (degrees) between the board normals (n, 3) of any two views (sign-free)."""
    cos = np.clip(np.abs(normals @ normals.T), 0.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def calibrate_views(views: list[View], image_size: tuple[int, int], opts: SolveOptions) -> SolveResult:
    """Fit the intrinsics of a (width, height) px camera to `views`; raises SolveError on refusal."""
    W, H = image_size
    if len(views) < opts.min_views:
        raise SolveError(
            "input",
            f"only {len(views)} usable view(s); at least {opts.min_views} distinct, sharp views of the "
            "pattern are needed (--min-views)",
        )
    flags = cv2.CALIB_FIX_K3 if opts.fix_k3 else 0
    kept = list(views)
    rejected: list[tuple[str, str]] = []
    while True:
        try:
            rms, K, dist, std, per_view, normals = _fit(kept, (W, H), flags)
        except cv2.error as exc:
            raise SolveError(
                "degenerate", f"OpenCV calibration failed: {exc.msg.strip()}", rejected
            ) from None
        median = float(np.median(per_view))
        worst = int(np.argmax(per_view))
        limit = max(opts.outlier_factor * median, opts.outlier_floor_px)
        if per_view[worst] <= limit or len(kept) <= opts.min_views:
            break
        rejected.append(
            (
                kept[worst].name,
                f"outlier: reprojection error {per_view[worst]:.2f} px > {limit:.2f} px "
                f"(max of {opts.outlier_factor:g} x median {median:.2f} px, {opts.outlier_floor_px:g} px)",
            )
        )
        kept.pop(worst)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SolveError("degenerate", "the fit returned a non-physical camera matrix", rejected)
    spread = normal_spread_deg(normals)
    if spread < opts.min_spread_deg:
        raise SolveError(
            "degenerate",
            f"degenerate views: all boards face the same way (their normals lie within {spread:.1f} deg of "
            f"each other, need {opts.min_spread_deg:g} deg); show the board tilted (20-45 deg) in several "
            "directions",
            rejected,
        )
    rel = np.array([std[0] / K[0, 0], std[1] / K[1, 1], std[2] / W, std[3] / H])
    if not np.all(np.isfinite(rel)) or np.any(rel > opts.max_rel_std):
        raise SolveError(
            "degenerate",
            "degenerate views: the intrinsics are not constrained "
            f"(std fx {std[0]:.1f} px, fy {std[1]:.1f} px, cx {std[2]:.1f} px, cy {std[3]:.1f} px; "
            f"limit {opts.max_rel_std:.0%}); show the board tilted (20-45 deg) in several directions and "
            "across the whole image",
            rejected,
        )
    if rms > opts.max_rms_px:
        raise SolveError(
            "verdict",
            f"reprojection RMS {rms:.3f} px exceeds --max-rms {opts.max_rms_px:g} px; check the pattern "
            "sizes, focus and that the board is flat",
            rejected,
        )
    used = [(v.name, float(e)) for v, e in zip(kept, per_view, strict=True)]
    if rms > opts.warn_rms_px:
        verdict = "warning"
        message = f"RMS {rms:.3f} px is above {opts.warn_rms_px:g} px: usable, but recalibrating is advised"
    else:
        verdict, message = "good", f"RMS {rms:.3f} px (<= {opts.warn_rms_px:g} px)"
    return SolveResult(rms, K, dist, std, used, rejected, verdict, message)
