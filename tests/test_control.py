"""The pursuit law against the paper's storage-function identity (Lemma S), by finite differences.

The error dynamics are integrated with scipy's expm on 4×4 matrices, independent of
flightstack.paper.geometry:
    ġ_e = û_e g_e + g_e V̂_w0,    ġ_c = û_c g_c − g_c û_e            (paper eq. e)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from flightstack.paper.control import (
    Gains,
    consensus_term,
    control_error,
    drone_velocity_command,
    pursuit_law,
    storage_function,
)
from flightstack.paper.geometry import Pose, ad_g, ad_R, compose, hat, inverse, vec

small = st.floats(-0.5, 0.5)
ang = st.floats(-1.2, 1.2)


def S_of(G_c: np.ndarray, G_e: np.ndarray) -> float:
    return storage_function(Pose.from_matrix(G_c), Pose.from_matrix(G_e))


def S_dot_fd(G_c: np.ndarray, G_e: np.ndarray, u_c: np.ndarray, u_e: np.ndarray, V0: np.ndarray) -> float:
    h = 1e-6

    def at(t: float) -> float:
        Ge = expm(hat(u_e) * t) @ G_e @ expm(hat(V0) * t)
        Gc = expm(hat(u_c) * t) @ G_c @ expm(-hat(u_e) * t)
        return S_of(Gc, Ge)

    return (at(h) - at(-h)) / (2 * h)


@st.composite
def error_state(draw: st.DrawFn) -> tuple[np.ndarray, ...]:
    g_c = Pose.make([draw(small), draw(small), draw(small)], draw(ang))
    g_e = Pose.make([draw(small), draw(small), draw(small)], draw(ang))
    u_c = np.array([draw(small) for _ in range(4)])
    u_e = np.array([draw(small) for _ in range(4)])
    V0 = np.array([draw(small) for _ in range(4)])
    return g_c, g_e, u_c, u_e, V0


@given(error_state())
@settings(max_examples=60, deadline=None)
def test_lemma_S_with_corrected_N(state: tuple) -> None:
    """Ṡ_i = e_iᵀ N_iᵀ u_i + e_iᵀ [0; Ad_{R(θe)}] V_w0 with N = [[I, 0], [−Ad_{Rᵀ(θc)}, I]]."""
    g_c, g_e, u_c, u_e, V0 = state
    e = np.concatenate([vec(g_c), vec(g_e)])
    N = np.block([[np.eye(4), np.zeros((4, 4))], [-ad_R(-g_c.theta), np.eye(4)]])
    predicted = e @ N.T @ np.concatenate([u_c, u_e]) + vec(g_e) @ ad_R(g_e.theta) @ V0
    assert math.isclose(
        S_dot_fd(g_c.matrix(), g_e.matrix(), u_c, u_e, V0), predicted, rel_tol=1e-6, abs_tol=1e-8
    )


def test_paper_N_as_printed_is_wrong() -> None:
    """The printed N (with Ad_{R(θc)}) disagrees with Ṡ when θ_c ≠ 0: the DESIGN §4 correction is needed."""
    g_c, g_e = Pose.make([0.3, -0.2, 0.1], 0.8), Pose.make([0.1, 0.2, -0.1], 0.3)
    u_c, u_e, V0 = np.array([0.1, 0.2, 0.0, 0.1]), np.array([0.3, -0.4, 0.1, 0.2]), np.zeros(4)
    e = np.concatenate([vec(g_c), vec(g_e)])
    N_printed = np.block([[np.eye(4), np.zeros((4, 4))], [-ad_R(g_c.theta), np.eye(4)]])
    wrong = e @ N_printed.T @ np.concatenate([u_c, u_e])
    assert abs(S_dot_fd(g_c.matrix(), g_e.matrix(), u_c, u_e, V0) - wrong) > 1e-3


@given(error_state(), st.floats(1.0, 50.0), st.floats(1.0, 50.0))
@settings(max_examples=60, deadline=None)
def test_law_with_exact_mu_makes_S_decrease(state: tuple, kc: float, ke: float) -> None:
    """With μ = V_w0 and no neighbours the law gives Ṡ = −eᵀ Nᵀ K N e ≤ 0 (the V_w0 term cancels)."""
    g_c, g_e, _, _, V0 = state
    gains = Gains.make(kc, ke, 0.0)
    e_c, e_e = vec(g_c), vec(g_e)
    u_c, u_e = pursuit_law(e_c, g_c.theta, e_e, g_e.theta, np.zeros(4), V0, gains, True)
    N = np.block([[np.eye(4), np.zeros((4, 4))], [-ad_R(-g_c.theta), np.eye(4)]])
    K = np.diag(np.concatenate([gains.k_c, gains.k_e]))
    e = np.concatenate([e_c, e_e])
    expected = -e @ N.T @ K @ N @ e
    sdot = S_dot_fd(g_c.matrix(), g_e.matrix(), u_c, u_e, V0)
    assert math.isclose(sdot, expected, rel_tol=1e-5, abs_tol=1e-7)
    assert sdot <= 1e-9


def test_law_matches_matrix_form() -> None:
    """u = −K N e − B k_s c − A μ with the matrices of the module docstring."""
    rng = np.random.default_rng(3)
    e_c, e_e, c, mu = (rng.normal(size=4) for _ in range(4))
    th_c, th_e = 0.4, -0.3
    gains = Gains.make([2, 2, 3, 4], [5, 5, 6, 7], 1.5)
    u_c, u_e = pursuit_law(e_c, th_c, e_e, th_e, c, mu, gains, True)
    N = np.block([[np.eye(4), np.zeros((4, 4))], [-ad_R(-th_c), np.eye(4)]])
    K = np.diag(np.concatenate([gains.k_c, gains.k_e]))
    B = np.vstack([ad_R(th_c), np.eye(4)])
    A = np.vstack([ad_R(th_c) @ ad_R(th_e), ad_R(th_e)])
    u = -K @ N @ np.concatenate([e_c, e_e]) - B @ (gains.k_s * c) - A @ mu
    assert np.allclose(np.concatenate([u_c, u_e]), u)
    # not visible: v_i = 0 removes the k_e term only
    u_c0, u_e0 = pursuit_law(e_c, th_c, e_e, th_e, c, mu, gains, False)
    assert np.allclose(u_c0, u_c)
    assert np.allclose(u_e0, u_e + gains.k_e * (e_e - ad_R(-th_c) @ e_c))


def test_drone_command_realises_u_c() -> None:
    """V_wi = −Ad_{g_d} u_c makes ġ_c = û_c g_c for u_e = 0 (g_c = g_d⁻¹ g_wi⁻¹ g_w0, static target)."""
    g_d = Pose.make([0.4, -0.2, 1.5], 0.3)
    g_wi = Pose.make([1.0, 0.5, -1.0], -0.2)
    g_w0 = Pose.make([1.3, 0.2, 0.4], 0.1)
    u_c = np.array([0.2, -0.1, 0.3, 0.4])
    V = drone_velocity_command(u_c, g_d)
    h = 1e-6

    def g_c(t: float) -> np.ndarray:
        Gwi = g_wi.matrix() @ expm(hat(V) * t)
        return np.linalg.inv(g_d.matrix()) @ np.linalg.inv(Gwi) @ g_w0.matrix()

    fd = (g_c(h) - g_c(-h)) / (2 * h)
    assert np.allclose(fd, hat(u_c) @ g_c(0.0), atol=1e-6)
    assert np.allclose(V, -ad_g(g_d) @ u_c)


def test_consensus_term() -> None:
    g = Pose.make([0.1, 0.2, 0.3], 0.4)
    assert np.allclose(consensus_term(g, [g, g]), 0.0)
    assert np.allclose(consensus_term(g, []), 0.0)
    h = Pose.make([0.3, -0.1, 0.2], -0.2)
    ref = np.linalg.inv(g.matrix()) @ h.matrix()
    assert np.allclose(consensus_term(g, [h]), [*ref[:3, 3], ref[1, 0]])


def test_control_error() -> None:
    g_d = Pose.make([0, 0, 1.5], 0.2)
    e_c, th = control_error(g_d, g_d)
    assert np.allclose(e_c, 0) and th == 0
    g = Pose.make([0.1, 0, 1.5], 0.5)
    e_c, th = control_error(g_d, g)
    assert np.allclose(e_c, vec(compose(inverse(g_d), g))) and math.isclose(th, 0.3)


def test_gains_validation() -> None:
    with pytest.raises(ValueError):
        Gains.make([1, 2, 3, 4], 1, 1)
    with pytest.raises(ValueError):
        Gains.make(1, 0, 1)
