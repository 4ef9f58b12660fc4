"""HSV thresholds for the target's coloured markers, picked from regions of sample frames (no GUI).

For each marker the user gives a region (pixels: x, y of the top-left corner, width, height) of one
sample frame that contains the marker. In the region, pixels with saturation ≥ _MIN_SAT and value ≥
_MIN_VAL are "coloured"; the peak of their (circular, smoothed) hue histogram is the marker's hue, and
the coloured pixels within _PEAK_HALF_WIDTH of it are the marker's pixels. The thresholds (OpenCV HSV:
H 0..179, S and V 0..255) are their 1st..99th hue percentiles widened by a margin, and a lower S and V
bound at a fraction of their 5th percentiles; S and V upper bounds are 255. The `rgb` paint colour is
the marker pixels' mean colour.

The thresholds are then verified with the mission's own extractor
(flightstack.vision.markers.extract_markers):
every sample must show exactly one blob per marker, i.e. exactly m blobs. If a sample fails, a few
wider and narrower variants are tried (VARIANTS); the first one that passes on every sample is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.vision.camera_file import CameraCalibration, MarkerColour
from flightstack.vision.markers import extract_markers

_MIN_SAT = 50
_MIN_VAL = 40
_PEAK_HALF_WIDTH = 20  # hue units (0..179)
_MIN_MARKER_PX = 6
#: (hue margin in hue units, fraction of the 5th S/V percentile used as the lower S/V bound), in the
#: order they are tried.
VARIANTS = ((6, 0.5), (10, 0.5), (6, 0.7), (14, 0.35), (3, 0.8))


class MarkerPickError(ValueError):
    """A region that does not show a usable marker; the message names the marker and the region."""


@dataclass(frozen=True)
class Region:
    """A marker's sample region: pixels (x, y top-left, w, h) in sample frame `frame` (index)."""

    name: str
    x: int
    y: int
    w: int
    h: int
    frame: int = 0

    @staticmethod
    def parse(text: str) -> Region:
        """'NAME=X,Y,W,H' or 'NAME=X,Y,W,H@FRAME' (pixels; FRAME is the sample index, default 0)."""
        try:
            name, rest = text.split("=", 1)
            frame = 0
            if "@" in rest:
                rest, f = rest.split("@", 1)
                frame = int(f)
            x, y, w, h = (int(v) for v in rest.split(","))
        except ValueError:
            raise ValueError(f"--marker {text!r}: expected NAME=X,Y,W,H[@FRAME] (pixels)") from None
        if not name.strip() or w <= 0 or h <= 0 or x < 0 or y < 0 or frame < 0:
            raise ValueError(f"--marker {text!r}: a name, x, y >= 0 and w, h > 0 are required")
        return Region(name.strip(), x, y, w, h, frame)

    def describe(self) -> str:
        return f"{self.name}={self.x},{self.y},{self.w},{self.h}@{self.frame}"


@dataclass(frozen=True)
class MarkerSample:
    """The marker pixels of one region: hue peak, hue offsets (n,) to it, S (n,), V (n,), mean RGB."""

    name: str
    hue_peak: int
    hue_offsets: np.ndarray
    sat: np.ndarray
    val: np.ndarray
    rgb: tuple[int, int, int]


def sample_marker(image_rgb: np.ndarray, region: Region) -> MarkerSample:
    """Collect the marker's pixels in `region` of an RGB uint8 frame; MarkerPickError if there are none."""
    H, W = image_rgb.shape[:2]
    x1, y1 = region.x + region.w, region.y + region.h
    if x1 > W or y1 > H:
        raise MarkerPickError(f"marker {region.describe()}: region exceeds the {W}x{H} frame")
    roi = np.ascontiguousarray(image_rgb[region.y : y1, region.x : x1])
    hsv = cv2.cvtColor(roi, cv2.COLOR_RGB2HSV).reshape(-1, 3).astype(int)
    coloured = (hsv[:, 1] >= _MIN_SAT) & (hsv[:, 2] >= _MIN_VAL)
    if coloured.sum() < _MIN_MARKER_PX:
        raise MarkerPickError(
            f"marker {region.describe()}: the region holds no coloured marker "
            f"({int(coloured.sum())} pixels with saturation >= {_MIN_SAT}); check the coordinates"
        )
    hist = np.bincount(hsv[coloured, 0], minlength=180)[:180].astype(float)
    smooth = sum(np.roll(hist, k) for k in range(-3, 4))
    peak = int(np.argmax(smooth))
    offsets = (hsv[:, 0] - peak + 90) % 180 - 90
    mine = coloured & (np.abs(offsets) <= _PEAK_HALF_WIDTH)
    if mine.sum() < _MIN_MARKER_PX:
        raise MarkerPickError(f"marker {region.describe()}: too few pixels of one colour in the region")
    rgb = roi.reshape(-1, 3)[mine]
    interior = hsv[mine, 1] >= np.median(hsv[mine, 1])
    mean_rgb = tuple(round(float(c)) for c in rgb[interior].mean(axis=0))
    return MarkerSample(region.name, peak, offsets[mine], hsv[mine, 1], hsv[mine, 2], mean_rgb)  # type: ignore[arg-type]


def thresholds(sample: MarkerSample, hue_margin: int, low_fraction: float) -> MarkerColour:
    """A MarkerColour from a sample: hue percentiles 1..99 ± hue_margin (hue units), lower S and V bounds
    at low_fraction × their 5th percentiles."""
    lo_off = float(np.percentile(sample.hue_offsets, 1)) - hue_margin
    hi_off = float(np.percentile(sample.hue_offsets, 99)) + hue_margin
    lo_off, hi_off = max(lo_off, -44.0), min(hi_off, 44.0)  # never wider than half the hue circle
    h_lo = int(np.floor(sample.hue_peak + lo_off)) % 180
    h_hi = int(np.ceil(sample.hue_peak + hi_off)) % 180
    s_lo = int(max(_MIN_SAT * 0.6, low_fraction * np.percentile(sample.sat, 5)))
    v_lo = int(max(_MIN_VAL * 0.6, low_fraction * np.percentile(sample.val, 5)))
    return MarkerColour(sample.name, (h_lo, s_lo, v_lo), (h_hi, 255, 255), sample.rgb)


def _hue_set(mk: MarkerColour) -> set[int]:
    lo, hi = mk.hsv_lo[0], mk.hsv_hi[0]
    return set(range(lo, hi + 1)) if lo <= hi else set(range(lo, 180)) | set(range(0, hi + 1))


def check_overlap(markers: tuple[MarkerColour, ...]) -> str | None:
    """A message if two markers' hue intervals share a hue value (they could not be told apart)."""
    for i, a in enumerate(markers):
        for b in markers[i + 1 :]:
            common = _hue_set(a) & _hue_set(b)
            if common:
                return f"markers '{a.name}' and '{b.name}' overlap in hue ({min(common)}..{max(common)})"
    return None


@dataclass
class MarkerPickResult:
    markers: tuple[MarkerColour, ...] | None
    per_frame: list[tuple[str, str | None]]  # (frame name, rejection reason or None) of the chosen variant
    message: str
    variant: tuple[int, float] | None = None


def verify(cal: CameraCalibration, frames: list[tuple[str, np.ndarray]]) -> list[tuple[str, str | None]]:
    """extract_markers on every (name, RGB frame): (name, None) when exactly the m markers are found."""
    return [(name, extract_markers(img, cal).reason) for name, img in frames]


def pick_markers(
    base: CameraCalibration, frames: list[tuple[str, np.ndarray]], regions: list[Region]
) -> MarkerPickResult:
    """Thresholds for `regions` (in the order given = the target's feature-point order) verified on `frames`.

    Raises MarkerPickError for an unusable region or overlapping colours. Returns markers None (with the
    best variant's per-frame reasons) when no variant finds exactly m blobs in every frame.
    """
    names = [r.name for r in regions]
    if len(set(names)) != len(names):
        raise MarkerPickError(f"--marker: duplicate marker names in {', '.join(names)}")
    samples = []
    for r in regions:
        if r.frame >= len(frames):
            raise MarkerPickError(f"marker {r.describe()}: there are only {len(frames)} sample frame(s)")
        samples.append(sample_marker(frames[r.frame][1], r))
    best: MarkerPickResult | None = None
    for margin, frac in VARIANTS:
        markers = tuple(thresholds(s, margin, frac) for s in samples)
        if check_overlap(markers):
            continue
        cal = CameraCalibration(**{**base.__dict__, "markers": markers})
        per_frame = verify(cal, frames)
        n_ok = sum(reason is None for _, reason in per_frame)
        if n_ok == len(frames):
            return MarkerPickResult(
                markers,
                per_frame,
                f"exactly {len(markers)} blobs in all {len(frames)} frames",
                (margin, frac),
            )
        if best is None or n_ok > sum(reason is None for _, reason in best.per_frame):
            best = MarkerPickResult(None, per_frame, "", (margin, frac))
    if best is None:
        overlap = check_overlap(tuple(thresholds(s, 3, 0.8) for s in samples))
        raise MarkerPickError(f"{overlap}; choose markers of more distinct colours")
    n_ok = sum(reason is None for _, reason in best.per_frame)
    best.message = (
        f"no thresholds find exactly {len(regions)} blobs in every frame "
        f"(best: {n_ok} of {len(frames)} frames)"
    )
    return best
