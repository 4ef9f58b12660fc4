"""The simulated lab's floor as a camera sees it: a tiled, mottled grey pattern fixed in the world.

Why: a plain floor flatters video concealment (a decoder that smears a lost datagram over a uniform grey
leaves the markers' surroundings intact), so the simulated and emulated labs can lay this floor instead
(`sim.render.floor: tiles`). The pattern is deterministic (a fixed seed), grey (R = G = B, so no colour
marker's threshold fires on it) and periodic: square tiles of TILE_M with darker grout lines, each tile its
own grey level, a fine mottle and a coarse one, blurred so that it holds no detail finer than about 1 cm
(the downward camera at 1 m sees 4 mm per pixel). It lies on the plane z = 0 of the world Σw (metres) and
repeats every PERIOD_M along x and y.

Per pixel, the camera's ray (the calibration's undistorted normalised coordinates, cached per calibration)
meets the floor through a homography of the camera's pose (`FloorView`); the texture is sampled there with
bilinear interpolation (cv2.remap, wrapping around the period). Rays that do not meet the floor in front of
the camera see HORIZON_GREY. Only the pixel centre is sampled: far floor seen at a grazing angle (a forward
camera's upper image) aliases.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.paper.geometry import Pose, rot_z

TEXEL_M = 0.004
"""Texture resolution (m per texel)."""
PERIOD_TEXELS = 1024
"""The pattern repeats every PERIOD_TEXELS texels (4.096 m, beyond the lab's 4 m fence)."""
PERIOD_M = TEXEL_M * PERIOD_TEXELS
TILE_TEXELS = 64
"""Tile side in texels (0.256 m; a whole number of tiles per period, so the pattern is seamless)."""
TILE_M = TEXEL_M * TILE_TEXELS
GROUT_TEXELS = 2
"""Width of the grout line between tiles (texels, 8 mm)."""
TILE_GREYS = (70, 130)
"""Range of the tiles' grey levels (0..255)."""
GROUT_GREY = 45
FINE_MOTTLE = (3.0, 10.0)
"""Fine mottle: Gaussian blur σ (texels) of white noise, then its standard deviation (grey levels)."""
COARSE_MOTTLE = (40.0, 8.0)
"""Coarse mottle: σ (texels) and standard deviation (grey levels)."""
SMOOTH_TEXELS = 1.0
"""The whole pattern's final blur σ (texels): no edge sharper than about a centimetre."""
HORIZON_GREY = 150
"""What a ray that does not meet the floor in front of the camera sees (a distant wall)."""
SEED = 20261206


@dataclass(frozen=True)
class FloorView:
    """The floor seen from a camera: R_wc (3, 3), the camera axes Σc as columns in Σw, and c_w (3,), the
    camera's centre in Σw (m)."""

    R_wc: np.ndarray
    c_w: np.ndarray


def floor_view(g_wi: Pose, R_ic: np.ndarray, t_ic: np.ndarray) -> FloorView:
    """The FloorView of a camera on a drone at g_wi (Σw) through its mount: R_ic (columns = Σc axes in the
    body frame FLU), t_ic (m, body frame)."""
    R_wi = rot_z(g_wi.theta)
    return FloorView(R_wi @ np.asarray(R_ic, dtype=float), np.asarray(g_wi.p, dtype=float) + R_wi @ t_ic)


def _smooth_noise(rng: np.random.Generator, sigma: float, std: float) -> np.ndarray:
    """Periodic Gaussian-blurred white noise of the given standard deviation (float32, one period)."""
    n = PERIOD_TEXELS
    white = rng.standard_normal((n, n)).astype(np.float32)
    blurred = _blur_periodic(white, sigma)
    return blurred * np.float32(std / max(float(blurred.std()), 1e-9))


def _blur_periodic(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (σ in texels) of one period of a periodic pattern, wrapping around its edges."""
    pad = int(np.ceil(4.0 * sigma)) + 1
    big = np.pad(img, pad, mode="wrap")
    return cv2.GaussianBlur(big, (0, 0), sigma)[pad:-pad, pad:-pad]


@functools.lru_cache(maxsize=1)
def texture() -> np.ndarray:
    """One period of the floor pattern: (PERIOD_TEXELS, PERIOD_TEXELS) float32 grey levels; row = y, column
    = x (texels from the origin of Σw). Deterministic (SEED); read-only."""
    rng = np.random.default_rng(SEED)
    n, t = PERIOD_TEXELS, TILE_TEXELS
    tiles = rng.uniform(*TILE_GREYS, size=(n // t, n // t)).astype(np.float32)
    img = np.kron(tiles, np.ones((t, t), dtype=np.float32))
    grout = (np.arange(n) % t) < GROUT_TEXELS
    img[grout, :] = GROUT_GREY
    img[:, grout] = GROUT_GREY
    img += _smooth_noise(rng, *FINE_MOTTLE) + _smooth_noise(rng, *COARSE_MOTTLE)
    img = _blur_periodic(img, SMOOTH_TEXELS)
    img = np.clip(img, 0.0, 255.0)
    img.setflags(write=False)
    return img


@functools.lru_cache(maxsize=1)
def grey_range() -> tuple[int, int]:
    """The lowest and highest grey level the floor shows (its texture's and HORIZON_GREY), rounded out."""
    tex = texture()
    return int(np.floor(min(float(tex.min()), HORIZON_GREY))), int(
        np.ceil(max(float(tex.max()), HORIZON_GREY))
    )


@functools.lru_cache(maxsize=1)
def _texture_u8() -> np.ndarray:
    return np.clip(texture() + 0.5, 0.0, 255.0).astype(np.uint8)


def floor_image(grid: np.ndarray, view: FloorView, bounds: tuple[float, float, float, float]) -> np.ndarray:
    """The floor seen by a camera at `view`: (H, W) uint8 grey.

    grid: (H, W, 2) float32, each pixel centre's undistorted normalised coordinates (x/z, y/z) in Σc;
    bounds: (x_min, x_max, y_min, y_max) of them.
    The ray d = R_wc (x, y, 1) from c_w meets z = 0 at c_w + s d, s = −c_z / d_z, where d_z < 0 (c_z > 0):
    X = (c_x d_z − c_z d_x) / d_z and likewise Y, a homography of (x, y, 1) (cv2.perspectiveTransform).
    """
    R, c = view.R_wc, view.c_w
    cz = float(c[2])
    hom = np.array([c[0] * R[2] - cz * R[0], c[1] * R[2] - cz * R[1], R[2]], dtype=np.float64)
    hom[:2] /= TEXEL_M  # texels
    texels = cv2.perspectiveTransform(grid, hom)
    out = cv2.remap(_texture_u8(), texels, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    x0, x1, y0, y1 = bounds
    corners = np.array([[x0, y0, 1.0], [x1, y0, 1.0], [x0, y1, 1.0], [x1, y1, 1.0]])
    if cz <= 0.0:
        out[:] = HORIZON_GREY
    elif (corners @ R[2]).max() > -1e-6:  # some rays may not go down: find them (a forward camera)
        dz = cv2.transform(grid, R[2, :2].reshape(1, 2).astype(np.float32)).reshape(out.shape)
        out[dz + np.float32(R[2, 2]) > -1e-6] = HORIZON_GREY
    return out
