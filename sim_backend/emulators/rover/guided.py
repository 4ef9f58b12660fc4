"""GUIDED set-points as ArduPilot Rover reads them, and the non-holonomic motion that follows.

`decode_setpoint` is ``GCS_MAVLINK_Rover::handle_set_position_target_local_ned`` (Rover/GCS_MAVLink_Rover.cpp)
with Rover's own type-mask groups (Rover/defines.h: velocity ignored if the vx OR vy bit is set,
acceleration ignored if the ax OR ay bit is set): the velocity vector becomes a speed ``|(vx, vy)|``
clamped to the speed limit and a heading ``atan2(vy, vx)`` (plus the vehicle's yaw in body frames); with a
yaw or yaw rate the speed takes the sign of ``vx``. `step` is ``ModeGuided::update`` (Rover/mode_guided.cpp)
on those targets: only a forward speed and a turn rate, never sideways (omni frames included); a turn rate
limited to ``ATC_STR_RAT_MAX`` and, with Ackermann steering, to ``|speed| / TURN_RADIUS``; a heading reached
with ``ATC_STR_ANG_P`` x error. Units: m, m/s, rad, rad/s; NED (x north, y east, yaw clockwise from north).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink import mavutil

mavlink = mavutil.mavlink
POS_IGNORE = 1 | 2  # Rover/defines.h MAVLINK_SET_POS_TYPE_MASK_*: x, y
VEL_IGNORE = 8 | 16  # vx, vy
ACC_IGNORE = 64 | 128  # ax, ay
YAW_IGNORE = 1024
YAW_RATE_IGNORE = 2048
FRAMES = (
    mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_BODY_NED,
    mavlink.MAV_FRAME_BODY_OFFSET_NED,
)  # fmt: skip


def wrap_angle(theta: float) -> float:
    """θ (rad) wrapped to (−π, π] as geometry.wrap_angle, in plain Python: that one is a numba kernel whose
    first call compiles for about a second, which stalled the emulator's loop (and its EKF clock)."""
    r = math.remainder(theta, 2.0 * math.pi)
    return math.pi if r == -math.pi else r


BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
# GCS_MAVLINK_Rover::send_acc_ignore_must_be_set_message
ACC_TEXT = "Ignoring SET_POSITION_TARGET_LOCAL_NED; set ACC_IGNORE in mask"


@dataclass(frozen=True)
class GuidedTarget:
    """``set_desired_turn_rate_and_speed`` (turn_rate set) or ``set_desired_heading_and_speed`` (heading
    set): speed m/s (negative: reverse), turn rate rad/s clockwise, heading rad clockwise from north."""

    speed: float
    turn_rate: float | None = None
    heading: float | None = None


@dataclass(frozen=True)
class Decoded:
    """What the handler did: a target, or a drop with its reason (``text`` when ArduPilot says so)."""

    target: GuidedTarget | None
    reason: str = ""
    text: str = ""


def decode_setpoint(
    frame: int,
    mask: int,
    v: tuple[float, float],
    yaw: float,
    yaw_rate: float,
    vehicle_yaw: float,
    speed_max: float,
) -> Decoded:
    """One SET_POSITION_TARGET_LOCAL_NED already known to be for a vehicle in GUIDED with an EKF origin."""
    if frame not in FRAMES:
        return Decoded(None, f"frame {frame} unsupported")
    vx, vy = v
    if not all(math.isfinite(f) for f in (vx, vy, yaw, yaw_rate)):
        return Decoded(None, "non-finite field")  # the C++ would propagate NaN; no motion here
    pos_ignore, vel_ignore = bool(mask & POS_IGNORE), bool(mask & VEL_IGNORE)
    acc_ignore, yaw_ignore, rate_ignore = (
        bool(mask & ACC_IGNORE),
        bool(mask & YAW_IGNORE),
        bool(mask & YAW_RATE_IGNORE),
    )
    body = frame in BODY_FRAMES
    speed, heading = 0.0, 0.0
    if not vel_ignore:
        speed = min(math.hypot(vx, vy), speed_max)
        heading = math.atan2(vy, vx) + (vehicle_yaw if body else 0.0)
    if not yaw_ignore:
        heading = yaw + (vehicle_yaw if body else 0.0)
    direction = -1.0 if (not vel_ignore and (not yaw_ignore or not rate_ignore) and vx < 0.0) else 1.0
    if not acc_ignore:
        return Decoded(None, "acceleration not ignored", ACC_TEXT)
    if not pos_ignore:
        return Decoded(None, "position target (not modelled)")
    heading = wrap_angle(heading)
    if not vel_ignore and rate_ignore:  # velocity alone, or velocity and heading
        return Decoded(GuidedTarget(direction * speed, heading=heading))
    if not vel_ignore and yaw_ignore:  # velocity and turn rate; with a yaw too nothing is consumed
        return Decoded(GuidedTarget(direction * speed, turn_rate=yaw_rate))
    if not yaw_ignore and rate_ignore:
        return Decoded(GuidedTarget(0.0, heading=heading))
    if yaw_ignore and not rate_ignore:
        return Decoded(GuidedTarget(0.0, turn_rate=yaw_rate))
    return Decoded(None, "nothing to consume")


@dataclass(frozen=True)
class Steering:
    """The turn limits: ``rate_max`` rad/s (ATC_STR_RAT_MAX, <= 0: none), ``angle_p`` 1/s (ATC_STR_ANG_P),
    ``turn_radius`` m with Ackermann steering (None: skid steering, turns in place)."""

    rate_max: float
    angle_p: float
    turn_radius: float | None


def twist(target: GuidedTarget, yaw: float, steering: Steering) -> tuple[float, float]:
    """(speed m/s, turn rate rad/s clockwise) the vehicle drives now toward `target`."""
    v = target.speed
    if target.turn_rate is not None:
        r = target.turn_rate
    else:
        r = steering.angle_p * wrap_angle((target.heading or 0.0) - yaw)
    if steering.rate_max > 0.0:
        r = max(-steering.rate_max, min(steering.rate_max, r))
    if steering.turn_radius is not None:
        limit = abs(v) / steering.turn_radius if steering.turn_radius > 0.0 else math.inf
        r = max(-limit, min(limit, r))
    return v, r


def arc(x: float, y: float, yaw: float, v: float, r: float, dt: float) -> tuple[float, float, float]:
    """Exact integration of a constant (speed, turn rate) over dt (s): the new (x, y, yaw)."""
    dpsi = r * dt
    if abs(dpsi) < 1e-9:
        bx, by = v * dt, 0.0
    else:
        bx, by = v * math.sin(dpsi) / r, v * (1.0 - math.cos(dpsi)) / r
    c, s = math.cos(yaw), math.sin(yaw)
    return x + c * bx - s * by, y + s * bx + c * by, wrap_angle(yaw + dpsi)
