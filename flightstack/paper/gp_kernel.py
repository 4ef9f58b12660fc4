"""The SE-ARD kernel of one GP expert, its hyperparameters and its log marginal likelihood with gradient.

Each output element i (``d`` here, 0..D-1) of expert (j) has its own squared-exponential ARD kernel
(Saito et al., IFAC 2023, "Distributed GP")

    k_i^{(j)}(x, x') = (σ_{fi}^{(j)})² exp(-Σ_{m=1}^{Din} (x_m - x'_m)² / (2 (l_{im}^{(j)})²)),

with σ_f in output units (e.g. m/s), l_m in the units of input column m (m or rad for x = [x, y, z, θ]) and
a fixed observation-noise variance σ_n² (output units squared). :class:`GPHyperparameters` holds σ_f (D,),
l (D, Din) and σ_n² (D,). :func:`log_marginal_likelihood_and_grad` is log p(Y_i | X) (nats) of one output
and its analytic gradient in log space, θ = [log σ_f, log l_1, ..., log l_Din]; :func:`lml_and_grad` is its
unvalidated core, called by the hyperparameter optimisation (flightstack/paper/gp_fit.py) and the
benchmarks. The GP expert itself (posterior prediction) is flightstack/paper/gp.py.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from flightstack.paper.gp_checks import as_finite_2d, readonly, validate_noise_var

__all__ = ["GPHyperparameters", "log_marginal_likelihood_and_grad"]

LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------------------------------------
# hyperparameters
# --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GPHyperparameters:
    """SE-ARD hyperparameters of the D independent output GPs of one expert.

    Attributes:
        sigma_f: (D,) signal standard deviation σ_{f,d} per output (units of the output, e.g. m/s).
        length_scales: (D, Din) length scales l_{d,m} (units of input column m).
        noise_var: (D,) fixed observation-noise variance σ_{n,d}² (output units squared). A scalar is
            accepted and broadcast to (D,).

    The arrays are copied to read-only float64 arrays. ``eq=False``: comparing instances with ``==`` is
    identity; compare the arrays explicitly (e.g. ``np.array_equal``).
    """

    sigma_f: np.ndarray
    length_scales: np.ndarray
    noise_var: np.ndarray

    def __post_init__(self) -> None:
        sigma_f = np.asarray(self.sigma_f, dtype=float)
        if sigma_f.ndim != 1 or sigma_f.size < 1:
            raise ValueError(f"sigma_f must have shape (D,), got shape {sigma_f.shape}")
        if not np.all(np.isfinite(sigma_f)) or np.any(sigma_f <= 0.0):
            raise ValueError(f"sigma_f (σ_f) must be finite and > 0, got {sigma_f}")
        n_out = sigma_f.shape[0]
        lengths = np.asarray(self.length_scales, dtype=float)
        if lengths.ndim != 2 or lengths.shape[0] != n_out or lengths.shape[1] < 1:
            raise ValueError(f"length_scales must have shape (D={n_out}, Din), got shape {lengths.shape}")
        if not np.all(np.isfinite(lengths)) or np.any(lengths <= 0.0):
            raise ValueError("length_scales (l) must be finite and > 0")
        noise = validate_noise_var(self.noise_var, n_out)
        object.__setattr__(self, "sigma_f", readonly(sigma_f))
        object.__setattr__(self, "length_scales", readonly(lengths))
        object.__setattr__(self, "noise_var", readonly(noise))

    @property
    def n_outputs(self) -> int:
        """D, the number of outputs."""
        return int(self.sigma_f.shape[0])

    @property
    def n_inputs(self) -> int:
        """Din, the input dimension."""
        return int(self.length_scales.shape[1])


# --------------------------------------------------------------------------------------------------------
# log marginal likelihood of one output dimension
# --------------------------------------------------------------------------------------------------------
def pairwise_sq_diff(X: np.ndarray) -> np.ndarray:
    """(M, Din) -> (M, M, Din) with entries (x_{a,m} - x_{b,m})²."""
    diff = X[:, None, :] - X[None, :, :]
    return diff * diff


_POTRF, _POTRS = scipy.linalg.lapack.dpotrf, scipy.linalg.lapack.dpotrs


@functools.lru_cache(maxsize=64)
def _eye(m: int) -> np.ndarray:
    """I_m, read-only (dpotrs copies its right-hand side)."""
    eye = np.eye(m)
    eye.flags.writeable = False
    return eye


def _potrs(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(L Lᵀ)⁻¹ b from the lower Cholesky factor L (LAPACK dpotrs, as scipy.linalg.cho_solve)."""
    x, info = _POTRS(L, b, lower=1)
    if info != 0:
        raise ValueError(f"illegal value in argument {-info} of LAPACK dpotrs")
    return np.asarray(x)


def lml_and_grad(
    sq_diff: np.ndarray, y: np.ndarray, log_sigma_f: float, log_lengths: np.ndarray, noise_var: float
) -> tuple[float, np.ndarray]:
    """Unvalidated core of :func:`log_marginal_likelihood_and_grad` (sq_diff from :func:`pairwise_sq_diff`).

    Raises ``numpy.linalg.LinAlgError`` if 𝒦 + σ_n² I is numerically not positive definite.
    """
    m = y.shape[0]
    # R_m[a, b] = (x_{a,m} - x_{b,m})² / l_m²
    R = sq_diff * np.exp(-2.0 * log_lengths)
    # 𝒦 (noise-free Gram matrix), and 𝒦 + σ_n² I
    K_f = math.exp(2.0 * log_sigma_f) * np.exp(-0.5 * R.sum(axis=-1))
    K_y = K_f.copy()
    K_y.flat[:: m + 1] += noise_var  # + σ_n² I on the diagonal (adding I's zeros elsewhere changes no bit)
    # LAPACK's potrf / potrs directly: what scipy.linalg.cholesky and cho_solve call (the same bits), without
    # their checks and batching wrappers, which cost more than the factorisation at these sizes (M ≤ ~100)
    L, info = _POTRF(K_y, lower=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"𝒦 + σ_n² I is not positive definite (potrf info {info})")
    alpha = _potrs(L, y)  # α = (𝒦 + σ_n² I)^{-1} y
    # log p(y | X, θ) = -½ yᵀα - Σ log L_aa - (M/2) log 2π
    lml = -0.5 * float(y @ alpha) - float(np.log(L.diagonal()).sum()) - 0.5 * m * LOG_2PI
    # ∂ log p / ∂θ = ½ tr((α αᵀ - (𝒦 + σ_n² I)^{-1}) ∂𝒦/∂θ), with
    #   ∂𝒦/∂ log σ_f = 2 𝒦,   ∂𝒦/∂ log l_m = 𝒦 ∘ R_m.
    K_inv = _potrs(L, _eye(m))
    WK = (alpha[:, None] * alpha[None, :] - K_inv) * K_f  # α αᵀ
    grad = np.empty(1 + log_lengths.shape[0])
    grad[0] = float(WK.sum())
    grad[1:] = 0.5 * np.einsum("ab,abm->m", WK, R)
    return lml, grad


def log_marginal_likelihood_and_grad(
    X: np.ndarray, y: np.ndarray, log_sigma_f: float, log_lengths: np.ndarray, noise_var: float
) -> tuple[float, np.ndarray]:
    """Log marginal likelihood of one output dimension and its analytic gradient.

    log p(y | X) = -½ yᵀ(𝒦 + σ_n² I)^{-1} y - ½ log|𝒦 + σ_n² I| - (M/2) log 2π, zero prior mean, SE-ARD 𝒦.

    Args:
        X: (M, Din) training inputs.
        y: (M,) training targets of this output dimension.
        log_sigma_f: natural log of σ_f.
        log_lengths: (Din,) natural logs of the length scales l_1..l_Din.
        noise_var: fixed σ_n² > 0 (not differentiated).

    Returns:
        ``(lml, grad)``: the log marginal likelihood (float, nats) and its gradient (1 + Din,) with respect
        to ``[log σ_f, log l_1, ..., log l_Din]``.

    Raises:
        ValueError: on bad shapes / non-finite values / noise_var <= 0, or if 𝒦 + σ_n² I is numerically not
            positive definite.
    """
    X = as_finite_2d(X, "X")
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or y.shape[0] != X.shape[0]:
        raise ValueError(f"y must have shape (M,) = ({X.shape[0]},), got shape {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError("y contains non-finite values (NaN or inf)")
    log_lengths = np.asarray(log_lengths, dtype=float)
    if log_lengths.shape != (X.shape[1],):
        raise ValueError(
            f"log_lengths must have shape (Din,) = ({X.shape[1]},), got shape {log_lengths.shape}"
        )
    if not (math.isfinite(float(log_sigma_f)) and np.all(np.isfinite(log_lengths))):
        raise ValueError("log_sigma_f and log_lengths must be finite")
    noise = float(validate_noise_var(noise_var, 1)[0])
    try:
        return lml_and_grad(pairwise_sq_diff(X), y, float(log_sigma_f), log_lengths, noise)
    except np.linalg.LinAlgError as exc:
        raise ValueError("𝒦 + σ_n² I is not positive definite (increase noise_var?)") from exc
