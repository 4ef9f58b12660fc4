"""Synthetic calibration images: a planar pattern seen through a known pinhole camera with OpenCV distortion.

Used to test the wizard against known intrinsics. Frames: the board frame Σb (metres, pattern plane
z = 0, as in flightstack.calibration.patterns) is mapped into the camera frame Σc (metres, z = optical axis,
x right,
y down) by P_c = R(rvec)·P_b + tvec. Pixels follow OpenCV (u right, v down, origin at the centre of the
top-left pixel).

Rendering is by inverse mapping: the centre of every sub-pixel sample (`supersample`² per pixel) is
undistorted to a ray (cv2.undistortPoints, iterated to 1e-12), intersected with the board plane, and the
board's printed texture is sampled there (bilinear); the samples are box-averaged to pixels
(cv2.INTER_AREA), so edges are anti-aliased by their covered fraction. The forward model is exactly the
one cv2.calibrateCamera fits (cv2.projectPoints).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from flightstack.calibration.patterns import PatternSpec

_RAY_CACHE: dict[tuple[object, ...], np.ndarray] = {}
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass(frozen=True)
class BoardTexture:
    """A printed pattern: grey image, texels per metre, and the continuous texture coordinate (texels) of
    Σb's origin (texel (i, j) covers [j, j + 1) × [i, i + 1))."""

    image: np.ndarray
    texels_per_m: float
    origin_texels: tuple[float, float]


def board_texture(spec: PatternSpec, texels_per_square: int = 64) -> BoardTexture:
    """The pattern as printed (black on white, one square of white margin), texels_per_square per square_m."""
    t = int(texels_per_square)
    s = spec.square_m
    if spec.kind == "chessboard":
        nx, ny = spec.cols + 1, spec.rows + 1  # squares
        img = np.full(((ny + 2) * t, (nx + 2) * t), 255, np.uint8)
        for i in range(ny):
            for j in range(nx):
                if (i + j) % 2 == 0:
                    img[(i + 1) * t : (i + 2) * t, (j + 1) * t : (j + 2) * t] = 0
        return BoardTexture(img, t / s, (2.0 * t, 2.0 * t))  # first inner corner: 1 margin + 1 square
    if spec.kind == "charuco":
        board = spec.charuco_board()
        inner = board.generateImage((spec.cols * t, spec.rows * t), marginSize=0, borderBits=1)
        img = np.full(((spec.rows + 2) * t, (spec.cols + 2) * t), 255, np.uint8)
        img[t:-t, t:-t] = inner
        return BoardTexture(img, t / s, (float(t), float(t)))  # Σb origin: the board's outer corner
    # asymmetric circles: centres at ((2j + i mod 2)·s, i·s), radius 0.4·s (neighbours are √2·s apart)
    shift = 4
    w = (2 * spec.cols + 3) * t
    h = (spec.rows + 3) * t
    img = np.full((h, w), 255, np.uint8)
    for i in range(spec.rows):
        for j in range(spec.cols):
            cx = (2 * j + i % 2 + 1.5) * t - 0.5
            cy = (i + 1.5) * t - 0.5
            centre = (round(cx * (1 << shift)), round(cy * (1 << shift)))
            cv2.circle(img, centre, round(0.4 * t * (1 << shift)), 0, -1, cv2.LINE_AA, shift)
    return BoardTexture(img, t / s, (1.5 * t, 1.5 * t))


def _rays(K: np.ndarray, dist: np.ndarray, size: tuple[int, int], ss: int) -> np.ndarray:
    """(ss·H, ss·W, 2) float64 undistorted normalised coordinates of every sub-pixel sample centre."""
    key = (K.tobytes(), dist.tobytes(), size, ss)
    if key not in _RAY_CACHE:
        W, H = size
        u = (np.arange(W * ss) + 0.5) / ss - 0.5
        v = (np.arange(H * ss) + 0.5) / ss - 0.5
        uu, vv = np.meshgrid(u, v)
        pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(pts, K, dist, criteria=_UNDISTORT_CRITERIA)
        _RAY_CACHE.clear()
        _RAY_CACHE[key] = xy.reshape(H * ss, W * ss, 2)
    return _RAY_CACHE[key]


def render_view(
    texture: BoardTexture,
    K: np.ndarray,
    dist: np.ndarray,
    size: tuple[int, int],
    rvec: np.ndarray,
    tvec: np.ndarray,
    *,
    supersample: int = 2,
    background: int = 110,
    noise_std: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Grey uint8 (H, W) image of the board at pose (rvec, tvec) (Σb → Σc, metres) seen by K, dist (px)."""
    K = np.asarray(K, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    xy = _rays(K, dist, size, supersample)
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    r3 = R[:, 2]  # board normal in Σc
    denom = xy[..., 0] * r3[0] + xy[..., 1] * r3[1] + r3[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(r3 @ t) / denom  # depth of the ray's intersection with the board plane
    # P_b = Rᵀ(λ·d − t); only its x and y are needed
    X = lam * (xy[..., 0] * R[0, 0] + xy[..., 1] * R[1, 0] + R[2, 0]) - float(R[:, 0] @ t)
    Y = lam * (xy[..., 0] * R[0, 1] + xy[..., 1] * R[1, 1] + R[2, 1]) - float(R[:, 1] @ t)
    s = texture.texels_per_m
    map_x = (X * s + texture.origin_texels[0] - 0.5).astype(np.float32)
    map_y = (Y * s + texture.origin_texels[1] - 0.5).astype(np.float32)
    behind = ~(lam > 0)
    map_x[behind] = -10.0
    map_y[behind] = -10.0
    fine = cv2.remap(
        texture.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=background
    )
    # cv2's stubs do not carry the dtype: resizing a float32 image gives float32
    img = cast(NDArray[np.float32], cv2.resize(fine.astype(np.float32), size, interpolation=cv2.INTER_AREA))
    if noise_std > 0:
        img += (rng or np.random.default_rng()).normal(0.0, noise_std, img.shape).astype(np.float32)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def random_poses(
    spec: PatternSpec,
    K: np.ndarray,
    dist: np.ndarray,
    size: tuple[int, int],
    n: int,
    rng: np.random.Generator,
    *,
    fill: tuple[float, float] = (0.25, 0.45),
    max_tilt_deg: float = 40.0,
    margin_px: float = 20.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """n board poses (rvec, tvec) that keep the whole printed board inside the image by margin_px.

    The pattern points span a `fill` fraction of the image width or height (random in the interval), its
    centre is anywhere in the middle 60 % of the image, and it is tilted by 30..100 % of max_tilt_deg about
    a random in-plane axis (plus a random rotation about its normal up to 30°).
    """
    W, H = size
    K = np.asarray(K, dtype=float)
    obj = spec.object_points().astype(np.float64)
    outline = np.concatenate([spec.outline_m(), np.zeros((4, 1))], axis=1)
    centre_b = outline.mean(axis=0)
    grow = 2.0 * spec.square_m  # the printed board (outer squares, white margin) around the points
    printed = centre_b + (outline - centre_b) + np.sign(outline - centre_b) * [grow, grow, 0.0]
    span_x, span_y = float(np.ptp(outline[:, 0])), float(np.ptp(outline[:, 1]))
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(200 * n):
        if len(poses) == n:
            break
        z = K[0, 0] * max(span_x / W, span_y / H) / rng.uniform(*fill)
        u, v = rng.uniform(0.2 * W, 0.8 * W), rng.uniform(0.2 * H, 0.8 * H)
        c = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        axis_angle = rng.uniform(0, 2 * math.pi)
        tilt = math.radians(rng.uniform(0.3, 1.0) * max_tilt_deg)
        r_tilt = np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0]) * tilt
        r_spin = np.array([0.0, 0.0, math.radians(rng.uniform(-30, 30))])
        R = cv2.Rodrigues(r_tilt)[0] @ cv2.Rodrigues(r_spin)[0]
        t = c - R @ centre_b
        rvec = cv2.Rodrigues(R)[0].reshape(3)
        px, _ = cv2.projectPoints(np.concatenate([obj, printed]), rvec, t, K, np.asarray(dist, dtype=float))
        px = px.reshape(-1, 2)
        if np.all((px[:, 0] > margin_px) & (px[:, 0] < W - 1 - margin_px)) and np.all(
            (px[:, 1] > margin_px) & (px[:, 1] < H - 1 - margin_px)
        ):
            poses.append((rvec, t))
    if len(poses) < n:
        raise ValueError(f"could only place {len(poses)} of {n} board poses inside the image")
    return poses
