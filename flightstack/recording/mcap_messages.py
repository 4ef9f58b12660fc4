"""The JSON messages and schemas of the MCAP export (flightstack.recording.mcap_export has the layout,
the time base and the writer): Foxglove's FrameTransform, PoseInFrame and Log, and plain JSON objects
per recorded array. Poses are [x, y, z, θ] in Σw (m, rad; yaw only); non-finite floats become null."""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable, Sequence
from importlib import resources
from typing import Any

import numpy as np

from flightstack.events import mission_time, severity
from flightstack.paper.geometry import yaw_quaternions
from flightstack.recording.files import json_safe
from flightstack.recording.timeseries import Recording

FOXGLOVE_SCHEMAS = ("FrameTransform", "PoseInFrame", "Log")
"""The Foxglove schemas the export writes, shipped as schemas/foxglove/<name>.json (README.md there)."""
WORLD_FRAME = "world"
"""Parent frame of every transform and frame of every pose: the world frame Σw."""
VEC4_KEYS = ("x", "y", "z", "theta")
"""Keys of a 4-vector [x, y, z, θ] (a pose or twist's components in the recording's order)."""
LOG_INFO, LOG_WARNING, LOG_ERROR = 2, 3, 4
"""foxglove.LogLevel values (Log.json)."""
_LOG_LEVELS = {"ERROR": LOG_ERROR, "WARNING": LOG_WARNING, "INFO": LOG_INFO}
FIELD_DOCS = {
    "e_c": "control error vec(g_d^-1 gbar_i0) of the drone (m, rad)",
    "e_e": "true estimation error vec(gbar_i0^-1 g_i0) (m, rad)",
    "e_e_meas": "measured estimation error J+(f - fbar) (m, rad)",
    "u_e": "observer input u_e, a body velocity (m/s, rad/s)",
    "mu_used": "fused GP mean of the target's body velocity used by the drone (m/s, rad/s)",
    "var_own": "the drone's own GP expert's predictive variance ((m/s)^2, (rad/s)^2)",
    "V_cmd": "body-velocity command sent, in the drone's frame (m/s, rad/s)",
    "visible": "the drone's camera saw the target this tick",
    "n_fused": "predictions fused (own + fresh neighbours)",
    "loop_period": "wall time from the previous tick's start to this one's (s); null: not measured",
    "loop_compute": "wall time of this tick's sensing, fusion, command and record (s); null: not measured",
    "frame_age": "age of the camera frame the tick used (s, mission clock); null: no frame",
    "pose_age": "age of the drone's own pose the tick used (s, mission clock); null: none",
}
"""What a plain topic's schema says about its field (units, frame); others get a generic line."""

Encoder = Callable[[int, int], bytes]
"""(tick index, log time in ns) -> the message's JSON bytes."""
Message = tuple[int, int, bytes]
"""(log time in ns, channel id, JSON bytes)."""


@functools.cache
def foxglove_schema(name: str) -> bytes:
    """The shipped JSON schema `foxglove.<name>` (package data schemas/foxglove/<name>.json)."""
    return (resources.files(__package__) / "schemas" / "foxglove" / f"{name}.json").read_bytes()


def plain_schema(name: str, keys: Sequence[str], a: np.ndarray, doc: str) -> bytes:
    """JSON schema `name` of a plain per-tick topic: an object of `keys`, each a boolean, an integer
    or a number-or-null by the array's dtype."""
    kind = {"b": "boolean", "i": "integer", "u": "integer"}.get(a.dtype.kind, "number")
    prop = {"type": [kind] if kind != "number" else ["number", "null"]}
    doc_ = {"title": name, "description": doc, "type": "object"}
    return dumps({**doc_, "properties": dict.fromkeys(keys, prop), "required": list(keys)})


def time_base(rec: Recording) -> float:
    """Seconds added to the mission clock t for log times: first wall_t − first t when wall_t is
    present and nonzero (epoch s), else 0."""
    wall = np.asarray(rec.wall_t, dtype=float)
    if len(rec.t) == 0 or wall.size == 0 or not math.isfinite(wall[0]) or wall[0] == 0.0:
        return 0.0
    return float(wall[0]) - float(rec.t[0])


def to_ns(base: float, t: float) -> int:
    """log_time (ns) of mission time t (s): int((base + t) · 1e9), at least 0 (MCAP times are unsigned)."""
    return max(0, int((base + t) * 1e9))


def dumps(obj: Any) -> bytes:
    """Compact strict JSON (a NaN left in `obj` raises ValueError)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def stamp(ns: int) -> dict[str, int]:
    """A Foxglove `time` {sec, nsec} of log time ns."""
    sec, nsec = divmod(ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def rows(a: np.ndarray) -> Callable[[int], Any]:
    """Row k of `a` as JSON-able Python values (non-finite floats None; cleaned only in the rows that
    have one)."""
    if a.dtype.kind != "f":
        return lambda k: a[k].tolist()
    bad = ~np.isfinite(a)
    bad_rows = bad.any(axis=tuple(range(1, a.ndim))) if a.ndim > 1 else bad
    return lambda k: json_safe(a[k].tolist()) if bad_rows[k] else a[k].tolist()


def pose_encoders(poses: np.ndarray, child: str) -> tuple[Encoder, Encoder]:
    """(foxglove.FrameTransform world → child, foxglove.PoseInFrame in world) encoders of the poses
    (N, 4) [x, y, z, θ] in Σw (m, rad): rotation (x, y, z, w) = (0, 0, sin θ/2, cos θ/2)."""
    xyz = rows(np.asarray(poses[:, :3], dtype=float))
    quat = rows(yaw_quaternions(poses[:, 3])[:, 2:])  # (z, w); x = y = 0

    def parts(k: int) -> tuple[dict[str, Any], dict[str, Any]]:
        x, y, z = xyz(k)
        qz, qw = quat(k)
        return {"x": x, "y": y, "z": z}, {"x": 0.0, "y": 0.0, "z": qz, "w": qw}

    def tf(k: int, ns: int) -> bytes:
        p, r = parts(k)
        head = {"timestamp": stamp(ns), "parent_frame_id": WORLD_FRAME, "child_frame_id": child}
        return dumps({**head, "translation": p, "rotation": r})

    def pose(k: int, ns: int) -> bytes:
        p, r = parts(k)
        return dumps(
            {"timestamp": stamp(ns), "frame_id": WORLD_FRAME, "pose": {"position": p, "orientation": r}}
        )

    return tf, pose


def plain_encoder(a: np.ndarray) -> tuple[Encoder, list[str]]:
    """Encoder of a per-tick array as a flat JSON object, and its keys: (N,) {"value"}, (N, 4)
    {"x", "y", "z", "theta"}, (N, k) {"c0", ..}."""
    row = rows(a)
    if a.ndim == 1:
        return (lambda k, ns: dumps({"value": row(k)})), ["value"]
    keys = list(VEC4_KEYS) if a.shape[1] == 4 else [f"c{j}" for j in range(a.shape[1])]
    return (lambda k, ns: dumps(dict(zip(keys, row(k), strict=True)))), keys


def event_level(ev: dict[str, Any]) -> int:
    """foxglove.LogLevel of an event: its flightstack.events.severity."""
    return _LOG_LEVELS[severity(ev)]


def event_text(ev: dict[str, Any]) -> str:
    """One line for a log viewer: `event[ drone i][: kind][ - detail or reason]  {the event's JSON}`."""
    head = str(ev.get("event", "event"))
    if ev.get("drone") is not None:
        head += f" drone {ev['drone']}"
    if ev.get("kind"):
        head += f": {ev['kind']}"
    tail = ev.get("detail") or ev.get("reason")
    if tail:
        head += f" - {tail}"
    return f"{head}  {json.dumps(json_safe(ev), allow_nan=False)}"


def event_messages(events: list[dict[str, Any]], base: float, first_ns: int, cid: int) -> list[Message]:
    """A mode's events as foxglove.Log messages on channel cid, sorted by time (stable: file order among
    equal times). An event is at base + its t (s) when t is a finite number on the mission clock, else
    (a device's monotonic stamp, no t) at the time of the event before it (first_ns for the first)."""
    out, last = [], first_ns
    for ev in events:
        t = mission_time(ev)
        if t is not None:
            last = to_ns(base, t)
        msg = {"timestamp": stamp(last), "level": event_level(ev), "message": event_text(ev)}
        msg.update(name=str(ev.get("source") or "flightstack"), file="", line=0)
        out.append((last, cid, dumps(msg)))
    out.sort(key=lambda m: m[0])
    return out
