"""Pinhole projection of the target's feature points and its image Jacobian (paper eq. f, DESIGN §4).

Frames: Σi is the drone's camera-aligned frame of the paper (z = optical axis, rotation about z only),
Σ0 the target frame, Σc the physical camera. A camera mounted otherwise (the Tello's downward camera
seen from a z-up body frame) is a fixed extrinsic: p_i = R_ic p_c + t_ic, so p_c = R_icᵀ (p_i − t_ic).
With the default extrinsic (identity) Σc = Σi, exactly the paper's model.

Image coordinates f are in the paper's metric image-plane units: f^j = λ/z^j [x^j, y^j] (λ = focal length,
same unit as f; λ = 1 gives normalised coordinates). Pixel measurements are converted by the caller.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flightstack.paper.geometry import Pose, rot_z


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


def points_in_drone_frame(g_i0: Pose, P0: np.ndarray) -> np.ndarray:
    """p_i^j = R(θ_i0) p_0^j + p_i0 for the m feature points P0 (m, 3) given in Σ0; returns (m, 3)."""
    return P0 @ rot_z(g_i0.theta).T + g_i0.p


def points_in_camera(g_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """Feature points in the physical camera frame Σc, shape (m, 3), metres."""
    return (points_in_drone_frame(g_i0, P0) - cam.t_ic) @ cam.R_ic


def project(points_c: np.ndarray, cam: CameraModel) -> np.ndarray:
    """f = [f^1; …; f^m], f^j = λ/z^j [x^j, y^j]; shape (2m,). Raises if any depth ≤ min_depth."""
    z = points_c[:, 2]
    zmin = z.min()
    if zmin <= cam.min_depth:
        raise TargetNotVisibleError(f"feature point behind the camera (min depth {zmin:.3g} m)")
    return (cam.focal_length * points_c[:, :2] / z[:, None]).reshape(-1)


def measure(g_i0: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """The measurement function f(g_i0) of the paper, shape (2m,)."""
    return project(points_in_camera(g_i0, P0, cam), cam)


def image_jacobian(g_bar: Pose, P0: np.ndarray, cam: CameraModel) -> np.ndarray:
    """J (2m × 4) at the estimate ḡ; see `features_and_jacobian`."""
    return features_and_jacobian(g_bar, P0, cam)[1]


def features_and_jacobian(g_bar: Pose, P0: np.ndarray, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """J (2m × 4) with f(ḡ exp(ξ̂)) ≈ f(ḡ) + J ξ for a small body-side perturbation ξ = [p_e, θ_e].

    Per point p0^j = (a, b, c) (DESIGN §4, with the extrinsic):
        J^j = (λ/z̄)·[[1, 0, −x̄/z̄], [0, 1, −ȳ/z̄]] · R_icᵀ · R̄ · [I₃ | (−b, a, 0)ᵀ]
    where (x̄, ȳ, z̄) is the point in Σc under the estimate ḡ. Since g_i0 = ḡ_i0 g_e, this is the
    Jacobian of f with respect to e_e = vec(g_e) to first order, so e_e ≈ J⁺ (f − f̄).
    Returns (f̄ = f(ḡ) (2m,), J (2m, 4)), sharing the point transform.
    """
    pc = points_in_camera(g_bar, P0, cam)
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    if z.min() <= cam.min_depth:
        raise TargetNotVisibleError("estimated feature point behind the camera")
    m = P0.shape[0]
    lam = cam.focal_length
    # ∂p_c/∂ξ = M [I | (−b, a, 0)ᵀ] with M = R_icᵀ R̄: columns M, and M (−b, a, 0)ᵀ per point
    M = cam.R_ic.T @ rot_z(g_bar.theta)
    rot_col = np.column_stack([-P0[:, 1], P0[:, 0], np.zeros(m)]) @ M.T  # (m, 3)
    D = np.empty((m, 3, 4))
    D[:, :, :3] = M
    D[:, :, 3] = rot_col
    # projection derivative (λ/z)[[1, 0, −x/z], [0, 1, −y/z]] applied to D
    inv_z = lam / z
    J = np.empty((m, 2, 4))
    J[:, 0, :] = inv_z[:, None] * (D[:, 0, :] - (x / z)[:, None] * D[:, 2, :])
    J[:, 1, :] = inv_z[:, None] * (D[:, 1, :] - (y / z)[:, None] * D[:, 2, :])
    f_bar = (pc[:, :2] * inv_z[:, None]).reshape(-1)
    return f_bar, J.reshape(2 * m, 4)
