"""What the gain condition κ > 0 of Theorem 1 would take, each change alone, in closed form (no flight).

    κ = λ_min(H) − (π/2) L_μ λ_max(P) − 1/(2γ²),  H = k_s L + D_v   (flightstack.paper.gain_analysis)

- **L_μ alone** (the GP's Lipschitz constant, e.g. `gp.hyperparameters: shared`): κ > 0 needs
  L_μ < L_μ,max = (λ_min(H) − 1/(2γ²)) / ((π/2) λ_max(P)) at the given gains.
- **Gains alone**: H is linear in the gains (λ_Ki of NᵀKN is linear in K), so scaling k_c, k_e and k_s
  by s scales λ_min(H) by s: κ > 0 needs s > s* = ((π/2) L_μ λ_max(P) + 1/(2γ²)) / λ_min(H). The
  sampled loop carries gains only while (k_max + k_s λ_max(L))·dt < 2 (gain_analysis.MAX_RATE_DT), a
  rate that scales by s too: the gains of κ > 0 need dt < 2 / rate(s*·gains).
- **Control rate alone**: dt does not enter κ, so no rate alone gives κ > 0; what a faster loop gives is
  room for the gains that do. Of the gains k_c, k_e scaled by s_K and k_s by s_s with κ = 0 (over a grid
  of the ratio s_s/s_K) the ones whose rate is lowest name the slowest loop (largest dt) that could
  carry κ > 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from flightstack.paper.control import Gains
from flightstack.paper.gain_analysis import (
    MAX_RATE_DT,
    gain_condition,
    laplacian_lambda_max,
    own_loop_rate,
)

RATIOS = np.geomspace(1e-3, 1e3, 121)
"""The ratios s_s/s_K searched for the gains with κ = 0 that need the slowest loop."""


@dataclass(frozen=True)
class KappaNeeds:
    """κ at the given gains and L_μ and the smallest change, each alone, that would make it positive.

    kappa, lambda_H, lambda_P, L_mu, gamma_sq: the condition's terms; dt_s (s) and rate_dt, the sampled
    loop's (k_max + k_s λ_max(L))·dt at the given gains (< 2 to fly). L_mu_max: the largest L_μ with κ > 0
    (None: no L_μ ≥ 0 does, λ_min(H) ≤ 1/(2γ²)). gain_scale: s* for k_c, k_e, k_s together (None:
    λ_min(H) = 0); gain_scale_dt_max_s: the largest dt that carries those gains (s). slow_k_c, slow_k_e,
    slow_k_s: the gains with κ = 0 whose loop rate is lowest, slow_dt_max_s the largest dt that carries
    them (s): below it a loop rate can hold gains with κ > 0."""

    kappa: float
    lambda_H: float
    lambda_P: float
    L_mu: float
    gamma_sq: float
    dt_s: float
    rate_dt: float
    L_mu_max: float | None
    gain_scale: float | None
    gain_scale_dt_max_s: float | None
    slow_k_c: list[float] | None
    slow_k_e: list[float] | None
    slow_k_s: float | None
    slow_dt_max_s: float | None

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def _terms(
    k_c: Sequence[float], k_e: Sequence[float], k_s: float, n: int, edges: Sequence[tuple[int, int]],
    visible: Sequence[bool], gamma_sq: float,
) -> tuple[float, float]:  # fmt: skip
    """(λ_min(H), λ_max(P)) of gain_analysis.gain_condition for these gains (no experts needed)."""
    gc = gain_condition(
        Gains.make(k_c, k_e, k_s), n, edges, visible, [], np.zeros((1, 4)), gamma_sq, 1.0, 0.5
    )
    return gc.lambda_H, gc.lambda_P


def loop_rate(k_c: Sequence[float], k_e: Sequence[float], k_s: float, lambda_max_L: float) -> float:
    """k_max + k_s λ_max(L) (1/s): the sampled loop needs it · dt < 2 (gain_analysis.fastest_error_rate)."""
    return float(own_loop_rate(k_c, k_e) + k_s * lambda_max_L)


def kappa_needs(
    k_c: Sequence[float],
    k_e: Sequence[float],
    k_s: float,
    n: int,
    edges: Sequence[tuple[int, int]],
    visible: Sequence[bool],
    L_mu: float,
    gamma_sq: float,
    dt_s: float,
) -> KappaNeeds:
    """κ and what κ > 0 would take (module docstring) at gains k_c (4,), k_e (4,), k_s (1/s) of a mission
    with n drones, graph `edges` (0-based pairs), `visible` (who sees the target), the experts' L_μ, γ²
    and the control period dt_s (s)."""
    lam_H, lam_P = _terms(k_c, k_e, k_s, n, edges, visible, gamma_sq)
    lam_L = laplacian_lambda_max(n, edges)
    c = 0.5 * math.pi * L_mu * lam_P + 1.0 / (2.0 * gamma_sq)
    kappa = lam_H - c
    L_max = (lam_H - 1.0 / (2.0 * gamma_sq)) / (0.5 * math.pi * lam_P)
    s_star = c / lam_H if lam_H > 0 else None
    kc, ke = [float(x) for x in k_c], [float(x) for x in k_e]

    def scaled(s: float, v: list[float]) -> list[float]:
        return [s * x for x in v]

    s_dt = (
        None
        if s_star is None
        else MAX_RATE_DT / loop_rate(scaled(s_star, kc), scaled(s_star, ke), s_star * k_s, lam_L)
    )
    best: tuple[float, float, float] | None = None  # (rate, s_K, s_s)
    for r in [float(x) for x in RATIOS] if k_s > 0 else [0.0]:
        h, _ = _terms(kc, ke, r * k_s, n, edges, visible, gamma_sq)
        if h <= 0:
            continue
        s_K = c / h
        rate = loop_rate(scaled(s_K, kc), scaled(s_K, ke), s_K * r * k_s, lam_L)
        if best is None or rate < best[0]:
            best = (rate, s_K, s_K * r)
    return KappaNeeds(
        kappa=kappa,
        lambda_H=lam_H,
        lambda_P=lam_P,
        L_mu=L_mu,
        gamma_sq=gamma_sq,
        dt_s=dt_s,
        rate_dt=loop_rate(kc, ke, k_s, lam_L) * dt_s,
        L_mu_max=L_max if L_max > 0 else None,
        gain_scale=s_star,
        gain_scale_dt_max_s=s_dt,
        slow_k_c=None if best is None else [float(best[1] * x) for x in kc],
        slow_k_e=None if best is None else [float(best[1] * x) for x in ke],
        slow_k_s=None if best is None else float(best[2] * k_s),
        slow_dt_max_s=None if best is None else MAX_RATE_DT / best[0],
    )


__all__ = ["RATIOS", "KappaNeeds", "kappa_needs", "loop_rate"]
