"""GP training data and experts as in the paper (Sec. 5; DESIGN §4).

From a run without GP, drone i's data are its own estimates X = ḡ_w,i = [x, y, z, θ] and the estimated
target body velocity Y = −u_ei (the body velocity of ḡ_w,i, since dḡ_w,i/dt = −ḡ_w,i û_ei) plus noise
N(0, σ_n² I), taken only while ḡ_w,i lies in drone i's expert region: band i of the xy plane.
`samples_per_region` samples are taken evenly spaced in time over the ticks inside the band.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flightstack.config.mission import Mission
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.paper.gp_shared_fit import fit_shared_hyperparameters
from flightstack.recording.timeseries import Recording


@dataclass(frozen=True)
class ExpertData:
    drone_id: int
    band: tuple[float, float]  # (lo, hi) along the region axis, metres
    X: np.ndarray  # (M, 4)
    Y: np.ndarray  # (M, 4)
    ticks: np.ndarray  # (M,) indices into the recording


def bands(mission: Mission) -> list[tuple[float, float]]:
    """Band k = [edge_{k-1}, edge_k) along gp.regions.axis, open-ended at both extremes."""
    e = [-np.inf, *mission.gp.regions.edges, np.inf]
    return [(float(e[k]), float(e[k + 1])) for k in range(len(e) - 1)]


def collect_datasets(mission: Mission, rec: Recording, seed: int) -> list[ExpertData]:
    """One dataset per drone (in mission order) from a recorded run; raises if a band has too few ticks."""
    axis = 0 if mission.gp.regions.axis == "x" else 1
    M = mission.gp.samples_per_region
    rng = np.random.default_rng(seed)
    sigma_n = np.sqrt(mission.gp.noise_var)
    out = []
    for k, (lo, hi) in enumerate(bands(mission)):
        coord = rec.g_bar_w[: rec.ticks_done, k, axis]
        inside = np.flatnonzero((coord >= lo) & (coord < hi))
        if inside.size < M:
            raise ValueError(
                f"drone {rec.drone_ids[k]}: only {inside.size} ticks inside its expert band {lo}..{hi} "
                f"({mission.gp.regions.axis}), need gp.samples_per_region = {M}"
            )
        ticks = inside[np.linspace(0, inside.size - 1, M).round().astype(int)]
        X = rec.g_bar_w[ticks, k].copy()
        Y = -rec.u_e[ticks, k] + sigma_n * rng.standard_normal((M, 4))
        out.append(ExpertData(rec.drone_ids[k], (lo, hi), X, Y, ticks))
    return out


def train_experts(mission: Mission, data: list[ExpertData], seed: int) -> dict[int, GPExpert]:
    """One GP expert per drone on its own dataset, hyperparameters by max. marginal likelihood: each
    expert's own (gp.hyperparameters: per_expert, seed + its index) or one set shared by all, maximising
    the sum of the experts' log marginal likelihoods (shared, seed). gp.output_kernel: shared makes the
    four outputs share one σ_f and one set of length scales too (the sum runs over the outputs as well)."""
    gp = mission.gp
    if gp.output_kernel == "shared":
        if gp.hyperparameters == "shared":
            hyper = _one_kernel([d.X for d in data], [d.Y for d in data], gp.noise_var, gp.restarts, seed)
            return {d.drone_id: GPExpert(d.X, d.Y, hyper) for d in data}
        return {
            d.drone_id: GPExpert(d.X, d.Y, _one_kernel([d.X], [d.Y], gp.noise_var, gp.restarts, seed + i))
            for i, d in enumerate(data)
        }
    if gp.hyperparameters == "shared":
        hyper = fit_shared_hyperparameters(
            [(d.X, d.Y) for d in data], gp.noise_var, restarts=gp.restarts, seed=seed
        )
        return {d.drone_id: GPExpert(d.X, d.Y, hyper) for d in data}
    return {
        d.drone_id: GPExpert.fit(d.X, d.Y, gp.noise_var, restarts=gp.restarts, seed=seed + i)
        for i, d in enumerate(data)
    }


def _one_kernel(
    Xs: list[np.ndarray], Ys: list[np.ndarray], noise_var: float, restarts: int, seed: int
) -> GPHyperparameters:
    """One (σ_f, l) for every output of every given dataset: the sum of their log marginal likelihoods
    maximised (each output of each dataset one term), tiled to the D outputs."""
    terms = [(X, Y[:, [d]]) for X, Y in zip(Xs, Ys, strict=True) for d in range(Y.shape[1])]
    one = fit_shared_hyperparameters(terms, noise_var, restarts=restarts, seed=seed)
    n_out = Ys[0].shape[1]
    return GPHyperparameters(
        np.full(n_out, one.sigma_f[0]), np.tile(one.length_scales[0], (n_out, 1)), np.full(n_out, noise_var)
    )


def save_experts(path: str | Path, experts: dict[int, GPExpert]) -> None:
    """One npz with every expert's data and hyperparameters: keys 'drone<id>__<field>'."""
    arrays: dict[str, np.ndarray] = {}
    for i, ex in experts.items():
        for key, val in ex.to_dict().items():
            arrays[f"drone{i}__{key}"] = np.asarray(val)
    np.savez(path, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as its `allow_pickle`


def load_experts(path: str | Path) -> dict[int, GPExpert]:
    """Inverse of save_experts; ValueError naming the file when it is not an experts file."""
    with np.load(path) as z:
        fields: dict[int, dict[str, np.ndarray]] = {}
        for key in z.files:
            head, sep, name = key.partition("__")
            if not sep or not head.startswith("drone") or not head[5:].isdigit():
                raise ValueError(f"{path}: not a flightstack experts file (unexpected key {key!r})")
            fields.setdefault(int(head[5:]), {})[name] = z[key]
    if not fields:
        raise ValueError(f"{path}: no experts in file")
    return {i: GPExpert.from_dict(f) for i, f in fields.items()}
