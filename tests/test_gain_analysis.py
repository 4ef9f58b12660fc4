"""Gain condition of Theorem 1 against closed forms and brute-force evaluation."""

from __future__ import annotations

import math

import numpy as np

from flightstack.paper.control import Gains
from flightstack.paper.gain_analysis import gain_condition, lambda_K, laplacian, lipschitz_and_delta, p_matrix


class LinearExpert:
    """μ(x) = A x, var = const: its Lipschitz constants are the row norms of A."""

    def __init__(self, A: np.ndarray, var: float) -> None:
        self.A, self.var = A, var

    def predict(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return Xs @ self.A.T, np.full((len(Xs), 4), self.var)

    def mean_gradient(self, Xs: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.A, (len(Xs), 4, 4)).copy()


def test_laplacian_complete_graph() -> None:
    L = laplacian(3, [(0, 1), (0, 2), (1, 2)])
    assert np.allclose(np.sort(np.linalg.eigvalsh(L)), [0, 3, 3])
    assert np.allclose(L.sum(axis=1), 0)


def test_lambda_K_closed_form() -> None:
    """For K = k I₈: Nᵀ N = [[2I, −I], [−I, I]] has λ_min = (3 − √5)/2."""
    assert math.isclose(lambda_K(Gains.make(100, 100, 0)), 100 * (3 - math.sqrt(5)) / 2, rel_tol=1e-12)


def test_lambda_K_independent_of_theta_c() -> None:
    gains = Gains.make([13, 13, 13, 7], 8, 1)
    K = np.diag(np.concatenate([gains.k_c, gains.k_e]))
    for th in (0.0, 0.5, -1.3):
        c, s = math.cos(th), math.sin(th)
        AdT = np.eye(4)
        AdT[:2, :2] = [[c, s], [-s, c]]
        N = np.block([[np.eye(4), np.zeros((4, 4))], [-AdT, np.eye(4)]])
        assert math.isclose(np.linalg.eigvalsh(N.T @ K @ N).min(), lambda_K(gains), rel_tol=1e-10)


def test_p_matrix_eigenvalue_n3() -> None:
    assert math.isclose(np.linalg.eigvalsh(p_matrix(3)).max(), (1 + math.sqrt(3)) / 2, rel_tol=1e-12)


def test_lipschitz_of_linear_expert() -> None:
    A = np.array([[1.0, 2, 0, 0], [0, 0, 3, 0], [0, 0, 0, 0.5], [1, 1, 1, 1]])
    X = np.random.default_rng(0).normal(size=(50, 4))
    L, D = lipschitz_and_delta([LinearExpert(A, 0.04), LinearExpert(0.5 * A, 0.01)], X, beta=2.0)
    assert np.allclose(L, np.linalg.norm(A, axis=1))
    assert np.allclose(D, 2.0 * 0.2)


def test_gain_condition_formula_and_sign() -> None:
    A = np.eye(4) * 3.0
    X = np.random.default_rng(1).normal(size=(20, 4))
    gains = Gains.make(100, 100, 70)
    gc = gain_condition(
        gains, 3, [(0, 1), (0, 2), (1, 2)], [True] * 3, [LinearExpert(A, 0.01)], X, 10.0, 2.0, 0.5
    )
    L_mu = math.sqrt(4 * 9.0)
    lam_P = (1 + math.sqrt(3)) / 2
    expected = lambda_K(gains) - math.pi / 2 * L_mu * lam_P - 1 / 20
    assert math.isclose(gc.kappa, expected, rel_tol=1e-12)
    assert gc.satisfied and math.isfinite(gc.bound_b) and gc.bound_b > 0
    # a violated condition is reported, not hidden
    weak = gain_condition(
        Gains.make(1, 1, 0.1),
        3,
        [(0, 1), (1, 2)],
        [True, False, False],
        [LinearExpert(A, 0.01)],
        X,
        10.0,
        2.0,
        0.5,
    )
    assert weak.kappa < 0 and not weak.satisfied and weak.to_dict()["bound_b"] is None


def test_partial_visibility_uses_laplacian() -> None:
    """Only drone 0 sees: H = k_s L + diag(λ_K, 0), positive definite for a connected graph (Lemma 1)."""
    gains = Gains.make([13, 13, 13, 7], 8, 1)
    gc = gain_condition(gains, 2, [(0, 1)], [True, False], [], np.zeros((1, 4)), 10.0, 2.0, 0.5)
    H = np.array([[1.0, -1.0], [-1.0, 1.0]]) + np.diag([lambda_K(gains), 0.0])
    assert math.isclose(gc.lambda_H, np.linalg.eigvalsh(H).min(), rel_tol=1e-12)
    assert gc.lambda_H > 0
