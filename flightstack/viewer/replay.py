"""A run directory → one Rerun recording (`flightstack view RUN_DIR`); the run directory stays the archive.

Everything comes from the run directory: every mode's Recording (flightstack.recording.run_reader.load_run:
the final npz, or the row stream of a run cut short), the resolved mission (mission_resolved.yaml: drones,
cameras, GP regions, dt), the experts (experts.npz: each expert's own μ) and the training inputs
(datasets.npz). Rates: 3-D entities every `layout.stride(dt, REPLAY_3D_HZ)`-th tick, scalars every
`layout.scalar_stride(N)`-th tick (every tick up to layout.SCALAR_CAP), every event.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from flightstack.paper.gp import GPExpert
from flightstack.viewer import layout, scene
from flightstack.viewer.mode_logger import ModeLogger

if TYPE_CHECKING:
    from rerun import RecordingStream

    from flightstack.config.mission import Mission
    from flightstack.recording.timeseries import Recording

_log = logging.getLogger(__name__)

SCALAR_FIELDS: tuple[str, ...] = (
    *("t", "e_c", "e_e", "mu_used", "var_own", "visible", "n_fused", "g_bar_w"),
    *layout.HEALTH_FIELDS,
)
POSE_FIELDS = ("t", "g_w0", "g_wi", "g_bar_w")


@dataclass
class ModeRates:
    """How one mode was logged: dt (s per tick), every `pose_stride`-th tick in 3-D (`pose_rows` rows per
    body), every `scalar_stride`-th tick in the time series (`scalar_rows` rows per series)."""

    ticks: int
    dt: float
    pose_stride: int
    scalar_stride: int
    pose_rows: int
    scalar_rows: int
    events: int


@dataclass
class Replay:
    """What a run directory holds for the viewer (load with `Replay.load`)."""

    run_dir: Path
    recordings: dict[str, Recording]
    mission: Mission | None
    experts: dict[int, GPExpert] = field(default_factory=dict)
    training: dict[int, np.ndarray] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    """Damaged optional files and row stream tails left out (`<file>: <what>`, run_reader.read_run)."""

    @staticmethod
    def load(run_dir: Path, mode: str | None = None) -> Replay:
        """Read `run_dir` (only `mode` when given). FileNotFoundError when it holds no recording (or not
        that mode, naming the ones it has); RunDirError naming the file when a recording is damaged
        (damaged optional files are skipped and listed in `skipped`: recording.run_reader.read_run)."""
        from flightstack.recording.run_reader import read_run, resolved_mission

        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise FileNotFoundError(f"{run_dir}: not a directory")
        mission, why = resolved_mission(run_dir)
        if why is not None:
            _log.warning("%s: %s: no expert regions or cameras", run_dir, why)
        contents = read_run(run_dir, mission)
        recs = contents.recordings
        if not recs:
            raise FileNotFoundError(f"{run_dir}: no recording (timeseries_<mode>.npz or .rows) found")
        if mode is not None:
            if mode not in recs:
                raise FileNotFoundError(f"{run_dir}: no mode {mode!r} recorded (modes: {', '.join(recs)})")
            recs = {mode: recs[mode]}
        skipped = list(contents.skipped)
        experts = _experts(run_dir, skipped)
        training = _training_inputs(run_dir, experts, skipped)
        return Replay(run_dir, recs, mission, experts, training, skipped)

    def rates(self, mode: str) -> ModeRates:
        """The rate rule applied to `mode` (layout): 3-D at most REPLAY_3D_HZ of mission time, scalars
        every tick up to SCALAR_CAP rows."""
        rec = self.recordings[mode]
        n = rec.ticks_done
        dt = self.mission.dt_s if self.mission is not None else layout.tick_period(rec.t[:n])
        ps, ss = layout.stride(dt, layout.REPLAY_3D_HZ), layout.scalar_stride(n)
        return ModeRates(n, dt, ps, ss, len(layout.ticks(n, ps)), len(layout.ticks(n, ss)), len(rec.events))

    def log(self, rr: ModuleType, stream: RecordingStream) -> dict[str, int]:
        """Log everything to `stream`: the static scene, then each mode's series, poses and events.
        Returns the rows sent per entity path (non-static)."""
        from flightstack.config.types import Mode

        scene.log_world(rr, stream)
        if self.mission is not None:
            scene.log_regions(rr, stream, self.mission, self._extent())
            scene.log_training(rr, stream, self.training, [d.id for d in self.mission.drones])
        rows: dict[str, int] = {}
        for mode, rec in self.recordings.items():
            try:
                uses_gp = Mode(mode).uses_gp
            except ValueError:
                uses_gp = False
            ids, n = list(rec.drone_ids), rec.ticks_done
            scene.log_bodies(rr, stream, mode, ids)
            if self.mission is not None:
                scene.log_cameras(rr, stream, self.mission, mode, ids)
            logger = ModeLogger(rr, stream, mode, ids, experts=self.experts, uses_gp=uses_gp)
            r = self.rates(mode)
            logger.scalars(_columns(rec, layout.ticks(n, r.scalar_stride), SCALAR_FIELDS))
            logger.poses(_columns(rec, layout.ticks(n, r.pose_stride), POSE_FIELDS))
            t_end = float(rec.t[n - 1]) if n else 0.0
            logger.events(rec.events, t_end)
            if rec.bus_dropped:
                drops = ", ".join(f"{k}: {v}" for k, v in rec.bus_dropped.items())
                logger.note("bus_dropped", f"bus dropped messages ({drops})", t_end, "WARN")
            rows.update(logger.rows)
        return rows

    def _extent(self) -> np.ndarray:
        """Positions (K, 3; m) the expert regions are drawn over: the target and every estimate."""
        pts = [np.zeros((0, 3))]
        for rec in self.recordings.values():
            n = rec.ticks_done
            pts.append(rec.g_w0[:n, :3])
            pts.append(rec.g_bar_w[:n, :, :3].reshape(-1, 3))
        return np.concatenate(pts)


def _columns(rec: Recording, idx: np.ndarray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The rows `idx` of the Recording's arrays `names`."""
    return {name: np.asarray(getattr(rec, name))[idx] for name in names}


def _experts(run_dir: Path, skipped: list[str]) -> dict[int, GPExpert]:
    """The run's experts (experts.npz), {} when there are none or the file is damaged (then listed in
    `skipped`)."""
    from flightstack.learning.training import load_experts
    from flightstack.recording.files import EXPERTS_FILE, RunDirError

    path = run_dir / EXPERTS_FILE
    if not path.exists():
        return {}
    try:
        experts = load_experts(path)
    except RunDirError as exc:
        skipped.append(f"{EXPERTS_FILE}: {exc.what}")
        return {}
    return dict(experts)


def _training_inputs(
    run_dir: Path, experts: Mapping[int, GPExpert], skipped: list[str]
) -> dict[int, np.ndarray]:
    """drone id → training inputs X (M, 4): datasets.npz (runtime.training.load_datasets), else the
    experts' own inputs (experts.npz); {} when there are neither (a damaged datasets.npz is listed in
    `skipped`)."""
    from flightstack.learning.training import load_datasets
    from flightstack.recording.files import DATASETS_FILE, RunDirError

    try:
        found = {d.drone_id: np.asarray(d.X) for d in load_datasets(run_dir / DATASETS_FILE)}
    except RunDirError as exc:
        skipped.append(f"{DATASETS_FILE}: {exc.what}")
        found = {}
    return found or {i: np.asarray(ex.X) for i, ex in experts.items()}
