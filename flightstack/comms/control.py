"""The operator channel's messages: abort, status, abort acknowledgements.

One JSON shape on every transport (the Zenoh key `{prefix}/{mission}/control`, and the loopback UDP
listener of in-process missions, flightstack/comms/operator_link.py):

    {"mission": str, "kind": "abort" | "status" | "abort_ack", "payload": {...}, "origin": [int, ...]}

`origin`: the drone ids hosted by the publishing process (empty for operator tools).
Abort payload: {"reason": str, "id": str}; `id` names one `flightstack abort` invocation so that its
acknowledgements can be told from those of an earlier abort.
Acknowledgement payload (ABORT_ACK): {"abort_id": str | null, "drones": [int, ...], "pid": int,
"host": str}; sent by every process hosting agents as soon as its bus receives an abort, before the
runner acts on it (the runner lands at its next check).

Status payload (STATUS, flightstack/runtime/fleet.py StatusPublisher, about twice a second per agent):
exactly
the fields of `StatusReport`.

`parse_control` validates (size bound, UTF-8 JSON object, field types, mission name, kind, then the
payload of that kind) and never raises: a bad message is the caller's to count under the returned reason
("<prefix>: malformed", "other mission", "unknown kind", "bad abort", "bad abort_ack", "bad status").
A payload is valid when every field of its kind is present with its type and bounds (below); fields a
kind does not have are ignored and removed (a newer sender's addition must not make an abort fail; no
consumer ever sees an unvalidated value). The event's payload is the validated one, in plain JSON types;
`AbortRequest`, `AckReport` and `StatusReport` are its typed views (`from_payload` → value or None).
Every string must be printable (no control characters: a forged message cannot drive a terminal that
shows it, `flightstack status`, `flightstack abort`, an agent's log), but for the abort's reason, whose
control characters are replaced (an abort is never refused for its wording). A message nests at most
MAX_NESTING levels of [ and { (checked before parsing).
Bounds: abort reason ≤ MAX_REASON_CHARS characters; abort id ≤ MAX_ID_CHARS; drone ids in
[0, MAX_DRONE_ID] (the mission's); origin and ack drone lists ≤ MAX_DRONES entries; pid in
[0, MAX_PID]; host ≤ MAX_HOST_CHARS; status: t finite with |t| ≤ MAX_STATUS_TIME_S s, tick and
n_fused ints in [0, MAX_COUNT], battery_pct in [0, 100] %, mode ≤ MAX_MODE_CHARS of [A-Za-z0-9_-],
rejection null or ≤ MAX_REJECTION_CHARS, dropped and restarts ≤ MAX_DROPPED_REASONS reasons or names
of ≤ MAX_REJECTION_CHARS characters → counts in [0, MAX_COUNT].
"""

from __future__ import annotations

import json
import os
import re
import socket
from dataclasses import dataclass
from typing import Any

ABORT = "abort"
STATUS = "status"
ABORT_ACK = "abort_ack"
CONTROL_KINDS = frozenset({ABORT, STATUS, ABORT_ACK})
MAX_CONTROL_BYTES = 65536  # bytes of one control message
MAX_HOST_CHARS = 255
MAX_REASON_CHARS = 1024  # an abort's reason (characters)
MAX_ID_CHARS = 128  # an abort's id (characters; send_abort uses 32 hex digits)
MAX_DRONE_ID = 2**16 - 1  # mission.DroneSpec.id < 2**16
MAX_DRONES = 1024  # ids in an origin or an acknowledgement
MAX_PID = 2**32 - 1
MAX_STATUS_TIME_S = 1e9  # |t| of a status (s): mission time, or time.monotonic() on hardware
MAX_COUNT = 2**53  # ticks, fused experts, drop counts
MAX_MODE_CHARS = 32
MAX_REJECTION_CHARS = 256  # a rejection or a drop reason (characters)
MAX_DROPPED_REASONS = 256  # distinct drop reasons in one status
MAX_NESTING = 8  # levels of [ and { in one control message (a valid one has at most 3)
_MODE = re.compile(rf"[A-Za-z0-9_-]{{1,{MAX_MODE_CHARS}}}")


@dataclass(frozen=True)
class ControlEvent:
    """One valid control message as received."""

    time: float  # receiver's time.monotonic() at receipt (s)
    kind: str  # "abort" | "status" | "abort_ack"
    payload: dict[str, Any]
    origin: tuple[int, ...]  # drone ids hosted by the publishing process


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite JSON constant {name}")


def encode_control(
    mission: str, kind: str, payload: dict[str, Any], origin: list[int] | tuple[int, ...]
) -> bytes:
    """UTF-8 JSON of one control message; ValueError for an unknown kind or a payload that is not a
    JSON-serialisable dict (NaN and infinities refused) or larger than MAX_CONTROL_BYTES."""
    if kind not in CONTROL_KINDS:
        raise ValueError(f"unknown control kind {kind!r} (expected one of {sorted(CONTROL_KINDS)})")
    if not isinstance(payload, dict):
        raise ValueError("control payload must be a dict")
    body = {"mission": mission, "kind": kind, "payload": payload, "origin": sorted(origin)}
    try:
        data = json.dumps(body, allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ValueError(f"control payload not JSON-serialisable: {exc}") from exc
    if len(data) > MAX_CONTROL_BYTES:
        raise ValueError(f"control message larger than {MAX_CONTROL_BYTES} bytes")
    return data


def parse_control(
    data: bytes,
    mission: str,
    t_recv: float,
    kinds: frozenset[str] = CONTROL_KINDS,
    max_bytes: int = MAX_CONTROL_BYTES,
    prefix: str = "control",
) -> tuple[ControlEvent | None, str | None]:
    """(event, None), or (None, "<prefix>: <reason>") for a message that is too large, malformed
    (not a UTF-8 JSON object of at most MAX_NESTING levels with a str kind, a dict payload and a list
    of drone ids as origin), of another mission, of a kind not in `kinds`, or whose payload is not valid
    for its kind ("<prefix>: bad <kind>"; the event carries the validated payload: module docstring).
    `t_recv`: receipt time, time.monotonic() (s). Never raises."""
    try:
        if len(data) > max_bytes:
            return None, f"{prefix}: too large"
        data = bytes(data)
        if too_deep(data, MAX_NESTING):
            return None, f"{prefix}: malformed"
        body = json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
        kind, payload, origin = body["kind"], body["payload"], body.get("origin", [])
        ok = (
            isinstance(kind, str)
            and isinstance(payload, dict)
            and isinstance(origin, list)
            and len(origin) <= MAX_DRONES
            and all(_int(i, 0, MAX_DRONE_ID) is not None for i in origin)
        )
    except Exception:  # not bytes, not UTF-8, not JSON, not an object, missing keys, too deeply nested, ...
        ok = False
    if not ok:
        return None, f"{prefix}: malformed"
    if body.get("mission") != mission:
        return None, f"{prefix}: other mission"
    if kind not in kinds or kind not in _PAYLOADS:
        return None, f"{prefix}: unknown kind"
    typed = _PAYLOADS[kind].from_payload(payload)
    if typed is None:
        return None, f"{prefix}: bad {kind}"
    return ControlEvent(t_recv, kind, typed.to_payload(), tuple(origin)), None


# ---- typed payloads ---------------------------------------------------------------------------------
_MISSING = object()


def too_deep(data: bytes, max_depth: int) -> bool:
    """JSON text `data` nests [ and { deeper than max_depth levels (brackets inside strings count too: an
    upper bound). Found without parsing, so that a deeply nested input never reaches the parser."""
    if data.count(b"[") + data.count(b"{") <= max_depth:
        return False
    import numpy as np

    a = np.frombuffer(data, dtype=np.uint8)
    step = (a == 0x5B).astype(np.int32) + (a == 0x7B) - (a == 0x5D) - (a == 0x7D)
    return int(np.cumsum(step).max()) > max_depth


def _int(x: object, lo: int, hi: int) -> int | None:
    return x if isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi else None


def _text(x: object, max_chars: int, printable: bool = True) -> str | None:
    """x if it is a str of at most max_chars characters (and printable: no control characters)."""
    if not (isinstance(x, str) and len(x) <= max_chars):
        return None
    return x if not printable or x.isprintable() else None


def _bool(x: object) -> bool | None:
    return x if isinstance(x, bool) else None


@dataclass(frozen=True)
class AbortRequest:
    """An abort payload: why (shown to people) and the id of the `flightstack abort` invocation. A control
    character in the reason is replaced by U+FFFD rather than refused: an abort is obeyed whatever the
    operator typed."""

    reason: str
    id: str

    @staticmethod
    def from_payload(p: object) -> AbortRequest | None:
        if not isinstance(p, dict):
            return None
        reason, abort_id = _text(p.get("reason"), MAX_REASON_CHARS, False), _text(p.get("id"), MAX_ID_CHARS)
        if reason is None or abort_id is None:
            return None
        return AbortRequest("".join(c if c.isprintable() else "\ufffd" for c in reason), abort_id)

    def to_payload(self) -> dict[str, Any]:
        return {"reason": self.reason, "id": self.id}


@dataclass(frozen=True)
class AckReport:
    """An acknowledgement payload: the abort's id (None: an abort without one), the acknowledging
    process's drones (at least one), pid and host name."""

    abort_id: str | None
    drones: tuple[int, ...]
    pid: int
    host: str

    @staticmethod
    def from_payload(p: object) -> AckReport | None:
        if not isinstance(p, dict) or "abort_id" not in p:
            return None
        abort_id = p["abort_id"]
        drones, pid = p.get("drones"), _int(p.get("pid"), 0, MAX_PID)
        host = _text(p.get("host"), MAX_HOST_CHARS)
        if abort_id is not None and _text(abort_id, MAX_ID_CHARS) is None:
            return None
        if not (isinstance(drones, list) and 1 <= len(drones) <= MAX_DRONES):
            return None
        if not all(_int(i, 0, MAX_DRONE_ID) is not None for i in drones) or pid is None or host is None:
            return None
        return AckReport(abort_id, tuple(drones), pid, host)

    def to_payload(self) -> dict[str, Any]:
        return {"abort_id": self.abort_id, "drones": list(self.drones), "pid": self.pid, "host": self.host}


@dataclass(frozen=True)
class StatusReport:
    """One agent's status (flightstack/runtime/fleet.py StatusPublisher): its drone, the mode flown, mission
    time t (s) and tick, battery (%), flying and telemetry link, whether it saw the target, how many
    experts it fused, whether its own motion-capture pose is fresh, the last vision rejection (None: none),
    its bus's drop counts by reason, and the messages its bus took by the restart rule, per sender's
    participant name (acceptance.py)."""

    drone: int
    mode: str
    t: float
    tick: int
    battery_pct: float
    flying: bool
    link_alive: bool
    visible: bool
    n_fused: int
    pose_fresh: bool
    rejection: str | None
    dropped: tuple[tuple[str, int], ...]
    restarts: tuple[tuple[str, int], ...]

    @staticmethod
    def from_payload(p: object) -> StatusReport | None:
        if not isinstance(p, dict):
            return None
        drone, tick = _int(p.get("drone"), 0, MAX_DRONE_ID), _int(p.get("tick"), 0, MAX_COUNT)
        n_fused, mode = _int(p.get("n_fused"), 0, MAX_COUNT), p.get("mode")
        t = _real(p.get("t"), -MAX_STATUS_TIME_S, MAX_STATUS_TIME_S)
        battery = _real(p.get("battery_pct"), 0.0, 100.0)
        flying, link_alive = _bool(p.get("flying")), _bool(p.get("link_alive"))
        visible, pose_fresh = _bool(p.get("visible")), _bool(p.get("pose_fresh"))
        rejection, dropped = p.get("rejection", _MISSING), p.get("dropped")
        if drone is None or tick is None or n_fused is None or t is None or battery is None:
            return None
        if flying is None or link_alive is None or visible is None or pose_fresh is None:
            return None
        if not (isinstance(mode, str) and _MODE.fullmatch(mode)):
            return None
        if rejection is not None and _text(rejection, MAX_REJECTION_CHARS) is None:
            return None
        counts, restarts = _counts(dropped), _counts(p.get("restarts"))
        if counts is None or restarts is None:
            return None
        return StatusReport(
            drone=drone,
            mode=mode,
            t=t,
            tick=tick,
            battery_pct=battery,
            flying=flying,
            link_alive=link_alive,
            visible=visible,
            n_fused=n_fused,
            pose_fresh=pose_fresh,
            rejection=rejection,
            dropped=counts,
            restarts=restarts,
        )

    def to_payload(self) -> dict[str, Any]:
        return {
            "drone": self.drone,
            "mode": self.mode,
            "t": self.t,
            "tick": self.tick,
            "battery_pct": self.battery_pct,
            "flying": self.flying,
            "link_alive": self.link_alive,
            "visible": self.visible,
            "n_fused": self.n_fused,
            "pose_fresh": self.pose_fresh,
            "rejection": self.rejection,
            "dropped": dict(self.dropped),
            "restarts": dict(self.restarts),
        }


def _counts(x: object) -> tuple[tuple[str, int], ...] | None:
    """A status's {text: count} object (≤ MAX_DROPPED_REASONS entries, each text ≤ MAX_REJECTION_CHARS,
    each count in [0, MAX_COUNT]) as pairs, or None."""
    if not (isinstance(x, dict) and len(x) <= MAX_DROPPED_REASONS):
        return None
    out: list[tuple[str, int]] = []
    for r, n in x.items():
        count = _int(n, 0, MAX_COUNT)
        if count is None or _text(r, MAX_REJECTION_CHARS) is None:
            return None
        out.append((r, count))
    return tuple(out)


def _real(x: object, lo: float, hi: float) -> float | None:
    """x as a float if it is a JSON number (not a bool) in [lo, hi], else None."""
    if isinstance(x, bool) or not isinstance(x, int | float) or not lo <= x <= hi:  # NaN fails lo <= x
        return None
    return float(x)


def status_report(ev: ControlEvent) -> StatusReport | None:
    """The status in `ev`, or None (another kind, or a malformed payload)."""
    return StatusReport.from_payload(ev.payload) if ev.kind == STATUS else None


_PAYLOADS: dict[str, Any] = {ABORT: AbortRequest, ABORT_ACK: AckReport, STATUS: StatusReport}


def ack_payload(abort: ControlEvent, drones: set[int] | frozenset[int]) -> dict[str, Any]:
    """The acknowledgement of `abort` by the process hosting `drones` (this process's pid and host)."""
    abort_id = abort.payload.get("id")
    return {
        "abort_id": abort_id if isinstance(abort_id, str) else None,
        "drones": sorted(drones),
        "pid": os.getpid(),
        "host": socket.gethostname()[:MAX_HOST_CHARS],
    }


@dataclass(frozen=True)
class AbortAck:
    """A valid acknowledgement of one abort, as the operator sees it."""

    time: float  # operator's time.monotonic() at receipt (s)
    drones: tuple[int, ...]
    pid: int
    host: str
    via: str  # "zenoh" | "loopback"


def read_ack(ev: ControlEvent, abort_id: str, known: set[int], via: str) -> AbortAck | None:
    """The acknowledgement in `ev` if it is one of abort `abort_id` naming only drones of `known`, else
    None (another abort's ack, another kind, or a malformed payload)."""
    ack = AckReport.from_payload(ev.payload) if ev.kind == ABORT_ACK else None
    if ack is None or ack.abort_id != abort_id or not all(i in known for i in ack.drones):
        return None
    return AbortAck(ev.time, tuple(sorted(ack.drones)), ack.pid, ack.host, via)


__all__ = [
    "ABORT",
    "ABORT_ACK",
    "CONTROL_KINDS",
    "MAX_CONTROL_BYTES",
    "STATUS",
    "AbortAck",
    "AbortRequest",
    "AckReport",
    "ControlEvent",
    "StatusReport",
    "ack_payload",
    "encode_control",
    "parse_control",
    "read_ack",
    "status_report",
]
