"""Colour-marker feature extraction: image → marker centres → the observer's image features.

The same code runs on simulated frames (flightstack.sim_backend.scene.render) and on real camera frames.
Input is an RGB uint8 image of the calibrated size; output are the m marker centres in the order of
cal.markers (the order of the target's feature points p0^j):

* pixels: sub-pixel centres (u, v) in the distorted image (OpenCV convention: u right, v down, origin at
  the centre of the top-left pixel);
* normalized: undistorted normalised coordinates (x/z, y/z) of the centres in the camera frame Σc
  (z = optical axis, x right, y down), via cv2.undistortPoints;
* features_from_detection: the observer's measurement f = λ·[x1, y1, x2, y2, …] (flightstack.paper.projection:
  f^j = λ/z^j [x^j, y^j], λ in the observer's image-plane units).

Detection per marker (on the frame shrunk by `downscale` for large frames): HSV threshold (per-channel
look-up tables, equivalent to cv2.inRange with two hue ranges when the hue wraps), a 3×3 opening against
speckle, connected components, components smaller than min_area_px ignored; exactly one component
(at most max_blobs_per_colour) or the frame is rejected, and so is a blob at the image border.

Centre per marker, always at full resolution: an intensity-weighted centroid over the blob's
neighbourhood (the blob dilated by _DILATE_PX pixels). Each pixel's weight is its linear colour
membership w = max(0, (c − b)·û), û = (ĉ − b)/‖ĉ − b‖, with b the local background colour (median of
the window's outer frame) and ĉ the mean colour of the blob's interior. For a pixel that is a mix
c = α·marker + (1 − α)·b, w is proportional to the covered fraction α, so anti-aliased and blurred edge
pixels count fractionally and a centred (motion) blur does not move the centroid. Strongly saturated
pixels of a clearly different hue get weight 0, so a touching marker of another colour does not pull
the centroid. The same weights give the blob's coverage-weighted area.

Known limit (geometry, not the extractor): the centroid of a disc's image is not the image of its centre
when the disc is tilted against the image plane; the offset is about f·sin τ cos τ·(r/z)² pixels (τ the
tilt, r the disc radius, z the depth), e.g. 0.2 px for f = 920 px, τ = 5°, r/z = 0.05.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from flightstack.vision.camera_file import CameraCalibration, MarkerColour

#: Radius (pixels) by which a component is dilated to collect its anti-aliased / blurred edge pixels.
_DILATE_PX = 3
#: Extra window margin (pixels) beyond the dilation, where the local background colour is measured.
_RING_PX = 2
#: Pixels with HSV saturation ≥ this have a reliable hue; they must match the marker's hue range
#: widened by _HUE_SLACK (OpenCV hue units, 0..179) or get weight 0.
_HUE_GATE_SAT = 60
_HUE_SLACK = 12
#: A border pixel whose weight exceeds this fraction of a fully covered pixel's means the marker is cut.
_BORDER_WEIGHT_FRACTION = 0.25
_OPEN_KERNEL = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)


@dataclass(frozen=True)
class MarkerDetection:
    """Result of extract_markers (or of detect_fiducial) for one frame; either all m markers or a rejection
    with its reason.

    pixels: (m, 2) sub-pixel centres (u, v) in the distorted image (pixels), in cal.markers order; None if
        rejected.
    normalized: (m, 2) undistorted normalised coordinates (x/z, y/z) of the centres in the camera frame Σc
        (dimensionless), same order; None if rejected.
    reason: why the frame was rejected (names the marker), None if accepted.
    areas: (m,) coverage-weighted blob areas in px (Σ weights / weight of a fully covered pixel, ≈ the
        projected disc area, edge pixels counted fractionally); None if rejected, and for a fiducial's
        corners (flightstack.vision.fiducial), which have no area.
    """

    pixels: np.ndarray | None
    normalized: np.ndarray | None
    reason: str | None
    areas: np.ndarray | None

    @property
    def ok(self) -> bool:
        """True when every marker was found."""
        return self.reason is None and self.pixels is not None

    @staticmethod
    def rejected(reason: str) -> MarkerDetection:
        return MarkerDetection(None, None, reason, None)


@functools.lru_cache(maxsize=32)
def _membership_tables(markers: tuple[MarkerColour, ...]) -> list[tuple[range, np.ndarray]]:
    """Per group of ≤ 8 markers: look-up tables (3, 256) uint8 mapping an H, S or V value to the bit mask
    of the markers of that group whose HSV box accepts the value (bit j − group start for marker j).

    A pixel is inside marker j's box iff bit j is set in all three of LUT_H[h], LUT_S[s], LUT_V[v]; the
    hue interval wraps around when hsv_lo[0] > hsv_hi[0]. Three single-channel LUTs and two ANDs
    threshold all markers of a group at once, much cheaper than one cv2.inRange per marker.
    """
    groups = []
    for start in range(0, len(markers), 8):
        idx = range(start, min(start + 8, len(markers)))
        tab = np.zeros((3, 256), dtype=np.uint8)
        values = np.arange(256)
        for j in idx:
            mk = markers[j]
            bit = np.uint8(1 << (j - start))
            lo, hi = mk.hsv_lo, mk.hsv_hi
            hue_in = (
                (values >= lo[0]) | (values <= hi[0])
                if mk.hue_wraps
                else (values >= lo[0]) & (values <= hi[0])
            )
            tab[0, hue_in & (values <= 179)] |= bit
            tab[1, (values >= lo[1]) & (values <= hi[1])] |= bit
            tab[2, (values >= lo[2]) & (values <= hi[2])] |= bit
        groups.append((idx, tab))
    return groups


@functools.lru_cache(maxsize=64)
def _foreign_hue_table(mk: MarkerColour) -> np.ndarray:
    """LUT (256,) uint8: 1 for hue values farther than _HUE_SLACK from the marker's hue interval."""
    lo, hi = int(mk.hsv_lo[0]), int(mk.hsv_hi[0])
    width = (hi - lo) % 180
    d = (np.arange(256) - lo) % 180  # offset into the (possibly wrapping) interval on the hue circle
    dist = np.where(d <= width, 0, np.minimum(d - width, 180 - d))
    return (dist > _HUE_SLACK).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def _disc_kernel(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _weighted_centre(
    image: np.ndarray,
    hsv: np.ndarray,
    comp: np.ndarray,
    box: tuple[int, int, int, int],
    dilate_px: int,
    mk: MarkerColour,
) -> tuple[float, float, float, bool] | str:
    """Intensity-weighted centroid of a blob: (u, v) pixels, soft area (px), whether the border cuts it.

    comp: the blob's binary mask (uint8 0/1) over the window `box` = (x0, y0, x1, y1) of the full-resolution
    image, which extends at least dilate_px + _RING_PX beyond the mask unless clipped by the image.
    hsv: the HSV pixels of the same window. The background colour b is the median of the window's outer
    frame outside the dilated mask; the marker colour is the mean of the eroded mask (its fully covered
    interior). The soft area is Σw / w_full, the coverage-weighted pixel count. Returns a reason string
    when no centroid can be formed.
    """
    H, W = image.shape[:2]
    x0, y0, x1, y1 = box
    win = image[y0:y1, x0:x1]
    neigh = cv2.dilate(comp, _disc_kernel(dilate_px))
    outside = neigh == 0
    frame = [
        win[0][outside[0]],
        win[-1][outside[-1]],
        win[1:-1, 0][outside[1:-1, 0]],
        win[1:-1, -1][outside[1:-1, -1]],
    ]
    bg_px = np.concatenate(frame)
    if len(bg_px) < 3:  # the window is clipped by the image border: fall back to all pixels outside
        bg_px = win[outside]
    if len(bg_px) == 0:
        return f"marker '{mk.name}': no background around the blob"
    bg = np.median(bg_px, axis=0).astype(np.float32)
    interior = cv2.erode(comp, _OPEN_KERNEL)
    if not interior.any():
        interior = comp
    colour = np.array(cv2.mean(win, mask=interior)[:3], dtype=np.float32)
    direction = colour - bg
    w_full = float(np.linalg.norm(direction))
    if not w_full > 1.0:
        return f"marker '{mk.name}': no contrast against the background"
    u = direction / np.float32(w_full)
    # w = (c − b)·û, the colour membership, linear in the covered fraction of the pixel
    # cv2's stubs do not carry the dtype: the transform of a float32 image is float32
    w = cast(NDArray[np.float32], cv2.transform(win.astype(np.float32), u.reshape(1, 3))).reshape(
        win.shape[:2]
    )
    w -= np.float32(bg @ u)
    np.maximum(w, 0.0, out=w)
    w *= neigh
    foreign = cast(NDArray[np.uint8], cv2.LUT(hsv[:, :, 0], _foreign_hue_table(mk)))  # uint8 table
    foreign &= hsv[:, :, 1] >= _HUE_GATE_SAT
    w[foreign.astype(bool)] = 0.0
    mom = cv2.moments(w)
    if not mom["m00"] > 1e-6:
        return f"marker '{mk.name}': empty centroid weights"
    limit = _BORDER_WEIGHT_FRACTION * w_full
    cut = (
        (x0 == 0 and w[:, 0].max() > limit)
        or (y0 == 0 and w[0, :].max() > limit)
        or (x1 == W and w[:, -1].max() > limit)
        or (y1 == H and w[-1, :].max() > limit)
    )
    return x0 + mom["m10"] / mom["m00"], y0 + mom["m01"] / mom["m00"], mom["m00"] / w_full, bool(cut)


def fires(pixels_rgb: np.ndarray, cal: CameraCalibration) -> bool:
    """Whether any of the RGB pixels (n, 3) uint8 is inside any marker's HSV box of cal.markers."""
    hsv = cv2.cvtColor(np.ascontiguousarray(pixels_rgb, dtype=np.uint8).reshape(1, -1, 3), cv2.COLOR_RGB2HSV)
    hue, sat, val = hsv[0, :, 0], hsv[0, :, 1], hsv[0, :, 2]
    return any(
        bool((tab[0][hue] & tab[1][sat] & tab[2][val]).any())
        for _, tab in _membership_tables(tuple(cal.markers))
    )


def extract_markers(
    image_rgb: np.ndarray,
    cal: CameraCalibration,
    *,
    min_area_px: float = 6.0,
    max_blobs_per_colour: int = 1,
    downscale: int | None = None,
    max_area_ratio: float = 16.0,
    min_spacing: float = 1.0,
    roi: tuple[int, int, int, int] | None = None,
) -> MarkerDetection:
    """Find the m colour markers of cal.markers in an RGB frame and return their sub-pixel centres.

    image_rgb: (cal.height, cal.width, 3) uint8, RGB channel order.
    min_area_px: thresholded components with fewer pixels (after the 3×3 opening; counted on the
        detection image and scaled by downscale²) are ignored as clutter.
    max_blobs_per_colour: more remaining components of one colour than this rejects the frame; with
        several allowed (≤ this), the largest is taken. Default 1: exactly one blob per colour.
    downscale: blobs are *found* on the image shrunk by this integer factor (cv2.INTER_AREA) and then
        *measured* at full resolution in a window around each blob. None: 2 for frames at least
        640×480, else 1. With 2, blobs narrower than about 6 px (disc radius < 3 px) are not found.

    max_area_ratio: the largest marker's area over the smallest's above this rejects the frame ("marker
        sizes"): the target's markers are alike and near one depth, so a blob much larger or smaller
        than the others is not one of them (a reflection, a smear of a damaged video frame).
    roi: (x0, y0, x1, y1) pixels, end exclusive: the caller's promise (a renderer's, e.g.
        flightstack.sim_backend.scene.render with region "markers") that no pixel outside it is in any
        marker's HSV box and that it extends more than 5 pixels beyond every such pixel; blobs are then
        searched only inside it, with the same result as on the whole frame (with downscale > 1 only
        when it divides the frame's size).
    min_spacing: two markers whose centres are closer than this many times the sum of their radii
        (radius = √(area/π)) reject the frame ("marker spacing"): the target's markers never overlap.

    Never raises on image content: a frame where any marker has no blob, too many blobs, a blob at the
    image border, no usable contrast, or sizes or spacing that cannot be the target's is returned
    rejected, with a reason naming the first such marker (or pair).
    Raises ValueError for a non-uint8 / non-(H, W, 3) array, a size other than the calibration's, or a
    calibration without markers.
    """
    if not isinstance(image_rgb, np.ndarray) or image_rgb.dtype != np.uint8:
        raise ValueError(
            f"image_rgb must be a uint8 numpy array, got {getattr(image_rgb, 'dtype', type(image_rgb))}"
        )
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
        raise ValueError(f"image_rgb must have shape (H, W, 3), got {image_rgb.shape}")
    H, W = image_rgb.shape[:2]
    if (cal.width, cal.height) != (W, H):
        raise ValueError(f"image is {W}x{H} but the calibration is for {cal.width}x{cal.height}")
    if not cal.markers:
        raise ValueError("the calibration defines no markers")
    if max_blobs_per_colour < 1:
        raise ValueError("max_blobs_per_colour must be >= 1")
    ds = (2 if (W >= 640 and H >= 480) else 1) if downscale is None else int(downscale)
    if ds < 1 or W // ds < 1 or H // ds < 1:
        raise ValueError(f"downscale must be >= 1 and leave at least one pixel, got {downscale}")
    image = np.ascontiguousarray(image_rgb)
    ox, oy, ex, ey = 0, 0, W, H  # the searched part of the frame (pixels, end exclusive)
    if roi is not None and W % ds == 0 and H % ds == 0:
        if roi[2] <= roi[0] or roi[3] <= roi[1]:
            return MarkerDetection.rejected(f"marker '{cal.markers[0].name}': 0 blobs")
        # on whole ds × ds blocks, so that the shrunk part is exactly that part of the shrunk frame
        ox, oy = max(0, int(roi[0])) // ds * ds, max(0, int(roi[1])) // ds * ds
        ex, ey = -(-min(W, int(roi[2])) // ds) * ds, -(-min(H, int(roi[3])) // ds) * ds
    part = image[oy:ey, ox:ex]
    hsv_full = cv2.cvtColor(part, cv2.COLOR_RGB2HSV) if ds == 1 else None
    if hsv_full is not None:  # ds == 1
        hsv = hsv_full
    else:
        small = cv2.resize(part, ((ex - ox) // ds, (ey - oy) // ds), interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(small, cv2.COLOR_RGB2HSV)
    h, w = H // ds, W // ds
    hue, sat, val = cv2.split(hsv)
    m = len(cal.markers)
    pixels = np.empty((m, 2))
    areas = np.empty(m)
    dilate_px = _DILATE_PX + ds - 1  # the upsampled coarse mask is uncertain by ds − 1 pixels
    pad = dilate_px + _RING_PX
    min_area = min_area_px / ds**2
    for idx, tab in _membership_tables(tuple(cal.markers)):
        bits = cv2.bitwise_and(cv2.LUT(hue, tab[0]), cv2.LUT(sat, tab[1]))
        bits = cast(NDArray[np.uint8], cv2.bitwise_and(bits, cv2.LUT(val, tab[2])))  # uint8 tables
        for j in idx:
            mk = cal.markers[j]
            in_box = bits & np.uint8(1 << (j - idx.start))  # (numpy: cv2 takes a 1×1 array for a scalar)
            mask = cv2.morphologyEx(in_box, cv2.MORPH_OPEN, _OPEN_KERNEL)
            rx, ry, rw, rh = cv2.boundingRect(mask)  # connected components only inside the non-empty part
            if rw == 0 or rh == 0:
                return MarkerDetection.rejected(f"marker '{mk.name}': 0 blobs")
            _, labels, stats, _ = cv2.connectedComponentsWithStats(
                mask[ry : ry + rh, rx : rx + rw], connectivity=8
            )
            big = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area) + 1
            if len(big) == 0 or len(big) > max_blobs_per_colour:
                return MarkerDetection.rejected(f"marker '{mk.name}': {len(big)} blobs")
            k = int(big[np.argmax(stats[big, cv2.CC_STAT_AREA])])
            bx, by, bw, bh = (int(v) for v in stats[k, :4])
            blob = labels[by : by + bh, bx : bx + bw] == k
            bx += rx + ox // ds
            by += ry + oy // ds
            if bx == 0 or by == 0 or bx + bw == w or by + bh == h:
                return MarkerDetection.rejected(f"marker '{mk.name}' touches the image border")
            # the blob's window at full resolution
            fx0, fy0, fx1, fy1 = bx * ds, by * ds, (bx + bw) * ds, (by + bh) * ds
            box = (max(0, fx0 - pad), max(0, fy0 - pad), min(W, fx1 + pad), min(H, fy1 + pad))
            comp = np.zeros((box[3] - box[1], box[2] - box[0]), dtype=np.uint8)
            if ds > 1:
                blob = np.repeat(np.repeat(blob, ds, axis=0), ds, axis=1)
            comp[fy0 - box[1] : fy1 - box[1], fx0 - box[0] : fx1 - box[0]] = blob
            if hsv_full is not None and box[0] >= ox and box[1] >= oy and box[2] <= ex and box[3] <= ey:
                hsv_win = hsv_full[box[1] - oy : box[3] - oy, box[0] - ox : box[2] - ox]
            else:
                hsv_win = cv2.cvtColor(image[box[1] : box[3], box[0] : box[2]], cv2.COLOR_RGB2HSV)
            res = _weighted_centre(image, hsv_win, comp, box, dilate_px, mk)
            if isinstance(res, str):
                return MarkerDetection.rejected(res)
            u, v, area, cut = res
            if cut:
                return MarkerDetection.rejected(f"marker '{mk.name}' touches the image border")
            pixels[j] = (u, v)
            areas[j] = area
    implausible = _implausible(pixels, areas, cal.markers, max_area_ratio, min_spacing)
    if implausible is not None:
        return MarkerDetection.rejected(implausible)
    return MarkerDetection(pixels, normalise(pixels, cal), None, areas)


def normalise(pixels: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """Undistorted normalised coordinates (x/z, y/z) in Σc, (m, 2), of pixels (m, 2) in the distorted image
    (cv2.undistortPoints with the calibration's K and distortion, iterated to 1e-12)."""
    return cv2.undistortPoints(
        np.asarray(pixels, dtype=float).reshape(-1, 1, 2),
        np.asarray(cal.camera_matrix, dtype=float),
        np.asarray(cal.dist_coeffs, dtype=float),
        criteria=_UNDISTORT_CRITERIA,
    ).reshape(-1, 2)


def _implausible(
    pixels: np.ndarray,
    areas: np.ndarray,
    markers: tuple[MarkerColour, ...] | list[MarkerColour],
    max_area_ratio: float,
    min_spacing: float,
) -> str | None:
    """Why these m blobs cannot be the target's markers (sizes, spacing), or None."""
    big, small = int(np.argmax(areas)), int(np.argmin(areas))
    if areas[small] <= 0 or areas[big] > max_area_ratio * areas[small]:
        return f"marker sizes: '{markers[big].name}' vs '{markers[small].name}'"
    radii = np.sqrt(np.maximum(areas, 0.0) / np.pi)
    for j in range(len(areas)):
        for k in range(j + 1, len(areas)):
            if np.hypot(*(pixels[j] - pixels[k])) < min_spacing * (radii[j] + radii[k]):
                return f"marker spacing: '{markers[j].name}' and '{markers[k].name}' overlap"
    return None


def features_from_detection(det: MarkerDetection, focal_length: float = 1.0) -> np.ndarray | None:
    """The observer's measurement f = λ·[x1, y1, …, xm, ym] (2m,) from a detection; None if rejected.

    focal_length λ is in the observer's image-plane units (flightstack.paper.projection: f^j = λ/z^j [x^j,
    y^j]);
    λ = 1 returns the normalised coordinates themselves.
    """
    if det.normalized is None or det.reason is not None:
        return None
    return focal_length * np.asarray(det.normalized, dtype=float).reshape(-1)
