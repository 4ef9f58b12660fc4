"""A run as one MCAP file for Foxglove and PlotJuggler, written with foxglove-sdk's MCAP writer
(`RunMcap`); the live writer (mcap_live.py) and `flightstack export --mcap` (mcap_export.py) both feed it.

**Topics**, per flown mode (each under its own prefix, so one file compares the modes), drone ids i:

- `/<mode>/tick` (`flightstack.Tick`, protobuf): every tick's per-tick arrays (t, wall_t, the loop's
  timing, the target's pose g_w0);
- `/<mode>/drone<i>` (`flightstack.DroneState`, protobuf): every tick, drone i's arrays (its pose, its
  estimate of the target, e_c, e_e, u_e, mu_used, var_own, V_cmd, ...; mcap_schema.py);
- `/<mode>/tf` (`foxglove.FrameTransforms`): the frame tree (mcap_scene.py): `world` (z up) →
  `sigma_w` (Σw) → `<mode>/target`, `<mode>/drone<i>` and `<mode>/drone<i>/estimate`, and each drone's
  camera `<mode>/drone<i>/camera`, at most every TF_PERIOD_S of mission time (for the 3D panel; every
  value is in the two topics above at full rate);
- `/<mode>/pose/target` (`foxglove.PoseInFrame`), `/<mode>/pose/drones` and `/<mode>/pose/estimates`
  (`foxglove.PosesInFrame`, one pose per drone in drone-id order): g_w0, g_wi and ḡ_w,i in `sigma_w`,
  with the transforms;
- `/<mode>/scene` (`foxglove.SceneUpdate`): the fence and the target's markers (mcap_scene.Scene), at the
  mode's first tick and every SCENE_PERIOD_S of mission time after (a live client that joins late, a
  player that seeks);
- `/<mode>/drone<i>/image` (`foxglove.CompressedImage`, JPEG, frame `<mode>/drone<i>/camera`): the camera
  frames of rigs with image cameras (camera_frames.py), at their stamps;
- `/<mode>/events` (`foxglove.Log`): the mode's events, level ERROR for failures, WARNING for safety
  events, INFO for the rest; the text ends with the event's JSON.

Poses are [x, y, z, θ] in Σw (m, rad; yaw only); a pose's rotation is (0, 0, sin θ/2, cos θ/2).

**Time base: the mission clock.** A tick at mission time t (s) is logged at int((base + t) · 1e9) ns, base =
the mode's first wall_t − its first t when that wall_t is nonzero and finite, else 0: a simulated run
keeps its real spacing (wall time would squeeze it); on hardware the two clocks advance together. An event
is at base + its t when t is on the mission clock, else at the time of the event before it (the mode's
first tick for the first). Within a topic times never decrease.

**Chunks**: zstd-compressed, at most CHUNK_BYTES uncompressed; `flush` closes the open chunk (the live
writer does every mcap_live.FLUSH_PERIOD_S), so a killed writer loses at most the chunk it had open.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any, Protocol

import foxglove
import numpy as np
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformsChannel,
    LogChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.mcap import MCAPWriteOptions
from foxglove.messages import (
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    Log,
    LogLevel,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    SceneUpdate,
    Vector3,
)

from flightstack.events import mission_time, severity
from flightstack.recording.camera_frames import CameraFrame
from flightstack.recording.files import json_safe
from flightstack.recording.mcap_scene import (
    SIGMA_W_FRAME,
    WORLD_FRAME,
    Scene,
    camera_frame,
    drone_frame,
    estimate_frame,
    stamp,
    target_frame,
)
from flightstack.recording.mcap_schema import (
    DRONE,
    DRONE_FIELDS,
    TICK,
    TICK_FIELDS,
    encode,
    file_descriptor_set,
    per_drone,
)

CHUNK_BYTES = 1 << 20
"""Target uncompressed size of a chunk (B); a killed writer loses at most one."""
TF_PERIOD_S = 0.02
"""Least mission time (s) between two /<mode>/tf messages, and two of each /<mode>/pose/ topic (50 Hz)."""
SCENE_PERIOD_S = 1.0
"""Mission time (s) between two /<mode>/scene messages."""
CHANNELS: dict[str, Callable[..., TopicLog]] = {
    FrameTransforms.get_schema().name: FrameTransformsChannel,
    Log.get_schema().name: LogChannel,
    PoseInFrame.get_schema().name: PoseInFrameChannel,
    PosesInFrame.get_schema().name: PosesInFrameChannel,
    SceneUpdate.get_schema().name: SceneUpdateChannel,
    CompressedImage.get_schema().name: CompressedImageChannel,
}
"""foxglove-sdk's channel of each Foxglove schema the run uses (protobuf, the schema in the file)."""
_LEVELS = {"ERROR": LogLevel.Error, "WARNING": LogLevel.Warning, "INFO": LogLevel.Info}


def topic(mode: str, what: str) -> str:
    """The topic `what` of `mode` (module docstring): `/<mode>/<what>`, e.g. topic("dgp", "pose/drones")."""
    return f"/{mode}/{what}"


def drone_topic(mode: str, i: int) -> str:
    """Drone i's `flightstack.DroneState` topic of `mode`."""
    return topic(mode, f"drone{i}")


def image_topic(mode: str, i: int) -> str:
    """Drone i's camera images (`foxglove.CompressedImage`) of `mode`."""
    return topic(mode, f"drone{i}/image")


def time_base(t0: float, wall0: float) -> float:
    """Seconds added to the mission clock for log times: wall0 − t0 when wall0 is finite and nonzero."""
    return wall0 - t0 if math.isfinite(wall0) and wall0 != 0.0 and math.isfinite(t0) else 0.0


def to_ns(base: float, t: np.ndarray | float) -> np.ndarray:
    """Log times (ns, int64, at least 0) of mission times t (s)."""
    return np.maximum(0, ((base + np.asarray(t, dtype=float)) * 1e9).astype(np.int64))


def _pose(p: np.ndarray) -> Pose:
    """A foxglove Pose of a pose [x, y, z, θ] (m, rad; yaw only)."""
    return Pose(
        position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=Quaternion(z=math.sin(p[3] / 2), w=math.cos(p[3] / 2)),
    )


def event_level(ev: Mapping[str, Any]) -> LogLevel:
    """The Foxglove log level of an event: its flightstack.events.severity."""
    return _LEVELS[severity(dict(ev))]


def event_text(ev: Mapping[str, Any]) -> str:
    """One line for a log viewer: `event[ drone i][: kind][ - detail or reason]  {the event's JSON}`."""
    head = str(ev.get("event", "event"))
    if ev.get("drone") is not None:
        head += f" drone {ev['drone']}"
    if ev.get("kind"):
        head += f": {ev['kind']}"
    tail = ev.get("detail") or ev.get("reason")
    if tail:
        head += f" - {tail}"
    return f"{head}  {json.dumps(json_safe(dict(ev)), allow_nan=False)}"


def library() -> str:
    """flightstack's and foxglove-sdk's versions (the MCAP's metadata)."""
    try:
        ours = metadata.version("flightstack")
    except metadata.PackageNotFoundError:  # a checkout that was never installed
        ours = "unknown"
    return f"flightstack {ours}; foxglove-sdk {metadata.version('foxglove-sdk')}"


class TopicLog(Protocol):
    """Where one topic's messages go: a foxglove-sdk channel, or the live view's own server."""

    def log(self, msg: Any, /, *, log_time: int | None = None) -> None: ...

    def topic(self) -> str: ...


OpenTopic = Callable[[str, foxglove.Schema], TopicLog]
"""Opens a topic with the given protobuf schema (`context_topics`, or the live view's server)."""


def context_topics(ctx: foxglove.Context) -> OpenTopic:
    """Topics as foxglove-sdk channels of `ctx`, logged to its sinks (an MCAP writer)."""

    def open_topic(name: str, schema: foxglove.Schema) -> TopicLog:
        typed = CHANNELS.get(schema.name)
        if typed is not None:
            return typed(name, context=ctx)
        return foxglove.Channel(name, schema=schema, message_encoding="protobuf", context=ctx)

    return open_topic


class _Mode:
    """One mode's channels, time base and cursors."""

    def __init__(self, open_topic: OpenTopic, schemas: Mapping[str, foxglove.Schema], mode: str) -> None:
        self.mode = mode
        self.open_topic = open_topic
        self.drone_schema = schemas[DRONE]
        self.tick = open_topic(topic(mode, "tick"), schemas[TICK])
        self.drones: dict[int, TopicLog] = {}
        self.tf = open_topic(topic(mode, "tf"), FrameTransforms.get_schema())
        self.target_pose = open_topic(topic(mode, "pose/target"), PoseInFrame.get_schema())
        self.drone_poses = open_topic(topic(mode, "pose/drones"), PosesInFrame.get_schema())
        self.estimates = open_topic(topic(mode, "pose/estimates"), PosesInFrame.get_schema())
        self.scene = open_topic(topic(mode, "scene"), SceneUpdate.get_schema())
        self.log = open_topic(topic(mode, "events"), Log.get_schema())
        self.images: dict[int, TopicLog] = {}
        self.image_ns: dict[int, int] = {}  # each camera's newest image's log time
        self.base: float | None = None
        self.last_ns = 0  # the newest tick's log time
        self.next_tf = -math.inf  # mission time of the next transform and poses
        self.next_scene = -math.inf  # mission time of the next scene update
        self.event_ns: int | None = None  # the previous event's log time
        self.pending: list[Mapping[str, Any]] = []  # events before the first tick
        self.pending_frames: list[CameraFrame] = []  # camera frames before the first tick

    def drone(self, i: int) -> TopicLog:
        if i not in self.drones:
            self.drones[i] = self.open_topic(drone_topic(self.mode, i), self.drone_schema)
        return self.drones[i]

    def image(self, i: int) -> TopicLog:
        if i not in self.images:
            self.images[i] = self.open_topic(image_topic(self.mode, i), CompressedImage.get_schema())
        return self.images[i]


class RunChannels:
    """The run's topics (module docstring), opened by `open_topic` (an MCAP file: RunMcap, through
    `context_topics`; the live WebSocket view: flightstack.viewer.foxglove_server): `ticks` for each block
    of ticks of a mode, in order, `events` for its events, `frames` for its camera frames. `scene`: the
    mission's frame tree and scene (mcap_scene.Scene; set it before a mode's first tick). `counts`:
    messages logged per topic. Not thread-safe."""

    def __init__(self, open_topic: OpenTopic, scene: Scene | None = None) -> None:
        self.open_topic = open_topic
        self.scene = Scene() if scene is None else scene
        data = file_descriptor_set()
        self._schemas = {
            TICK: foxglove.Schema(name=TICK, encoding="protobuf", data=data),
            DRONE: foxglove.Schema(name=DRONE, encoding="protobuf", data=data),
        }
        self.modes: dict[str, _Mode] = {}
        self.counts: Counter[str] = Counter()
        self.span: dict[str, tuple[float, float]] = {}  # mode -> (first t, last t) written (s)
        self.first_ns: int | None = None  # the earliest tick's log time

    def _mode(self, mode: str) -> _Mode:
        if mode not in self.modes:
            self.modes[mode] = _Mode(self.open_topic, self._schemas, mode)
        return self.modes[mode]

    def ticks(self, mode: str, drone_ids: list[int], cols: Mapping[str, np.ndarray]) -> None:
        """N further ticks of `mode` (in order, after those written): every array of the recording
        (timeseries.ARRAY_FIELDS, N rows each; per-drone arrays (N, n, ...) in drone_ids' order)."""
        m = self._mode(mode)
        t = np.asarray(cols["t"], dtype=float)
        n = len(t)
        if n == 0:
            return
        if m.base is None:
            m.base = time_base(float(t[0]), float(np.asarray(cols["wall_t"], dtype=float)[0]))
            self.span[mode] = (float(t[0]), float(t[0]))
            m.event_ns = int(to_ns(m.base, float(t[0])))
        ns = np.maximum.accumulate(np.maximum(to_ns(m.base, t), m.last_ns))
        m.last_ns = int(ns[-1])
        self.first_ns = int(ns[0]) if self.first_ns is None else min(self.first_ns, int(ns[0]))
        self.span[mode] = (self.span[mode][0], float(t[-1]))
        self._log_rows(m.tick, encode(TICK, {f: cols[f] for f in TICK_FIELDS}), ns)
        for j, i in enumerate(drone_ids):
            one = {f: np.asarray(cols[f])[:, j] for f in DRONE_FIELDS if f not in ("t", "drone")}
            one.update(t=t, drone=np.full(n, i, dtype=np.uint32))
            self._log_rows(m.drone(i), encode(DRONE, one), ns)
        self._poses(m, drone_ids, cols, t, ns)
        if m.pending:
            pending, m.pending = m.pending, []
            self.events(mode, pending)
        if m.pending_frames:
            held, m.pending_frames = m.pending_frames, []
            self.frames(mode, held)

    def _log_rows(self, channel: TopicLog, msgs: np.ndarray, ns: np.ndarray) -> None:
        data = msgs.tobytes()
        size = msgs.shape[1]
        log = channel.log
        for k, when in enumerate(ns.tolist()):
            log(data[k * size : (k + 1) * size], log_time=when)
        self.counts[channel.topic()] += len(ns)

    def _log(self, channel: TopicLog, msg: Any, when: int) -> None:
        channel.log(msg, log_time=when)
        self.counts[channel.topic()] += 1

    def _poses(
        self, m: _Mode, ids: list[int], cols: Mapping[str, np.ndarray], t: np.ndarray, ns: np.ndarray
    ) -> None:
        """The thinned ticks' frame tree and poses (every TF_PERIOD_S), and the scene (SCENE_PERIOD_S)."""
        g_w0, g_wi, g_bar = (np.asarray(cols[f], dtype=float) for f in ("g_w0", "g_wi", "g_bar_w"))
        scene, mode = self.scene, m.mode
        for k in range(len(t)):
            if t[k] < m.next_tf:
                continue
            m.next_tf = t[k] + TF_PERIOD_S
            when = int(ns[k])
            ts = stamp(when)
            if t[k] >= m.next_scene:
                m.next_scene = t[k] + SCENE_PERIOD_S
                self._log(m.scene, scene.update(mode, ts), when)
            frames = [(target_frame(mode), g_w0[k])]
            for j, i in enumerate(ids):
                frames += [(drone_frame(mode, i), g_wi[k, j]), (estimate_frame(mode, i), g_bar[k, j])]
            tfs = [scene.root(ts)]
            tfs += [
                FrameTransform(
                    timestamp=ts,
                    parent_frame_id=SIGMA_W_FRAME,
                    child_frame_id=child,
                    translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    rotation=Quaternion(z=math.sin(p[3] / 2), w=math.cos(p[3] / 2)),
                )
                for child, p in frames
            ]
            tfs += scene.camera_transforms(mode, ids, ts)
            self._log(m.tf, FrameTransforms(transforms=tfs), when)
            self._log(
                m.target_pose, PoseInFrame(timestamp=ts, frame_id=SIGMA_W_FRAME, pose=_pose(g_w0[k])), when
            )
            drones = [_pose(g_wi[k, j]) for j in range(len(ids))]
            self._log(m.drone_poses, PosesInFrame(timestamp=ts, frame_id=SIGMA_W_FRAME, poses=drones), when)
            estimates = [_pose(g_bar[k, j]) for j in range(len(ids))]
            self._log(m.estimates, PosesInFrame(timestamp=ts, frame_id=SIGMA_W_FRAME, poses=estimates), when)

    def image_channel(self, mode: str, i: int) -> TopicLog:
        """Drone i's image topic of `mode`, opened (advertised) if it was not."""
        return self._mode(mode).image(i)

    def frames(self, mode: str, frames: Sequence[CameraFrame]) -> None:
        """Camera frames of `mode` (each camera's in stamp order) as JPEG CompressedImages in their camera's
        frame, at their stamps on the mode's time base; held until the mode's first tick fixes it."""
        m = self._mode(mode)
        if m.base is None:
            m.pending_frames.extend(frames)
            return
        for fr in frames:
            when = max(int(to_ns(m.base, fr.stamp)), m.image_ns.get(fr.drone, 0))
            m.image_ns[fr.drone] = when
            msg = CompressedImage(
                timestamp=stamp(when), frame_id=camera_frame(mode, fr.drone), data=fr.jpeg, format="jpeg"
            )
            self._log(m.image(fr.drone), msg, when)

    def events(self, mode: str, evs: Sequence[Mapping[str, Any]]) -> None:
        """Events of `mode` in file order; held until the mode's first tick fixes its time base (or
        `close`, which writes them at base 0)."""
        m = self._mode(mode)
        if m.base is None:
            m.pending.extend(evs)
            return
        for ev in evs:
            t = mission_time(dict(ev))
            when = int(to_ns(m.base, t)) if t is not None else (m.event_ns or 0)
            m.event_ns = when
            msg = Log(
                timestamp=stamp(when),
                level=event_level(ev),
                message=event_text(ev),
                name=str(ev.get("source") or "flightstack"),
            )
            self._log(m.log, msg, when)

    def release_held_events(self) -> dict[str, _Mode]:
        """Log the events and frames held for a mode that never had a tick (at base 0); the modes."""
        for mode, m in self.modes.items():
            if m.base is None and (m.pending or m.pending_frames):
                m.base, m.event_ns = 0.0, 0
                pending, m.pending = m.pending, []
                self.events(mode, pending)
                held, m.pending_frames = m.pending_frames, []
                self.frames(mode, held)
        return self.modes


class RunMcap:
    """An MCAP file being written (module docstring): `ticks` for each block of ticks of a mode, in order,
    `events` for its events, then `close`. `channels.counts`: messages written per topic. Not thread-safe."""

    def __init__(
        self, path: Path | str, *, chunk_bytes: int = CHUNK_BYTES, scene: Scene | None = None
    ) -> None:
        self.path = Path(path)
        ctx = foxglove.Context()
        options = MCAPWriteOptions(chunk_size=chunk_bytes, compression_threads=0, compression_level=1)
        self._writer = foxglove.open_mcap(
            self.path, allow_overwrite=True, context=ctx, writer_options=options
        )
        self.channels = RunChannels(context_topics(ctx), scene)
        self.closed = False

    def ticks(self, mode: str, drone_ids: list[int], cols: Mapping[str, np.ndarray]) -> None:
        """RunChannels.ticks."""
        self.channels.ticks(mode, drone_ids, cols)

    def events(self, mode: str, evs: Sequence[Mapping[str, Any]]) -> None:
        """RunChannels.events."""
        self.channels.events(mode, evs)

    def frames(self, mode: str, frames: Sequence[CameraFrame]) -> None:
        """RunChannels.frames."""
        self.channels.frames(mode, frames)

    @property
    def counts(self) -> Counter[str]:
        return self.channels.counts

    @property
    def first_ns(self) -> int | None:
        return self.channels.first_ns

    def attach(self, name: str, media_type: str, data: bytes, when_ns: int = 0) -> None:
        self._writer.attach(
            log_time=when_ns, create_time=when_ns, name=name, media_type=media_type, data=data
        )

    def metadata(self, name: str, values: Mapping[str, str]) -> None:
        self._writer.write_metadata(name, dict(values))

    def flush(self) -> None:
        """Close the open chunk and write it to the file."""
        self._writer.flush()

    def close(self) -> None:
        """Write held events, the metadata record `flightstack` (modes, drones, time bases) and the
        summary; idempotent."""
        if self.closed:
            return
        modes = self.channels.release_held_events()
        bases = {mode: m.base for mode, m in modes.items()}
        self.metadata(
            "flightstack",
            {
                "modes": ",".join(modes),
                "time_base_s": json.dumps(bases),
                "drone_ids": json.dumps({mode: sorted(m.drones) for mode, m in modes.items()}),
                "time": "log_time = int((base + t) * 1e9) ns; t: mission clock (s); base: time_base_s[mode]",
                "library": library(),
            },
        )
        self._writer.close()
        self.closed = True


__all__ = [
    "CHANNELS",
    "CHUNK_BYTES",
    "SCENE_PERIOD_S",
    "TF_PERIOD_S",
    "WORLD_FRAME",
    "OpenTopic",
    "RunChannels",
    "RunMcap",
    "TopicLog",
    "context_topics",
    "drone_topic",
    "event_level",
    "event_text",
    "image_topic",
    "per_drone",
    "time_base",
    "to_ns",
    "topic",
]
