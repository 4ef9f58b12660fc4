"""Target body-velocity fields of the paper (pure functions; used by the simulator and as ground truth).

Duffing-like field of the paper's simulation (Sec. 5), with the world position p_w0 = (x, y, z):
    V_w0 = 0.5 Ad_{Rᵀ(θ_w0)} [y, z, v_z, 2ω]ᵀ
    v_z  = 0.2 (−δ z − α y − 3β x² y − γ ω sin θ_w0)
(ω is a constant of the field, 0.4 rad/s; the yaw rate is 0.5 · 2ω = ω.)
duffing_body_velocity is kernels.duffing_body_velocity (the world step and the oracle use it); the batch
version, vectorised numpy for training-data checks and benchmarks, is tested equal to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose


@dataclass(frozen=True)
class DuffingParams:
    alpha: float = -1.0
    beta: float = 1.0
    gamma: float = 0.39
    delta: float = 0.1
    omega: float = 0.4

    def packed(self) -> np.ndarray:
        """[α, β, γ, δ, ω]: the parameters as kernels.duffing_body_velocity takes them."""
        return np.array((self.alpha, self.beta, self.gamma, self.delta, self.omega), dtype=float)


def duffing_body_velocity(g_w0: Pose, prm: DuffingParams) -> np.ndarray:
    """V_w0 (4,) in the target's body frame: linear m/s, angular rad/s."""
    V = np.empty(4)
    g = np.array((g_w0.p[0], g_w0.p[1], g_w0.p[2], g_w0.theta), dtype=float)
    kern.duffing_body_velocity(g, prm.packed(), V)
    return V


def duffing_body_velocity_batch(X: np.ndarray, prm: DuffingParams) -> np.ndarray:
    """Vectorised duffing_body_velocity for rows X (N, 4) = [x, y, z, θ]; returns (N, 4)."""
    x, y, z, th = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    v_z = 0.2 * (
        -prm.delta * z - prm.alpha * y - 3.0 * prm.beta * x * x * y - prm.gamma * prm.omega * np.sin(th)
    )
    wx, wy, wz = 0.5 * y, 0.5 * z, 0.5 * v_z
    c, s = np.cos(th), np.sin(th)
    return np.stack([c * wx + s * wy, -s * wx + c * wy, wz, np.full_like(x, prm.omega)], axis=1)


@dataclass(frozen=True)
class DuffingField:
    """The Duffing-like field as the world's target field: g_w0 ↦ V_w0 (the compiled loop reads `prm`)."""

    prm: DuffingParams

    def __call__(self, g_w0: Pose) -> np.ndarray:
        return duffing_body_velocity(g_w0, self.prm)
