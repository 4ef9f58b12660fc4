"""A run directory as one MCAP file for Foxglove and PlotJuggler (`flightstack export RUN_DIR --mcap FILE`).

**Layout.** One file holds every mode of the run (or those asked for), each under its own topic prefix
`/<mode>/`, so one file compares the modes side by side. Per mode, with drone ids i:

- `/<mode>/target/tf`, `/<mode>/drone<i>/tf`, `/<mode>/drone<i>/estimate/tf` (`foxglove.FrameTransform`):
  the target's true pose g_w0, drone i's true pose g_wi and its estimate ḡ_w,i of the target's pose, as
  the transforms from frame `world` (Σw) to the child frames `<mode>/target`, `<mode>/drone<i>` and
  `<mode>/drone<i>/estimate`;
- `/<mode>/target/pose`, `/<mode>/drone<i>/pose`, `/<mode>/drone<i>/estimate/pose`
  (`foxglove.PoseInFrame`, frame `world`): the same poses;
- `/<mode>/drone<i>/<field>` for every other per-drone array of
  `flightstack.recording.timeseries.ARRAY_FIELDS` (looked up at run time, so a field added there is
  exported without a change here): (N, n, 4) as `{"x", "y", "z", "theta"}` (the vector's components in
  the recording's order [x, y, z, θ]), (N, n) as `{"value"}`; `/<mode>/<field>` for a per-tick array
  (N,) (e.g. `loop_period`) as `{"value"}`; `/<mode>/clock` `{"t", "wall_t"}` (mission clock and
  epoch seconds). Each of these plain JSON objects has its own small JSON schema `flightstack.<field>`;
  PlotJuggler's MCAP loader plots every number and boolean of a `json` message;
- `/<mode>/events` (`foxglove.Log`): the mode's events (events.jsonl), level ERROR for failures,
  WARNING for safety events, INFO for the rest (`mcap_messages.event_level`); the message text ends
  with the event's full JSON.

Poses are [x, y, z, θ] in Σw (m, rad; yaw only): translation (x, y, z), rotation the quaternion
(x, y, z, w) = (0, 0, sin θ/2, cos θ/2). metrics.json, mission_resolved.yaml and recording.json are
attached (MCAP attachments) and a metadata record `flightstack` names the modes, drones and time bases.

**Time base: the mission clock.** A tick at mission time t (s) is logged at log_time = publish_time =
int((base + t) · 1e9) ns, where base is the mode's first wall_t minus its first t when wall_t is
present and nonzero, else 0 (the `timestamp` inside Foxglove messages is the same instant). A simulated
run flies faster than real time, so wall time would squeeze it; the mission clock keeps its real
spacing. On hardware the two clocks advance together and base only moves the mission clock to the
epoch. Each mode has its own base, so on a simulated rig the modes (flown one after the other in a
fraction of their mission time) overlap on the file's time line: pick one by its topic prefix. An
event is logged at base + its `t` when that is a number on the mission clock, else (a device's
monotonic stamp, a missing t) at the time of the mode's event before it (its first tick for the first).
Messages are written in time order across all topics; within a topic times never decrease.

**Values** are the recording's: floats are JSON numbers written with Python's shortest round-trip repr
(they read back equal), booleans and integers as such; NaN and ±inf are not valid JSON and are written
as null (PlotJuggler's JSON parser skips a null; a null in a pose is outside Foxglove's schema, and
what Foxglove then shows was not checked here). A time before the epoch would be clamped to 0.
"""

from __future__ import annotations

import heapq
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib import metadata
from itertools import accumulate
from pathlib import Path
from typing import IO, TYPE_CHECKING

import mcap
import numpy as np
from mcap.writer import Writer

from flightstack.recording.files import METRICS_FILE, MISSION_FILE, STATE_FILE
from flightstack.recording.mcap_messages import (
    FIELD_DOCS,
    Encoder,
    Message,
    dumps,
    event_messages,
    foxglove_schema,
    plain_encoder,
    plain_schema,
    pose_encoders,
    rows,
    time_base,
    to_ns,
)
from flightstack.recording.run_reader import read_run
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

POSE_FIELDS = ("g_w0", "g_wi", "g_bar_w")
"""Arrays exported as transforms and poses (the target, each drone, each drone's estimate)."""
CLOCK_FIELDS = ("t", "wall_t")
"""Arrays exported together as /<mode>/clock."""
ATTACHMENTS = {
    METRICS_FILE: "application/json",
    STATE_FILE: "application/json",
    MISSION_FILE: "application/yaml",
}
"""Files of the run directory attached to the MCAP file (when present), with their media types."""


class ExportError(ValueError):
    """The run directory cannot be exported (missing, no recording, an unknown mode)."""


@dataclass
class ExportSummary:
    """What `export_mcap` wrote: per topic its message count and schema name; per mode its ticks and
    mission-clock span (s); the file's first and last log time (ns)."""

    path: Path
    modes: list[str]
    topics: dict[str, int] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)
    mode_ticks: dict[str, int] = field(default_factory=dict)
    mode_seconds: dict[str, float] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    skipped: list[str] = field(default_factory=list)
    """Damaged optional files and row stream tails left out (`<file>: <what>`, run_reader.read_run)."""

    @property
    def messages(self) -> int:
        return sum(self.topics.values())

    @property
    def duration_s(self) -> float:
        """Span of the file's time line (s): first to last message of any topic."""
        return (self.end_ns - self.start_ns) / 1e9


def export_mcap(
    run_dir: Path | str, out: Path | str, modes: list[str] | None = None, mission: Mission | None = None
) -> ExportSummary:
    """Write the run directory's recording (every mode, or `modes` in that order) to the MCAP file `out`
    (replaced atomically if it exists; the module docstring has the topics and the time base).
    mission: lets `read_run` recompute e_c and e_e of a recording cut short (a row stream). Raises
    ExportError for a missing run directory, one without a recording, or an unknown mode; RunDirError
    (naming the file) for a damaged recording; OSError when `out` cannot be written."""
    run_dir, out = Path(run_dir), Path(out)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: no such run directory")
    contents = read_run(run_dir, mission)
    recs = contents.recordings
    if not recs:
        raise ExportError(f"{run_dir}: no recording (timeseries_<mode>.npz or .rows) in it")
    chosen = list(recs) if modes is None else list(modes)
    unknown = [m for m in chosen if m not in recs]
    if unknown:
        raise ExportError(f"{run_dir}: no mode {', '.join(unknown)} recorded (it has {', '.join(recs)})")
    tmp = out.with_name(f".{out.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            summary = _write(fh, run_dir, {m: recs[m] for m in chosen}, out)
        os.replace(tmp, out)
        summary.skipped = contents.skipped
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return summary


class _Plan:
    """The MCAP schemas and channels of an export, each schema registered once; per mode its per-tick
    topics in the order every tick writes them."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.schema_ids: dict[str, int] = {}
        self.schemas: dict[str, str] = {}  # topic -> schema name
        self.channels: dict[int, str] = {}  # channel id -> topic

    def channel(self, topic: str, schema: str, data: bytes) -> int:
        if schema not in self.schema_ids:
            self.schema_ids[schema] = self.writer.register_schema(schema, "jsonschema", data)
        cid = self.writer.register_channel(topic, "json", self.schema_ids[schema])
        self.schemas[topic] = schema
        self.channels[cid] = topic
        return cid

    def fox(self, topic: str, name: str) -> int:
        return self.channel(topic, f"foxglove.{name}", foxglove_schema(name))

    def mode_topics(self, mode: str, rec: Recording) -> list[tuple[int, Encoder]]:
        """(channel id, encoder) of every per-tick topic of a mode."""
        out: list[tuple[int, Encoder]] = []
        t, wall = rows(np.asarray(rec.t, dtype=float)), rows(np.asarray(rec.wall_t, dtype=float))
        doc = "mission clock t (s) and wall-clock time wall_t (s since the epoch) of the tick"
        cid = self.channel(
            f"/{mode}/clock", "flightstack.clock", plain_schema("flightstack.clock", CLOCK_FIELDS, rec.t, doc)
        )
        out.append((cid, lambda k, ns: dumps({"t": t(k), "wall_t": wall(k)})))

        def poses(entity: str, a: np.ndarray) -> None:
            tf, pose = pose_encoders(a, f"{mode}/{entity}")
            out.append((self.fox(f"/{mode}/{entity}/tf", "FrameTransform"), tf))
            out.append((self.fox(f"/{mode}/{entity}/pose", "PoseInFrame"), pose))

        poses("target", rec.g_w0)
        for j, i in enumerate(rec.drone_ids):
            poses(f"drone{i}", rec.g_wi[:, j])
            poses(f"drone{i}/estimate", rec.g_bar_w[:, j])
        for f in ARRAY_FIELDS:
            if f in POSE_FIELDS or f in CLOCK_FIELDS:
                continue
            a = np.asarray(getattr(rec, f))
            schema = f"flightstack.{f}"
            doc = FIELD_DOCS.get(f, f"per-tick array {f} of the recording (flightstack.recording.timeseries)")
            if a.ndim >= 2 and a.shape[1] == len(rec.drone_ids):  # per drone
                cols = [(f"/{mode}/drone{i}/{f}", a[:, j]) for j, i in enumerate(rec.drone_ids)]
            else:
                cols = [(f"/{mode}/{f}", a)]
            for topic, col in cols:
                enc, keys = plain_encoder(col)
                out.append((self.channel(topic, schema, plain_schema(schema, keys, col, doc)), enc))
        return out


def _tick_messages(topics: list[tuple[int, Encoder]], ns: list[int]) -> Iterator[Message]:
    for k, when in enumerate(ns):
        for cid, enc in topics:
            yield when, cid, enc(k, when)


def _library() -> str:
    """The MCAP header's library string: flightstack's and mcap's versions."""
    try:
        ours = metadata.version("flightstack")
    except metadata.PackageNotFoundError:  # a checkout that was never installed
        ours = "unknown"
    return f"flightstack {ours}; mcap-python {mcap.__version__}"


def _write(fh: IO[bytes], run_dir: Path, recs: dict[str, Recording], out: Path) -> ExportSummary:
    """Every message of `recs` in time order (heapq.merge of the modes' tick and event streams, each
    in time order), then metadata and attachments."""
    writer = Writer(fh)
    writer.start(profile="", library=_library())
    plan = _Plan(writer)
    summary = ExportSummary(out, list(recs))
    streams: list[Iterator[Message]] = []
    bases: dict[str, float] = {}
    for mode, rec in recs.items():
        if rec.ticks_done != len(rec.t):  # read_run's recordings hold exactly their ticks; never export more
            rec = rec.truncated()
        n_ticks = rec.ticks_done
        bases[mode] = base = time_base(rec)
        # times never decrease within a topic, even for a (never seen) tick whose t goes back
        ns = list(accumulate((to_ns(base, float(x)) for x in rec.t), max))
        summary.mode_ticks[mode] = n_ticks
        summary.mode_seconds[mode] = float(rec.t[-1] - rec.t[0]) if n_ticks else 0.0
        streams.append(_tick_messages(plan.mode_topics(mode, rec), ns))
        events_cid = plan.fox(f"/{mode}/events", "Log")
        streams.append(iter(event_messages(rec.events, base, ns[0] if ns else to_ns(base, 0.0), events_cid)))
    counts = dict.fromkeys(plan.channels, 0)
    first: int | None = None
    last = 0
    for when, cid, data in heapq.merge(*streams, key=lambda m: m[0]):
        writer.add_message(cid, log_time=when, data=data, publish_time=when, sequence=counts[cid])
        counts[cid] += 1
        first = when if first is None else first
        last = when
    summary.start_ns, summary.end_ns = first or 0, last
    summary.topics = {plan.channels[c]: counts[c] for c in plan.channels}
    summary.schemas = dict(plan.schemas)
    meta = {"run_dir": str(run_dir), "modes": ",".join(recs), "time_base_s": json.dumps(bases)}
    meta["drone_ids"] = json.dumps({m: r.drone_ids for m, r in recs.items()})
    meta["time"] = "log_time = int((base + t) * 1e9) ns: t the mission clock (s), base time_base_s[mode]"
    writer.add_metadata("flightstack", meta)
    for name, media_type in ATTACHMENTS.items():
        path = run_dir / name
        if path.is_file():
            writer.add_attachment(summary.start_ns, summary.start_ns, name, media_type, path.read_bytes())
    writer.finish()
    return summary
