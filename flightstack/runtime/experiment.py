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

from flightstack.analysis.metrics import build_metrics
from flightstack.config.mission import Mission, mission_to_dict
from flightstack.config.types import Mode
from flightstack.learning.training import (
    ExpertData,
    collect_datasets,
    load_experts,
    save_datasets,
    save_experts,
    train_experts,
)
from flightstack.paper.geometry import Pose
from flightstack.paper.gp import GPExpert
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity
from flightstack.recording.files import DATASETS_FILE, EXPERTS_FILE, MISSION_FILE
from flightstack.recording.run_dir import RunWriter
from flightstack.recording.timeseries import Recording
from flightstack.runtime.agent import Predictor
from flightstack.runtime.resources import check_recording_fits
from flightstack.runtime.runner import run_mode
from flightstack.runtime.taps import TickTap


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
    res.metrics = build_metrics(
        mission, res.recordings, res.experts, gp_info, time.perf_counter() - wall0,
        interrupted=res.interrupted, error=res.error,
    )  # fmt: skip
    return res


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
