"""Hyperparameters shared by all GP experts (Deisenroth & Ng 2015; flightstack/paper/gp_shared_fit.py):
the joint objective, its gradient, the fit, scikit-learn as a reference, and the mission option."""

from __future__ import annotations

import inspect
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import resolved_document
from flightstack.learning.training import ExpertData, train_experts
from flightstack.paper.gp import GPExpert, GPHyperparameters, log_marginal_likelihood_and_grad
from flightstack.paper.gp_fit import LOG_LENGTH_BOUNDS, LOG_SIGMA_F_BOUNDS, fit_hyperparameters
from flightstack.paper.gp_shared_fit import (
    fit_shared_hyperparameters,
    shared_log_marginal_likelihood_and_grad,
)
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch

NOISE_VAR = 0.01
EDGES = (-0.7, 0.6)  # paper_sim's expert bands along x
SEEDS = (0, 1, 2)


def duffing_experts(seed: int, m: int = 10) -> list[tuple[np.ndarray, np.ndarray]]:
    """3 experts × m samples of the paper's Duffing body velocity + N(0, 0.01 I), along the closed path
    x = 1.5 cos t, y = sin t, z = 0, θ = t + φ wrapped to [−π, π) (φ from the seed), split into the x bands
    (−∞, −0.7), [−0.7, 0.6), [0.6, ∞); m samples evenly spaced along the path inside each band."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0 * math.pi, 2000, endpoint=False)
    theta = (t + rng.uniform(-math.pi, math.pi) + math.pi) % (2.0 * math.pi) - math.pi
    path = np.stack([1.5 * np.cos(t), np.sin(t), np.zeros_like(t), theta], axis=1)
    edges = [-math.inf, *EDGES, math.inf]
    out = []
    for lo, hi in itertools.pairwise(edges):
        inside = np.flatnonzero((path[:, 0] >= lo) & (path[:, 0] < hi))
        X = path[inside[np.linspace(0, inside.size - 1, m).round().astype(int)]]
        Y = duffing_body_velocity_batch(X, DuffingParams())
        out.append((X, Y + math.sqrt(NOISE_VAR) * rng.standard_normal(Y.shape)))
    return out


def summed_lml(datasets: list[tuple[np.ndarray, np.ndarray]], hyper: GPHyperparameters, d: int) -> float:
    """Σ_k log p(Y_k,d | X_k, θ_d), each term from the validated single-expert function."""
    return sum(
        log_marginal_likelihood_and_grad(
            X, Y[:, d], math.log(hyper.sigma_f[d]), np.log(hyper.length_scales[d]), hyper.noise_var[d]
        )[0]
        for X, Y in datasets
    )


def fit_shared(datasets: list[tuple[np.ndarray, np.ndarray]], seed: int = 0) -> GPHyperparameters:
    return fit_shared_hyperparameters(datasets, NOISE_VAR, restarts=5, seed=seed)


def fit_own(X: np.ndarray, Y: np.ndarray, seed: int = 0) -> GPHyperparameters:
    return fit_hyperparameters(
        X,
        Y,
        NOISE_VAR,
        restarts=5,
        seed=seed,
        log_sigma_f_bounds=LOG_SIGMA_F_BOUNDS,
        log_length_bounds=LOG_LENGTH_BOUNDS,
        maxiter=None,
    )[2]


# --------------------------------------------------------------------------------------------------------
# the joint objective
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", SEEDS)
def test_joint_gradient_matches_central_differences(seed: int) -> None:
    data = duffing_experts(seed)
    rng = np.random.default_rng(100 + seed)
    h = 1e-5
    for d in range(4):
        one_output = [(X, Y[:, d]) for X, Y in data]
        theta = rng.uniform([-2.0, -1.5, -1.5, -1.5, -1.5], [1.0, 1.5, 1.5, 1.5, 1.5])
        lml, grad = shared_log_marginal_likelihood_and_grad(one_output, theta[0], theta[1:], NOISE_VAR)
        fd = np.empty_like(theta)
        for i in range(theta.size):
            e = np.zeros_like(theta)
            e[i] = h
            up, dn = (
                shared_log_marginal_likelihood_and_grad(one_output, t[0], t[1:], NOISE_VAR)[0]
                for t in (theta + e, theta - e)
            )
            fd[i] = (up - dn) / (2.0 * h)
        assert math.isfinite(lml)
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * max(1.0, abs(lml)))


@pytest.mark.parametrize("seed", SEEDS)
def test_joint_objective_is_the_sum_of_the_experts_lmls(seed: int) -> None:
    data = duffing_experts(seed)
    rng = np.random.default_rng(200 + seed)
    for d in range(4):
        log_sf, log_l = rng.uniform(-2.0, 1.0), rng.uniform(-1.5, 1.5, 4)
        lml, grad = shared_log_marginal_likelihood_and_grad(
            [(X, Y[:, d]) for X, Y in data], log_sf, log_l, NOISE_VAR
        )
        terms = [log_marginal_likelihood_and_grad(X, Y[:, d], log_sf, log_l, NOISE_VAR) for X, Y in data]
        np.testing.assert_allclose(lml, sum(t[0] for t in terms), rtol=1e-12)
        np.testing.assert_allclose(grad, sum(t[1] for t in terms), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_one_expert_shared_fit_is_the_per_expert_fit(seed: int) -> None:
    X, Y = duffing_experts(seed)[seed]
    shared = fit_shared([(X, Y)], seed=seed)
    own = fit_own(X, Y, seed=seed)
    for d in range(4):
        assert summed_lml([(X, Y)], shared, d) == pytest.approx(summed_lml([(X, Y)], own, d), abs=1e-6)


def test_default_bounds_are_gpexpert_fits() -> None:
    params = inspect.signature(GPExpert.fit).parameters
    assert params["log_sigma_f_bounds"].default == LOG_SIGMA_F_BOUNDS
    assert params["log_length_bounds"].default == LOG_LENGTH_BOUNDS


# --------------------------------------------------------------------------------------------------------
# scikit-learn as the reference of the LML at the fitted θ
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", SEEDS)
def test_lml_at_the_fitted_theta_matches_sklearn(seed: int) -> None:
    X, Y = duffing_experts(seed)[1]
    d = (0, 1, 2)[seed]
    hyper = fit_shared([(X, Y[:, d : d + 1])], seed=seed)
    sf, lengths = float(hyper.sigma_f[0]), hyper.length_scales[0]
    kernel = ConstantKernel(sf**2) * RBF(length_scale=lengths) + WhiteKernel(
        NOISE_VAR, noise_level_bounds="fixed"
    )
    ref = GaussianProcessRegressor(kernel=kernel, alpha=0.0, optimizer=None, normalize_y=False).fit(
        X, Y[:, d]
    )
    ref_lml, ref_grad = ref.log_marginal_likelihood(ref.kernel_.theta, eval_gradient=True)
    lml, grad = shared_log_marginal_likelihood_and_grad(
        [(X, Y[:, d])], math.log(sf), np.log(lengths), NOISE_VAR
    )
    np.testing.assert_allclose(lml, ref_lml, rtol=1e-9)
    # sklearn's θ is [log σ_f², log l_1..l_4]: ∂/∂log σ_f = 2 ∂/∂log σ_f²; at the optimum both ≈ 0
    np.testing.assert_allclose(grad, ref_grad * np.array([2.0, 1, 1, 1, 1]), atol=1e-7)


# --------------------------------------------------------------------------------------------------------
# the shared fit maximises the summed LML
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", SEEDS)
def test_shared_fit_beats_every_experts_own_hyperparameters(seed: int) -> None:
    data = duffing_experts(seed)
    shared = fit_shared(data, seed=seed)
    owns = [fit_own(X, Y, seed=seed + k) for k, (X, Y) in enumerate(data)]
    for d in range(4):
        best = summed_lml(data, shared, d)
        for own in owns:
            assert best >= summed_lml(data, own, d) - 1e-6
    # and it is a stationary point of the summed objective (or on a bound)
    for d in range(4):
        theta = np.concatenate([[math.log(shared.sigma_f[d])], np.log(shared.length_scales[d])])
        _, grad = shared_log_marginal_likelihood_and_grad(
            [(X, Y[:, d]) for X, Y in data], theta[0], theta[1:], NOISE_VAR
        )
        lo = np.array([LOG_SIGMA_F_BOUNDS[0]] + [LOG_LENGTH_BOUNDS[0]] * 4)
        hi = np.array([LOG_SIGMA_F_BOUNDS[1]] + [LOG_LENGTH_BOUNDS[1]] * 4)
        free = (theta > lo + 1e-6) & (theta < hi - 1e-6)
        assert np.all(np.abs(grad[free]) < 1e-3)


def test_shared_fit_rejects_bad_datasets() -> None:
    (X0, Y0), (X1, Y1), _ = duffing_experts(0)
    with pytest.raises(ValueError, match="at least one"):
        fit_shared([])
    with pytest.raises(ValueError, match="expert 1: data has Din=3"):
        fit_shared([(X0, Y0), (X1[:, :3], Y1)])
    with pytest.raises(ValueError, match="expert 1: need at least M = 2"):
        fit_shared([(X0, Y0), (X1[:1], Y1[:1])])
    with pytest.raises(ValueError, match="noise_var"):
        fit_shared_hyperparameters([(X0, Y0)], np.ones(3), restarts=1, seed=0)
    with pytest.raises(ValueError, match="restarts"):
        fit_shared_hyperparameters([(X0, Y0)], NOISE_VAR, restarts=0, seed=0)


# --------------------------------------------------------------------------------------------------------
# the mission option
# --------------------------------------------------------------------------------------------------------
def mission_file(tmp_path: Path, **gp: object) -> Path:
    doc = resolved_document("paper_sim")
    doc["gp"].update(gp)
    f = tmp_path / "m.yaml"
    f.write_text(yaml.safe_dump(doc))
    return f


def expert_data(seed: int) -> list[ExpertData]:
    edges = [-math.inf, *EDGES, math.inf]
    return [
        ExpertData(k + 1, (edges[k], edges[k + 1]), X, Y, np.arange(X.shape[0]))
        for k, (X, Y) in enumerate(duffing_experts(seed))
    ]


def test_shared_mission_trains_experts_with_identical_hyperparameters(tmp_path: Path) -> None:
    m = load_mission(mission_file(tmp_path, hyperparameters="shared"))
    assert m.gp.hyperparameters == "shared"
    data = expert_data(0)
    experts = train_experts(m, data, seed=7)
    assert sorted(experts) == [1, 2, 3]
    ref = fit_shared_hyperparameters([(d.X, d.Y) for d in data], NOISE_VAR, restarts=m.gp.restarts, seed=7)
    for d, ex in zip(data, experts.values(), strict=True):
        np.testing.assert_array_equal(ex.X, d.X)
        np.testing.assert_array_equal(ex.hyper.sigma_f, ref.sigma_f)
        np.testing.assert_array_equal(ex.hyper.length_scales, ref.length_scales)
        np.testing.assert_array_equal(ex.hyper.noise_var, ref.noise_var)


def test_default_mission_keeps_per_expert_hyperparameters() -> None:
    m = load_mission("paper_sim", rig="ideal")
    assert m.gp.hyperparameters == "per_expert"
    experts = list(train_experts(m, expert_data(0), seed=7).values())
    assert not np.allclose(experts[0].hyper.length_scales, experts[1].hyper.length_scales)


def test_invalid_hyperparameters_option_names_the_key(tmp_path: Path) -> None:
    with pytest.raises(MissionError) as exc:
        load_mission(mission_file(tmp_path, hyperparameters="pooled"))
    assert "gp.hyperparameters" in str(exc.value)
    assert "per_expert" in str(exc.value) and "shared" in str(exc.value)
