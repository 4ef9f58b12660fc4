"""The camera calibration wizard: frames → diverse sharp pattern views → intrinsics → calibration file.

`run_camera_wizard` reads frames from a source (flightstack.calibration.sources), finds the pattern in each
(flightstack.calibration.patterns), keeps a view only if it is sharp enough and not a near-duplicate of a
kept one
(flightstack.calibration.views), stops after `max_views` kept views, then fits the intrinsics with outlier
rejection (flightstack.calibration.solve). Every frame that was not used is reported with its reason. The
calibration (flightstack.vision.camera_file format, with the pattern and each view's error) is returned
only when the fit is trustworthy; `write_calibration` then writes it atomically.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

import cv2
import numpy as np

from flightstack.calibration.patterns import PatternDetector, PatternSpec
from flightstack.calibration.solve import SolveError, SolveOptions, View, calibrate_views
from flightstack.calibration.views import Coverage, edge_width_px, outline_distance, outline_in_image
from flightstack.vision.camera_file import CalibrationError, CameraCalibration, load_calibration

#: Exit codes of the calibrate commands.
EXIT_OK, EXIT_VERDICT, EXIT_BAD_INPUT = 0, 1, 2


@dataclass(frozen=True)
class CaptureOptions:
    """View selection. max_blur_px: largest accepted edge width (px, see flightstack.calibration.views);
    min_change: smallest outline change to every kept view, as a fraction of the image diagonal;
    max_views: stop capturing after this many kept views."""

    max_blur_px: float = 5.0
    min_change: float = 0.015
    max_views: int = 40


@dataclass
class WizardResult:
    """Outcome of the wizard. exit_code: 0 ok, 1 verdict failed (degenerate / RMS), 2 bad input."""

    exit_code: int
    message: str
    calibration: CameraCalibration | None = None
    verdict: str = "failed"
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (view, reason), in source order
    used: list[tuple[str, float]] = field(default_factory=list)  # (view, RMS px)
    frames_seen: int = 0
    coverage: Coverage | None = None


class _Outcome(TypedDict):
    """The WizardResult fields every outcome of the wizard reports."""

    rejected: list[tuple[str, str]]
    frames_seen: int
    coverage: Coverage | None


@dataclass
class _Capture:
    views: list[View] = field(default_factory=list)
    outlines: list[np.ndarray] = field(default_factory=list)
    rejected: list[tuple[str, str]] = field(default_factory=list)
    size: tuple[int, int] | None = None
    coverage: Coverage | None = None
    frames: int = 0
    found: int = 0


def _capture(
    source: object,
    detector: PatternDetector,
    opts: CaptureOptions,
    on_frame: Callable[[_Capture], None] | None,
) -> _Capture:
    cap = _Capture()
    outline_m = detector.spec.outline_m()
    for frame in source.frames():  # type: ignore[attr-defined]
        cap.frames += 1
        try:
            if frame.image is None:
                cap.rejected.append((frame.name, frame.error or "unreadable"))
                continue
            h, w = frame.image.shape[:2]
            if cap.size is None:
                cap.size = (w, h)
                cap.coverage = Coverage(w, h)
            elif cap.size != (w, h):
                cap.rejected.append(
                    (
                        frame.name,
                        f"image size {w}x{h} differs from the first image's {cap.size[0]}x{cap.size[1]}",
                    )
                )
                continue
            gray = cv2.cvtColor(frame.image, cv2.COLOR_RGB2GRAY)
            det = detector.detect(gray)
            if isinstance(det, str):
                cap.rejected.append((frame.name, f"pattern not found: {det}"))
                continue
            cap.found += 1
            blur = edge_width_px(gray, det.image_points)
            if blur > opts.max_blur_px:
                cap.rejected.append(
                    (frame.name, f"blurry: edge width {blur:.1f} px > {opts.max_blur_px:g} px (--max-blur)")
                )
                continue
            outline = outline_in_image(det.object_points, det.image_points, outline_m)
            diag = float(np.hypot(w, h))
            dists = [outline_distance(outline, o) for o in cap.outlines]
            if dists and min(dists) < opts.min_change * diag:
                j = int(np.argmin(dists))
                cap.rejected.append(
                    (
                        frame.name,
                        f"near-duplicate of {cap.views[j].name}: the board moved {min(dists) / diag:.1%} of "
                        f"the image diagonal < {opts.min_change:.1%} (--min-change)",
                    )
                )
                continue
            cap.views.append(View(frame.name, det.image_points, det.object_points))
            cap.outlines.append(outline)
            assert cap.coverage is not None
            cap.coverage.add(det.image_points)
        finally:
            if on_frame is not None:
                on_frame(cap)
        if len(cap.views) >= opts.max_views:
            break
    return cap


def run_camera_wizard(
    source: object,
    spec: PatternSpec,
    capture: CaptureOptions | None = None,
    solve: SolveOptions | None = None,
    device: str = "",
    on_frame: Callable[[_Capture], None] | None = None,
) -> WizardResult:
    """Calibrate from `source` (flightstack.calibration.sources); never raises on image content (see
    WizardResult)."""
    capture = capture or CaptureOptions()
    solve = solve or SolveOptions()
    cap = _capture(source, PatternDetector(spec), capture, on_frame)
    base: _Outcome = {"rejected": cap.rejected, "frames_seen": cap.frames, "coverage": cap.coverage}
    if cap.frames == 0:
        return WizardResult(EXIT_BAD_INPUT, "the source delivered no frames", **base)
    if cap.size is None:
        return WizardResult(EXIT_BAD_INPUT, f"none of the {cap.frames} frame(s) could be read", **base)
    if cap.found == 0:
        return WizardResult(
            EXIT_BAD_INPUT,
            f"the pattern ({spec.describe()}) was not found in any of the {cap.frames} frame(s); "
            "check --pattern, --cols and --rows",
            **base,
        )
    try:
        res = calibrate_views(cap.views, cap.size, solve)
    except SolveError as exc:
        code = EXIT_BAD_INPUT if exc.kind == "input" else EXIT_VERDICT
        return WizardResult(code, str(exc), **(base | {"rejected": cap.rejected + exc.rejected}))
    cal = CameraCalibration(
        width=cap.size[0],
        height=cap.size[1],
        camera_matrix=res.camera_matrix,
        dist_coeffs=res.dist_coeffs,
        rms_px=res.rms_px,
        device=device,
        date=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        pattern=spec.to_dict(),
        views=tuple(res.used),
    )
    return WizardResult(
        EXIT_OK,
        res.message,
        cal,
        res.verdict,
        cap.rejected + res.rejected,
        res.used,
        cap.frames,
        cap.coverage,
    )


def write_calibration(cal: CameraCalibration, out: str | Path) -> list[str]:
    """Write `cal` to `out` (YAML, or JSON for *.json) atomically. What an existing valid calibration file
    of the same image size at `out` says about the target and the stream (its marker colours or fiducial,
    its image kind and stream layout) is kept; returns notes about what was kept."""
    out = Path(out)
    notes: list[str] = []
    if out.exists():
        try:
            old = load_calibration(out)
        except CalibrationError:
            old = None
        if old is not None and (old.width, old.height) == (cal.width, cal.height):
            kept = {
                "markers": old.markers,
                "fiducial": old.fiducial,
                "image": old.image,
                "stream": old.stream,
            }
            cal = CameraCalibration(**{**cal.__dict__, **kept})
            if old.markers:
                notes.append(f"kept the {len(old.markers)} marker colour(s) already in {out}")
            if old.fiducial is not None:
                notes.append(
                    f"kept the fiducial (ArUco {old.fiducial.dictionary} id {old.fiducial.id}) in {out}"
                )
            if old.image != "colour" or old.stream is not None:
                notes.append(f"kept the image kind ({old.image}) and stream layout already in {out}")
    cal.save(out)
    return notes
