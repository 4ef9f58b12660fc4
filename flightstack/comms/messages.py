"""The prediction message agents exchange every tick (DESIGN §6), fixed binary layout, strict decoding.

Layout (little endian), schema version 1:
    magic "FSPM" | version u8 | flags u8 (bit 0: visible) | sender u16 | seq u32 | stamp f64 (s) |
    mission name length u8 | mission name (UTF-8, ≤ 64 bytes) |
    ḡ_w,i = x, y, z (m), θ (rad) | μ (4) | var (4) | prior_var (4)            (16 × f64)
μ and var are the sender's own expert evaluated at its own estimate ḡ_w,i (body velocity of the target,
m/s and rad/s); prior_var (σ_f²) lets receivers use the BCM/rBCM fusion rules. A sender without a GP
publishes μ = 0 and var = prior_var = 1 (never used for fusion in mode `none`).

`decode` returns (message, None) or (None, reason) and never raises: bad input is the caller's to count.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MAGIC = b"FSPM"
SCHEMA_VERSION = 1
MAX_MISSION_NAME = 64
_HEAD = struct.Struct("<4sBBHIdB")
_BODY = struct.Struct("<16d")


@dataclass(frozen=True)
class PredictionMessage:
    mission: str
    sender: int
    seq: int
    stamp: float
    visible: bool
    g_bar_w: np.ndarray  # (4,) [x, y, z, θ]
    mu: np.ndarray  # (4,)
    var: np.ndarray  # (4,)
    prior_var: np.ndarray  # (4,)


def encode(msg: PredictionMessage) -> bytes:
    """Serialise; raises ValueError for a message this side would itself reject (never sends garbage)."""
    name = msg.mission.encode("utf-8")
    if len(name) > MAX_MISSION_NAME:
        raise ValueError(f"mission name longer than {MAX_MISSION_NAME} bytes")
    fields = [
        np.asarray(a, dtype=float).reshape(-1).tolist() for a in (msg.g_bar_w, msg.mu, msg.var, msg.prior_var)
    ]
    reason = _check_fields(msg.sender, msg.seq, msg.stamp, *fields)
    if reason:
        raise ValueError(f"refusing to encode invalid message: {reason}")
    head = _HEAD.pack(
        MAGIC, SCHEMA_VERSION, 1 if msg.visible else 0, msg.sender, msg.seq, msg.stamp, len(name)
    )
    body = _BODY.pack(*fields[0], *fields[1], *fields[2], *fields[3])
    return head + name + body


def _check_fields(
    sender: int,
    seq: int,
    stamp: float,
    g: Sequence[float],
    mu: Sequence[float],
    var: Sequence[float],
    prior_var: Sequence[float],
) -> str | None:
    """Reason the fields are invalid, or None. Pure Python on 16 floats: this runs twice per message."""
    if not (0 <= sender < 2**16) or not (0 <= seq < 2**32):
        return "sender or seq out of range"
    if not math.isfinite(stamp):
        return "non-finite stamp"
    for name, arr in (("g_bar_w", g), ("mu", mu), ("var", var), ("prior_var", prior_var)):
        if len(arr) != 4:
            return f"{name} must have 4 elements"
        if not all(map(math.isfinite, arr)):
            return f"non-finite {name}"
    if min(var) <= 0 or min(prior_var) <= 0:
        return "variance must be > 0"
    return None


def decode(
    data: bytes, mission: str, known_senders: frozenset[int] | set[int]
) -> tuple[PredictionMessage | None, str | None]:
    """Parse and validate one message for `mission`; (None, reason) on any defect, never raises."""
    try:
        if not isinstance(data, bytes | bytearray | memoryview):
            return None, "not bytes"
        data = bytes(data)
        if len(data) < _HEAD.size:
            return None, "truncated header"
        magic, version, flags, sender, seq, stamp, name_len = _HEAD.unpack_from(data, 0)
        if magic != MAGIC:
            return None, "bad magic"
        if version != SCHEMA_VERSION:
            return None, f"unsupported schema version {version}"
        if flags & ~1:
            return None, "unknown flag bits"
        if name_len > MAX_MISSION_NAME:
            return None, "mission name too long"
        end_name = _HEAD.size + name_len
        if len(data) != end_name + _BODY.size:
            return None, "wrong length"
        try:
            name = data[_HEAD.size : end_name].decode("utf-8")
        except UnicodeDecodeError:
            return None, "mission name not UTF-8"
        if name != mission:
            return None, "other mission"
        if sender not in known_senders:
            return None, "unknown sender"
        vals = _BODY.unpack_from(data, end_name)
        g, mu, var, prior = vals[0:4], vals[4:8], vals[8:12], vals[12:16]
        reason = _check_fields(sender, seq, stamp, g, mu, var, prior)
        if reason:
            return None, reason
        msg = PredictionMessage(
            name,
            sender,
            seq,
            stamp,
            bool(flags & 1),
            np.array(g),
            np.array(mu),
            np.array(var),
            np.array(prior),
        )
        return msg, None
    except Exception as exc:  # pragma: no cover - belt and braces: the decoder must never raise
        return None, f"decoder error: {type(exc).__name__}"
