"""A simulated mission end to end: data run, GP training, gain analysis, compared modes, metrics.

For `compare_modes: [none, local, dgp]` (the paper's Sec. 5): the `none` run doubles as the data run
(the paper trains on a run without GP), experts are fitted on it, κ is evaluated, then the GP modes fly.
Everything derives from the mission's seed, so a run is reproducible.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from flightstack.config.mission import Mission, mission_to_dict
from flightstack.config.types import Mode
from flightstack.paper.control import Gains
from flightstack.paper.gain_analysis import gain_condition, region_samples
from flightstack.paper.geometry import Pose
from flightstack.paper.gp import GPExpert
from flightstack.paper.metrics import PAPER_RATIOS, PAPER_SQ_MEAN_ERROR, mode_metrics
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity
from flightstack.recording.files import DATASETS_FILE, EXPERTS_FILE, MISSION_FILE
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import Predictor
from flightstack.runtime.resources import check_recording_fits
from flightstack.runtime.runner import run_mode
from flightstack.runtime.taps import TickTap
from flightstack.runtime.training import (
    ExpertData,
    collect_datasets,
    load_experts,
    save_datasets,
    save_experts,
    train_experts,
)

NO_EXPERTS = "no GP expert was trained or loaded (kappa needs the experts' Lipschitz constant)"
"""metrics.json → gain_condition.reason of a run without experts (then "evaluated": false)."""


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
    run_writer: RunWriter | None = None,
    taps: Sequence[TickTap] = (),
) -> ExperimentResult:
    """Run every mode of `mission.compare_modes` (plus the data run if needed) and compute metrics.

    run_writer: records each mode to its run directory as it flies (flightstack.recording.run_dir); the caller
    closes it after `write_run_dir`. taps: observers of every mode's flight (runner.run_mode). Raises
    MissionError first when the recordings would not fit in memory (flightstack.runtime.resources)."""
    check_recording_fits(mission)  # MissionError before anything is allocated or takes off
    wall0 = time.perf_counter()
    res = ExperimentResult()
    n_ticks = round(mission.duration_s / mission.dt_s)
    needs_gp = any(Mode(m).uses_gp for m in mission.compare_modes)
    if needs_gp and mission.gp.experts_file is not None:
        res.experts = load_experts(mission.resolve(mission.gp.experts_file))
        missing = {d.id for d in mission.drones} - set(res.experts)
        if missing:
            raise ValueError(f"gp.experts_file has no expert for drone(s) {sorted(missing)}")
        needs_gp = False  # trained already: no data run needed
    order = mission.flown_modes()  # the data run `none` first when the experts are trained here

    def prog(mode: str) -> Callable[[int], None] | None:
        return progress_factory(mode, n_ticks) if progress_factory else None

    gp_info: dict[str, object] = {}
    for mode in order:
        predictors: Mapping[int, Predictor] | None = None
        if Mode(mode).uses_gp:
            predictors = res.experts
        elif mode == Mode.ORACLE:
            prm = DuffingParams(**mission.target.duffing.model_dump())
            predictors = {d.id: TruthPredictor(prm) for d in mission.drones}
        writer = (
            None if run_writer is None else run_writer.mode(mode, [d.id for d in mission.drones], n_ticks)
        )
        rec = run_mode(mission, mode, predictors, prog(mode), writer=writer, taps=taps)
        res.recordings[mode] = rec
        if rec.interrupted or rec.error:
            res.interrupted = rec.interrupted
            res.error = rec.error
            break
        if mode == Mode.NONE and needs_gp:
            t0 = time.perf_counter()
            try:
                res.datasets = collect_datasets(mission, rec, mission.seed)
            except ValueError as exc:  # too little data in a region: say so, keep the `none` run
                res.error = f"GP training data: {exc} (fly longer, or lower gp.samples_per_region)"
                break
            res.experts = train_experts(mission, res.datasets, mission.seed)
            if run_writer is not None:  # on disk now: a run killed later still has them for `report`
                _write_training(run_writer, res)
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
    """metrics.json of a run: per mode (those of compare_modes; every recorded one if none of them was
    recorded, e.g. an agent's run or a failed data run), the gain condition, GP facts, safety events, and
    for the paper's Duffing target with a dgp run the ratios none/dgp and local/dgp of each error metric
    (`ratios.<metric>`), and `paper`: our sq_mean_error (‖time mean of e‖², the reading of the paper's
    "squared mean of e") per mode and its ratios, each beside the paper's value of the same quantity
    (flightstack.paper.metrics explains both readings).

    wall: wall time of the whole run (s). A recording of only some of the mission's drones (an agent's)
    gets the metrics that need no mission. `gain_condition` has "evaluated": true and Theorem 1's numbers
    when res.experts holds experts; without any (no GP mode, a data run cut short, an agent flying
    `none`) it is {"evaluated": false, "reason", "region_lo", "region_hi"}: no κ or L_μ is made up."""
    ids = [d.id for d in mission.drones]
    shown = [m for m in res.recordings if m in mission.compare_modes] or list(res.recordings)
    modes: dict[str, dict[str, Any]] = {
        m: mode_metrics(res.recordings[m], mission if res.recordings[m].drone_ids == ids else None)
        for m in shown
    }
    gains = Gains.make(mission.gains.k_c, mission.gains.k_e, mission.gains.k_s)
    ref = res.recordings.get("none") or next(iter(res.recordings.values()), None)
    if ref is not None and ref.ticks_done > 0:
        xyz = ref.g_w0[: ref.ticks_done, :3]
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    else:
        lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    region = {"region_lo": lo.tolist(), "region_hi": hi.tolist()}
    gc: dict[str, object] = {"evaluated": False, "reason": NO_EXPERTS, **region}
    if res.experts:  # L_μ and Δ̄ are the experts': without one, κ would be a made-up number
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
        gc = {"evaluated": True, **cond.to_dict(), **region}
    out: dict[str, object] = {
        "mission": mission.name,
        "modes": modes,
        "gain_condition": gc,
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
        ratios = {k: _ratios(modes, k) for k in ("mean_sq_error", "sq_mean_error") if modes["dgp"].get(k)}
        out["ratios"] = ratios
        if "sq_mean_error" in ratios:
            out["paper"] = {
                "metric": "sq_mean_error",
                "modes": {
                    m: {"ours": float(modes[m]["sq_mean_error"]), "paper": PAPER_SQ_MEAN_ERROR[m]}
                    for m in PAPER_SQ_MEAN_ERROR
                    if "sq_mean_error" in modes.get(m, {})
                },
                "ratios": {
                    k: {"ours": v, "paper": PAPER_RATIOS[k]} for k, v in ratios["sq_mean_error"].items()
                },
            }
    return out


def _ratios(modes: Mapping[str, Mapping[str, Any]], key: str) -> dict[str, float]:
    """{"none/dgp": ..., "local/dgp": ...} of metric `key` (the modes flown; dgp's value is not 0)."""
    d = float(modes["dgp"][key])
    return {f"{m}/dgp": float(modes[m][key]) / d for m in ("none", "local") if m in modes and key in modes[m]}


def resolved_mission_yaml(mission: Mission) -> str:
    """The mission as YAML with absolute file paths, so that it loads from the run directory."""
    resolved = mission_to_dict(mission)
    for d in resolved["drones"]:
        if d.get("camera") and d["camera"].get("calibration"):
            d["camera"]["calibration"] = str(mission.resolve(d["camera"]["calibration"]))
    if resolved["gp"].get("experts_file"):
        resolved["gp"]["experts_file"] = str(mission.resolve(resolved["gp"]["experts_file"]))
    return yaml.safe_dump(resolved, sort_keys=False)


def write_run_dir(
    out: Path, mission: Mission, res: ExperimentResult, run_writer: RunWriter | None = None
) -> dict[str, Any]:
    """Resolved mission, one npz per mode, events.jsonl, the datasets and experts, then metrics.json
    (res.metrics + "recording": {"complete", "reason"}, written atomically); returns what metrics.json
    holds.

    run_writer: the writer that recorded the run as it flew (its modes' npz and events are on disk
    already; the caller closes it). Without one, everything is written here through a new RunWriter.
    A write error of the datasets or experts marks the recording incomplete; one of metrics.json raises
    OSError. After an error (res.error, e.g. a diverged state) non-finite metrics are written as null."""
    own = run_writer is None
    writer = RunWriter(out) if run_writer is None else run_writer
    try:
        writer.write_file(MISSION_FILE, resolved_mission_yaml(mission))
        for rec in res.recordings.values():
            writer.record(rec)
        _write_training(writer, res)
        # a run that ended in an error (a diverged state) need not have finite metrics: null in the JSON
        return writer.write_metrics(res.metrics, strict=res.error is None)
    finally:
        if own:
            writer.close()


def _write_training(writer: RunWriter, res: ExperimentResult) -> None:
    """experts.npz and datasets.npz (when there are any); a write error stops the recording."""
    out = writer.out
    try:
        if res.experts:
            save_experts(out / EXPERTS_FILE, res.experts)
        if res.datasets:
            save_datasets(out / DATASETS_FILE, res.datasets)
    except OSError as exc:
        writer.fail(f"experts/datasets not written: {exc.strerror or exc}")
