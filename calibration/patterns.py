"""Calibration targets (chessboard, ChArUco, asymmetric circle grid): geometry and detection.

Board frame Σb: metres, the board plane is z = 0, x along a row of the pattern, y along a column.
Image points are pixels in the OpenCV convention (u right, v down, origin at the centre of the top-left
pixel).

* chessboard: `cols` × `rows` *inner* corners, squares of side `square_m`; corner (i, j) (row i, column j)
  at (j·s, i·s, 0). Found with cv2.findChessboardCorners, refined with cv2.cornerSubPix.
* charuco: `cols` × `rows` *squares* with ArUco markers of side `marker_m` from `dictionary`; its
  (cols − 1)·(rows − 1) inner corners at OpenCV's CharucoBoard positions (origin at the board's outer
  corner). Partial views are allowed (at least MIN_CHARUCO_CORNERS corners). Found with
  cv2.aruco.CharucoDetector (its corners are sub-pixel refined).
* acircles: OpenCV's asymmetric circle grid, `cols` circles per row and `rows` rows; circle (i, j) at
  ((2j + i mod 2)·s, i·s, 0), s = `square_m` (half the centre distance along a row). Found with
  cv2.findCirclesGrid (blob centroids, sub-pixel).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.vision.camera_file import PATTERN_KINDS

#: A ChArUco view with fewer interpolated corners than this is not used.
MIN_CHARUCO_CORNERS = 8
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


@dataclass(frozen=True)
class PatternSpec:
    """What the user holds in front of the camera (sizes in metres)."""

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float | None = None
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in PATTERN_KINDS:
            raise ValueError(f"--pattern: one of {', '.join(PATTERN_KINDS)} required, got {self.kind!r}")
        minimum = 3 if self.kind == "charuco" else 2
        if self.cols < minimum or self.rows < minimum:
            raise ValueError(
                f"--cols/--rows: at least {minimum} each for {self.kind}, got {self.cols}x{self.rows}"
            )
        if self.kind == "acircles" and self.cols * self.rows < 6:
            raise ValueError("--cols/--rows: an asymmetric circle grid needs at least 6 circles")
        if not (self.square_m > 0 and np.isfinite(self.square_m)):
            raise ValueError(f"--square: a positive length in metres required, got {self.square_m}")
        if self.kind == "charuco":
            if self.marker_m is None or not (0 < self.marker_m < self.square_m):
                raise ValueError(
                    f"--marker-size: the ArUco marker side (metres) must be in (0, square={self.square_m}), "
                    f"got {self.marker_m}"
                )
            if not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(
                    f"--dictionary: unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50)"
                )

    def describe(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard {self.cols}x{self.rows} inner corners, {self.square_m * 1000:g} mm squares"
        if self.kind == "charuco":
            assert self.marker_m is not None  # required for charuco (__post_init__)
            return (
                f"ChArUco {self.cols}x{self.rows} squares ({self.dictionary}), "
                f"{self.square_m * 1000:g} mm squares, {self.marker_m * 1000:g} mm markers"
            )
        return f"asymmetric circle grid {self.cols}x{self.rows}, spacing {self.square_m * 1000:g} mm"

    def to_dict(self) -> dict[str, object]:
        """The calibration file's `pattern` mapping."""
        d: dict[str, object] = {
            "kind": self.kind,
            "cols": self.cols,
            "rows": self.rows,
            "square_m": self.square_m,
        }
        if self.kind == "charuco":
            d.update(marker_m=self.marker_m, dictionary=self.dictionary)
        return d

    def object_points(self) -> np.ndarray:
        """(n, 3) float32 board-frame coordinates (metres) of all points, in detection order."""
        s = self.square_m
        if self.kind == "chessboard":
            ii, jj = np.mgrid[0 : self.rows, 0 : self.cols]
            xy = np.stack([jj.ravel() * s, ii.ravel() * s], axis=1)
        elif self.kind == "acircles":
            ii, jj = np.mgrid[0 : self.rows, 0 : self.cols]
            xy = np.stack([(2 * jj.ravel() + ii.ravel() % 2) * s, ii.ravel() * s], axis=1)
        else:
            return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float32).reshape(-1, 3)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1).astype(np.float32)

    def outline_m(self) -> np.ndarray:
        """(4, 2) corners (metres, Σb) of the rectangle spanned by all pattern points, in cyclic order."""
        xy = self.object_points()[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]], dtype=float)

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        assert self.marker_m is not None, "charuco_board needs a charuco PatternSpec (marker_m)"
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, float(self.marker_m), dictionary)


@dataclass(frozen=True)
class PatternView:
    """The pattern found in one image: image_points (n, 2) float32 px, object_points (n, 3) float32 m."""

    image_points: np.ndarray
    object_points: np.ndarray


class PatternDetector:
    """Finds one PatternSpec in grayscale images; `detect` returns a PatternView or a reason string."""

    def __init__(self, spec: PatternSpec) -> None:
        self.spec = spec
        self._obj = spec.object_points()
        if spec.kind == "charuco":
            self._board = spec.charuco_board()
            self._charuco = cv2.aruco.CharucoDetector(self._board)
        if spec.kind == "acircles":
            params = cv2.SimpleBlobDetector.Params()
            params.maxArea = 20000.0  # OpenCV's default 5000 px² misses circles of radius > 40 px
            self._blobs = cv2.SimpleBlobDetector.create(params)

    def detect(self, gray: np.ndarray) -> PatternView | str:
        """Find the pattern in a uint8 (H, W) image; a string says why not."""
        kind = self.spec.kind
        size = (self.spec.cols, self.spec.rows)
        if kind == "chessboard":
            flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
            found, corners = cv2.findChessboardCorners(gray, size, flags=flags)
            if not found:
                return f"no {size[0]}x{size[1]} chessboard found"
            pts = corners.reshape(-1, 2)
            spacing = _min_neighbour_distance(pts, self.spec.cols)
            half = int(np.clip(0.4 * spacing, 2, 11))
            corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
            return PatternView(corners.reshape(-1, 2).astype(np.float32), self._obj)
        if kind == "acircles":
            found, centres = cv2.findCirclesGrid(
                gray, size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID, blobDetector=self._blobs
            )
            if not found:
                return f"no {size[0]}x{size[1]} asymmetric circle grid found"
            return PatternView(centres.reshape(-1, 2).astype(np.float32), self._obj)
        corners, ids, _, _ = self._charuco.detectBoard(gray)
        n = 0 if ids is None else len(ids)
        if n < MIN_CHARUCO_CORNERS:
            return f"only {n} ChArUco corners found (need {MIN_CHARUCO_CORNERS})"
        ids = ids.reshape(-1)
        return PatternView(corners.reshape(-1, 2).astype(np.float32), self._obj[ids])


def _min_neighbour_distance(pts: np.ndarray, cols: int) -> float:
    """Smallest distance (px) between consecutive corners along rows and columns of a corner grid."""
    grid = pts.reshape(-1, cols, 2)
    parts = [
        np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
    ]
    d = np.concatenate([x for x in parts if x.size])
    return float(d.min()) if d.size else 10.0
