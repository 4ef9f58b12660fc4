"""A simulated mission end to end: data run, GP training, gain analysis, compared modes, metrics.

For `compare_modes: [none, local, dgp]` (the paper's Sec. 5): the `none` run doubles as the data run
(the paper trains on a run without GP), experts are fitted on it, κ is evaluated, then the GP modes fly.
Everything derives from the mission's seed, so a run is reproducible.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from flightstack.control import Gains
from flightstack.gain_analysis import gain_condition, region_samples
from flightstack.geometry import Pose
from flightstack.gp import GPExpert
from flightstack.metrics import mode_metrics
from flightstack.mission import Mission, mission_to_dict
from flightstack.recording import Recording
from flightstack.runner import run_mode
from flightstack.target_motion import DuffingParams, duffing_body_velocity
from flightstack.training import ExpertData, collect_datasets, load_experts, save_experts, train_experts

PAPER_MEAN_SQ_ERROR = {"none": 3.0e-7, "local": 3.6e-8, "dgp": 5.6e-9}


class TruthPredictor:
    """μ = the true target body velocity at the given pose (mode `oracle`; sim-only reference)."""

    def __init__(self, prm: DuffingParams) -> None:
        self.prm = prm

    def predict_one(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return duffing_body_velocity(Pose.from_vector(x), self.prm), np.full(4, 1e-9)

    def prior_var(self) -> np.ndarray:
        return np.ones(4)


@dataclass
class ExperimentResult:
    recordings: dict[str, Recording] = field(default_factory=dict)
    datasets: list[ExpertData] = field(default_factory=list)
    experts: dict[int, GPExpert] = field(default_factory=dict)
    metrics: dict[str, object] = field(default_factory=dict)
    interrupted: bool = False
    error: str | None = None


def run_experiment(
    mission: Mission,
    progress_factory: Callable[[str, int], Callable[[int], None]] | None = None,
) -> ExperimentResult:
    """Run every mode of `mission.compare_modes` (plus the data run if needed) and compute metrics."""
    wall0 = time.perf_counter()
    res = ExperimentResult()
    n_ticks = round(mission.duration_s / mission.dt_s)
    needs_gp = any(m in ("local", "dgp") for m in mission.compare_modes)
    if needs_gp and mission.gp.experts_file is not None:
        res.experts = load_experts(mission.resolve(mission.gp.experts_file))
        missing = {d.id for d in mission.drones} - set(res.experts)
        if missing:
            raise ValueError(f"gp.experts_file has no expert for drone(s) {sorted(missing)}")
        needs_gp = False  # trained already: no data run needed
    order = list(mission.compare_modes)
    if needs_gp:
        order = ["none"] + [m for m in order if m != "none"]

    def prog(mode: str) -> Callable[[int], None] | None:
        return progress_factory(mode, n_ticks) if progress_factory else None

    gp_info: dict[str, object] = {}
    for mode in order:
        predictors = None
        if mode in ("local", "dgp"):
            predictors = res.experts
        elif mode == "oracle":
            prm = DuffingParams(**mission.target.duffing.model_dump())
            predictors = {d.id: TruthPredictor(prm) for d in mission.drones}
        rec = run_mode(mission, mode, predictors, prog(mode))
        res.recordings[mode] = rec
        if rec.interrupted or rec.error:
            res.interrupted = rec.interrupted
            res.error = rec.error
            break
        if mode == "none" and needs_gp:
            t0 = time.perf_counter()
            try:
                res.datasets = collect_datasets(mission, rec, mission.seed)
            except ValueError as exc:  # too little data in a region: say so, keep the `none` run
                res.error = f"GP training data: {exc} (fly longer, or lower gp.samples_per_region)"
                break
            res.experts = train_experts(mission, res.datasets, mission.seed)
            gp_info = {
                "train_seconds": time.perf_counter() - t0,
                "experts": {
                    str(i): {
                        "samples": int(ex.X.shape[0]),
                        "sigma_f": ex.hyper.sigma_f.tolist(),
                        "length_scales": ex.hyper.length_scales.tolist(),
                        "log_marginal_likelihood": ex.log_marginal_likelihood().tolist(),
                    }
                    for i, ex in res.experts.items()
                },
            }
    res.metrics = build_metrics(mission, res, gp_info, time.perf_counter() - wall0)
    return res


def build_metrics(mission: Mission, res: ExperimentResult, gp_info: dict[str, object], wall: float) -> dict:
    modes = {m: mode_metrics(r, mission) for m, r in res.recordings.items() if m in mission.compare_modes}
    gains = Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s)
    ref = res.recordings.get("none") or next(iter(res.recordings.values()), None)
    if ref is not None and ref.ticks_done > 0:
        xyz = ref.g_w0[: ref.ticks_done, :3]
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    else:
        lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    ga = mission.gain_analysis
    cond = gain_condition(
        gains,
        len(mission.drones),
        mission.edge_index_pairs(),
        [d.sees_target for d in mission.drones],
        list(res.experts.values()),
        region_samples(lo, hi, ga.samples, mission.seed),
        ga.gamma_sq,
        ga.beta,
        ga.eta,
    )
    out: dict[str, object] = {
        "mission": mission.name,
        "modes": modes,
        "gain_condition": {**cond.to_dict(), "region_lo": lo.tolist(), "region_hi": hi.tolist()},
        "gp": gp_info,
        "sim_seconds": float(sum(m.get("sim_seconds", 0.0) for m in modes.values())),
        "wall_seconds": wall,
        "seed": mission.seed,
        "interrupted": res.interrupted,
        "error": res.error,
        "safety_events": [
            {k: v for k, v in e.items() if k != "event"}
            for r in res.recordings.values()
            for e in r.events
            if e.get("event") == "safety"
        ],
    }
    if "dgp" in modes and modes["dgp"].get("mean_sq_error") and mission.target.motion == "duffing":
        d = modes["dgp"]["mean_sq_error"]
        ratios = {f"{m}/dgp": modes[m]["mean_sq_error"] / d for m in ("none", "local") if m in modes}
        paper = {f"{m}/dgp": PAPER_MEAN_SQ_ERROR[m] / PAPER_MEAN_SQ_ERROR["dgp"] for m in ("none", "local")}
        out["ratios"] = {"ours": ratios, "paper": paper}
    return out


def write_run_dir(out: Path, mission: Mission, res: ExperimentResult) -> None:
    """Resolved mission, metrics.json, one npz per mode, the datasets and experts."""
    out.mkdir(parents=True, exist_ok=True)
    resolved = mission_to_dict(mission)
    for d in resolved["drones"]:  # absolute paths, so the resolved mission loads from the run directory
        if d.get("camera"):
            d["camera"]["calibration"] = str(mission.resolve(d["camera"]["calibration"]))
    if resolved["gp"].get("experts_file"):
        resolved["gp"]["experts_file"] = str(mission.resolve(resolved["gp"]["experts_file"]))
    (out / "mission_resolved.yaml").write_text(yaml.safe_dump(resolved, sort_keys=False))
    for mode, rec in res.recordings.items():
        rec.save(str(out / f"timeseries_{mode}.npz"))
    if res.experts:
        save_experts(out / "experts.npz", res.experts)
    if res.datasets:
        np.savez(
            out / "datasets.npz",
            **{f"drone{d.drone_id}__{k}": getattr(d, k) for d in res.datasets for k in ("X", "Y", "ticks")},
        )
    with (out / "events.jsonl").open("w") as fh:
        for rec in res.recordings.values():
            for ev in rec.events:
                fh.write(json.dumps(ev) + "\n")
    (out / "metrics.json").write_text(json.dumps(res.metrics, indent=2, allow_nan=False) + "\n")
