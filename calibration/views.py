"""Which views to keep: blur, near-duplicates, image coverage (all in pixels of the analysed image).

* Blur: `edge_width_px` is the width (px) of the steepest edges inside the pattern's bounding box,
  contrast / maximum gradient, i.e. the length of the linear ramp that has the same contrast and slope.
  A sharp, well-focused edge measures about 2 px; a Gaussian blur of σ px adds about 2.5·σ. It does not
  depend on the pattern's size in the image.
* Near-duplicates: each view is summarised by where the rectangle spanned by the pattern points (its
  outline in the board frame) lands in the image, through the homography fitted to the detected points.
  Two views whose outlines differ by less than `min_change` × the image diagonal at every corner (over
  the four cyclic relabellings and the reversal, since a symmetric board may be detected from another
  corner) are near-duplicates.
* Coverage: an occupancy grid over the image of the pattern points of all kept views.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Coverage grid (columns, rows) over the image.
COVERAGE_GRID = (8, 6)


def edge_width_px(gray: np.ndarray, points: np.ndarray) -> float:
    """Steepest-edge width (px) inside the bounding box of `points` (n, 2) px of a uint8 (H, W) image."""
    H, W = gray.shape[:2]
    x, y, w, h = cv2.boundingRect(np.asarray(points, dtype=np.float32).reshape(-1, 1, 2))
    x0, y0, x1, y1 = max(0, x - 2), max(0, y - 2), min(W, x + w + 2), min(H, y + h + 2)
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    if roi.shape[0] < 3 or roi.shape[1] < 3:
        return float("inf")
    gx = cv2.Sobel(roi, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(roi, cv2.CV_32F, 0, 1, ksize=3)
    steepest = float(np.percentile(np.hypot(gx, gy), 99.5)) / 8.0  # Sobel 3x3 gain: 8 per grey level/px
    contrast = float(np.percentile(roi, 95) - np.percentile(roi, 5))
    if steepest <= 1e-6 or contrast <= 1e-6:
        return float("inf")
    return contrast / steepest


def outline_in_image(
    object_points: np.ndarray, image_points: np.ndarray, outline_m: np.ndarray
) -> np.ndarray:
    """(4, 2) px: the board-frame rectangle `outline_m` (4, 2) m mapped through the homography fitted to
    the (n, 3) object points (z = 0) and their (n, 2) image points."""
    Hm, _ = cv2.findHomography(
        np.asarray(object_points, dtype=np.float64)[:, :2], np.asarray(image_points, dtype=np.float64)
    )
    if Hm is None:
        return np.full((4, 2), np.nan)
    return cv2.perspectiveTransform(outline_m.reshape(-1, 1, 2).astype(np.float64), Hm).reshape(4, 2)


def outline_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Largest corner distance (px) between two outlines (4, 2), minimised over the relabellings of b."""
    best = float("inf")
    for cand in (b, b[::-1]):
        for k in range(4):
            best = min(best, float(np.max(np.linalg.norm(a - np.roll(cand, k, axis=0), axis=1))))
    return best


class Coverage:
    """How many kept views put at least one pattern point into each cell of a grid over the image."""

    def __init__(self, width: int, height: int, grid: tuple[int, int] = COVERAGE_GRID) -> None:
        self.width, self.height, self.grid = width, height, grid
        self.counts = np.zeros((grid[1], grid[0]), dtype=int)

    def add(self, image_points: np.ndarray) -> None:
        pts = np.asarray(image_points, dtype=float).reshape(-1, 2)
        cu = np.clip((pts[:, 0] + 0.5) * self.grid[0] / self.width, 0, self.grid[0] - 1).astype(int)
        cv = np.clip((pts[:, 1] + 0.5) * self.grid[1] / self.height, 0, self.grid[1] - 1).astype(int)
        hit = np.zeros_like(self.counts, dtype=bool)
        hit[cv, cu] = True
        self.counts += hit

    @property
    def fraction(self) -> float:
        """Fraction of grid cells that hold a point of at least one view (0..1)."""
        return float(np.mean(self.counts > 0))

    def render(self) -> str:
        """ASCII map, one character per cell: '.' empty, 1-9 views, '#' ten or more."""
        rows = ["".join("." if c == 0 else ("#" if c >= 10 else str(c)) for c in r) for r in self.counts]
        return "\n".join("  |" + r + "|" for r in rows)
