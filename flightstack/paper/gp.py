"""One GP expert of the distributed GP (Saito et al., IFAC 2023, section "Distributed GP").

Drone j owns the data set D^{(j)} = {X^{(j)}, Y^{(j)}} of M_j pairs (input x = [x, y, z, θ] ∈ R^4, output
y = body velocity of the target ∈ R^4 plus noise ε_i ~ N(0, σ_{ni}²)) and regresses each output element i
with an independent zero-mean GP with its own SE-ARD kernel

    k_i^{(j)}(x, x') = (σ_{fi}^{(j)})² exp(-Σ_{m=1}^{Din} (x_m - x'_m)² / (2 (l_{im}^{(j)})²)).

For a test input x_* the paper's predictive mean and (latent, noise-free) variance are

    μ_i^{(j)}   = (k_{i*}^{(j)})^T (𝒦_i^{(j)} + σ_{ni}² I_{M_j})^{-1} Y_i^{(j)},
    var_i^{(j)} = k_i^{(j)}(x_*, x_*) - (k_{i*}^{(j)})^T (𝒦_i^{(j)} + σ_{ni}² I_{M_j})^{-1} k_{i*}^{(j)},

with [𝒦_i^{(j)}]_{ll'} = k_i^{(j)}(x^{(jl)}, x^{(jl')}) and [k_{i*}^{(j)}]_l = k_i^{(j)}(x_*, x^{(jl)}).

Naming in this module: the paper's output index i is ``d`` (0..D-1), the expert index (j) is implicit (one
:class:`GPExpert` object per drone), M = M_j is the number of training points, Din the input dimension.
The noise variance σ_n² is fixed (given), only σ_f and l are learned by maximising the log marginal
likelihood (:meth:`GPExpert.fit`). Everything is numpy/scipy only.

This module is the expert and the public face of the GP: the SE-ARD kernel, its hyperparameters and the log
marginal likelihood are in flightstack/paper/gp_kernel.py, the hyperparameter optimisation in
flightstack/paper/gp_fit.py, the argument checks in flightstack/paper/gp_checks.py; their public names are
re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import scipy.linalg
from scipy.spatial.distance import cdist

from flightstack.paper import kernels as kern
from flightstack.paper.gp_checks import as_finite_2d, readonly, validate_training_data
from flightstack.paper.gp_fit import fit_hyperparameters
from flightstack.paper.gp_kernel import LOG_2PI, GPHyperparameters, log_marginal_likelihood_and_grad

__all__ = ["VAR_FLOOR_REL", "GPExpert", "GPHyperparameters", "log_marginal_likelihood_and_grad"]

#: Predictive latent variances are clipped from below at ``VAR_FLOOR_REL * σ_f²`` (per output dimension).
#: Analytically var ≥ 0, but σ_f² − ‖L^{-1} k_*‖² suffers cancellation close to the training inputs when
#: σ_n² ≪ σ_f²; the floor keeps downstream precisions 1/var (PoE fusion) finite and positive.
VAR_FLOOR_REL = 1e-12


# --------------------------------------------------------------------------------------------------------
# the expert
# --------------------------------------------------------------------------------------------------------
class GPExpert:
    """Multi-output GP expert R^Din -> R^D: D independent SE-ARD GPs sharing the training inputs X.

    Attributes:
        X: (M, Din) training inputs (read-only copy).
        Y: (M, D) training outputs (read-only copy).
        hyper: :class:`GPHyperparameters` (σ_f (D,), l (D, Din), σ_n² (D,)).

    Caches built at construction, per output dimension d:
        * ``L[d]``: (M, M) lower Cholesky factor of 𝒦_d + σ_{n,d}² I,
        * ``alpha[d]``: (M,) α_d = (𝒦_d + σ_{n,d}² I)^{-1} Y_d,
        * ``L_inv[d]``: (M, M) L_d^{-1}, so that v = L_d^{-1} k_* and var = σ_f² − ‖v‖² in
          :meth:`predict_one` (the compiled kernel kernels.gp_predict_one, the control tick's only copy;
          :meth:`predict` is the vectorised scipy form for many points, and the tests hold the two equal).
    """

    def __init__(self, X: np.ndarray, Y: np.ndarray, hyper: GPHyperparameters) -> None:
        X, Y = validate_training_data(X, Y)
        if not isinstance(hyper, GPHyperparameters):
            raise ValueError(f"hyper must be a GPHyperparameters, got {type(hyper).__name__}")
        if hyper.n_outputs != Y.shape[1] or hyper.n_inputs != X.shape[1]:
            raise ValueError(
                f"hyperparameters are for D={hyper.n_outputs} outputs, Din={hyper.n_inputs} inputs, but the "
                f"data has D={Y.shape[1]}, Din={X.shape[1]}"
            )
        self.X: np.ndarray = readonly(X)
        self.Y: np.ndarray = readonly(Y)
        self.hyper: GPHyperparameters = hyper

        m, n_out = Y.shape
        self._sf2 = hyper.sigma_f**2  # σ_f², (D,)
        self._var_floor = VAR_FLOOR_REL * self._sf2  # (D,)
        # One kernel for every output when their hyperparameters are equal (gp.output_kernel: shared, or
        # experts built so): then 𝒦 + σ_n² I, its factor and k_* are the same for all D outputs, so they are
        # kept once (Dk = 1) and predict_one computes k_* and L⁻¹k_* once: the same numbers, D× less work.
        self.shared_kernel = bool(
            np.all(hyper.sigma_f == hyper.sigma_f[0])
            and np.all(hyper.length_scales == hyper.length_scales[0])
            and np.all(hyper.noise_var == hyper.noise_var[0])
        )
        n_k = 1 if self.shared_kernel else n_out
        self._inv_l = 1.0 / hyper.length_scales[:n_k]  # (Dk, Din)
        self._Z = X[None, :, :] * self._inv_l[:, None, :]  # scaled inputs x/l_d, (Dk, M, Din)
        eye = np.eye(m)
        L = np.empty((n_k, m, m))
        alpha = np.empty((n_out, m))
        L_inv = np.empty((n_k, m, m))
        for d in range(n_k):
            # 𝒦_d + σ_{n,d}² I
            K_y = self._sf2[d] * np.exp(-0.5 * cdist(self._Z[d], self._Z[d], "sqeuclidean"))
            K_y[np.diag_indices(m)] += hyper.noise_var[d]
            try:
                c, _ = scipy.linalg.cho_factor(K_y, lower=True, check_finite=False)
            except np.linalg.LinAlgError as exc:
                raise ValueError(
                    f"𝒦 + σ_n² I of output {d} is not positive definite (increase noise_var?)"
                ) from exc
            L[d] = np.tril(c)
            L_inv[d] = scipy.linalg.solve_triangular(L[d], eye, lower=True, check_finite=False)
        for d in range(n_out):
            alpha[d] = scipy.linalg.cho_solve((L[self._k(d)], True), Y[:, d], check_finite=False)
        self.L = L  # (Dk, M, M): the factor of output d is L[self._k(d)]
        self.alpha = alpha
        self.L_inv = L_inv
        self._n_in = X.shape[1]

    def _k(self, d: int) -> int:
        """The index of output d's kernel caches (0 for every d with a shared kernel)."""
        return 0 if self.shared_kernel else d

    # ---------------------------------------------------------------------------------------------------
    # construction
    # ---------------------------------------------------------------------------------------------------
    @classmethod
    def from_hyperparameters(cls, X: np.ndarray, Y: np.ndarray, hyper: GPHyperparameters) -> GPExpert:
        """Build an expert from data X (M, Din), Y (M, D) and given hyperparameters (computes the caches)."""
        return cls(X, Y, hyper)

    @classmethod
    def fit(
        cls,
        X: np.ndarray,
        Y: np.ndarray,
        noise_var: float | np.ndarray,
        *,
        restarts: int = 5,
        seed: int = 0,
        log_sigma_f_bounds: tuple[float, float] = (math.log(1e-3), math.log(1e3)),
        log_length_bounds: tuple[float, float] = (math.log(1e-2), math.log(1e3)),
        maxiter: int | None = None,
    ) -> GPExpert:
        """Type-II maximum likelihood of σ_{f,d}, l_{d,·} per output dimension d, with σ_n² fixed.

        For each d, maximises :func:`log_marginal_likelihood_and_grad` over θ = [log σ_f, log l_1..l_Din]
        with L-BFGS-B (analytic gradient) within the given log-space bounds, from ``restarts`` starting
        points: the first data-driven (σ_f = std(Y_d), or 1 if that is ~0; l_m = std of input column m, or 1
        if ~0; clipped into the bounds), the others drawn from ``np.random.default_rng(seed)`` uniformly in
        log space within the bounds, narrowed to σ_f within a factor 100 of the data-driven value and l_m from
        std/100 up to the upper bound (very long length scales, i.e. ARD switching an input off, are a common
        optimum). The best optimum is kept; a restart that fails (e.g. Cholesky breakdown) is skipped. The
        LML is multimodal in l, so the result depends on ``restarts`` and ``seed`` (deterministically).

        Args:
            X: (M, Din) training inputs, M >= 2.
            Y: (M, D) training outputs.
            noise_var: fixed σ_n², scalar or (D,), > 0.
            restarts: number of starting points per output dimension (>= 1).
            seed: seed of the random restarts (the result is deterministic for a fixed seed).
            log_sigma_f_bounds: (lo, hi) bounds on log σ_f.
            log_length_bounds: (lo, hi) bounds on every log l_m.
            maxiter: cap on L-BFGS-B iterations per starting point (None: run to the tolerances; a cap
                bounds the cost of large M, e.g. in benchmarks/run.py).

        Raises:
            ValueError: on bad inputs, or if every restart of some output dimension failed.
        """
        X, Y, hyper = fit_hyperparameters(
            X,
            Y,
            noise_var,
            restarts=restarts,
            seed=seed,
            log_sigma_f_bounds=log_sigma_f_bounds,
            log_length_bounds=log_length_bounds,
            maxiter=maxiter,
        )
        return cls(X, Y, hyper)

    # ---------------------------------------------------------------------------------------------------
    # prediction
    # ---------------------------------------------------------------------------------------------------
    @property
    def n_inputs(self) -> int:
        """Din."""
        return self._n_in

    @property
    def n_outputs(self) -> int:
        """D."""
        return int(self.Y.shape[1])

    def _check_query(self, Xs: np.ndarray) -> np.ndarray:
        Xs = as_finite_2d(Xs, "Xs")
        if Xs.shape[1] != self._n_in:
            raise ValueError(f"Xs must have shape (N, Din={self._n_in}), got shape {Xs.shape}")
        return Xs

    def _k_star(self, Xs: np.ndarray, d: int) -> np.ndarray:
        """k_* for output d: (N, M) with [k_*]_{nl} = k_d(x_{*n}, x^{(l)})."""
        k = self._k(d)
        return self._sf2[d] * np.exp(-0.5 * cdist(Xs * self._inv_l[k], self._Z[k], "sqeuclidean"))

    def predict(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predictive mean μ_i^{(j)} and latent variance var_i^{(j)} at N test inputs.

        Args:
            Xs: (N, Din) test inputs.

        Returns:
            ``(mean, var)``, both (N, D): mean = k_*ᵀ α (output units); var = σ_f² − ‖L^{-1} k_*‖²
            (output units², latent f, no σ_n² added), clipped from below at ``VAR_FLOOR_REL * σ_f²``.
        """
        Xs = self._check_query(Xs)
        n = Xs.shape[0]
        mean = np.empty((n, self.n_outputs))
        var = np.empty((n, self.n_outputs))
        for d in range(self.n_outputs):
            Ks = self._k_star(Xs, d)  # (N, M)
            mean[:, d] = Ks @ self.alpha[d]
            v = scipy.linalg.solve_triangular(self.L[self._k(d)], Ks.T, lower=True, check_finite=False)
            var[:, d] = self._sf2[d] - np.einsum("mn,mn->n", v, v)
        return mean, np.maximum(var, self._var_floor)

    def predict_one(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fast single-point prediction (control-loop path), same result as ``predict(x[None])``.

        Args:
            x: (Din,) test input. Not checked for finiteness (NaN propagates) to keep the call cheap.

        Returns:
            ``(mean, var)``, both (D,), as in :meth:`predict`.
        """
        x = np.asarray(x, dtype=float)
        if x.shape != (self._n_in,):
            raise ValueError(f"x must have shape (Din,) = ({self._n_in},), got shape {x.shape}")
        mu, var = np.empty(self.n_outputs), np.empty(self.n_outputs)
        kern.gp_predict_one(np.ascontiguousarray(x), *self.kernel_arrays(), mu, var)
        return mu, var

    def kernel_arrays(
        self,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """(1/l (D, Din), X/l (D, M, Din), σ_f² (D,), α (D, M), L⁻¹ (D, M, M), variance floor (D,), M): the
        expert as kernels.gp_predict_one takes it (read-only views; the compiled loop stacks them)."""
        n_k = self._inv_l.shape[0]
        return (
            self._inv_l,
            self._Z,
            self._sf2[:n_k],
            self.alpha,
            self.L_inv,
            self._var_floor[:n_k],
            int(self.X.shape[0]),
        )

    def mean_gradient(self, Xs: np.ndarray) -> np.ndarray:
        """Analytic input gradient of the predictive mean.

        ∂μ_d/∂x_{*m} = −Σ_l α_{d,l} k_d(x_*, x^{(l)}) (x_{*m} − x^{(l)}_m) / l_{d,m}².

        Args:
            Xs: (N, Din) test inputs.

        Returns:
            (N, D, Din) array of ∂μ_d/∂x_m (output units per input unit).
        """
        Xs = self._check_query(Xs)
        grad = np.empty((Xs.shape[0], self.n_outputs, self._n_in))
        diff = Xs[:, None, :] - self.X[None, :, :]  # (N, M, Din)
        for d in range(self.n_outputs):
            w = self._k_star(Xs, d) * self.alpha[d]  # (N, M)
            grad[:, d, :] = -np.einsum("nl,nlm->nm", w, diff) * self._inv_l[self._k(d)] ** 2
        return grad

    def prior_var(self) -> np.ndarray:
        """(D,) prior variance σ_f² = k_d(x, x) (what the fusion rules call σ_**²)."""
        return self._sf2.copy()

    def log_marginal_likelihood(self) -> np.ndarray:
        """(D,) log marginal likelihood log p(Y_d | X) at the current hyperparameters (nats)."""
        m = self.X.shape[0]
        data_fit = -0.5 * np.einsum("md,dm->d", self.Y, self.alpha)
        log_det = np.sum(np.log(np.diagonal(self.L, axis1=1, axis2=2)), axis=1)[
            [self._k(d) for d in range(self.n_outputs)]
        ]
        return data_fit - log_det - 0.5 * m * LOG_2PI

    # ---------------------------------------------------------------------------------------------------
    # (de)serialisation
    # ---------------------------------------------------------------------------------------------------
    _DICT_KEYS = ("X", "Y", "sigma_f", "length_scales", "noise_var")

    def to_dict(self) -> dict[str, np.ndarray]:
        """Arrays sufficient to rebuild the expert (``np.savez(path, **expert.to_dict())``)."""
        return {
            "X": np.array(self.X),
            "Y": np.array(self.Y),
            "sigma_f": np.array(self.hyper.sigma_f),
            "length_scales": np.array(self.hyper.length_scales),
            "noise_var": np.array(self.hyper.noise_var),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, np.ndarray]) -> GPExpert:
        """Inverse of :meth:`to_dict`; also accepts the ``NpzFile`` returned by ``np.load``."""
        missing = [k for k in cls._DICT_KEYS if k not in d]
        if missing:
            raise ValueError(f"missing keys {missing} (need {list(cls._DICT_KEYS)})")
        hyper = GPHyperparameters(
            sigma_f=np.asarray(d["sigma_f"]),
            length_scales=np.asarray(d["length_scales"]),
            noise_var=np.asarray(d["noise_var"]),
        )
        return cls(np.asarray(d["X"]), np.asarray(d["Y"]), hyper)

    def __repr__(self) -> str:
        return f"GPExpert(M={self.X.shape[0]}, Din={self._n_in}, D={self.n_outputs})"
