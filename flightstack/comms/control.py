"""The operator channel's messages (issue 6, issue 15): abort, status, abort acknowledgements.

One JSON shape on every transport (the Zenoh key `{prefix}/{mission}/control`, and the loopback UDP
listener of in-process missions, flightstack/comms/operator_link.py):

    {"mission": str, "kind": "abort" | "status" | "abort_ack", "payload": {...}, "origin": [int, ...]}

`origin`: the drone ids hosted by the publishing process (empty for operator tools).
Abort payload: {"reason": str, "id": str}; `id` names one `flightstack abort` invocation so that its
acknowledgements can be told from those of an earlier abort.
Acknowledgement payload (ABORT_ACK): {"abort_id": str | null, "drones": [int, ...], "pid": int,
"host": str}; sent by every process hosting agents as soon as its bus receives an abort, before the
runner acts on it (the runner lands at its next check).

`parse_control` validates (size bound, UTF-8 JSON object, field types, mission name, kind) and never
raises: a bad message is the caller's to count under the returned reason.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass
from typing import Any

ABORT = "abort"
STATUS = "status"
ABORT_ACK = "abort_ack"
CONTROL_KINDS = frozenset({ABORT, STATUS, ABORT_ACK})
MAX_CONTROL_BYTES = 65536  # bytes of one control message
MAX_HOST_CHARS = 255


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
    (not a UTF-8 JSON object with a str kind, a dict payload and a list of int origin), of another
    mission, or of a kind not in `kinds`. `t_recv`: receipt time, time.monotonic() (s). Never raises."""
    if len(data) > max_bytes:
        return None, f"{prefix}: too large"
    try:
        body = json.loads(bytes(data).decode("utf-8"), parse_constant=_reject_constant)
        kind, payload, origin = body["kind"], body["payload"], body.get("origin", [])
        ok = (
            isinstance(kind, str)
            and isinstance(payload, dict)
            and isinstance(origin, list)
            and all(isinstance(i, int) and not isinstance(i, bool) for i in origin)
        )
    except Exception:  # not UTF-8, not JSON, not an object, missing keys, too deeply nested, ...
        ok = False
    if not ok:
        return None, f"{prefix}: malformed"
    if body.get("mission") != mission:
        return None, f"{prefix}: other mission"
    if kind not in kinds:
        return None, f"{prefix}: unknown kind"
    return ControlEvent(t_recv, kind, payload, tuple(origin)), None


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
    p = ev.payload
    drones, pid, host = p.get("drones"), p.get("pid"), p.get("host")
    if ev.kind != ABORT_ACK or p.get("abort_id") != abort_id:
        return None
    if not isinstance(drones, list) or not drones:
        return None
    if not all(isinstance(i, int) and not isinstance(i, bool) and i in known for i in drones):
        return None
    if not isinstance(pid, int) or not isinstance(host, str) or len(host) > MAX_HOST_CHARS:
        return None
    return AbortAck(ev.time, tuple(sorted(drones)), pid, host, via)


__all__ = [
    "ABORT",
    "ABORT_ACK",
    "CONTROL_KINDS",
    "MAX_CONTROL_BYTES",
    "STATUS",
    "AbortAck",
    "ControlEvent",
    "ack_payload",
    "encode_control",
    "parse_control",
    "read_ack",
]
