"""The prediction message agents exchange every tick (DESIGN §6), fixed binary layout, strict decoding.

Layout (little endian), schema version 1 (the byte table: `HEAD`, `HEAD_FIELDS`, `BODY`, `BODY_FIELDS`;
docs/wire-format.md is generated from them):
    magic "FSPM" | version u8 | flags u8 (bit 0: visible) | sender u16 | seq u32 | stamp f64 (s) |
    mission name length u8 | mission name (UTF-8, ≤ 64 bytes) |
    ḡ_w,i = x, y, z (m), θ (rad) | μ (4) | var (4) | prior_var (4)            (16 × f64)
μ and var are the sender's own expert evaluated at its own estimate ḡ_w,i (body velocity of the target,
m/s and rad/s); prior_var (σ_f²) lets receivers use the BCM/rBCM fusion rules. A sender without a GP
publishes μ = 0 and var = prior_var = 1 (never used for fusion in mode `none`).

`decode` returns (message, None) or (None, reason) and never raises: bad input is the caller's to count.

Flat layout in memory: the 16 floats are one float64 array, written with one `tobytes()` and
read with one `np.frombuffer`; a message built by `decode` (or `PredictionMessage.of_body`) has its four
fields as views of that array (`body()`). The checks on the 16 floats, and the receiver's
AcceptanceBounds (acceptance.py), are one compiled kernel (flightstack.paper.kernels.message_check)
returning the first defect in a fixed order, named by `REASONS`.
"""

from __future__ import annotations

import math
import struct
import sys
from dataclasses import dataclass

import numpy as np

from flightstack.paper import kernels as kern

MAGIC = b"FSPM"
SCHEMA_VERSION = 1
MAX_MISSION_NAME = 64
HEAD = struct.Struct("<4sBBHIdB")
"""The header (21 bytes, little endian); then the mission name (name_len bytes), then BODY."""
BODY = struct.Struct("<16d")
"""The body: 16 little-endian float64 (packed and read as one float64 array)."""
HEAD_FIELDS: tuple[tuple[str, str], ...] = (
    ("magic", 'the 4 ASCII bytes "FSPM"'),
    ("version", "schema version, SCHEMA_VERSION (1)"),
    ("flags", "bit 0: the sender sees the target (visible); the other bits are 0"),
    ("sender", "the sender's drone id; equals the {i} of the key pred/{i}"),
    ("seq", "the sender's message count, + 1 per message, from 0 when its process starts"),
    ("stamp", "the sender's mission time of the tick (s)"),
    ("name_len", "L: the mission name's length (bytes, at most MAX_MISSION_NAME = 64)"),
)
"""HEAD's fields in order: (name, what it holds, with units)."""
BODY_FIELDS: tuple[tuple[str, str], ...] = (
    ("g_bar_w.x", "the sender's estimate ḡ_w,i of the target pose in the world frame Σw: x (m)"),
    ("g_bar_w.y", "ḡ_w,i: y (m)"),
    ("g_bar_w.z", "ḡ_w,i: z (m)"),
    ("g_bar_w.theta", "ḡ_w,i: yaw θ about the world's z axis (rad)"),
    ("mu.v_x", "μ: the sender's GP mean of the target's body velocity at ḡ_w,i, target frame: v_x (m/s)"),
    ("mu.v_y", "μ: v_y (m/s)"),
    ("mu.v_z", "μ: v_z (m/s)"),
    ("mu.omega", "μ: yaw rate ω (rad/s)"),
    ("var.v_x", "the GP's predictive variance of v_x ((m/s)²), > 0"),
    ("var.v_y", "variance of v_y ((m/s)²)"),
    ("var.v_z", "variance of v_z ((m/s)²)"),
    ("var.omega", "variance of ω ((rad/s)²)"),
    ("prior_var.v_x", "the GP's prior variance σ_f² of v_x ((m/s)²; BCM/rBCM fusion), > 0"),
    ("prior_var.v_y", "σ_f² of v_y ((m/s)²)"),
    ("prior_var.v_z", "σ_f² of v_z ((m/s)²)"),
    ("prior_var.omega", "σ_f² of ω ((rad/s)²)"),
)
"""BODY's 16 values in order (FIELDS × 4 components): (name, what it holds, with units and frame)."""
_LE_F64 = np.dtype("<f8")
_NATIVE_LE = sys.byteorder == "little"
_BYTES_LIKE = (bytes, bytearray, memoryview)
FIELDS = ("g_bar_w", "mu", "var", "prior_var")

#: kernels.message_check's codes → the reasons decode rejects (codes < kern.MSG_OUT_OF_BOUNDS: the wire
#: checks) and AcceptanceBounds.violation names (the others); every reason is a drop counter's name
REASONS: tuple[str | None, ...] = (
    None,
    "non-finite g_bar_w",
    "non-finite mu",
    "non-finite var",
    "non-finite prior_var",
    "variance must be > 0",
    "variance out of bounds",
    "mu out of bounds",
    "pose out of bounds",
)
#: decode's own checks pass any in-range value: the bounds used when no AcceptanceBounds are asked for
_NO_BOUNDS = np.array([0.0, math.inf, math.inf, math.inf, math.inf, math.inf])


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

    @classmethod
    def of_body(
        cls, mission: str, sender: int, seq: int, stamp: float, visible: bool, body: np.ndarray
    ) -> PredictionMessage:
        """A message whose four fields are views of body = [ḡ_w, μ, var, prior_var] (16 floats). A writable
        float64 (16,) array that owns its data is kept as it is (the caller hands it over), anything else
        is copied into one (the compiled checks see one array type)."""
        owned = body.base is None and body.flags.writeable
        if not owned or body.dtype != np.float64 or body.shape != (16,):
            body = np.asarray(body, dtype=np.float64).reshape(16).copy()
        return cls._viewing(mission, sender, seq, stamp, visible, body)

    @classmethod
    def _viewing(
        cls, mission: str, sender: int, seq: int, stamp: float, visible: bool, body: np.ndarray
    ) -> PredictionMessage:
        """`of_body` for a body known to be a writable float64 (16,) array owning its data."""
        msg = cls(mission, sender, seq, stamp, visible, body[0:4], body[4:8], body[8:12], body[12:16])
        object.__setattr__(msg, "_body", body)
        return msg

    def body(self) -> np.ndarray | None:
        """The (16,) float64 array [ḡ_w, μ, var, prior_var] the four fields are views of, or None when
        they are separate arrays (a message built by the constructor, `dataclasses.replace` or a copy)."""
        b: np.ndarray | None = self.__dict__.get("_body")
        if (
            b is None
            or self.g_bar_w.base is not b
            or self.mu.base is not b
            or self.var.base is not b
            or self.prior_var.base is not b
        ):
            return None
        return b


def encode(msg: PredictionMessage) -> bytes:
    """Serialise; raises ValueError for a message this side would itself reject (never sends garbage)."""
    name = msg.mission.encode("utf-8")
    if len(name) > MAX_MISSION_NAME:
        raise ValueError(f"mission name longer than {MAX_MISSION_NAME} bytes")
    body, reason = _flatten(msg) if (cached := msg.body()) is None else (cached, None)
    reason = _head_reason(msg.sender, msg.seq, msg.stamp) or reason  # the order of the checks
    if reason is None and body is not None:
        reason = REASONS[kern.message_check(body, _NO_BOUNDS)]  # the wire checks only (no bounds)
    if reason or body is None:
        raise ValueError(f"refusing to encode invalid message: {reason}")
    head = HEAD.pack(
        MAGIC, SCHEMA_VERSION, 1 if msg.visible else 0, msg.sender, msg.seq, msg.stamp, len(name)
    )
    return head + name + (body.tobytes() if _NATIVE_LE else body.astype(_LE_F64).tobytes())


def _flatten(msg: PredictionMessage) -> tuple[np.ndarray | None, str | None]:
    """The four fields as one (16,) float64 array, or (None, the reason) when one has not 4 elements
    (the first such field, unless a field before it is not finite: the order of the checks)."""
    fields = (msg.g_bar_w, msg.mu, msg.var, msg.prior_var)
    for a in fields:
        if type(a) is not np.ndarray or a.dtype != np.float64 or a.shape != (4,):
            break
    else:  # four float64 (4,) arrays: as they are (no conversion)
        return np.concatenate(fields), None
    flat = [np.asarray(a, dtype=float).reshape(-1) for a in fields]
    for name, arr in zip(FIELDS, flat, strict=True):
        if len(arr) != 4:
            return None, f"{name} must have 4 elements"
        if not np.all(np.isfinite(arr)):
            return None, f"non-finite {name}"
    return np.concatenate(flat), None


def sender_of(data: bytes) -> int | None:
    """The sender id a message's header names (None when it has no readable header); nothing checked."""
    if not isinstance(data, _BYTES_LIKE) or len(data) < HEAD.size:
        return None
    magic, _version, _flags, sender, *_ = HEAD.unpack_from(bytes(data[: HEAD.size]), 0)
    return int(sender) if magic == MAGIC else None


def _head_reason(sender: int, seq: int, stamp: float) -> str | None:
    """Why sender, seq or stamp cannot be sent, or None (checked before the 16 floats)."""
    if not (0 <= sender < 2**16) or not (0 <= seq < 2**32):
        return "sender or seq out of range"
    if not math.isfinite(stamp):
        return "non-finite stamp"
    return None


def decode(
    data: bytes, mission: str, known_senders: frozenset[int] | set[int]
) -> tuple[PredictionMessage | None, str | None]:
    """Parse and validate one message for `mission`; (None, reason) on any defect, never raises."""
    msg, reason, _ = decode_checked(data, mission, known_senders, _NO_BOUNDS)
    return msg, reason


def decode_checked(
    data: bytes, mission: str, known_senders: frozenset[int] | set[int], bounds: np.ndarray
) -> tuple[PredictionMessage | None, str | None, str | None]:
    """`decode`, plus the first AcceptanceBounds violation of a decoded message (None if none), checked in
    the same compiled pass; bounds: `AcceptanceBounds.packed` (a float64 (6,) array). Never raises."""
    try:
        if not isinstance(data, _BYTES_LIKE):
            return None, "not bytes", None
        data = bytes(data)
        if len(data) < HEAD.size:
            return None, "truncated header", None
        magic, version, flags, sender, seq, stamp, name_len = HEAD.unpack_from(data, 0)
        if magic != MAGIC:
            return None, "bad magic", None
        if version != SCHEMA_VERSION:
            return None, f"unsupported schema version {version}", None
        if flags & ~1:
            return None, "unknown flag bits", None
        if name_len > MAX_MISSION_NAME:
            return None, "mission name too long", None
        end_name = HEAD.size + name_len
        if len(data) != end_name + BODY.size:
            return None, "wrong length", None
        try:
            name = data[HEAD.size : end_name].decode("utf-8")
        except UnicodeDecodeError:
            return None, "mission name not UTF-8", None
        if name != mission:
            return None, "other mission", None
        if sender not in known_senders:
            return None, "unknown sender", None
        reason = _head_reason(sender, seq, stamp)
        if reason:
            return None, reason, None
        body = np.frombuffer(data, _LE_F64, 16, end_name)  # read-only, little endian: copied to native
        body = body.copy() if _NATIVE_LE else body.astype(np.float64)
        code = kern.message_check(body, bounds)
        if code and code < kern.MSG_OUT_OF_BOUNDS:
            return None, REASONS[code], None
        msg = PredictionMessage._viewing(name, sender, seq, stamp, bool(flags & 1), body)
        return msg, None, REASONS[code]
    except Exception as exc:  # pragma: no cover - belt and braces: the decoder must never raise
        return None, f"decoder error: {type(exc).__name__}", None
