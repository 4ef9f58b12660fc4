"""GP training data and experts as in the paper (Sec. 5; DESIGN §4).

From a run without GP, drone i's data are its own estimates X = ḡ_w,i = [x, y, z, θ] and the estimated
target body velocity Y = −u_ei (the body velocity of ḡ_w,i, since dḡ_w,i/dt = −ḡ_w,i û_ei) plus noise
N(0, σ_n² I), taken only while ḡ_w,i lies in drone i's expert region: band i of the xy plane.
`samples_per_region` samples are taken evenly spaced in time over the ticks inside the band.
`training_shortfall` predicts, before anything flies, whether a run is long enough for that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flightstack.config.mission import Mission
from flightstack.config.types import Mode
from flightstack.paper import kernels as kern
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.paper.gp_shared_fit import fit_shared_hyperparameters
from flightstack.paper.target_motion import DuffingParams
from flightstack.recording.files import RunDirError, read_npz
from flightstack.recording.timeseries import Recording

SHORTFALL_HORIZON_S = 300.0
"""How far (s, at least 10 × duration_s) training_shortfall follows the predicted path to say how long a
run that is too short would have to be."""
SHORTFALL_MAX_TICKS = 1_000_000
"""Bound on the ticks of that longer prediction (its cost: about 1 µs each)."""


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


def predicted_target_path(mission: Mission, n_ticks: int | None = None) -> np.ndarray:
    """The target's poses [x, y, z, θ] (n_ticks, 4) at ticks k = 0 … n_ticks − 1 (t = k·dt_s) of a run,
    as the simulation moves it; default n_ticks = mission.n_ticks.

    duffing: the field integrated from target.initial_pose in steps of dt_s, re-evaluated target.substeps
    times per step (kernels.world_advance: the ideal rig's own world step, compiled; no drones);
    square: the reference path of its law (Mission.target_law; the robot starts on it and its law tracks
    it)."""
    dt = mission.dt_s
    n = mission.n_ticks if n_ticks is None else int(n_ticks)
    tgt = mission.target
    path = np.empty((n, 4))
    if tgt.motion == "square":
        law = mission.target_law()
        for k in range(n):
            path[k] = law.reference(k * dt)[0].as_vector()
        return path
    prm = DuffingParams(**tgt.duffing.model_dump()).packed()
    g = np.array([*tgt.initial_pose.p, tgt.initial_pose.theta], dtype=float)
    V, clock, no_drones, no_commands = np.zeros(4), np.zeros(1), np.zeros((0, 4)), np.zeros((0, 4))
    for k in range(n):
        path[k] = g
        kern.world_advance(clock, (k + 1) * dt, dt, g, V, no_drones, no_commands, tgt.substeps, prm)
    return path


def band_text(axis: str, lo: float, hi: float) -> str:
    """A band as an inequality, e.g. `x >= 0.6` or `-0.7 <= x < 0.6`."""
    if math.isinf(lo) and math.isinf(hi):
        return f"every {axis}"
    if math.isinf(lo):
        return f"{axis} < {hi:g}"
    if math.isinf(hi):
        return f"{axis} >= {lo:g}"
    return f"{lo:g} <= {axis} < {hi:g}"


def _ticks_in_bands(mission: Mission, path: np.ndarray) -> list[np.ndarray]:
    """Per band (bands(mission) order): a boolean per tick of `path`, True where the pose is inside."""
    coord = path[:, 0 if mission.gp.regions.axis == "x" else 1]
    return [(coord >= lo) & (coord < hi) for lo, hi in bands(mission)]


def training_shortfall(mission: Mission) -> str | None:
    """Why a run of `mission` cannot train its GP experts, said before anything flies; None when it can
    or trains nothing (no GP mode in compare_modes, or gp.experts_file gives trained experts).

    The data run (mode `none`) trains drone k's expert on gp.samples_per_region ticks of its estimate
    ḡ_w,k inside band k (collect_datasets). The estimates follow the target, so the target's predicted
    path over duration_s (predicted_target_path) is counted per band. The prediction ignores the
    estimates' transient: a band with just enough ticks may still come up short in flight, which the run
    then reports after its data run."""
    if mission.gp.experts_file is not None or not any(Mode(m).uses_gp for m in mission.compare_modes):
        return None
    need = mission.gp.samples_per_region
    n = mission.n_ticks
    counts = [int(inside.sum()) for inside in _ticks_in_bands(mission, predicted_target_path(mission, n))]
    short = [k for k, c in enumerate(counts) if c < need]
    if not short:
        return None
    axis, edges = mission.gp.regions.axis, bands(mission)
    where = "; ".join(
        f"drone {mission.drones[k].id}'s band {band_text(axis, *edges[k])}: {counts[k]} ticks" for k in short
    )
    what = (
        f"duration_s = {mission.duration_s:g} s is too short to train the GP experts: the target's "
        f"predicted path ({mission.target.motion}) leaves too few ticks in an expert band ({where}; "
        f"gp.samples_per_region = {need} needed in each)"
    )
    horizon = _horizon(mission)
    least = minimum_duration(mission)
    if least is None:
        longer = f"the path does not fill every band within {horizon:g} s: move gp.regions.edges"
    else:
        longer = f"fly at least {least:g} s (--duration, or duration_s)"
    return (
        f"{what}; {longer}, lower gp.samples_per_region, or train the experts once "
        "(`flightstack train`) and set gp.experts_file"
    )


def minimum_duration(mission: Mission) -> float | None:
    """The shortest duration_s (s, rounded up to 0.1 s) whose data run puts gp.samples_per_region ticks of
    the target's predicted path in every expert band (what training_shortfall asks for); None when the
    path does not fill every band within the search horizon (SHORTFALL_HORIZON_S, or ten durations)."""
    dt = mission.dt_s
    most = max(mission.n_ticks, round(_horizon(mission) / dt))
    n = min(most, max(1, round(1.0 / dt)))  # a path of 1 s, then twice as long until it fills the bands
    while (
        needed := _ticks_to_fill(mission, predicted_target_path(mission, n), mission.gp.samples_per_region)
    ) is None:
        if n >= most:
            return None
        n = min(most, 2 * n)
    return math.ceil(needed * dt * 10) / 10


def _horizon(mission: Mission) -> float:
    """How far ahead (s) minimum_duration searches."""
    return min(max(10.0 * mission.duration_s, SHORTFALL_HORIZON_S), SHORTFALL_MAX_TICKS * mission.dt_s)


def _ticks_to_fill(mission: Mission, path: np.ndarray, need: int) -> int | None:
    """The fewest leading ticks of `path` that put `need` ticks in every band; None if it never does."""
    first = 0
    for inside in _ticks_in_bands(mission, path):
        count = np.cumsum(inside)
        if count.size == 0 or count[-1] < need:
            return None
        first = max(first, int(np.searchsorted(count, need)) + 1)
    return first


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
            hyper = one_kernel([d.X for d in data], [d.Y for d in data], gp.noise_var, gp.restarts, seed)
            return {d.drone_id: GPExpert(d.X, d.Y, hyper) for d in data}
        return {
            d.drone_id: GPExpert(d.X, d.Y, one_kernel([d.X], [d.Y], gp.noise_var, gp.restarts, seed + i))
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


def one_kernel(
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


def save_datasets(path: str | Path, datasets: list[ExpertData]) -> None:
    """One npz with every expert's training data: keys 'drone<id>__X', '__Y', '__ticks' (the band is not
    stored)."""
    arrays = {f"drone{d.drone_id}__{k}": getattr(d, k) for d in datasets for k in ("X", "Y", "ticks")}
    np.savez(path, **arrays)


def load_datasets(path: str | Path) -> list[ExpertData]:
    """Inverse of save_datasets, by drone id ([] when the file is missing; the band is NaN). RunDirError
    (a ValueError, naming the file) for a file that is not a datasets file: each drone needs X and Y of
    shape (M, 4) and integer ticks of shape (M,)."""
    path = Path(path)
    if not path.exists():
        return []
    fields = _by_drone(path, read_npz(path))
    nan = (float("nan"), float("nan"))
    out = []
    for i in sorted(fields):
        f = fields[i]
        X, Y, ticks = f.get("X"), f.get("Y"), f.get("ticks")
        if X is None or Y is None or ticks is None or set(f) != {"X", "Y", "ticks"}:
            raise RunDirError(path, f"drone {i}: keys {sorted(f)}, expected X, Y, ticks")
        M = ticks.shape[0] if ticks.ndim == 1 and ticks.dtype.kind in "iu" else -1
        numbers = X.dtype.kind in "fiu" and Y.dtype.kind in "fiu"
        if X.shape != (M, 4) or Y.shape != (M, 4) or not numbers:
            raise RunDirError(
                path, f"drone {i}: X {X.shape}, Y {Y.shape}, ticks {ticks.shape}: not numbers (M, 4), (M,)"
            )
        out.append(ExpertData(i, nan, X, Y, ticks))
    return out


def _by_drone(path: Path, arrays: dict[str, np.ndarray]) -> dict[int, dict[str, np.ndarray]]:
    """The arrays `drone<id>__<field>` of an npz by drone id and field; RunDirError for another key."""
    fields: dict[int, dict[str, np.ndarray]] = {}
    for key, a in arrays.items():
        head, sep, name = key.partition("__")
        if not sep or not head.startswith("drone") or not head[5:].isdigit() or len(head) > 12:
            raise RunDirError(path, f"unexpected key {key[:40]!r} (not drone<id>__<field>)")
        fields.setdefault(int(head[5:]), {})[name] = a
    return fields


def save_experts(path: str | Path, experts: dict[int, GPExpert]) -> None:
    """One npz with every expert's data and hyperparameters: keys 'drone<id>__<field>'."""
    arrays: dict[str, np.ndarray] = {}
    for i, ex in experts.items():
        for key, val in ex.to_dict().items():
            arrays[f"drone{i}__{key}"] = np.asarray(val)
    np.savez(path, **arrays)  # type: ignore[arg-type]  # numpy's stub types **kwds as its `allow_pickle`


def load_experts(path: str | Path) -> dict[int, GPExpert]:
    """Inverse of save_experts; RunDirError (a ValueError) naming the file when it is not an experts file."""
    path = Path(path)
    fields = _by_drone(path, read_npz(path))
    if not fields:
        raise RunDirError(path, "no experts in file")
    try:
        return {i: GPExpert.from_dict(f) for i, f in fields.items()}
    except (ValueError, np.linalg.LinAlgError) as exc:  # missing keys, shapes that do not fit
        raise RunDirError(path, f"not an experts file ({exc})") from None
