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
tests/test_control.py checks by finite differences.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from flightstack.paper.geometry import Pose, ad_g, compose, inverse, vec, wrap_angle


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


def control_error(g_d: Pose, g_bar_i0: Pose) -> tuple[np.ndarray, float]:
    """e_c = vec(g_d⁻¹ ḡ_i0) (4,) and θ_c (rad)."""
    g_c = compose(inverse(g_d), g_bar_i0)
    return vec(g_c), g_c.theta


def consensus_term(g_bar_w_i: Pose, g_bar_w_neighbours: Sequence[Pose]) -> np.ndarray:
    """c_i = Σ_{j∈N_i} vec(ḡ_w,i⁻¹ ḡ_w,j) (4,); zero for no neighbours."""
    inv_i = inverse(g_bar_w_i)
    # vec(ḡ_w,i⁻¹ ḡ_w,j) with compose() and vec() inlined on floats (same arithmetic, no temporaries)
    ca, sa = math.cos(inv_i.theta), math.sin(inv_i.theta)
    ax, ay, az = inv_i.p.tolist()
    c0 = c1 = c2 = c3 = 0.0
    for g_j in g_bar_w_neighbours:
        bx, by, bz = g_j.p.tolist()
        c0 += ax + ca * bx - sa * by
        c1 += ay + sa * bx + ca * by
        c2 += az + bz
        c3 += math.sin(wrap_angle(inv_i.theta + g_j.theta))
    return np.array([c0, c1, c2, c3])


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
    v_i = 1.0 if visible else 0.0
    # the same element-wise arithmetic as the numpy expressions
    #   u_e = −v_i k_e (e_e − Ad_{Rᵀ(θc)} e_c) − k_s c_i − Ad_{R(θe)} μ_i
    #   u_c = −k_c e_c − k_s Ad_{R(θc)} c_i − Ad_{R(θc)} Ad_{R(θe)} μ_i
    # on Python floats (4-vectors are cheaper in scalar code than in numpy calls; results are identical)
    ee = e_e.tolist() if isinstance(e_e, np.ndarray) else [float(v) for v in e_e]
    ec = e_c.tolist() if isinstance(e_c, np.ndarray) else [float(v) for v in e_c]
    ci = c_i.tolist() if isinstance(c_i, np.ndarray) else [float(v) for v in c_i]
    m = mu.tolist() if isinstance(mu, np.ndarray) else [float(v) for v in mu]
    ke, kc, ks = gains.k_e.tolist(), gains.k_c.tolist(), gains.k_s
    # Ad_{R(θe)} μ_i
    c, s = math.cos(theta_e), math.sin(theta_e)
    mu_e = (c * m[0] - s * m[1], s * m[0] + c * m[1], m[2], m[3])
    # Ad_{Rᵀ(θc)} e_c = Ad_{R(−θc)} e_c
    c, s = math.cos(-theta_c), math.sin(-theta_c)
    ec_r = (c * ec[0] - s * ec[1], s * ec[0] + c * ec[1], ec[2], ec[3])
    u_e = [-v_i * ke[k] * (ee[k] - ec_r[k]) - ks * ci[k] - mu_e[k] for k in range(4)]
    # Ad_{R(θc)} c_i and Ad_{R(θc)} Ad_{R(θe)} μ_i
    c, s = math.cos(theta_c), math.sin(theta_c)
    ci_r = (c * ci[0] - s * ci[1], s * ci[0] + c * ci[1], ci[2], ci[3])
    mu_r = (c * mu_e[0] - s * mu_e[1], s * mu_e[0] + c * mu_e[1], mu_e[2], mu_e[3])
    u_c = [-kc[k] * ec[k] - ks * ci_r[k] - mu_r[k] for k in range(4)]
    return np.array(u_c), np.array(u_e)


def drone_velocity_command(u_c: np.ndarray, g_d: Pose) -> np.ndarray:
    """V_wi = −Ad_{g_d} u_c: body velocity of the drone (m/s, rad/s) that realises û_c = −g_d⁻¹V̂_wi g_d."""
    return -(ad_g(g_d) @ u_c)


def storage_function(e_c_pose: Pose, e_e_pose: Pose) -> float:
    """S_i = ½‖p_e‖² + ½φ(R_e) + ½‖p_c‖² + ½φ(R_c), φ(R) = ½‖I − R‖²_F = 2 − 2cos θ for R = Rz(θ)."""
    return (
        0.5 * float(e_e_pose.p @ e_e_pose.p)
        + (1.0 - math.cos(e_e_pose.theta))
        + 0.5 * float(e_c_pose.p @ e_c_pose.p)
        + (1.0 - math.cos(e_c_pose.theta))
    )
