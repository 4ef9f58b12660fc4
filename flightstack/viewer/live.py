"""The live viewer: a `TickTap` (flightstack.runtime.taps) that never holds the control loop.

On the control thread the tap only copies: after each recorded tick or chunk, the rows new since the last
call at the live scalar rate (layout.LIVE_SCALAR_HZ of mission time; the 3-D rows, LIVE_3D_HZ, are a subset
of them), the new events and, on rigs with image cameras, at most layout.IMAGE_HZ frames per drone and
second. The copies go on a bounded queue.Queue that drops when full (`dropped` counts the batches lost;
events are kept for the next batch instead). A daemon thread sends them to Rerun in batches, at most
layout.LIVE_FLUSH_HZ per second: e_c and e_e computed from the poses (the Recording fills them only after
landing), the own expert's μ, JPEG-encoded images. close() hands over the mode's last events and waits
for the thread, bounded (CLOSE_WAIT_S); finish() ends the thread and closes the sink (an .rrd gets its
footer).

Camera frames: the tap wraps each agent's camera in a `FrameKeeper` for the mode (and unwraps it at
close) and shows the frame the agent itself measured (why: flightstack.runtime.camera_tap).
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.paper.gp import GPExpert
from flightstack.runtime.camera_tap import FrameKeeper, has_image_cameras, keep_frames, release_frames
from flightstack.viewer import layout, scene
from flightstack.viewer.mode_logger import ModeLogger

if TYPE_CHECKING:
    from rerun import RecordingStream

    from flightstack.config.mission import Mission
    from flightstack.recording.timeseries import Recording
    from flightstack.runtime.fleet import Fleet
    from flightstack.viewer.sinks import Sink

_log = logging.getLogger(__name__)

QUEUE_SIZE = 64
"""Batches waiting for the logging thread (about 3 s of a 20 Hz real-time loop); more are dropped."""
CLOSE_WAIT_S = 5.0
"""close(): the longest wait for the thread to send a mode's last batch; finish(): for it to end."""
EXTENT_TICKS = 100_000
"""The expert regions of a live view are drawn over the target's predicted path, at most this many ticks."""
LIVE_FIELDS = ("t", "g_w0", "g_wi", "g_bar_w", "mu_used", "var_own", "visible", "n_fused")


@dataclass
class _Start:
    mode: str
    ids: list[int]
    g_d: np.ndarray  # (n, 4) desired relative poses, recording order
    mission: Mission
    experts: dict[int, GPExpert]
    uses_gp: bool


@dataclass
class _Rows:
    mode: str
    cols: dict[str, np.ndarray]  # rows at the scalar rate (t, poses, GP, ...)
    pose: np.ndarray  # bool per row: also a 3-D row
    events: list[dict[str, Any]] = field(default_factory=list)
    # (drone id, stamp s, RGB image, the markers the agent detected in it: (m, 2) pixels or None)
    images: list[tuple[int, float, np.ndarray, np.ndarray | None]] = field(default_factory=list)


@dataclass
class _Close:
    mode: str
    rows: _Rows
    bus_dropped: dict[str, int]
    dropped: int
    t_end: float
    done: threading.Event = field(default_factory=threading.Event)


class RerunTap:
    """TickTap sending a flight to a Rerun recording stream (entity layout: flightstack.viewer.layout).

    mission: the flight's mission (its cameras, dt and geometry); dropped: batches the full queue refused;
    errors: batches the thread failed to send (logged)."""

    def __init__(
        self, rr: ModuleType, stream: RecordingStream, mission: Mission, *, queue_size: int = QUEUE_SIZE
    ) -> None:
        self.rr, self.stream, self.mission = rr, stream, mission
        self.queue: queue.Queue[_Start | _Rows | _Close | None] = queue.Queue(maxsize=queue_size)
        self.dropped = 0
        self.errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rerun-viewer", daemon=True)
        self._thread.start()
        # control-thread state of the mode flying
        self._mode = ""
        self._k = 0
        self._n_events = 0
        self._every = 1
        self._pose_every = 1
        self._keepers: dict[int, FrameKeeper] = {}
        self._agents: list[Any] = []
        self._last_image = -math.inf
        self._mode_dropped = 0
        # thread state
        self._loggers: dict[str, ModeLogger] = {}
        self._g_d: dict[str, np.ndarray] = {}
        self._static_done: set[str] = set()
        self._finished = False

    @classmethod
    def open(cls, sink: Sink, mission: Mission, modes: Sequence[str], name: str) -> RerunTap:
        """A tap sending to `sink` (spawn, connect, save), with a blueprint of `modes`. ViewerUnavailable
        without rerun-sdk; OSError when the .rrd cannot be created."""
        from flightstack.viewer import blueprint
        from flightstack.viewer.rerun_import import load_rerun
        from flightstack.viewer.sinks import open_stream

        rr = load_rerun()
        return cls(rr, open_stream(rr, sink, name, blueprint.build(rr, list(modes))), mission)

    # ---- TickTap (control thread: copies only, never waits) ----------------------------------------
    def start(self, f: Fleet, rec: Recording) -> None:
        from flightstack.config.types import Mode

        mission = self.mission
        self._mode, self._k, self._n_events, self._mode_dropped = rec.mode, 0, 0, 0
        self._every = layout.stride(mission.dt_s, layout.LIVE_SCALAR_HZ)
        self._pose_every = layout.stride(mission.dt_s, layout.LIVE_3D_HZ, base=self._every)
        self._agents = list(f.agents)
        self._keepers = keep_frames(self._agents) if has_image_cameras(mission) else {}
        try:
            uses_gp = Mode(rec.mode).uses_gp
        except ValueError:
            uses_gp = False
        experts = {a.cfg.drone_id: a.predictor for a in self._agents if isinstance(a.predictor, GPExpert)}
        self._put(
            _Start(rec.mode, list(rec.drone_ids), np.array(f.g_d, dtype=float), mission, experts, uses_gp)
        )

    def on_tick(self, f: Fleet, rec: Recording, k_end: int) -> None:
        rows = self._rows(rec, k_end)
        if rows.cols["t"].shape[0] == 0 and not rows.events and not rows.images:
            return
        if self._put(rows):
            self._n_events += len(rows.events)
            self._k = k_end
        else:
            self._mode_dropped += 1
            self._k = k_end  # rows are lost; events stay for the next batch

    def close(self, rec: Recording) -> None:
        release_frames(self._agents, self._keepers)  # the agents get their own cameras back
        self._keepers = {}
        rows = self._rows(rec, rec.ticks_done)
        t_end = float(rec.t[rec.ticks_done - 1]) if rec.ticks_done else 0.0
        job = _Close(rec.mode, rows, dict(rec.bus_dropped), self._mode_dropped, t_end)
        try:
            self.queue.put(job, timeout=CLOSE_WAIT_S)
        except queue.Full:
            self.dropped += 1
            _log.warning("viewer: the last batch of mode %s was dropped (queue full)", rec.mode)
            return
        if not job.done.wait(CLOSE_WAIT_S):
            _log.warning("viewer: mode %s not sent within %.0f s; going on", rec.mode, CLOSE_WAIT_S)
        try:
            self.stream.flush(timeout_sec=CLOSE_WAIT_S)
        except Exception as exc:  # a viewer that went away: the flight does not care
            _log.warning("viewer: flush failed: %s", exc)

    # ---- end of the run ------------------------------------------------------------------------------
    def finish(self) -> None:
        """End the thread (bounded by CLOSE_WAIT_S) and close the sink; idempotent."""
        if self._finished:
            return
        self._finished = True
        self._stop.set()
        with contextlib.suppress(queue.Full):  # the thread also ends on the stop event
            self.queue.put_nowait(None)
        self._thread.join(CLOSE_WAIT_S)
        from flightstack.viewer.sinks import close_stream

        try:
            close_stream(self.stream, CLOSE_WAIT_S)
        except Exception as exc:
            _log.warning("viewer: closing the recording failed: %s", exc)
        if self.dropped or self.errors:
            _log.warning(
                "viewer: %d batches dropped (queue full), %d not sent (errors)", self.dropped, self.errors
            )

    # ---- helpers (control thread) --------------------------------------------------------------------
    def _put(self, job: _Start | _Rows) -> bool:
        try:
            self.queue.put_nowait(job)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def _rows(self, rec: Recording, k_end: int) -> _Rows:
        """Copies of the rows in [last call, k_end) on the scalar grid, the events not yet sent, and the
        agents' newest frames when IMAGE_HZ allows."""
        e = self._every
        idx = np.arange(-(-self._k // e) * e, k_end, e)
        cols = {name: np.array(getattr(rec, name)[idx]) for name in (*LIVE_FIELDS, *layout.HEALTH_FIELDS)}
        events = [dict(ev) for ev in rec.events[self._n_events :]]
        images: list[tuple[int, float, np.ndarray, np.ndarray | None]] = []
        now = time.monotonic()
        if self._keepers and now - self._last_image >= 1.0 / layout.IMAGE_HZ:
            markers = {a.cfg.drone_id: a.markers_px for a in self._agents}
            for i, keeper in self._keepers.items():
                fr = keeper.last
                if fr is not None and fr.image is not None:
                    px = markers.get(i)
                    seen = None if px is None else np.array(px, dtype=float)
                    images.append((i, float(fr.stamp), np.array(fr.image, dtype=np.uint8), seen))
            if images:
                self._last_image = now
        return _Rows(self._mode, cols, idx % self._pose_every == 0, events, images)

    # ---- the logging thread --------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / layout.LIVE_FLUSH_HZ
        while True:
            try:
                first = self.queue.get(timeout=period)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            jobs = [first]
            while True:
                try:
                    jobs.append(self.queue.get_nowait())
                except queue.Empty:
                    break
            t0 = time.monotonic()
            for job in _merged(jobs):
                if job is None:
                    continue
                try:
                    self._send(job)
                except Exception as exc:  # never ends the thread: the next batch may work
                    self.errors += 1
                    _log.warning("viewer: batch not sent (%s: %s)", type(exc).__name__, exc)
                finally:
                    if isinstance(job, _Close):
                        job.done.set()
            if any(j is None for j in jobs) or (self._stop.is_set() and self.queue.empty()):
                return
            self._stop.wait(max(0.0, period - (time.monotonic() - t0)))

    def _send(self, job: _Start | _Rows | _Close) -> None:
        if isinstance(job, _Start):
            self._send_start(job)
        elif isinstance(job, _Rows):
            self._send_rows(job)
        else:
            self._send_rows(job.rows)
            logger = self._loggers.get(job.mode)
            if logger is None:
                return
            if job.bus_dropped:
                drops = ", ".join(f"{k}: {v}" for k, v in job.bus_dropped.items())
                logger.note("bus_dropped", f"bus dropped messages ({drops})", job.t_end, "WARN")
            if job.dropped:
                logger.note(
                    "viewer", f"live viewer dropped {job.dropped} batches (queue full)", job.t_end, "WARN"
                )

    def _send_start(self, job: _Start) -> None:
        rr, stream = self.rr, self.stream
        if "world" not in self._static_done:
            from flightstack.learning.training import predicted_target_path

            scene.log_world(rr, stream)
            n = min(job.mission.n_ticks, EXTENT_TICKS)
            scene.log_regions(rr, stream, job.mission, predicted_target_path(job.mission, n)[:, :3])
            self._static_done.add("world")
        if job.experts and "training" not in self._static_done:
            inputs = {i: np.asarray(ex.X) for i, ex in job.experts.items()}
            scene.log_training(rr, stream, inputs, [d.id for d in job.mission.drones])
            self._static_done.add("training")
        scene.log_bodies(rr, stream, job.mode, job.ids)
        scene.log_cameras(rr, stream, job.mission, job.mode, job.ids)
        self._loggers[job.mode] = ModeLogger(
            rr, stream, job.mode, job.ids, experts=job.experts, uses_gp=job.uses_gp
        )
        self._g_d[job.mode] = job.g_d

    def _send_rows(self, job: _Rows) -> None:
        logger = self._loggers.get(job.mode)
        if logger is None:  # its start was dropped
            return
        cols = job.cols
        n = cols["t"].shape[0]
        if n:
            cols = {**cols, **_true_errors(job.mode, logger.ids, cols, self._g_d[job.mode])}
            logger.scalars(cols)
            logger.poses({k: v[job.pose] for k, v in cols.items()})
        t_default = float(cols["t"][-1]) if n else 0.0
        logger.events(job.events, t_default)
        for i, stamp, img, px in job.images:
            self.stream.set_time(layout.TIMELINE, duration=stamp)
            model = "RGB" if img.ndim == 3 else "L"  # a grey camera's frames are H x W
            enc = self.rr.Image(img, color_model=model).compress(jpeg_quality=layout.JPEG_QUALITY)
            self.stream.log(layout.image(job.mode, i), enc)
            if px is None:  # nothing detected in this frame: no stale markers over it
                self.stream.log(layout.markers(job.mode, i), self.rr.Clear(recursive=False))
            else:
                labels = [f"marker {k + 1}" for k in range(px.shape[0])]
                self.stream.log(layout.markers(job.mode, i), self.rr.Points2D(px, radii=3.0, labels=labels))


def _true_errors(
    mode: str, ids: list[int], cols: Mapping[str, np.ndarray], g_d: np.ndarray
) -> dict[str, np.ndarray]:
    """e_c = vec(g_d⁻¹ ḡ_i0) and e_e = vec(ḡ_i0⁻¹ g_i0) of the rows (the Recording's own formula,
    flightstack.recording.timeseries.Recording.fill_true_errors), (K, n, 4)."""
    from flightstack.recording.timeseries import Recording

    rec = Recording.from_columns(mode, ids, {k: cols[k] for k in ("t", "g_w0", "g_wi", "g_bar_w")})
    rec.fill_true_errors(g_d)
    return {"e_c": rec.e_c, "e_e": rec.e_e}


def _merged(jobs: list[_Start | _Rows | _Close | None]) -> list[_Start | _Rows | _Close | None]:
    """Consecutive row batches of one mode joined into one (one send_columns per entity per flush)."""
    out: list[_Start | _Rows | _Close | None] = []
    for job in jobs:
        prev = out[-1] if out else None
        if isinstance(job, _Rows) and isinstance(prev, _Rows) and prev.mode == job.mode:
            cols = {k: np.concatenate([prev.cols[k], job.cols[k]]) for k in prev.cols}
            out[-1] = _Rows(
                job.mode,
                cols,
                np.concatenate([prev.pose, job.pose]),
                prev.events + job.events,
                prev.images + job.images,
            )
        else:
            out.append(job)
    return out
