"""Planar SE(3): rigid-body poses that rotate about the world z axis only.

The paper (Saito et al., IFAC 2023, Sec. 2) writes a pose as g = (p, R(θ)) with p ∈ R³ in metres and
R(θ) = Rz(θ), θ ∈ (-π, π] in radians. A body velocity is V = [v (3,), ω] ∈ R⁴ (m/s, rad/s) expressed in
the body frame, and rigid motion is ġ = g V̂.

Conventions used everywhere in flightstack (DESIGN.md section 3):
    vec(g)  = [p, sin θ]                                   (paper: vec)
    Ad_R(θ) = diag(R(θ), 1)                                (paper: Ad_{R(θ)})
    Ad_g    = [[R, (p_y, -p_x, 0)^T], [0, 1]]              (adjoint restricted to planar twists)

All functions are pure; poses are immutable. The arithmetic of wrap_angle, compose, inverse, exp_twist and
integrate_body_velocity is the compiled kernels' (flightstack.paper.kernels, the only copy, also used by the
control tick and the compiled simulator); these functions convert Poses to and from pose vectors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightstack.paper import kernels as kern

TWO_PI = 2.0 * math.pi


_wrap_angle = kern.wrap_angle.py_func
"""kernels.wrap_angle's own Python code, run by the interpreter: the same operations, so the same bits,
without the compiled dispatch, whose first call in a process starts numba's compiler (about 1 s of CPU). A
process that only builds poses (the MCAP follower reading a mission) then never starts it."""


def wrap_angle(theta: float) -> float:
    """Wrap an angle in radians to (-π, π] (kernels.wrap_angle: equal to math.remainder(θ, 2π), −π → π)."""
    return float(_wrap_angle(float(theta)))


def rot_z(theta: float) -> np.ndarray:
    """R(θ): rotation by θ (rad) about z, shape (3, 3)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def hat(V: np.ndarray) -> np.ndarray:
    """V̂ ∈ R^{4×4} for a planar body velocity V = [v, ω] (the paper's ∧ operator)."""
    v = np.asarray(V, dtype=float)
    out = np.zeros((4, 4))
    out[0, 1] = -v[3]
    out[1, 0] = v[3]
    out[:3, 3] = v[:3]
    return out


@dataclass(frozen=True, slots=True)
class Pose:
    """g = (p, R(θ)): position p (3,) in metres and yaw θ in radians, wrapped to (-π, π]."""

    p: np.ndarray
    theta: float

    @staticmethod
    def make(p: np.ndarray | list[float] | tuple[float, ...], theta: float) -> Pose:
        """Build a pose from any 3-sequence and an angle; validates finiteness."""
        arr = np.array(p, dtype=float).reshape(3)
        if not (all(map(math.isfinite, arr.tolist())) and math.isfinite(theta)):
            raise ValueError(f"pose must be finite, got p={arr}, theta={theta}")
        return Pose(arr, wrap_angle(float(theta)))

    @staticmethod
    def identity() -> Pose:
        return Pose(np.zeros(3), 0.0)

    @property
    def R(self) -> np.ndarray:
        return rot_z(self.theta)

    def matrix(self) -> np.ndarray:
        """Homogeneous 4×4 matrix [[R, p], [0, 1]]."""
        g = np.eye(4)
        g[:3, :3] = self.R
        g[:3, 3] = self.p
        return g

    @staticmethod
    def from_matrix(g: np.ndarray) -> Pose:
        """Inverse of `matrix` for a rotation about z only (the tilt is not checked here)."""
        return Pose(np.array(g[:3, 3], dtype=float), wrap_angle(math.atan2(g[1, 0], g[0, 0])))

    def as_vector(self) -> np.ndarray:
        """ǧ = [p, θ] (4,): the GP input of the paper (eq. observe_vel)."""
        return np.array([self.p[0], self.p[1], self.p[2], self.theta])

    @staticmethod
    def from_vector(x: np.ndarray) -> Pose:
        return Pose(np.array(x[:3], dtype=float), wrap_angle(float(x[3])))


def _v(g: Pose) -> np.ndarray:
    """The pose vector [x, y, z, θ] the kernels take."""
    return np.array((g.p[0], g.p[1], g.p[2], g.theta), dtype=float)


def _pose(v: np.ndarray) -> Pose:
    return Pose(v[:3].copy(), float(v[3]))


def compose(a: Pose, b: Pose) -> Pose:
    """a·b = (p_a + R_a p_b, θ_a + θ_b)."""
    out = np.empty(4)
    kern.compose4(_v(a), _v(b), out)
    return _pose(out)


def inverse(g: Pose) -> Pose:
    """g⁻¹ = (-Rᵀ p, -θ)."""
    out = np.empty(4)
    kern.inverse4(_v(g), out)
    return _pose(out)


def relative(a: Pose, b: Pose) -> Pose:
    """a⁻¹·b (e.g. g_ij = g_wi⁻¹ g_wj)."""
    out = np.empty(4)
    kern.relative4(_v(a), _v(b), out)
    return _pose(out)


def vec(g: Pose) -> np.ndarray:
    """vec(g) = [p, sin θ] ∈ R⁴ (paper, Sec. 2.4)."""
    return np.array([g.p[0], g.p[1], g.p[2], math.sin(g.theta)])


def ad_R(theta: float) -> np.ndarray:
    """Ad_{R(θ)} = diag(R(θ), 1) ∈ R^{4×4}."""
    out = np.eye(4)
    out[:3, :3] = rot_z(theta)
    return out


def ad_g(g: Pose) -> np.ndarray:
    """Ad_g for planar twists: V' = Ad_g V is the body velocity V seen in the frame that g maps from.

    Ad_g = [[R, (p_y, -p_x, 0)^T], [0, 1]], i.e. (g V̂ g⁻¹)^∨.
    """
    out = np.eye(4)
    out[:3, :3] = rot_z(g.theta)
    out[0, 3] = g.p[1]
    out[1, 3] = -g.p[0]
    return out


def rotate_twist(theta: float, V: np.ndarray) -> np.ndarray:
    """Ad_{R(θ)} V without building the matrix (hot path)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c * V[0] - s * V[1], s * V[0] + c * V[1], V[2], V[3]])


def exp_twist(V: np.ndarray, dt: float) -> Pose:
    """exp(V̂ dt) as a Pose: the displacement after moving with constant body velocity V for dt seconds.

    Closed form for rotation about z (exact, no integration error):
        θ = ω dt,  p_xy = [[sin θ, -(1 - cos θ)], [1 - cos θ, sin θ]] / ω · v_xy,  p_z = v_z dt,
    with a Taylor series for |ω dt| < 1e-6 so that ω → 0 is smooth (kernels.exp_twist4).
    """
    out = np.empty(4)
    kern.exp_twist4(np.asarray(V, dtype=float).reshape(4).copy(), float(dt), out)
    return _pose(out)


def integrate_body_velocity(g: Pose, V: np.ndarray, dt: float) -> Pose:
    """g(t + dt) = g(t) exp(V̂ dt) for a body velocity V held constant over dt (zero-order hold)."""
    out = np.empty(4)
    kern.integrate4(_v(g), np.asarray(V, dtype=float).reshape(4).copy(), float(dt), out)
    return _pose(out)


# ---- batched versions on arrays of pose vectors [..., 4] = [x, y, z, θ] (for recordings) -----------------
def compose_arrays(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a·b for arrays of pose vectors [x, y, z, θ] (broadcasting over leading axes)."""
    c, s = np.cos(a[..., 3]), np.sin(a[..., 3])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    out[..., 1] = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    out[..., 2] = a[..., 2] + b[..., 2]
    out[..., 3] = np.angle(np.exp(1j * (a[..., 3] + b[..., 3])))
    return out


def inverse_arrays(g: np.ndarray) -> np.ndarray:
    """g⁻¹ for arrays of pose vectors."""
    c, s = np.cos(g[..., 3]), np.sin(g[..., 3])
    out = np.empty_like(g, dtype=float)
    out[..., 0] = -(c * g[..., 0] + s * g[..., 1])
    out[..., 1] = -(-s * g[..., 0] + c * g[..., 1])
    out[..., 2] = -g[..., 2]
    out[..., 3] = -g[..., 3]
    return out


def vec_arrays(g: np.ndarray) -> np.ndarray:
    """vec(g) = [p, sin θ] for arrays of pose vectors."""
    out = np.array(g, dtype=float)
    out[..., 3] = np.sin(g[..., 3])
    return out


def yaw_quaternions(theta: np.ndarray) -> np.ndarray:
    """The rotations about z by θ (rad) as unit quaternions (x, y, z, w) = (0, 0, sin θ/2, cos θ/2),
    shape θ.shape + (4,) (the 3-D viewers' form of a planar pose's attitude)."""
    half = 0.5 * np.asarray(theta, dtype=float)
    zero = np.zeros_like(half)
    return np.stack([zero, zero, np.sin(half), np.cos(half)], axis=-1)
