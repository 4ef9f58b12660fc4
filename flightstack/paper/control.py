"""Passivity-based cooperative pursuit law with a learned target velocity (paper eq. ui, DESIGN §4).

Symbols as in the paper. For drone i with estimate ḡ_i0, desired relative pose g_d and estimation
error e_e (from the image):
    g_c = g_d⁻¹ ḡ_i0,  e_c = vec(g_c),  c_i = Σ_{j∈N_i} vec(ḡ_w,i⁻¹ ḡ_w,j)
    u_c = −k_c e_c − k_s Ad_{R(θc)} c_i − Ad_{R(θc)} Ad_{R(θe)} μ_i
    u_e = −v_i k_e (e_e − Ad_{Rᵀ(θc)} e_c) − k_s c_i − Ad_{R(θe)} μ_i
    V_wi = −Ad_{g_d} u_c                                   (the drone's body-velocity command)
This is u = −K N e − B k_s c − A μ with N = [[I, 0], [−Ad_{Rᵀ(θc)}, I]], B = [Ad_{R(θc)}; I],
A = [Ad_{R(θc)} Ad_{R(θe)}; Ad_{R(θe)}]: the paper prints N with Ad_{R(θc)} and A, B transposed; the
versions here are the ones for which Lemma S (Ṡ_i = eᵢᵀ Nᵢᵀ uᵢ + eᵢᵀ [0; Ad_{R(θe)}] V_w0) holds, which
tests/test_control.py checks by finite differences. The arithmetic is the compiled kernels'
(flightstack.paper.kernels: control_error, consensus_term, pursuit_law, drone_velocity_command).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose


@dataclass(frozen=True)
class Gains:
    """k_c (4,), k_e (4,) per component of [p, sin θ]; k_s the consensus gain (all 1/s)."""

    k_c: np.ndarray
    k_e: np.ndarray
    k_s: float

    @staticmethod
    def make(k_c: Sequence[float] | float, k_e: Sequence[float] | float, k_s: float) -> Gains:
        kc = np.broadcast_to(np.asarray(k_c, dtype=float), (4,)).copy()
        ke = np.broadcast_to(np.asarray(k_e, dtype=float), (4,)).copy()
        if np.any(kc <= 0) or np.any(ke <= 0) or k_s < 0:
            raise ValueError("gains must be k_c > 0, k_e > 0, k_s >= 0")
        if kc[0] != kc[1] or ke[0] != ke[1]:
            # Ad_R mixes x and y; unequal x/y gains would make the law frame-dependent.
            raise ValueError("k_c and k_e must be equal in x and y (components 1 and 2)")
        return Gains(kc, ke, float(k_s))


def _vec4(x: np.ndarray | Sequence[float]) -> np.ndarray:
    out = np.array(x, dtype=float).reshape(-1)
    if out.shape != (4,):
        raise ValueError(f"expected 4 numbers, got shape {out.shape}")
    return out


def _pose4(g: Pose) -> np.ndarray:
    return np.array((g.p[0], g.p[1], g.p[2], g.theta), dtype=float)


def control_error(g_d: Pose, g_bar_i0: Pose) -> tuple[np.ndarray, float]:
    """e_c = vec(g_d⁻¹ ḡ_i0) (4,) and θ_c (rad)."""
    e_c = np.empty(4)
    theta_c = kern.control_error(_pose4(g_d), _pose4(g_bar_i0), e_c)
    return e_c, float(theta_c)


def consensus_term(g_bar_w_i: Pose, g_bar_w_neighbours: Sequence[Pose]) -> np.ndarray:
    """c_i = Σ_{j∈N_i} vec(ḡ_w,i⁻¹ ḡ_w,j) (4,); zero for no neighbours."""
    G = np.array([_pose4(g) for g in g_bar_w_neighbours], dtype=float).reshape(-1, 4)
    c_i = np.empty(4)
    kern.consensus_term(_pose4(g_bar_w_i), G, G.shape[0], c_i)
    return c_i


def pursuit_law(
    e_c: np.ndarray,
    theta_c: float,
    e_e: np.ndarray,
    theta_e: float,
    c_i: np.ndarray,
    mu: np.ndarray,
    gains: Gains,
    visible: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(u_c, u_e), each (4,), of the paper's law with the DESIGN §4 corrections (see module doc).

    visible is v_i: when the target is not seen, the innovation term v_i k_e (…) is dropped.
    """
    u_c, u_e = np.empty(4), np.empty(4)
    kern.pursuit_law(
        _vec4(e_c), float(theta_c), _vec4(e_e), float(theta_e), _vec4(c_i), _vec4(mu),
        gains.k_c, gains.k_e, float(gains.k_s), bool(visible), u_c, u_e,
    )  # fmt: skip
    return u_c, u_e


def drone_velocity_command(u_c: np.ndarray, g_d: Pose) -> np.ndarray:
    """V_wi = −Ad_{g_d} u_c: body velocity of the drone (m/s, rad/s) that realises û_c = −g_d⁻¹V̂_wi g_d."""
    V = np.empty(4)
    kern.drone_velocity_command(_vec4(u_c), _pose4(g_d), V)
    return V


def storage_function(e_c_pose: Pose, e_e_pose: Pose) -> float:
    """S_i = ½‖p_e‖² + ½φ(R_e) + ½‖p_c‖² + ½φ(R_c), φ(R) = ½‖I − R‖²_F = 2 − 2cos θ for R = Rz(θ)."""
    return (
        0.5 * float(e_e_pose.p @ e_e_pose.p)
        + (1.0 - math.cos(e_e_pose.theta))
        + 0.5 * float(e_c_pose.p @ e_c_pose.p)
        + (1.0 - math.cos(e_c_pose.theta))
    )
