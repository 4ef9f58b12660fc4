"""Fusing the predictions of K GP experts (Deisenroth & Ng, "Distributed Gaussian Processes", ICML 2015).

Drone i fuses its own expert's prediction N(μ_j^{(i)}, var_j^{(i)}) with those of its neighbours
k ∈ 𝒩_i, output dimension j by output dimension j. The paper (Saito et al., IFAC 2023, eqs. poe_mu /
poe_var) uses the product of experts (PoE)

    (var_j^{poe(i)})^{-1} = Σ_{k ∈ 𝒩_i ∪ {i}} (var_j^{(k)})^{-1},
    μ_j^{poe(i)}          = Σ_{k ∈ 𝒩_i ∪ {i}} w_{ijk} μ_j^{(k)},
    w_{ijk}               = var_j^{poe(i)} (var_j^{(k)})^{-1}.

Also implemented: the generalised PoE (gPoE, β_k = 1/K), the Bayesian committee machine (BCM) and the
robust BCM (rBCM). All rules have the form

    (var^{fused})^{-1} = Σ_k β_k var_k^{-1} + c · σ_**^{-2},
    μ^{fused}          = var^{fused} Σ_k β_k var_k^{-1} μ_k,

    rule  | β_k                          | c
    poe   | 1                            | 0
    gpoe  | 1/K                          | 0
    bcm   | 1                            | 1 − K
    rbcm  | ½ (log σ_**² − log var_k)    | 1 − Σ_k β_k

where σ_**² is the prior variance of the latent function (σ_f² of the SE kernel). Array convention here:
``mu``/``var`` are (K, D) — row k is expert k (row 0 the own expert; the order is otherwise irrelevant),
column d is the output dimension (the paper's j).

`fuse` runs the compiled kernel (flightstack.paper.kernels.fuse, the copy the control tick uses);
`fusion_weights` is the same rules written as numpy array expressions (weights w_k), and the tests hold
the two equal.
"""

from __future__ import annotations

import math

import numpy as np

from flightstack.paper import kernels as kern

__all__ = ["FUSION_RULES", "fuse", "fusion_weights"]

FUSION_RULES: tuple[str, ...] = ("poe", "gpoe", "bcm", "rbcm")


def _check_var(var: np.ndarray) -> np.ndarray:
    var = np.asarray(var, dtype=float)
    if var.ndim != 2 or var.shape[0] < 1 or var.shape[1] < 1:
        raise ValueError(f"var must have shape (K, D) with K, D >= 1, got shape {var.shape}")
    # finite and > 0 ⇔ min > 0 (False for NaN) and max finite; two reductions (this runs every tick)
    if not (var.min() > 0.0 and math.isfinite(var.max())):
        raise ValueError("var must be finite and > 0 (expert predictive variances)")
    return var


def _check_rule(rule: str) -> None:
    if rule not in FUSION_RULES:
        raise ValueError(f"unknown fusion rule {rule!r}; valid rules are {', '.join(FUSION_RULES)}")


def _prior_var_star(prior_var: np.ndarray | None, shape: tuple[int, int], rule: str) -> np.ndarray:
    """σ_**² per output dimension, (D,): mean over experts of ``prior_var`` (broadcast to (K, D))."""
    if prior_var is None:
        raise ValueError(f"rule {rule!r} needs prior_var (the experts' prior variances σ_f²)")
    pv = np.asarray(prior_var, dtype=float)
    try:
        pv = np.broadcast_to(pv, shape)
    except ValueError as exc:
        raise ValueError(f"prior_var must broadcast to (K, D) = {shape}, got shape {pv.shape}") from exc
    if not np.all(np.isfinite(pv)) or np.any(pv <= 0.0):
        raise ValueError("prior_var must be finite and > 0")
    return pv.mean(axis=0)


def _fused_var_and_weights(
    var: np.ndarray, rule: str, prior_var: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Fused variance (D,) and mean weights w (K, D) with μ^{fused} = Σ_k w_k μ_k. ``var`` is validated."""
    _check_rule(rule)
    n_experts = var.shape[0]
    prec = 1.0 / var  # var_k^{-1}, (K, D)
    if rule == "poe":  # β_k = 1: w_k = var^{fused} var_k^{-1}
        fused_var = 1.0 / prec.sum(axis=0)
        return fused_var, fused_var[None, :] * prec
    elif rule == "gpoe":
        beta = np.full_like(var, 1.0 / n_experts)
        fused_prec = (beta * prec).sum(axis=0)
    elif rule == "bcm":
        prior_star = _prior_var_star(prior_var, var.shape, rule)  # σ_**²
        beta = np.ones_like(var)
        fused_prec = prec.sum(axis=0) + (1.0 - n_experts) / prior_star
        # Fallback: precision never below the smallest expert precision (no-op for consistent inputs).
        fused_prec = np.maximum(fused_prec, prec.min(axis=0))
    else:  # rbcm
        prior_star = _prior_var_star(prior_var, var.shape, rule)  # σ_**²
        beta = 0.5 * (np.log(prior_star)[None, :] - np.log(var))  # β_k = ½ (log σ_**² − log var_k)
        fused_prec = (beta * prec).sum(axis=0) + (1.0 - beta.sum(axis=0)) / prior_star
    fused_var = 1.0 / fused_prec
    return fused_var, fused_var[None, :] * beta * prec


def fusion_weights(var: np.ndarray, rule: str = "poe", prior_var: np.ndarray | None = None) -> np.ndarray:
    """Weights w_k of the fused mean, μ^{fused} = Σ_k w_k μ_k (the paper's w_{ijk} for ``rule="poe"``).

    w_k = var^{fused} β_k var_k^{-1}. For poe and gpoe Σ_k w_k = 1 (convex combination); for bcm/rbcm the
    remaining weight 1 − Σ_k w_k multiplies the zero prior mean.

    Args:
        var: (K, D) expert predictive variances, finite and > 0.
        rule: one of :data:`FUSION_RULES`.
        prior_var: (K, D) (or anything broadcastable to it) expert prior variances σ_f²; needed by bcm/rbcm.

    Returns:
        (K, D) weights (dimensionless).
    """
    _check_rule(rule)
    return _fused_var_and_weights(_check_var(var), rule, prior_var)[1]


def fuse(
    mu: np.ndarray, var: np.ndarray, rule: str = "poe", prior_var: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse K experts' Gaussian predictions per output dimension.

    Rules (Deisenroth & Ng 2015), per output dimension, σ_**² = prior variance:

    * ``"poe"`` (the paper's eqs. poe_mu, poe_var): (var)^{-1} = Σ_k var_k^{-1}, μ = var Σ_k var_k^{-1} μ_k.
    * ``"gpoe"``: β_k = 1/K, (var)^{-1} = Σ_k β_k var_k^{-1}, μ = var Σ_k β_k var_k^{-1} μ_k. The mean equals
      the PoE mean and the variance is K times the PoE variance (the harmonic mean of the var_k).
    * ``"bcm"``: (var)^{-1} = Σ_k var_k^{-1} + (1 − K) σ_**^{-2}, μ = var Σ_k var_k^{-1} μ_k.
    * ``"rbcm"``: β_k = ½ (log σ_**² − log var_k), (var)^{-1} = Σ_k β_k var_k^{-1} + (1 − Σ_k β_k) σ_**^{-2},
      μ = var Σ_k β_k var_k^{-1} μ_k.

    σ_**²: the BCM derivation assumes all experts share one GP prior (the textbook case, where all rows of
    ``prior_var`` are equal). Experts with separately learned σ_f² do not; we then use the mean over the
    experts of ``prior_var`` for each output dimension.

    BCM fallback: the textbook BCM precision can be ≤ 0 when some expert reports a variance larger than
    σ_**² (impossible for exact GP posteriors sharing the prior, possible with different priors or
    approximate variances). We therefore use

        (var^{bcm})^{-1} = max(Σ_k var_k^{-1} + (1 − K) σ_**^{-2}, min_k var_k^{-1}),

    i.e. the fused variance is never larger than the largest expert variance (conservative, never more
    confident than the input warrants, always finite and positive). This is a no-op for consistent inputs
    (var_k ≤ σ_**² for all k): writing P_k = var_k^{-1}, P_** = σ_**^{-2} and k_min = argmin_k P_k, the BCM
    precision is P_{k_min} + Σ_{k ≠ k_min} (P_k − P_**) ≥ P_{k_min}. The mean keeps the BCM form
    μ = var Σ_k var_k^{-1} μ_k with the clipped var.

    The rBCM needs no fallback: its precision is P_** + Σ_k ½ log(P_k / P_**) (P_k − P_**) ≥ P_** > 0
    because the two factors of every term have the same sign.

    Args:
        mu: (K, D) expert predictive means (row 0 = own expert).
        var: (K, D) expert predictive (latent) variances, finite and > 0.
        rule: one of :data:`FUSION_RULES`.
        prior_var: (K, D) (or broadcastable to it) expert prior variances σ_f²; required for bcm and rbcm,
            ignored by poe and gpoe.

    Returns:
        ``(mu_fused, var_fused)``, both (D,), in the units of ``mu`` and ``var``.

    Raises:
        ValueError: unknown rule, bad shapes, non-finite mu, var not finite and > 0, missing or invalid
            prior_var for bcm/rbcm.
    """
    _check_rule(rule)
    var = _check_var(var)
    mu = np.asarray(mu, dtype=float)
    if mu.shape != var.shape:
        raise ValueError(f"mu and var must have the same shape (K, D), got {mu.shape} and {var.shape}")
    if not np.isfinite(mu).all():
        raise ValueError("mu must be finite")
    if rule in ("bcm", "rbcm"):
        _prior_var_star(prior_var, var.shape, rule)  # validates; the kernel takes the mean over experts
        prior = np.ascontiguousarray(np.broadcast_to(np.asarray(prior_var, dtype=float), var.shape))
    else:
        prior = var  # unused by poe and gpoe
    mu_f, var_f = np.empty(var.shape[1]), np.empty(var.shape[1])
    kern.fuse(
        np.ascontiguousarray(mu),
        np.ascontiguousarray(var),
        FUSION_RULES.index(rule),
        prior,
        var.shape[0],
        mu_f,
        var_f,
    )
    return mu_f, var_f
