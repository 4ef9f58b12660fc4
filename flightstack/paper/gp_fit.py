"""Hyperparameter optimisation of one GP expert: type-II maximum likelihood (Saito et al., IFAC 2023).

For each output element i (``d`` here) of expert (j), σ_{fi}^{(j)} and l_{i,1..Din}^{(j)} of the SE-ARD
kernel (flightstack/paper/gp_kernel.py) maximise the log marginal likelihood log p(Y_i | X) (nats) with the
noise variance σ_{ni}² fixed, over θ = [log σ_f, log l_1, ..., log l_Din] (natural logs of output units and
of the input columns' units, m or rad) with L-BFGS-B and random restarts. :meth:`GPExpert.fit`
(flightstack/paper/gp.py) builds the expert from the result.

The start points, the restart loop and the option checks below are shared with the joint fit of one set of
hyperparameters for all experts (flightstack/paper/gp_shared_fit.py), which maximises a sum of such terms.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import scipy.optimize

from flightstack.paper.gp_checks import validate_log_bounds, validate_noise_var, validate_training_data
from flightstack.paper.gp_kernel import GPHyperparameters, lml_and_grad, pairwise_sq_diff

__all__ = ["LOG_LENGTH_BOUNDS", "LOG_SIGMA_F_BOUNDS", "fit_hyperparameters"]

#: Default bounds of the search, natural logs: σ_f ∈ [1e-3, 1e3] (output units), l ∈ [1e-2, 1e3] (input
#: units). The same values as the defaults of :meth:`GPExpert.fit` (tests/test_gp_shared.py checks this).
LOG_SIGMA_F_BOUNDS: tuple[float, float] = (math.log(1e-3), math.log(1e3))
LOG_LENGTH_BOUNDS: tuple[float, float] = (math.log(1e-2), math.log(1e3))

#: Random restarts of :meth:`GPExpert.fit` are drawn within ± this (natural-log) distance of the
#: data-driven start (intersected with the bounds), i.e. within a factor 100 of it; for the length scales
#: only the lower end is narrowed, the upper end is the bound itself.
_RESTART_LOG_HALF_WIDTH = math.log(100.0)
#: Tighter than scipy's defaults (ftol 2.2e-9, gtol 1e-5): the fit is offline and the optimum should not
#: depend on where the optimiser happened to stop.
LBFGSB_OPTIONS: dict[str, float] = {"ftol": 1e-12, "gtol": 1e-8}

#: θ = [log σ_f, log l_1..l_Din] -> (log marginal likelihood (nats), gradient (1 + Din,)); may raise
#: ``numpy.linalg.LinAlgError`` (Cholesky breakdown).
Objective = Callable[[np.ndarray], tuple[float, np.ndarray]]


def fit_hyperparameters(
    X: np.ndarray,
    Y: np.ndarray,
    noise_var: float | np.ndarray,
    *,
    restarts: int,
    seed: int,
    log_sigma_f_bounds: tuple[float, float],
    log_length_bounds: tuple[float, float],
    maxiter: int | None,
) -> tuple[np.ndarray, np.ndarray, GPHyperparameters]:
    """The optimisation behind :meth:`GPExpert.fit` (same arguments and errors, documented there).

    For each d, maximises :func:`log_marginal_likelihood_and_grad` over θ = [log σ_f, log l_1..l_Din]
    with L-BFGS-B (analytic gradient) within the given log-space bounds, from ``restarts`` starting
    points: the first data-driven, the others drawn from ``np.random.default_rng(seed)``; the best optimum
    is kept and a restart that fails (e.g. Cholesky breakdown) is skipped.

    Returns:
        ``(X, Y, hyper)``: the validated training data, (M, Din) and (M, D), and the fitted
        :class:`GPHyperparameters` (σ_f (D,), l (D, Din), σ_n² (D,)).
    """
    X, Y = validate_training_data(X, Y)
    noise = validate_noise_var(noise_var, Y.shape[1])
    lo, hi, options = check_fit_options(restarts, log_sigma_f_bounds, log_length_bounds, maxiter, X.shape[1])
    sq_diff = pairwise_sq_diff(X)
    objectives = [expert_lml(sq_diff, Y[:, d], float(noise[d])) for d in range(Y.shape[1])]
    hyper = fit_outputs(objectives, X, Y, noise, lo, hi, restarts=restarts, seed=seed, options=options)
    return X, Y, hyper


# --------------------------------------------------------------------------------------------------------
# shared by fit_hyperparameters and gp_shared_fit.fit_shared_hyperparameters
# --------------------------------------------------------------------------------------------------------
def check_fit_options(
    restarts: int,
    log_sigma_f_bounds: tuple[float, float],
    log_length_bounds: tuple[float, float],
    maxiter: int | None,
    n_in: int,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Validate the search options; returns the bounds of θ, lo and hi (1 + Din,), and L-BFGS-B's options."""
    if isinstance(restarts, bool) or not isinstance(restarts, int | np.integer) or restarts < 1:
        raise ValueError(f"restarts must be an integer >= 1, got {restarts!r}")
    f_lo, f_hi = validate_log_bounds(log_sigma_f_bounds, "log_sigma_f_bounds")
    l_lo, l_hi = validate_log_bounds(log_length_bounds, "log_length_bounds")
    if maxiter is not None and (isinstance(maxiter, bool) or not isinstance(maxiter, int) or maxiter < 1):
        raise ValueError(f"maxiter must be None or an integer >= 1, got {maxiter!r}")
    options = LBFGSB_OPTIONS if maxiter is None else {**LBFGSB_OPTIONS, "maxiter": maxiter}
    return np.array([f_lo] + [l_lo] * n_in), np.array([f_hi] + [l_hi] * n_in), options


def expert_lml(sq_diff: np.ndarray, y: np.ndarray, noise_var: float) -> Objective:
    """One expert's log p(y | X, θ) and its gradient, on its own data only (sq_diff of its X, (M, M, Din))."""

    def lml(theta: np.ndarray) -> tuple[float, np.ndarray]:
        return lml_and_grad(sq_diff, y, float(theta[0]), theta[1:], noise_var)

    return lml


def fit_outputs(
    objectives: Sequence[Objective],
    X: np.ndarray,
    Y: np.ndarray,
    noise: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    restarts: int,
    seed: int,
    options: dict[str, float],
) -> GPHyperparameters:
    """Maximise ``objectives[d]`` over θ for every output d; X (N, Din), Y (N, D) set the data-driven start.

    Start points of output d: θ0 = [log std(Y_d), log std(X_m)] (1 where a std is ~0), clipped into
    [lo, hi], then ``restarts - 1`` draws of ``np.random.default_rng(seed)`` (one generator for all d, in
    order) uniform in a box around θ0 (within a factor 100 for σ_f and the lower end of l, up to the upper
    bound for l). L-BFGS-B (analytic gradient) from each; the best finite optimum is kept, failed restarts
    are skipped; ValueError if all of some output's restarts failed.
    """
    x_std = X.std(axis=0)
    log_l0 = np.log(np.where(x_std > 1e-12, x_std, 1.0))
    bounds = list(zip(lo, hi, strict=True))
    rng = np.random.default_rng(seed)
    sigma_f = np.empty(len(objectives))
    lengths = np.empty((len(objectives), lo.shape[0] - 1))
    for d, objective in enumerate(objectives):
        y_std = float(Y[:, d].std())
        theta0 = np.clip(np.concatenate([[math.log(y_std if y_std > 1e-12 else 1.0)], log_l0]), lo, hi)
        # narrowed sampling box for the random restarts (non-empty: theta0 lies inside the bounds)
        box_lo = np.maximum(lo, theta0 - _RESTART_LOG_HALF_WIDTH)
        box_hi = np.minimum(hi, theta0 + _RESTART_LOG_HALF_WIDTH)
        box_hi[1:] = hi[1:]  # long length scales (input switched off by ARD) stay reachable
        starts = [theta0] + [rng.uniform(box_lo, box_hi) for _ in range(restarts - 1)]

        def neg_lml(theta: np.ndarray, objective: Objective = objective) -> tuple[float, np.ndarray]:
            try:
                lml, grad = objective(theta)
            except np.linalg.LinAlgError:
                return math.inf, np.zeros_like(theta)
            return -lml, -grad

        best_theta: np.ndarray | None = None
        best_lml = -math.inf
        for theta_start in starts:
            try:
                res = scipy.optimize.minimize(
                    neg_lml, theta_start, method="L-BFGS-B", jac=True, bounds=bounds, options=options
                )
                theta = np.clip(np.asarray(res.x, dtype=float), lo, hi)
                lml, _ = objective(theta)
            except (np.linalg.LinAlgError, ValueError, ArithmeticError):  # failed restart: skip it
                continue
            if math.isfinite(lml) and lml > best_lml:
                best_lml, best_theta = lml, theta
        if best_theta is None:
            raise ValueError(
                f"hyperparameter optimisation failed for output {d} from all {restarts} starting points"
            )
        sigma_f[d] = math.exp(best_theta[0])
        lengths[d] = np.exp(best_theta[1:])
    return GPHyperparameters(sigma_f=sigma_f, length_scales=lengths, noise_var=noise)
