"""One set of GP hyperparameters shared by all experts (Deisenroth & Ng, "Distributed Gaussian Processes",
ICML 2015, Sec. 2.1), the `gp.hyperparameters: shared` option of a mission.

Per output d, the K experts' SE-ARD kernels (flightstack/paper/gp_kernel.py) share θ_d = [log σ_{f,d},
log l_{d,1}, ..., log l_{d,Din}] (natural logs of output units and of the input columns' units, m or rad),
trained jointly by type-II maximum likelihood of the product of the experts' marginal likelihoods:

    log p(Y_d | X, θ_d) ≈ Σ_{k=1}^{K} log p(Y_{k,d} | X_k, θ_d)   (nats),

each term (and its gradient) computed by expert k on its own data D_k = {X_k, Y_k} only (no pooled kernel
matrix: K Cholesky factorisations of M_k × M_k instead of one of ΣM_k × ΣM_k), then summed. σ_{n,d}² is
fixed. Bounds, data-driven start, seeded restarts and L-BFGS-B are those of the per-expert fit
(flightstack/paper/gp_fit.py); each expert is then ``GPExpert(X_k, Y_k, shared_hyper)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from flightstack.paper.gp_checks import validate_noise_var, validate_training_data
from flightstack.paper.gp_fit import (
    LOG_LENGTH_BOUNDS,
    LOG_SIGMA_F_BOUNDS,
    Objective,
    check_fit_options,
    expert_lml,
    fit_outputs,
)
from flightstack.paper.gp_kernel import GPHyperparameters, pairwise_sq_diff

__all__ = ["fit_shared_hyperparameters", "shared_log_marginal_likelihood_and_grad"]


def fit_shared_hyperparameters(
    datasets: Sequence[tuple[np.ndarray, np.ndarray]],
    noise_var: float | np.ndarray,
    *,
    restarts: int,
    seed: int,
    log_sigma_f_bounds: tuple[float, float] = LOG_SIGMA_F_BOUNDS,
    log_length_bounds: tuple[float, float] = LOG_LENGTH_BOUNDS,
    maxiter: int | None = None,
) -> GPHyperparameters:
    """Type-II maximum likelihood of one θ_d per output d shared by all experts, σ_n² fixed.

    Maximises Σ_k log p(Y_{k,d} | X_k, θ_d) over θ_d = [log σ_f, log l_1..l_Din] with L-BFGS-B (the summed
    analytic gradients) within the log-space bounds, from ``restarts`` starting points exactly as
    :meth:`GPExpert.fit` draws them, with the data-driven start taken from all experts' data together
    (σ_f = std of the pooled Y_d, l_m = std of the pooled input column m). With a single expert this is
    :meth:`GPExpert.fit`'s optimisation.

    Args:
        datasets: K >= 1 pairs (X_k (M_k, Din), Y_k (M_k, D)), M_k >= 2, the same Din and D for every k;
            X in the inputs' units (m, rad), Y in the outputs' units (m/s, rad/s).
        noise_var: fixed σ_n² (output units squared), scalar or (D,), > 0, the same for every expert.
        restarts: number of starting points per output (>= 1).
        seed: seed of the random restarts (the result is deterministic for a fixed seed).
        log_sigma_f_bounds: (lo, hi) bounds on log σ_f.
        log_length_bounds: (lo, hi) bounds on every log l_m.
        maxiter: cap on L-BFGS-B iterations per starting point (None: run to the tolerances).

    Returns:
        The shared :class:`GPHyperparameters` (σ_f (D,), l (D, Din), σ_n² (D,)).

    Raises:
        ValueError: on bad inputs (naming the expert), or if every restart of some output failed.
    """
    Xs, Ys = _validate_datasets(datasets)
    noise = validate_noise_var(noise_var, Ys[0].shape[1])
    lo, hi, options = check_fit_options(
        restarts, log_sigma_f_bounds, log_length_bounds, maxiter, Xs[0].shape[1]
    )
    sq_diffs = [pairwise_sq_diff(X) for X in Xs]
    objectives = [
        _summed([expert_lml(sq, Y[:, d], float(noise[d])) for sq, Y in zip(sq_diffs, Ys, strict=True)])
        for d in range(noise.shape[0])
    ]
    return fit_outputs(
        objectives, np.vstack(Xs), np.vstack(Ys), noise, lo, hi, restarts=restarts, seed=seed, options=options
    )


def shared_log_marginal_likelihood_and_grad(
    datasets: Sequence[tuple[np.ndarray, np.ndarray]],
    log_sigma_f: float,
    log_lengths: np.ndarray,
    noise_var: float,
) -> tuple[float, np.ndarray]:
    """The objective of :func:`fit_shared_hyperparameters` for one output: Σ_k log p(y_k | X_k, θ).

    Args:
        datasets: K >= 1 pairs (X_k (M_k, Din), y_k (M_k,)) of one output dimension.
        log_sigma_f: natural log of the shared σ_f.
        log_lengths: (Din,) natural logs of the shared length scales.
        noise_var: fixed σ_n² > 0 (not differentiated).

    Returns:
        ``(lml, grad)``: the summed log marginal likelihood (nats) and its gradient (1 + Din,) with respect
        to ``[log σ_f, log l_1, ..., log l_Din]``.

    Raises:
        ValueError: on bad inputs, or if some expert's 𝒦 + σ_n² I is numerically not positive definite.
    """
    pairs = []
    for k, (X, y) in enumerate(datasets):
        y = np.asarray(y, dtype=float)
        if y.ndim != 1:
            raise ValueError(f"expert {k}: y must have shape (M,), got shape {y.shape}")
        pairs.append((X, y[:, None]))
    Xs, ys = _validate_datasets(pairs)
    theta = np.concatenate([[float(log_sigma_f)], np.asarray(log_lengths, dtype=float).ravel()])
    if theta.shape != (1 + Xs[0].shape[1],) or not np.all(np.isfinite(theta)):
        raise ValueError(f"log_sigma_f and log_lengths ({Xs[0].shape[1]},) must be finite, got {theta}")
    nv = float(validate_noise_var(noise_var, 1)[0])
    objective = _summed([expert_lml(pairwise_sq_diff(X), y[:, 0], nv) for X, y in zip(Xs, ys, strict=True)])
    try:
        return objective(theta)
    except np.linalg.LinAlgError as exc:
        raise ValueError("some expert's 𝒦 + σ_n² I is not positive definite (increase noise_var?)") from exc


def _summed(terms: Sequence[Objective]) -> Objective:
    """θ -> (Σ_k lml_k(θ), Σ_k ∇lml_k(θ)): the experts' terms, each evaluated on its own data."""

    def total(theta: np.ndarray) -> tuple[float, np.ndarray]:
        lml, grad = 0.0, np.zeros(theta.shape[0])
        for term in terms:
            lml_k, grad_k = term(theta)
            lml += lml_k
            grad += grad_k
        return lml, grad

    return total


def _validate_datasets(
    datasets: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each (X_k, Y_k) checked as one expert's data; all with the same Din and D; at least one."""
    Xs: list[np.ndarray] = []
    Ys: list[np.ndarray] = []
    for k, (X, Y) in enumerate(datasets):
        try:
            X, Y = validate_training_data(X, Y)
        except ValueError as exc:
            raise ValueError(f"expert {k}: {exc}") from None
        if Xs and (X.shape[1], Y.shape[1]) != (Xs[0].shape[1], Ys[0].shape[1]):
            raise ValueError(
                f"expert {k}: data has Din={X.shape[1]}, D={Y.shape[1]}, expert 0 has "
                f"Din={Xs[0].shape[1]}, D={Ys[0].shape[1]}"
            )
        Xs.append(X)
        Ys.append(Y)
    if not Xs:
        raise ValueError("need at least one expert's data set")
    return Xs, Ys
