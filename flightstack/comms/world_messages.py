"""Messages between the served simulated world (`flightstack world`) and agent processes.

Keys (same key space as the prediction bus):
    {prefix}/{mission}/world/tick/{id}   world → agent `id`: what its sensors see at tick k
    {prefix}/{mission}/world/cmd/{id}    agent `id` → world: what it did to its drone during tick k

Layout: u32 little-endian length L | L bytes of UTF-8 JSON header | optional raw image bytes (H×W×3 RGB
uint8, row-major) when the header's frame has an `image` shape. JSON keeps floats exact (Python writes
the shortest repr that reads back identically), so a served simulation is as deterministic as a local one.

Tick header: {"v": 1, "k": tick, "t": mission time (s), "state": {battery_pct, height_m, link_alive,
flying, phase}, "poses": {body: [stamp, x, y, z, θ]} (motion capture of the agent's own body and the
target, absent when stale), "truth": {"target": [x, y, z, θ], "drone": [x, y, z, θ]} (sim only, for
recordings), "frame": null or {"stamp", "features": [2m] or null, "image": [H, W] or null}}.
Cmd header: {"v": 1, "k": tick, "calls": [[name, args...], ...]}: the hal.Drone calls of this tick in
order (connect, takeoff, land, emergency_stop, send_body_velocity [v_x, v_y, v_z, ω] m/s and rad/s,
close). Decoding never raises: it returns None and the reason, for counting.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any

import numpy as np

VERSION = 1
_LEN = struct.Struct("<I")
MAX_HEADER = 1 << 20
DRONE_CALLS = frozenset({"connect", "takeoff", "land", "emergency_stop", "send_body_velocity", "close"})


def tick_key(prefix: str, mission: str, drone_id: int | str) -> str:
    return f"{prefix}/{mission}/world/tick/{drone_id}"


def cmd_key(prefix: str, mission: str, drone_id: int | str) -> str:
    return f"{prefix}/{mission}/world/cmd/{drone_id}"


def pack(header: dict[str, Any], image: np.ndarray | None = None) -> bytes:
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    tail = b"" if image is None else np.ascontiguousarray(image, dtype=np.uint8).tobytes()
    return _LEN.pack(len(head)) + head + tail


def unpack(data: bytes) -> tuple[dict[str, Any] | None, bytes, str | None]:
    """(header, trailing bytes, None) or (None, b"", reason)."""
    if len(data) < _LEN.size:
        return None, b"", "truncated"
    (n,) = _LEN.unpack_from(data)
    if n > MAX_HEADER or len(data) < _LEN.size + n:
        return None, b"", "bad length"
    try:
        header = json.loads(data[_LEN.size : _LEN.size + n], parse_constant=_refuse_constant)
    except ValueError:  # bad UTF-8, bad JSON, or NaN/Infinity literals
        return None, b"", "not JSON"
    if not isinstance(header, dict) or header.get("v") != VERSION or not isinstance(header.get("k"), int):
        return None, b"", "bad header"
    return header, data[_LEN.size + n :], None


def _refuse_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} in a world message")


def _finite(xs: object, n: int) -> bool:
    return (
        isinstance(xs, list)
        and len(xs) == n
        and all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in xs)
    )


def decode_cmd(data: bytes) -> tuple[dict[str, Any] | None, str | None]:
    """A validated cmd header, or (None, reason). Unknown calls and non-finite velocities are refused."""
    header, _, reason = unpack(data)
    if header is None:
        return None, reason
    calls = header.get("calls")
    if not isinstance(calls, list):
        return None, "no calls"
    for c in calls:
        if not (isinstance(c, list) and c and c[0] in DRONE_CALLS):
            return None, "unknown call"
        if c[0] == "send_body_velocity" and not _finite(c[1] if len(c) > 1 else None, 4):
            return None, "bad velocity"
    return header, None


def decode_tick(data: bytes) -> tuple[dict[str, Any] | None, np.ndarray | None, str | None]:
    """(header, image or None, None) or (None, None, reason)."""
    header, tail, reason = unpack(data)
    if header is None:
        return None, None, reason
    if not (isinstance(header.get("t"), float | int) and isinstance(header.get("state"), dict)):
        return None, None, "bad tick"
    poses, truth = header.get("poses", {}), header.get("truth")
    if not (isinstance(poses, dict) and all(_finite(row, 5) for row in poses.values())):
        return None, None, "bad poses"
    if not (isinstance(truth, dict) and _finite(truth.get("target"), 4) and _finite(truth.get("drone"), 4)):
        return None, None, "bad truth"
    frame = header.get("frame")
    if isinstance(frame, dict):
        feats = frame.get("features")
        if feats is not None and not _finite(feats, len(feats) if isinstance(feats, list) else -1):
            return None, None, "bad features"
    image = None
    if isinstance(frame, dict) and frame.get("image") is not None:
        shape = frame["image"]
        if not (isinstance(shape, list) and len(shape) == 2 and len(tail) == shape[0] * shape[1] * 3):
            return None, None, "bad image"
        image = np.frombuffer(tail, dtype=np.uint8).reshape(shape[0], shape[1], 3)
    return header, image, None
