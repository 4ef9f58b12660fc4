"""The gain condition of the paper's Theorem 1 (eq. gain_condition) and the ultimate bound b (eq. dgp_B).

    H = k_s L + D_v,  D_v = diag(v_i λ_Ki),  λ_Ki = λ_min(N_iᵀ K_i N_i)   (Lemma network_S)
    κ = λ_min(H) − (π/2) L_μ λ_max(P^i) − 1/(2γ²)
    b = γ Δ̄ sqrt(n / (2 κ_ η)),  κ_ = min(κ, λ_min(Λ))

Decisions (docs/parameters.md, docs/paper-comparison.md):
- The paper writes H = L + D_v; the consensus input −k_s c_i enters Ṡ as −k_s e_eᵀ (L ⊗ I) e_e, so the
  Laplacian is weighted by k_s here.
- λ_Ki is independent of θ_c (Ad_R is orthogonal and K has equal x/y gains), so it is computed at θ_c = 0.
- L_μ: for each expert and output j the largest ‖∇μ_j‖ over sample points of the region 𝒳 × (−π, π]
  (analytic gradients), max over experts, then the 2-norm over j (paper Sec. 3.2).
- Δ̄_j = max over experts and region samples of β·sqrt(var_j); β is a stated parameter (the theoretical
  β of Srinivas et al. needs the RKHS norm and information gain, which are unknown in practice).
Nothing here hides a κ ≤ 0: it is reported as is, with `satisfied = False` and b = inf.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from flightstack.paper.control import Gains


class Expert(Protocol):
    def predict(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def mean_gradient(self, Xs: np.ndarray) -> np.ndarray: ...


def laplacian(n: int, edges: Sequence[tuple[int, int]]) -> np.ndarray:
    """Graph Laplacian L (n × n) of an undirected graph given by 0-based index pairs."""
    L = np.zeros((n, n))
    for a, b in edges:
        if a == b:
            continue
        L[a, b] = L[b, a] = -1.0
    np.fill_diagonal(L, 0.0)
    np.fill_diagonal(L, -L.sum(axis=1))
    return L


def laplacian_lambda_max(n: int, edges: Sequence[tuple[int, int]]) -> float:
    """Largest eigenvalue of the Laplacian of an undirected graph on n nodes (0-based index pairs)."""
    if n < 2:
        return 0.0
    return float(np.linalg.eigvalsh(laplacian(n, edges))[-1])


MAX_RATE_DT = 2.0
"""The sampled error loop e⁺ = (I − M dt) e diverges once λ_max(M)·dt exceeds 2 (explicit Euler)."""


def own_loop_rate(k_c: Sequence[float], k_e: Sequence[float]) -> float:
    """k_max (1/s): the fastest mode of one drone's own pursuit loop without consensus, the largest
    eigenvalue of Nᵀ K N = [[k_c + k_e, −k_e], [−k_e, k_e]] over the four components (closed form).

    Linearised at e = 0, the law (45) with θ_c = θ_e = 0 gives ė = Nᵀu, u = −K N e, so ė = −NᵀKN e: the
    control and observer errors are coupled, and the fastest rate is (k_c + 2k_e + sqrt(k_c² + 4k_e²))/2,
    not max(k_c, k_e) (k_c = k_e = k: 2.618 k; the ideal rig diverges at k·dt ≈ 2/2.618 = 0.76)."""
    return max(0.5 * (c + 2.0 * e + math.sqrt(c * c + 4.0 * e * e)) for c, e in zip(k_c, k_e, strict=True))


def fastest_error_rate(k_c: Sequence[float], k_e: Sequence[float], k_s: float, lambda_max_L: float) -> float:
    """k_max + k_s·λ_max(L) (1/s): a bound on the fastest mode of the linearised network error dynamics
    ė = −(NᵀKN ⊗ I_n + diag(0, k_s L)) e (consensus −k_s c_i enters ė_e as −k_s L e_e and cancels in ė_c).

    By Weyl's inequality λ_max of the sum is at most k_max + k_s λ_max(L), exactly k_max when k_s = 0; a
    drone that does not see the target (v_i = 0) only lowers its block (NᵀKN ⪰ diag(k_c, 0)). So
    fastest_error_rate·dt < MAX_RATE_DT is sufficient for the sampled loop not to diverge."""
    return own_loop_rate(k_c, k_e) + k_s * lambda_max_L


def lambda_K(gains: Gains) -> float:
    """λ_min(Nᵀ K N) with N = [[I, 0], [−Ad_{Rᵀ(θc)}, I]] at θ_c = 0 and K = diag(k_c, k_e)."""
    N = np.block([[np.eye(4), np.zeros((4, 4))], [-np.eye(4), np.eye(4)]])
    K = np.diag(np.concatenate([gains.k_c, gains.k_e]))
    return float(np.linalg.eigvalsh(N.T @ K @ N).min())


def p_matrix(n: int, i: int = 0) -> np.ndarray:
    """P^i of eq. p_i: 1 at (i, i), 0.5 elsewhere on row and column i, 0 otherwise."""
    P = np.zeros((n, n))
    P[i, :] = 0.5
    P[:, i] = 0.5
    P[i, i] = 1.0
    return P


@dataclass(frozen=True)
class GainCondition:
    lambda_H: float
    lambda_K: list[float]
    lambda_P: float
    L_mu: float
    L_mu_per_output: list[float]
    gamma_sq: float
    kappa: float
    kappa_underline: float
    Delta_bar: float
    beta: float
    eta: float
    bound_b: float
    satisfied: bool

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        if not math.isfinite(self.bound_b):
            d["bound_b"] = None  # JSON has no inf
        return d


def region_samples(lo: np.ndarray, hi: np.ndarray, n: int, seed: int) -> np.ndarray:
    """n uniform samples of 𝒳 × (−π, π] for a box 𝒳 = [lo, hi] ⊂ R³; shape (n, 4)."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(lo, hi, size=(n, 3))
    th = rng.uniform(-math.pi, math.pi, size=(n, 1))
    return np.hstack([xyz, th])


def lipschitz_and_delta(
    experts: Sequence[Expert], samples: np.ndarray, beta: float
) -> tuple[np.ndarray, np.ndarray]:
    """(L_μj, Δ̄_j) per output j (4,) each: max over experts and samples of ‖∇μ_j‖ and β·sqrt(var_j)."""
    L = np.zeros(4)
    D = np.zeros(4)
    for ex in experts:
        grad = ex.mean_gradient(samples)  # (N, 4, 4)
        L = np.maximum(L, np.linalg.norm(grad, axis=2).max(axis=0))
        _, var = ex.predict(samples)
        D = np.maximum(D, beta * np.sqrt(var.max(axis=0)))
    return L, D


def gain_condition(
    gains: Gains,
    n: int,
    edges: Sequence[tuple[int, int]],
    visible: Sequence[bool],
    experts: Sequence[Expert],
    samples: np.ndarray,
    gamma_sq: float,
    beta: float,
    eta: float,
) -> GainCondition:
    """Evaluate κ, L_μ, λ_min(H) and the bound b of Theorem 1 for trained experts (none → L_μ = 0)."""
    lam_K = lambda_K(gains)
    # Λ = diag(λ_Ki): λ_min(NᵀKN) for drones that see the target, λ_min(K_c) for the others.
    lam_Ks = [lam_K if v else float(gains.k_c.min()) for v in visible]
    H = gains.k_s * laplacian(n, edges) + np.diag([lam_K if v else 0.0 for v in visible])
    lam_H = float(np.linalg.eigvalsh(H).min())
    lam_P = float(np.linalg.eigvalsh(p_matrix(n)).max())
    if experts:
        L_j, D_j = lipschitz_and_delta(experts, samples, beta)
    else:
        L_j, D_j = np.zeros(4), np.zeros(4)
    L_mu = float(np.linalg.norm(L_j))
    Delta_bar = float(np.linalg.norm(D_j))
    kappa = lam_H - 0.5 * math.pi * L_mu * lam_P - 1.0 / (2.0 * gamma_sq)
    kappa_u = min(kappa, *lam_Ks)
    ok = kappa > 0
    b = math.sqrt(gamma_sq) * Delta_bar * math.sqrt(n / (2.0 * kappa_u * eta)) if ok else math.inf
    return GainCondition(
        lambda_H=lam_H,
        lambda_K=lam_Ks,
        lambda_P=lam_P,
        L_mu=L_mu,
        L_mu_per_output=[float(x) for x in L_j],
        gamma_sq=gamma_sq,
        kappa=kappa,
        kappa_underline=kappa_u,
        Delta_bar=Delta_bar,
        beta=beta,
        eta=eta,
        bound_b=b,
        satisfied=ok,
    )
