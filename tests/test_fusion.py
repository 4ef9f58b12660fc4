"""Tests of flightstack.paper.fusion: PoE vs numerical density product, BCM vs exact Bayes, rule
properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.integrate import simpson
from scipy.stats import norm

from flightstack.paper.fusion import FUSION_RULES, fuse, fusion_weights


@st.composite
def experts(draw, max_k: int = 6, max_d: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(mu, var), both (K, D): means in [-100, 100], variances in [1e-4, 1e2]."""
    k = draw(st.integers(1, max_k))
    d = draw(st.integers(1, max_d))
    mu = draw(arrays(float, (k, d), elements=st.floats(-100.0, 100.0)))
    var = draw(arrays(float, (k, d), elements=st.floats(1e-4, 1e2)))
    return mu, var


# --------------------------------------------------------------------------------------------------------
# PoE vs an independent numerical reference
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(5))
def test_poe_matches_numerical_product_of_densities(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_experts, n_out = 2 + seed % 3, 3
    mu = rng.uniform(-2.0, 2.0, (n_experts, n_out))
    var = rng.uniform(0.05, 2.0, (n_experts, n_out))
    mu_poe, var_poe = fuse(mu, var, "poe")
    for d in range(n_out):
        lo = mu[:, d].min() - 12.0 * np.sqrt(var[:, d].max())
        hi = mu[:, d].max() + 12.0 * np.sqrt(var[:, d].max())
        x = np.linspace(lo, hi, 200_001)
        density = np.prod([norm.pdf(x, mu[k, d], np.sqrt(var[k, d])) for k in range(n_experts)], axis=0)
        density /= simpson(density, x=x)
        mean = simpson(x * density, x=x)
        variance = simpson((x - mean) ** 2 * density, x=x)
        np.testing.assert_allclose(mu_poe[d], mean, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(var_poe[d], variance, rtol=1e-8)


def test_poe_is_the_papers_formula_by_hand() -> None:
    mu = np.array([[1.0], [3.0]])
    var = np.array([[1.0], [3.0]])
    # precisions 1 and 1/3: var = 1 / (4/3) = 0.75, μ = 0.75 (1 + 1) = 1.5
    mu_poe, var_poe = fuse(mu, var)
    np.testing.assert_allclose(var_poe, [0.75])
    np.testing.assert_allclose(mu_poe, [1.5])
    np.testing.assert_allclose(fusion_weights(var, "poe")[:, 0], [0.75, 0.25])


# --------------------------------------------------------------------------------------------------------
# BCM vs the exact Bayesian posterior
# --------------------------------------------------------------------------------------------------------
def exact_experts(
    prior_var: np.ndarray, noise_var: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Scalar x ~ N(0, s²) per column; y_k ~ N(x, r_k) independent.

    Returns the experts' posteriors (each from the prior and its own observation only), (K, D) each, and
    the exact posterior given all K observations, (D,) each.
    """
    prec_k = 1.0 / prior_var + 1.0 / noise_var
    var_k = 1.0 / prec_k
    mu_k = var_k * y / noise_var
    var_all = 1.0 / (1.0 / prior_var + np.sum(1.0 / noise_var, axis=0))
    mu_all = var_all * np.sum(y / noise_var, axis=0)
    return mu_k, var_k, mu_all, var_all


@pytest.mark.parametrize("seed", range(5))
def test_bcm_equals_exact_bayes_and_poe_does_not(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_experts, n_out = 2 + seed, 4
    s2 = rng.uniform(0.5, 3.0, n_out)  # prior variance per output dimension
    r = rng.uniform(0.1, 5.0, (n_experts, n_out))  # observation-noise variances
    x_true = rng.normal(0.0, np.sqrt(s2))
    y = x_true + rng.normal(0.0, np.sqrt(r))
    mu_k, var_k, mu_all, var_all = exact_experts(s2, r, y)

    mu_bcm, var_bcm = fuse(mu_k, var_k, "bcm", prior_var=np.broadcast_to(s2, (n_experts, n_out)))
    np.testing.assert_allclose(mu_bcm, mu_all, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(var_bcm, var_all, rtol=1e-10)

    # PoE counts the prior K times: its precision exceeds the exact one by exactly (K − 1)/s².
    mu_poe, var_poe = fuse(mu_k, var_k, "poe")
    assert np.all(var_poe < var_all * (1.0 - 1e-3))
    np.testing.assert_allclose(1.0 / var_poe - 1.0 / var_all, (n_experts - 1) / s2, rtol=1e-10)
    assert not np.allclose(mu_poe, mu_all, rtol=1e-6, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 8),
    st.floats(0.1, 10.0),
    st.lists(st.floats(0.01, 10.0), min_size=8, max_size=8),
    st.lists(st.floats(-5.0, 5.0), min_size=8, max_size=8),
)
def test_bcm_exact_bayes_property(k: int, s2: float, r: list[float], y: list[float]) -> None:
    noise = np.array(r[:k])[:, None]
    obs = np.array(y[:k])[:, None]
    mu_k, var_k, mu_all, var_all = exact_experts(np.array([s2]), noise, obs)
    mu_bcm, var_bcm = fuse(mu_k, var_k, "bcm", prior_var=s2)
    np.testing.assert_allclose(var_bcm, var_all, rtol=1e-10)
    np.testing.assert_allclose(mu_bcm, mu_all, rtol=1e-9, atol=1e-10)


def test_bcm_uses_mean_prior_over_experts() -> None:
    mu = np.array([[0.3, -1.0], [0.5, 2.0], [0.1, 0.0]])
    var = np.array([[0.2, 0.5], [0.4, 0.3], [0.3, 0.9]])
    prior = np.array([[1.0, 2.0], [1.5, 2.5], [2.0, 3.0]])
    for rule in ("bcm", "rbcm"):
        a = fuse(mu, var, rule, prior_var=prior)
        b = fuse(mu, var, rule, prior_var=prior.mean(axis=0))
        np.testing.assert_allclose(a, b, rtol=1e-14)


def test_bcm_fallback_when_textbook_precision_is_not_positive() -> None:
    # three experts all claiming twice the prior variance: Σ 1/var_k + (1 − K)/σ_**² = 1.5 − 2 = −0.5
    mu = np.array([[0.2], [-0.1], [0.4]])
    var = np.full((3, 1), 2.0)
    mu_f, var_f = fuse(mu, var, "bcm", prior_var=1.0)
    assert np.all(np.isfinite(var_f)) and np.all(var_f > 0)
    np.testing.assert_allclose(var_f, [2.0])  # = max_k var_k (precision clipped at min_k var_k^{-1})
    np.testing.assert_allclose(mu_f, var_f * np.sum(mu / var, axis=0))
    # precision just above zero (0 < textbook < min_k var_k^{-1}) is clipped too: continuous in the inputs
    var2 = np.array([[1.0], [1.6], [1.8]])
    textbook = np.sum(1.0 / var2) - 2.0
    assert 0.0 < textbook < 1.0 / 1.8
    np.testing.assert_allclose(fuse(mu, var2, "bcm", prior_var=1.0)[1], [1.8])


@settings(max_examples=200, deadline=None)
@given(experts(), st.floats(1e-3, 1e3))
def test_bcm_fallback_is_noop_for_consistent_inputs(ex: tuple[np.ndarray, np.ndarray], prior: float) -> None:
    mu, var = ex
    var = np.minimum(var, prior)  # consistent: no expert less certain than the prior
    k = var.shape[0]
    _, var_f = fuse(mu, var, "bcm", prior_var=prior)
    np.testing.assert_allclose(1.0 / var_f, np.sum(1.0 / var, axis=0) + (1 - k) / prior, rtol=1e-10)
    assert np.all(var_f <= var.min(axis=0) * (1 + 1e-12))  # more data, more certain than any expert


# --------------------------------------------------------------------------------------------------------
# gPoE / rBCM properties
# --------------------------------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(experts())
def test_gpoe_mean_equals_poe_and_variance_is_k_times(ex: tuple[np.ndarray, np.ndarray]) -> None:
    mu, var = ex
    k = var.shape[0]
    mu_poe, var_poe = fuse(mu, var, "poe")
    mu_g, var_g = fuse(mu, var, "gpoe")
    np.testing.assert_allclose(mu_g, mu_poe, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(var_g, k * var_poe, rtol=1e-12)
    # gPoE variance is the harmonic mean of the expert variances
    assert np.all(var_g >= var.min(axis=0) * (1 - 1e-12))
    assert np.all(var_g <= var.max(axis=0) * (1 + 1e-12))
    np.testing.assert_allclose(fusion_weights(var, "gpoe").sum(axis=0), 1.0, rtol=1e-12)


@pytest.mark.parametrize("k", [1, 2, 5])
def test_rbcm_with_all_experts_at_prior_returns_prior(k: int) -> None:
    prior = np.array([0.7, 2.0, 5.0])
    mu = np.random.default_rng(k).normal(size=(k, 3))
    var = np.broadcast_to(prior, (k, 3)).copy()
    mu_f, var_f = fuse(mu, var, "rbcm", prior_var=prior)
    np.testing.assert_allclose(var_f, prior, rtol=1e-14)
    np.testing.assert_array_equal(fusion_weights(var, "rbcm", prior_var=prior), 0.0)
    np.testing.assert_array_equal(mu_f, 0.0)


def test_rbcm_by_hand() -> None:
    # one expert at the prior (β = 0), one with var = σ_**² e^{-2} (β = 1): β-weighted precision e²
    prior = 1.0
    var = np.array([[1.0], [np.exp(-2.0)]])
    mu = np.array([[5.0], [0.5]])
    mu_f, var_f = fuse(mu, var, "rbcm", prior_var=prior)
    # (var)^{-1} = 0·1 + 1·e² + (1 − 1)·1 = e²
    np.testing.assert_allclose(var_f, [np.exp(-2.0)], rtol=1e-14)
    np.testing.assert_allclose(mu_f, [0.5], rtol=1e-14)


@settings(max_examples=200, deadline=None)
@given(experts(), st.floats(1e-2, 1e2))
def test_rbcm_never_less_certain_than_prior(ex: tuple[np.ndarray, np.ndarray], prior: float) -> None:
    mu, var = ex
    mu_f, var_f = fuse(mu, var, "rbcm", prior_var=prior)
    assert np.all(np.isfinite(mu_f)) and np.all(var_f > 0)
    assert np.all(var_f <= prior * (1 + 1e-9))


def test_single_expert_is_returned_by_poe_gpoe_bcm() -> None:
    mu = np.array([[0.3, -2.0]])
    var = np.array([[0.1, 0.4]])
    for rule in ("poe", "gpoe", "bcm"):
        mu_f, var_f = fuse(mu, var, rule, prior_var=1.0)
        np.testing.assert_allclose(mu_f, mu[0], rtol=1e-14)
        np.testing.assert_allclose(var_f, var[0], rtol=1e-14)


def test_identical_experts_poe_shrinks_gpoe_does_not() -> None:
    k = 3
    mu = np.repeat(np.array([[0.3, -2.0]]), k, axis=0)
    var = np.repeat(np.array([[0.1, 0.4]]), k, axis=0)
    np.testing.assert_allclose(fuse(mu, var, "poe"), (mu[0], var[0] / k), rtol=1e-14)
    np.testing.assert_allclose(fuse(mu, var, "gpoe"), (mu[0], var[0]), rtol=1e-14)


# --------------------------------------------------------------------------------------------------------
# weights
# --------------------------------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(experts(), st.floats(1e-2, 1e2))
def test_fusion_weights_reproduce_the_mean(ex: tuple[np.ndarray, np.ndarray], prior: float) -> None:
    mu, var = ex
    w_poe = fusion_weights(var, "poe")
    assert w_poe.shape == var.shape
    np.testing.assert_allclose(w_poe.sum(axis=0), 1.0, rtol=1e-12)
    assert np.all(w_poe >= 0)
    for rule in FUSION_RULES:
        w = fusion_weights(var, rule, prior_var=prior)
        mu_f, _ = fuse(mu, var, rule, prior_var=prior)
        np.testing.assert_allclose(mu_f, np.sum(w * mu, axis=0), rtol=1e-12, atol=1e-9)


@settings(max_examples=300, deadline=None)
@given(experts())
def test_poe_mean_within_expert_means_and_variance_below_each(ex: tuple[np.ndarray, np.ndarray]) -> None:
    mu, var = ex
    mu_f, var_f = fuse(mu, var, "poe")
    scale = 1e-12 * np.maximum(1.0, np.abs(mu).max(axis=0))
    assert np.all(mu_f >= mu.min(axis=0) - scale)
    assert np.all(mu_f <= mu.max(axis=0) + scale)
    assert np.all(var_f <= var.min(axis=0) * (1 + 1e-12))


# --------------------------------------------------------------------------------------------------------
# invalid inputs
# --------------------------------------------------------------------------------------------------------
def test_invalid_inputs_raise() -> None:
    mu = np.zeros((2, 3))
    var = np.ones((2, 3))
    bad = var.copy()
    cases = [
        (lambda: fuse(mu, var, "product"), "valid rules are poe, gpoe, bcm, rbcm"),
        (lambda: fusion_weights(var, "moe"), "unknown fusion rule 'moe'"),
        (lambda: fuse(mu, np.where(np.eye(2, 3) > 0, 0.0, 1.0)), "var must be finite and > 0"),
        (lambda: fuse(mu, -var), "var must be finite and > 0"),
        (lambda: fuse(mu, np.full((2, 3), np.inf)), "var must be finite and > 0"),
        (lambda: fuse(mu, np.full((2, 3), np.nan)), "var must be finite and > 0"),
        (lambda: fuse(mu, var, "bcm"), "needs prior_var"),
        (lambda: fuse(mu, var, "rbcm"), "needs prior_var"),
        (lambda: fusion_weights(var, "bcm"), "needs prior_var"),
        (lambda: fuse(mu, var, "bcm", prior_var=0.0), "prior_var must be finite and > 0"),
        (lambda: fuse(mu, var, "rbcm", prior_var=np.ones(4)), "prior_var must broadcast"),
        (lambda: fuse(mu[:1], var), "same shape"),
        (lambda: fuse(np.full((2, 3), np.nan), var), "mu must be finite"),
        (lambda: fuse(mu[0], var[0]), r"var must have shape \(K, D\)"),
        (lambda: fuse(np.zeros((0, 3)), np.ones((0, 3))), r"var must have shape \(K, D\)"),
    ]
    bad[0, 0] = 0.0
    cases.append((lambda: fuse(mu, bad, "poe"), "var must be finite and > 0"))
    for call, message in cases:
        with pytest.raises(ValueError, match=message):
            call()
