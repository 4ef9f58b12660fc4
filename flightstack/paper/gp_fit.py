"""Hyperparameter optimisation of one GP expert: type-II maximum likelihood (Saito et al., IFAC 2023).

For each output element i (``d`` here) of expert (j), σ_{fi}^{(j)} and l_{i,1..Din}^{(j)} of the SE-ARD
kernel (flightstack/paper/gp_kernel.py) maximise the log marginal likelihood log p(Y_i | X) (nats) with the
noise variance σ_{ni}² fixed, over θ = [log σ_f, log l_1, ..., log l_Din] (natural logs of output units and
of the input columns' units, m or rad) with L-BFGS-B and random restarts. :meth:`GPExpert.fit`
(flightstack/paper/gp.py) builds the expert from the result.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.optimize

from flightstack.paper.gp_checks import _validate_log_bounds, _validate_noise_var, _validate_training_data
from flightstack.paper.gp_kernel import GPHyperparameters, _lml_and_grad, _pairwise_sq_diff

__all__ = ["fit_hyperparameters"]

#: Random restarts of :meth:`GPExpert.fit` are drawn within ± this (natural-log) distance of the
#: data-driven start (intersected with the bounds), i.e. within a factor 100 of it; for the length scales
#: only the lower end is narrowed, the upper end is the bound itself.
_RESTART_LOG_HALF_WIDTH = math.log(100.0)
#: Tighter than scipy's defaults (ftol 2.2e-9, gtol 1e-5): the fit is offline and the optimum should not
#: depend on where the optimiser happened to stop.
_LBFGSB_OPTIONS: dict[str, float] = {"ftol": 1e-12, "gtol": 1e-8}


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
    X, Y = _validate_training_data(X, Y)
    noise = _validate_noise_var(noise_var, Y.shape[1])
    if isinstance(restarts, bool) or not isinstance(restarts, int | np.integer) or restarts < 1:
        raise ValueError(f"restarts must be an integer >= 1, got {restarts!r}")
    f_lo, f_hi = _validate_log_bounds(log_sigma_f_bounds, "log_sigma_f_bounds")
    l_lo, l_hi = _validate_log_bounds(log_length_bounds, "log_length_bounds")
    if maxiter is not None and (isinstance(maxiter, bool) or not isinstance(maxiter, int) or maxiter < 1):
        raise ValueError(f"maxiter must be None or an integer >= 1, got {maxiter!r}")
    options = _LBFGSB_OPTIONS if maxiter is None else {**_LBFGSB_OPTIONS, "maxiter": maxiter}

    n_in = X.shape[1]
    n_out = Y.shape[1]
    sq_diff = _pairwise_sq_diff(X)
    lo = np.array([f_lo] + [l_lo] * n_in)
    hi = np.array([f_hi] + [l_hi] * n_in)
    bounds = list(zip(lo, hi, strict=True))
    x_std = X.std(axis=0)
    log_l0 = np.log(np.where(x_std > 1e-12, x_std, 1.0))
    rng = np.random.default_rng(seed)

    sigma_f = np.empty(n_out)
    lengths = np.empty((n_out, n_in))
    for d in range(n_out):
        y = Y[:, d]
        y_std = float(y.std())
        theta0 = np.clip(np.concatenate([[math.log(y_std if y_std > 1e-12 else 1.0)], log_l0]), lo, hi)
        # narrowed sampling box for the random restarts (non-empty: theta0 lies inside the bounds)
        box_lo = np.maximum(lo, theta0 - _RESTART_LOG_HALF_WIDTH)
        box_hi = np.minimum(hi, theta0 + _RESTART_LOG_HALF_WIDTH)
        box_hi[1:] = hi[1:]  # long length scales (input switched off by ARD) stay reachable
        starts = [theta0] + [rng.uniform(box_lo, box_hi) for _ in range(restarts - 1)]
        nv = float(noise[d])

        def neg_lml(theta: np.ndarray, y: np.ndarray = y, nv: float = nv) -> tuple[float, np.ndarray]:
            try:
                lml, grad = _lml_and_grad(sq_diff, y, float(theta[0]), theta[1:], nv)
            except np.linalg.LinAlgError:
                return math.inf, np.zeros_like(theta)
            return -lml, -grad

        best_theta: np.ndarray | None = None
        best_lml = -math.inf
        for theta_start in starts:
            try:
                res = scipy.optimize.minimize(
                    neg_lml,
                    theta_start,
                    method="L-BFGS-B",
                    jac=True,
                    bounds=bounds,
                    options=options,
                )
                theta = np.clip(np.asarray(res.x, dtype=float), lo, hi)
                lml, _ = _lml_and_grad(sq_diff, y, float(theta[0]), theta[1:], nv)
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
    return X, Y, GPHyperparameters(sigma_f=sigma_f, length_scales=lengths, noise_var=noise)
