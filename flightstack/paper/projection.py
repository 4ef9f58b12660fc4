"""Pinhole projection of the target's feature points and its image Jacobian (paper eq. f, DESIGN §4).

Frames: Σi is the drone's camera-aligned frame of the paper (z = optical axis, rotation about z only),
Σ0 the target frame, Σc the physical camera. A camera mounted otherwise (the Tello's downward camera
seen from a z-up body frame) is a fixed extrinsic: p_i = R_ic p_c + t_ic, so p_c = R_icᵀ (p_i − t_ic).
With the default extrinsic (identity) Σc = Σi, exactly the paper's model.

Image coordinates f are in the paper's metric image-plane units: f^j = λ/z^j [x^j, y^j] (λ = focal length,
same unit as f; λ = 1 gives normalised coordinates). Pixel measurements are converted by the caller.

The arithmetic is the compiled kernels' (flightstack.paper.kernels: points_in_camera, measure,
features_and_jacobian); these functions check shapes and turn a depth ≤ min_depth into
TargetNotVisibleError.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose


class TargetNotVisibleError(ValueError):
    """A feature point is on or behind the camera plane (z_c ≤ min_depth)."""


@dataclass(frozen=True)
class CameraModel:
    """λ and the fixed camera extrinsic (R_ic (3,3), t_ic (3,) metres) in the drone frame Σi."""

    focal_length: float = 1.0
    R_ic: np.ndarray = field(default_factory=lambda: np.eye(3))
    t_ic: np.ndarray = field(default_factory=lambda: np.zeros(3))
    min_depth: float = 1e-3

    def __post_init__(self) -> None:
        if not self.focal_length > 0:
            raise ValueError(f"focal_length must be > 0, got {self.focal_length}")
        R = np.asarray(self.R_ic, dtype=float)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise ValueError("R_ic must be a 3x3 rotation matrix")
        t = np.asarray(self.t_ic, dtype=float).reshape(3)
        packed = np.concatenate([[float(self.focal_length), float(self.min_depth)], R.reshape(9), t])
        object.__setattr__(self, "packed", packed)

    #: [λ, min_depth, R_ic (row-major), t_ic]: the camera as the kernels take it (set in __post_init__)
    packed: np.ndarray = field(init=False, repr=False, compare=False)


def _pose_vec(g: Pose) -> np.ndarray:
    return np.array((g.p[0], g.p[1], g.p[2], g.theta), dtype=float)


def _points(P0: np.ndarray) -> np.ndarray:
    P = np.ascontiguousarray(P0, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"P0 must have shape (m, 3), got {P.shape}")
    return P


def points_in_camera(g_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """Feature points in the physical camera frame Σc, shape (m, 3), metres."""
    P = _points(P0)
    out = np.empty_like(P)
    kern.points_in_camera(_pose_vec(g_i0), P, cam.packed, out)
    return out


def project(points_c: np.ndarray, cam: CameraModel) -> np.ndarray:
    """f = [f^1; …; f^m], f^j = λ/z^j [x^j, y^j]; shape (2m,). Raises if any depth ≤ min_depth."""
    z = points_c[:, 2]
    zmin = z.min()
    if zmin <= cam.min_depth:
        raise TargetNotVisibleError(f"feature point behind the camera (min depth {zmin:.3g} m)")
    return (cam.focal_length * points_c[:, :2] / z[:, None]).reshape(-1)


def measure(g_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """The measurement function f(g_i0) of the paper, shape (2m,)."""
    f = measure_vector(_pose_vec(g_i0), P0, cam)
    if f is None:
        raise TargetNotVisibleError("feature point on or behind the camera plane")
    return f


def measure_vector(g_i0: np.ndarray, P0: np.ndarray, cam: CameraModel) -> np.ndarray | None:
    """`measure` of g_i0 given as its pose vector [x, y, z, θ] (C-contiguous float64 (4,)); None where
    `measure` raises TargetNotVisibleError (the ideal camera's hot path: no Pose, no exception)."""
    P = _points(P0)
    f = np.empty(2 * P.shape[0])
    return f if kern.measure(g_i0, P, cam.packed, f) else None


def image_jacobian(g_bar: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """J (2m × 4) at the estimate ḡ; see `features_and_jacobian`."""
    return features_and_jacobian(g_bar, P0, cam)[1]


def features_and_jacobian(g_bar: Pose, P0: np.ndarray, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """J (2m × 4) with f(ḡ exp(ξ̂)) ≈ f(ḡ) + J ξ for a small body-side perturbation ξ = [p_e, θ_e].

    Per point p0^j = (a, b, c) (DESIGN §4, with the extrinsic):
        J^j = (λ/z̄)·[[1, 0, −x̄/z̄], [0, 1, −ȳ/z̄]] · R_icᵀ · R̄ · [I₃ | (−b, a, 0)ᵀ]
    where (x̄, ȳ, z̄) is the point in Σc under the estimate ḡ. Since g_i0 = ḡ_i0 g_e, this is the
    Jacobian of f with respect to e_e = vec(g_e) to first order, so e_e ≈ J⁺ (f − f̄).
    Returns (f̄ = f(ḡ) (2m,), J (2m, 4)).
    """
    P = _points(P0)
    m = P.shape[0]
    f_bar, J = np.empty(2 * m), np.empty((2 * m, 4))
    if not kern.features_and_jacobian(_pose_vec(g_bar), P, cam.packed, f_bar, J):
        raise TargetNotVisibleError("estimated feature point behind the camera")
    return f_bar, J
