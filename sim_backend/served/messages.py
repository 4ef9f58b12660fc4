"""Messages between the served simulated world (`flightstack world`) and agent processes.

Keys (same key space as the prediction bus):
    {prefix}/{mission}/world/tick/{id}   world → agent `id`: what its sensors see at tick k
    {prefix}/{mission}/world/cmd/{id}    agent `id` → world: what it did to its drone during tick k

Layout: u32 little-endian length L | L bytes of UTF-8 JSON header | optional raw image bytes (H×W×3 RGB,
or H×W grey, uint8, row-major) when the header's frame has an `image` shape. JSON keeps floats exact
(Python writes the shortest repr that reads back identically), so a served simulation is as deterministic
as a local one.

Tick header: {"v": 1, "k": tick, "t": mission time (s), "state": {battery_pct, height_m, link_alive,
flying, phase}, "poses": {body: [stamp, x, y, z, θ]} (motion capture of the agent's own body and the
target, absent when stale), "truth": {"target": [x, y, z, θ], "drone": [x, y, z, θ]} (sim only, for
recordings), "frame": null or {"stamp", "features": [2m] or null, "image": [H, W] (RGB), [H, W, 1] (grey)
or null}}.
Cmd header: {"v": 1, "k": tick, "calls": [[name, args...], ...]}: the hal.Drone calls of this tick in
order (connect, takeoff, land, emergency_stop, close: no argument; send_body_velocity: one argument
[v_x, v_y, v_z, ω] in m/s and rad/s). k = -1 is the agent's hello (it is subscribed to its ticks).

Decoding is total: `decode_tick` and `decode_cmd` never raise on any input; they return a validated,
typed value (`WorldTick`, `WorldCmd`: frozen dataclasses) or None and the reason, for counting. Every key
of the layout above is required, with exactly its type; keys not in the layout are ignored (they never
reach a consumer: only typed values do). Bounds (a value outside is refused):
- header: at most MAX_HEADER bytes, at most MAX_NESTING levels of [ and { (checked before parsing,
  so no input can exhaust the parser's recursion); NaN and ±Infinity literals are refused;
- k: an int in [0, MAX_TICK] (cmd: [-1, MAX_TICK]); times and stamps: finite, |t| ≤ MAX_TIME_S s;
- state: battery_pct in [0, 100] %, |height_m| ≤ MAX_COORD_M m, link_alive and flying JSON booleans,
  phase one of the hal.FlightPhase values;
- poses: at most MAX_BODIES bodies, names of 1..MAX_BODY_CHARS characters, each [stamp, x, y, z, θ] with
  |x|, |y|, |z| ≤ MAX_COORD_M m and |θ| ≤ MAX_ANGLE_RAD rad; truth: target and drone [x, y, z, θ], same
  bounds;
- frame: null, or stamp; features null or an even number (≤ MAX_FEATURES) of finite numbers; image
  null or [H, W] (or [H, W, 1], a grey camera's) with 1 ≤ H, W ≤ MAX_IMAGE_SIDE px, and then exactly
  H·W·3 (H·W) trailing bytes (none without an image);
- calls: at most MAX_CALLS, each a known name with exactly its arity; a body velocity is 4 finite numbers
  with |(v_x, v_y, v_z)| ≤ MAX_SPEED_MPS m/s and |ω| ≤ MAX_YAW_RATE rad/s: what a Tello can fly (its
  fastest mode is ~8 m/s; the paper's control commands ≤ 1 m/s). `saturate_velocity` brings any command
  in range; an agent sends at most MAX_CALLS calls per cmd (a longer backlog goes in several cmds).
Reasons: "not bytes", "truncated", "bad length", "too deep", "not JSON", "bad header"; tick: "bad tick",
"bad state", "bad poses", "bad truth", "bad frame", "bad features", "bad image"; cmd: "no calls", "too
many calls", "unknown call", "bad call", "bad velocity", "velocity out of range".
"""

from __future__ import annotations

import json
import math
import struct
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from flightstack.comms.acl import cmd_key as cmd_key  # the key layout lives with its access control
from flightstack.comms.acl import tick_key as tick_key
from flightstack.comms.control import too_deep
from flightstack.hal import FlightPhase

VERSION = 1
_LEN = struct.Struct("<I")
MAX_HEADER = 1 << 20  # bytes of one JSON header
MAX_NESTING = 8  # levels of [ and { in one header (a valid tick or cmd has at most 4)
MAX_TICK = 2**31 - 1  # largest tick index (≈ 248 days at dt = 10 ms)
MAX_TIME_S = 1e9  # |mission time| and |stamps| (s)
MAX_COORD_M = 1e4  # |x|, |y|, |z| of a pose and |height_m| (m): 10 km, far beyond any lab
MAX_ANGLE_RAD = 2 * math.pi  # |θ| of a pose (rad); poses are wrapped to (-π, π]
MAX_BODIES = 64  # bodies in one tick's poses
MAX_BODY_CHARS = 64  # characters of a body name
MAX_FEATURES = 512  # numbers in a frame's feature vector (256 image points)
MAX_IMAGE_SIDE = 4096  # rows and columns of an image (px); the Tello's is 960 × 720
MAX_CALLS = 256  # hal.Drone calls in one cmd
MAX_SPEED_MPS = 8.0  # |(v_x, v_y, v_z)| of a commanded body velocity (m/s)
MAX_YAW_RATE = 5.0  # |ω| of a commanded body velocity (rad/s)
_MAX_FLOAT = sys.float_info.max
PHASES = frozenset(p.value for p in FlightPhase)
VELOCITY_CALL = "send_body_velocity"
DRONE_CALLS = frozenset({"connect", "takeoff", "land", "emergency_stop", VELOCITY_CALL, "close"})
_ARITY = {name: 1 if name == VELOCITY_CALL else 0 for name in DRONE_CALLS}

PoseRow = tuple[float, float, float, float, float]  # [stamp (s), x, y, z (m), θ (rad)]
Vec4 = tuple[float, float, float, float]


# ---- typed values -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TickState:
    """The agent's drone as the world sees it: battery (%), height above ground (m), telemetry link,
    airborne and obeying velocity commands, hal.FlightPhase value."""

    battery_pct: float
    height_m: float
    link_alive: bool
    flying: bool
    phase: str


@dataclass(frozen=True)
class Truth:
    """True poses [x, y, z (m), θ (rad)] of the target and of the agent's drone (recordings only)."""

    target: Vec4
    drone: Vec4


@dataclass(frozen=True)
class FrameHead:
    """A camera sample: its stamp (s), features (2m,) or None, image shape (H, W) px (RGB), (H, W, 1) (grey)
    or None (the image itself travels as the message's trailing bytes)."""

    stamp: float
    features: tuple[float, ...] | None
    image_shape: tuple[int, int] | tuple[int, int, int] | None


@dataclass(frozen=True)
class WorldTick:
    """What the agent sees at tick k (mission time t, s). `poses`: read-only body name → PoseRow."""

    k: int
    t: float
    state: TickState
    poses: Mapping[str, PoseRow]
    truth: Truth
    frame: FrameHead | None

    def header(self) -> dict[str, Any]:
        s, f = self.state, self.frame
        return {
            "v": VERSION,
            "k": self.k,
            "t": self.t,
            "state": {
                "battery_pct": s.battery_pct,
                "height_m": s.height_m,
                "link_alive": s.link_alive,
                "flying": s.flying,
                "phase": s.phase,
            },
            "poses": {b: list(row) for b, row in self.poses.items()},
            "truth": {"target": list(self.truth.target), "drone": list(self.truth.drone)},
            "frame": None
            if f is None
            else {
                "stamp": f.stamp,
                "features": None if f.features is None else list(f.features),
                "image": None if f.image_shape is None else list(f.image_shape),
            },
        }


@dataclass(frozen=True)
class DroneCall:
    """One hal.Drone call: its name (DRONE_CALLS) and, for send_body_velocity, [v_x, v_y, v_z] m/s and ω
    rad/s (else None)."""

    name: str
    velocity: Vec4 | None = None

    def row(self) -> list[Any]:
        return [self.name] if self.velocity is None else [self.name, list(self.velocity)]


@dataclass(frozen=True)
class WorldCmd:
    """The hal.Drone calls an agent made during tick k, in order (k = -1: hello, no calls)."""

    k: int
    calls: tuple[DroneCall, ...]

    def header(self) -> dict[str, Any]:
        return {"v": VERSION, "k": self.k, "calls": [c.row() for c in self.calls]}


def make_tick(
    k: int,
    t: float,
    state: TickState,
    poses: Mapping[str, PoseRow],
    truth: Truth,
    frame: FrameHead | None,
) -> WorldTick:
    """A WorldTick whose poses mapping is a read-only copy."""
    return WorldTick(k, t, state, MappingProxyType(dict(poses)), truth, frame)


# ---- framing ------------------------------------------------------------------------------------------
def pack(header: dict[str, Any], image: np.ndarray | None = None) -> bytes:
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    tail = b"" if image is None else np.ascontiguousarray(image, dtype=np.uint8).tobytes()
    return _LEN.pack(len(head)) + head + tail


def encode_tick(tick: WorldTick, image: np.ndarray | None = None) -> bytes:
    """The wire form of `tick` with `image` (H×W×3 or H×W uint8, the shape tick.frame.image_shape says)."""
    return pack(tick.header(), image)


def encode_cmd(cmd: WorldCmd) -> bytes:
    return pack(cmd.header())


def unpack(data: bytes) -> tuple[dict[str, Any] | None, bytes, str | None]:
    """(header, trailing bytes, None) or (None, b"", reason): a JSON object of VERSION with an int k in
    [-1, MAX_TICK]. Never raises."""
    if not isinstance(data, bytes | bytearray | memoryview):
        return None, b"", "not bytes"
    data = bytes(data)
    if len(data) < _LEN.size:
        return None, b"", "truncated"
    (n,) = _LEN.unpack_from(data)
    if n > MAX_HEADER or len(data) < _LEN.size + n:
        return None, b"", "bad length"
    head = data[_LEN.size : _LEN.size + n]
    if too_deep(head, MAX_NESTING):
        return None, b"", "too deep"
    try:
        header = json.loads(head.decode("utf-8"), parse_constant=_refuse_constant)
    except (ValueError, RecursionError):  # bad UTF-8, bad JSON, NaN/Infinity literals, too many digits
        return None, b"", "not JSON"
    if not (isinstance(header, dict) and _int(header.get("v"), VERSION, VERSION) is not None):
        return None, b"", "bad header"
    if _int(header.get("k"), -1, MAX_TICK) is None:
        return None, b"", "bad header"
    return header, data[_LEN.size + n :], None


def _refuse_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} in a world message")


# ---- field checks: each returns the typed value or None -----------------------------------------------
def _int(x: object, lo: int, hi: int) -> int | None:
    return x if isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi else None


def _real(x: object, bound: float) -> float | None:
    """x as a float if it is a JSON number (not a bool) with |x| ≤ bound, else None."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return None
    if not -bound <= x <= bound:  # also refuses NaN; an int is compared exactly, before float()
        return None
    return float(x)


def _reals(xs: object, bounds: tuple[float, ...]) -> tuple[float, ...] | None:
    if not (isinstance(xs, list) and len(xs) == len(bounds)):
        return None
    out = tuple(_real(x, b) for x, b in zip(xs, bounds, strict=True))
    return None if None in out else out  # type: ignore[return-value]


_POSE4 = (MAX_COORD_M, MAX_COORD_M, MAX_COORD_M, MAX_ANGLE_RAD)
_ROW5 = (MAX_TIME_S, *_POSE4)


def _bool(x: object) -> bool | None:
    return x if isinstance(x, bool) else None


def _state(s: object) -> TickState | None:
    if not isinstance(s, dict):
        return None
    battery, height = _real(s.get("battery_pct"), 100.0), _real(s.get("height_m"), MAX_COORD_M)
    alive, flying, phase = _bool(s.get("link_alive")), _bool(s.get("flying")), s.get("phase")
    if battery is None or battery < 0.0 or height is None or alive is None or flying is None:
        return None
    if not (isinstance(phase, str) and phase in PHASES):
        return None
    return TickState(battery, height, alive, flying, phase)


def _poses(p: object) -> dict[str, PoseRow] | None:
    if not (isinstance(p, dict) and len(p) <= MAX_BODIES):
        return None
    out: dict[str, PoseRow] = {}
    for body, row in p.items():
        r = _reals(row, _ROW5)
        if r is None or not 1 <= len(body) <= MAX_BODY_CHARS:
            return None
        out[body] = r  # type: ignore[assignment]
    return out


def _truth(t: object) -> Truth | None:
    if not isinstance(t, dict):
        return None
    target, drone = _reals(t.get("target"), _POSE4), _reals(t.get("drone"), _POSE4)
    return None if target is None or drone is None else Truth(target, drone)  # type: ignore[arg-type]


def _features(f: object) -> tuple[float, ...] | None:
    """The feature vector, or None when malformed (the caller tells null apart)."""
    if not (isinstance(f, list) and len(f) % 2 == 0 and len(f) <= MAX_FEATURES):
        return None
    return _reals(f, (_MAX_FLOAT,) * len(f))


def _shape(s: object) -> tuple[int, int] | tuple[int, int, int] | None:
    """[H, W] (RGB) or [H, W, 1] (grey), else None."""
    if not (isinstance(s, list) and (len(s) == 2 or (len(s) == 3 and _int(s[2], 1, 1) == 1))):
        return None
    h, w = _int(s[0], 1, MAX_IMAGE_SIDE), _int(s[1], 1, MAX_IMAGE_SIDE)
    if h is None or w is None:
        return None
    return (h, w) if len(s) == 2 else (h, w, 1)


_MISSING = object()


def decode_tick(data: bytes) -> tuple[WorldTick | None, np.ndarray | None, str | None]:
    """(tick, image (H×W×3 or, grey, H×W uint8, read-only) or None, None) or (None, None, reason). Never
    raises."""
    header, tail, reason = unpack(data)
    if header is None:
        return None, None, reason
    k, t = _int(header["k"], 0, MAX_TICK), _real(header.get("t"), MAX_TIME_S)
    if k is None or t is None:
        return None, None, "bad tick"
    state = _state(header.get("state"))
    if state is None:
        return None, None, "bad state"
    poses = _poses(header.get("poses"))
    if poses is None:
        return None, None, "bad poses"
    truth = _truth(header.get("truth"))
    if truth is None:
        return None, None, "bad truth"
    f = header.get("frame", _MISSING)
    frame: FrameHead | None = None
    if f is not None:
        if not (isinstance(f, dict) and "features" in f and "image" in f):
            return None, None, "bad frame"
        stamp = _real(f.get("stamp"), MAX_TIME_S)
        if stamp is None:
            return None, None, "bad frame"
        feats = None if f["features"] is None else _features(f["features"])
        if f["features"] is not None and feats is None:
            return None, None, "bad features"
        shape = None if f["image"] is None else _shape(f["image"])
        if f["image"] is not None and shape is None:
            return None, None, "bad image"
        frame = FrameHead(stamp, feats, shape)
    shape = None if frame is None else frame.image_shape
    channels = 0 if shape is None else 3 if len(shape) == 2 else 1
    if len(tail) != (0 if shape is None else shape[0] * shape[1] * channels):
        return None, None, "bad image"
    image = None
    if shape is not None:
        flat = np.frombuffer(tail, dtype=np.uint8)
        image = flat.reshape(shape[0], shape[1], 3) if channels == 3 else flat.reshape(shape[0], shape[1])
    return WorldTick(k, t, state, MappingProxyType(poses), truth, frame), image, None


def _call(c: object) -> tuple[DroneCall | None, str | None]:
    if not (isinstance(c, list) and c and isinstance(c[0], str) and c[0] in DRONE_CALLS):
        return None, "unknown call"
    name = c[0]
    if len(c) != 1 + _ARITY[name]:
        return None, "bad call" if name != VELOCITY_CALL else "bad velocity"
    if name != VELOCITY_CALL:
        return DroneCall(name), None
    v = _reals(c[1], (_MAX_FLOAT,) * 4)
    if v is None:
        return None, "bad velocity"
    if math.hypot(v[0], v[1], v[2]) > MAX_SPEED_MPS or abs(v[3]) > MAX_YAW_RATE:
        return None, "velocity out of range"
    return DroneCall(name, v), None  # type: ignore[arg-type]


def decode_cmd(data: bytes) -> tuple[WorldCmd | None, str | None]:
    """(cmd, None) or (None, reason); one bad call refuses the whole cmd. Never raises."""
    header, _, reason = unpack(data)
    if header is None:
        return None, reason
    calls = header.get("calls")
    if not isinstance(calls, list):
        return None, "no calls"
    if len(calls) > MAX_CALLS:
        return None, "too many calls"
    out: list[DroneCall] = []
    for c in calls:
        call, why = _call(c)
        if call is None:
            return None, why
        out.append(call)
    return WorldCmd(header["k"], tuple(out)), None


def saturate_velocity(V: object) -> Vec4:
    """[v_x, v_y, v_z, ω] that `decode_cmd` accepts: non-finite components become 0, (v_x, v_y, v_z) is
    scaled down to MAX_SPEED_MPS keeping its direction, ω clipped to ±MAX_YAW_RATE (what a Tello does
    with a command beyond its range). Unchanged when already in range."""
    v = [float(x) if math.isfinite(x) else 0.0 for x in np.asarray(V, dtype=float).reshape(4)]
    sp = math.hypot(v[0], v[1], v[2])
    if sp > MAX_SPEED_MPS:
        scale = MAX_SPEED_MPS / sp * (1.0 - 1e-9)  # strictly inside after rounding
        v[0], v[1], v[2] = v[0] * scale, v[1] * scale, v[2] * scale
    v[3] = min(MAX_YAW_RATE, max(-MAX_YAW_RATE, v[3]))
    return (v[0], v[1], v[2], v[3])
