"""The safety layer's limits, events and pure rules (no I/O, no state): flightstack/safety/drone.py applies
them to every drone (its docstring lists the closed set of event kinds; the rules: docs/safety.md).

Units: m, m/s, rad/s, s (mission clock), percent; positions in the world frame Σw (z up).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter
from dataclasses import dataclass
from typing import get_args

import numpy as np

from flightstack.events import Event, SafetyKind, log_level
from flightstack.paper.geometry import Pose

_logger = logging.getLogger("flightstack.safety")

EVENT_KINDS: frozenset[str] = frozenset(get_args(SafetyKind))
"""The kinds a safety event may have (flightstack.events.KINDS says what each means)."""

_AXES = ("x", "y", "z")

MAX_FENCE_M = 100.0
"""Every corner of the hard fence (the fence grown by `hard_margin`) lies within ±MAX_FENCE_M of Σw's
origin on each axis (m): no motion-capture volume is larger, so a fence beyond it fences nothing."""
MAX_SPEED_MPS = 8.0
"""`max_speed_xy` and `max_speed_z` are at most this (m/s): a Tello's top speed (DJI's specification), so
a larger limit limits nothing."""
MAX_YAW_RATE_RPS = 2 * math.pi
"""`max_yaw_rate` is at most one turn a second (rad/s), faster than a Tello turns."""


class SafetyError(RuntimeError):
    """A safety rule refused an operator action (e.g. takeoff on a low battery)."""


# ---- limits and events -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class SafetyLimits:
    """Safety limits of one mission (the mission's `safety:` section).

    Speeds are limits on the body-frame command V = [v_x, v_y, v_z, ω_z]: `max_speed_xy` (m/s) bounds the
    norm of (v_x, v_y), `max_speed_z` (m/s) bounds |v_z|, `max_yaw_rate` (rad/s) bounds |ω_z|. The fence
    is an axis-aligned box [fence_lo, fence_hi] in the world frame Σw (motion-capture frame, z up, m);
    the hard fence is that box grown by `hard_margin` (m) on every face. Times are in seconds of mission
    clock, battery levels in percent.
    """

    max_speed_xy: float = 0.5
    max_speed_z: float = 0.3
    max_yaw_rate: float = 1.0
    fence_lo: tuple[float, float, float] = (-2.0, -2.0, 0.3)
    fence_hi: tuple[float, float, float] = (2.0, 2.0, 2.0)
    hard_margin: float = 0.3
    command_timeout: float = 0.5
    pose_timeout: float = 0.3
    pose_land_after: float = 2.0
    min_battery_takeoff: float = 30.0
    land_battery: float = 15.0
    target_lost_hover_after: float = 3.0
    target_lost_land_after: float = 15.0
    """Every drone has lost the target for this long (s): land them all rather than hover on (the target
    has left every camera's view; a hovering Tello would only drain its battery near people)."""
    land_retry_s: float = 1.0
    """A land the wrapped drone refused or did not confirm is retried after this long (s, mission clock):
    a bounded rate, while every tick keeps the other rules (and a hover, when the link is silent) going."""
    landed_height: float = 0.15
    """z (m, Σw) of a drone's motion-capture body at or below which a landing drone counts as down (the
    lab's floor is z = 0): motion capture confirms a landing that the drone's own telemetry cannot."""
    emergency_stop_if_land_fails: bool = False
    """Cut the motors of a drone whose land() raised during land_all. Off by default: a Tello with its
    motors cut falls from up to 2 m next to people; the failed land is retried on every tick instead."""

    def __post_init__(self) -> None:
        lo = tuple(float(v) for v in self.fence_lo)
        hi = tuple(float(v) for v in self.fence_hi)
        if len(lo) != 3 or len(hi) != 3:
            raise ValueError(f"fence_lo and fence_hi need 3 values (x, y, z), got {lo} and {hi}")
        object.__setattr__(self, "fence_lo", lo)
        object.__setattr__(self, "fence_hi", hi)
        if not all(math.isfinite(v) for v in lo + hi):
            raise ValueError(f"fence must be finite, got lo={lo}, hi={hi}")
        if any(h <= low for low, h in zip(lo, hi, strict=True)):
            raise ValueError(f"fence_hi must exceed fence_lo on every axis, got lo={lo}, hi={hi}")
        positive: tuple[str, ...] = ("max_speed_xy", "max_speed_z", "max_yaw_rate", "command_timeout")
        positive += ("pose_timeout", "pose_land_after", "target_lost_hover_after", "target_lost_land_after")
        positive += ("land_retry_s",)
        for name in positive:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.landed_height) and self.landed_height < self.fence_lo[2]):
            raise ValueError(
                f"landed_height ({self.landed_height} m) must be finite and below the fence floor "
                f"fence_lo z ({self.fence_lo[2]} m)"
            )
        if not (math.isfinite(self.hard_margin) and self.hard_margin >= 0.0):
            raise ValueError(f"hard_margin must be finite and >= 0, got {self.hard_margin}")
        if max(abs(v) for v in self.hard_lo + self.hard_hi) > MAX_FENCE_M:
            raise ValueError(
                f"the hard fence (fence_lo, fence_hi grown by hard_margin) must lie within "
                f"±{MAX_FENCE_M:g} m on every axis (no motion-capture volume is larger), got "
                f"lo={self.hard_lo}, hi={self.hard_hi}"
            )
        for name, most, unit in [
            ("max_speed_xy", MAX_SPEED_MPS, "m/s, a Tello's top speed"),
            ("max_speed_z", MAX_SPEED_MPS, "m/s, a Tello's top speed"),
            ("max_yaw_rate", MAX_YAW_RATE_RPS, "rad/s, one turn a second"),
        ]:
            if getattr(self, name) > most:
                raise ValueError(f"{name} must be at most {most:.4g} ({unit}), got {getattr(self, name)}")
        if self.target_lost_land_after <= self.target_lost_hover_after:
            raise ValueError(
                f"target_lost_land_after ({self.target_lost_land_after} s) must exceed "
                f"target_lost_hover_after ({self.target_lost_hover_after} s)"
            )
        if self.pose_land_after < self.pose_timeout:
            raise ValueError(
                f"pose_land_after ({self.pose_land_after} s) must be >= pose_timeout ({self.pose_timeout} s)"
            )
        for name in ("min_battery_takeoff", "land_battery"):
            v = getattr(self, name)
            if not (0.0 <= v <= 100.0):
                raise ValueError(f"{name} must be a percentage in [0, 100], got {v}")
        if self.land_battery > self.min_battery_takeoff:
            raise ValueError(
                f"land_battery ({self.land_battery} %) must not exceed min_battery_takeoff "
                f"({self.min_battery_takeoff} %): the drone would land right after takeoff"
            )

    @property
    def hard_lo(self) -> tuple[float, float, float]:
        """Lower corner of the hard fence in Σw (m)."""
        m = self.hard_margin
        return (self.fence_lo[0] - m, self.fence_lo[1] - m, self.fence_lo[2] - m)

    @property
    def hard_hi(self) -> tuple[float, float, float]:
        """Upper corner of the hard fence in Σw (m)."""
        m = self.hard_margin
        return (self.fence_hi[0] + m, self.fence_hi[1] + m, self.fence_hi[2] + m)


SafetyEvent = Event
"""A safety event is an `Event` (flightstack.events) with source "safety", on the mission clock, kind in
EVENT_KINDS; the name stays for readability at the call sites."""


class EventLog:
    """Append-only, thread-safe list of SafetyEvent (also echoed to the `flightstack.safety` logger, at the
    kind's severity in flightstack.events.KINDS).

    Uses a re-entrant lock so that a signal handler running on the main thread may log while the main
    thread is itself inside `append`.
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._events: list[SafetyEvent] = []

    def append(self, event: SafetyEvent) -> None:
        """Add one event; its kind must be in EVENT_KINDS (ValueError otherwise: a programming error)."""
        if event.kind not in EVENT_KINDS:
            raise ValueError(f"unknown safety event kind {event.kind!r}; valid: {sorted(EVENT_KINDS)}")
        with self._lock:
            self._events.append(event)
        who = "mission" if event.drone is None else f"drone {event.drone}"
        _logger.log(log_level(event.kind), "t=%.3f %s %s: %s", event.t, who, event.kind, event.detail)

    def record(self, t: float, drone: int | None, kind: SafetyKind, detail: str) -> SafetyEvent:
        """Build, append and return an event."""
        ev = Event(float(t), drone, kind, detail, source="safety")
        self.append(ev)
        return ev

    @property
    def events(self) -> list[SafetyEvent]:
        """A snapshot copy of the events, oldest first."""
        with self._lock:
            return list(self._events)

    def of_kind(self, kind: str) -> list[SafetyEvent]:
        return [e for e in self.events if e.kind == kind]

    def counts(self) -> dict[str, int]:
        """Number of events per kind (kinds that never occurred are absent)."""
        return dict(Counter(e.kind for e in self.events))

    def __len__(self) -> int:
        with self._lock:
            return len(self._events)


# ---- pure rules ------------------------------------------------------------------------------------------
def sanitize(V: object) -> tuple[np.ndarray, str | None]:
    """V as a float array (4,), or zeros and the reason when V is not 4 finite numbers."""
    try:
        arr = np.asarray(V, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        return np.zeros(4), f"not numeric ({type(exc).__name__}: {exc})"
    if arr.size != 4:
        return np.zeros(4), f"expected 4 values [vx, vy, vz, wz], got {arr.size}"
    if not all(map(math.isfinite, arr.tolist())):
        return np.zeros(4), f"non-finite command {arr.tolist()}"
    return arr.copy(), None


def saturate(V: np.ndarray, limits: SafetyLimits) -> tuple[np.ndarray, bool]:
    """Saturate a finite body velocity V = [v_x, v_y, v_z, ω_z] (m/s, rad/s, body frame).

    (v_x, v_y) is scaled down to norm `max_speed_xy` keeping its direction (computed without overflow,
    and never increasing a component's magnitude); v_z and ω_z are clipped. Returns (V_sat, changed).
    """
    out = np.array(V, dtype=float).reshape(4)
    vx, vy = float(out[0]), float(out[1])
    changed = False
    m = max(abs(vx), abs(vy))
    if m > 0.0:
        ux, uy = vx / m, vy / m  # |u| in [1, √2]: no overflow in hypot
        norm_u = math.hypot(ux, uy)
        if m * norm_u > limits.max_speed_xy:
            # 4 ulp of margin so that rounding never leaves the result above the limit
            k = limits.max_speed_xy / norm_u * (1.0 - 4.0 * np.finfo(float).eps)
            out[0] = float(np.clip(ux * k, -abs(vx), abs(vx)))
            out[1] = float(np.clip(uy * k, -abs(vy), abs(vy)))
            changed = True
    for i, lim in ((2, limits.max_speed_z), (3, limits.max_yaw_rate)):
        if abs(out[i]) > lim:
            out[i] = math.copysign(lim, out[i])
            changed = True
    return out, changed


def climb_cap(z: float, limits: SafetyLimits, own_timeout_s: float) -> float:
    """The largest upward velocity (m/s; world z, equal to body z) that may be sent to a drone at height z
    (m, Σw) which keeps flying its last command for `own_timeout_s` (s) once nothing of ours is left to
    command it: (fence_hi z − z) / own_timeout_s, never below 0. Held that long it ends at the soft
    fence's ceiling; the hard margin takes what the drone adds (docs/safety.md, "What no process on the
    laptop can cover")."""
    return max(0.0, (limits.fence_hi[2] - float(z)) / own_timeout_s)


def outside_soft_fence(p: np.ndarray, limits: SafetyLimits) -> list[str]:
    """Faces of the soft fence that the world position p (m, Σw) is beyond, e.g. ['+x', '-z']."""
    faces = []
    for k, ax in enumerate(_AXES):
        if p[k] > limits.fence_hi[k]:
            faces.append(f"+{ax}")
        elif p[k] < limits.fence_lo[k]:
            faces.append(f"-{ax}")
    return faces


def outside_hard_fence(p: np.ndarray, limits: SafetyLimits, check_floor: bool = True) -> list[str]:
    """Faces of the hard fence that the world position p (m, Σw) is beyond.

    `check_floor=False` ignores the lower z face (used before the drone has climbed into the fence after
    takeoff, when it still stands on the floor and motion-capture noise can put z slightly below it).
    """
    lo, hi = limits.hard_lo, limits.hard_hi
    faces = []
    for k, ax in enumerate(_AXES):
        if p[k] > hi[k]:
            faces.append(f"+{ax}")
        elif p[k] < lo[k] and (k != 2 or check_floor):
            faces.append(f"-{ax}")
    return faces


def fence_clip(V: np.ndarray, pose: Pose, limits: SafetyLimits) -> tuple[np.ndarray, list[str]]:
    """Remove from the body velocity V every world-frame component that leaves the soft fence further.

    V = [v_x, v_y, v_z, ω_z] is in the body frame of `pose` (world pose of the drone, yaw θ about z, so
    v_world = R(θ) v_body and v_z is the same in both frames). For each axis on which the drone is
    beyond the soft fence, the world velocity component pointing further out is set to zero; the others,
    and ω_z, are kept. Returns (V_clipped in the body frame, clipped world axes such as ['+x']).
    """
    p = pose.p
    c, s = math.cos(pose.theta), math.sin(pose.theta)
    vw = [c * V[0] - s * V[1], s * V[0] + c * V[1], float(V[2])]
    clipped = []
    for k, ax in enumerate(_AXES):
        if p[k] > limits.fence_hi[k] and vw[k] > 0.0:
            vw[k] = 0.0
            clipped.append(f"+{ax}")
        elif p[k] < limits.fence_lo[k] and vw[k] < 0.0:
            vw[k] = 0.0
            clipped.append(f"-{ax}")
    out = np.array(V, dtype=float).reshape(4)
    if not clipped:
        return out, clipped
    if any(a[1] in "xy" for a in clipped):  # back to the body frame: v_body = R(θ)ᵀ v_world
        out[0] = c * vw[0] + s * vw[1]
        out[1] = -s * vw[0] + c * vw[1]
    out[2] = vw[2]
    return out, clipped


def valid_pose(sp: object) -> bool:
    """A StampedPose-like object with a finite stamp, a finite position (3,) and a finite yaw."""
    try:
        pose = sp.pose  # type: ignore[attr-defined]
        p = np.asarray(pose.p, dtype=float)
        return (
            math.isfinite(float(sp.stamp))  # type: ignore[attr-defined]
            and p.shape == (3,)
            and all(map(math.isfinite, p.tolist()))
            and math.isfinite(float(pose.theta))
        )
    except (TypeError, ValueError, AttributeError):
        return False
