"""The ground robot's motion check before the drones take off: nudge it and let motion capture confirm it
moved as commanded.

After the operator's confirmation and before any drone leaves the ground (`runner.take_off`), the robot
is commanded forward (or backward, whichever end stays inside the fence) at NUDGE_SPEED_MPS for NUDGE_S,
then stopped; SETTLE_S later its motion-capture pose is compared with the start. The commanded
displacement is d = NUDGE_SPEED_MPS · NUDGE_S = 0.05 m along the robot's start heading. It passes iff
the measured displacement along that heading lies in [1 − TOLERANCE, 1 + TOLERANCE] · d (signed: a robot
that drove the wrong way fails) and the sideways one is at most TOLERANCE · d. Anything else (it did not
move, moved too far, sideways, or motion capture lost it) stops the mission before takeoff with one line
(RuntimeError). A robot behind a first-order lag of time constant τ ≤ 0.5 s covers d within
d·τ·e^(−SETTLE_S/τ)/NUDGE_S ≤ 9 % of it: well inside the tolerance.

Run where the robot is a device (backend `tello`: the real lab, the emulated lab); the simulated lab's
robot has no fault that would keep it still, so the check is not flown there (its runs stay as they were).
Times in seconds on the fleet's clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flightstack.hal import Clock, GroundRobot, PoseSource, ReportsState

NUDGE_SPEED_MPS = 0.05
"""Forward speed of the nudge (m/s; the issue's bound is 0.1)."""
NUDGE_S = 1.0
"""How long the nudge is commanded (s; the issue's bound is 2)."""
SETTLE_S = 0.5
"""After the stop, how long before the end pose is read (s)."""
TOLERANCE = 0.5
"""Relative tolerance on the displacement: along the heading within ±50 % of the commanded 0.05 m,
sideways at most 50 % of it (2.5 cm). Motion capture's noise (sub-mm) and a robot's start-up lag fit
well inside; a robot that stays put, drives the other way, or twice as far does not."""
BODY = "target"


@dataclass(frozen=True)
class MotionCheck:
    """What the nudge did: commanded and measured displacement (m) in the start heading's frame."""

    commanded_m: float  # signed: + forward, − backward
    along_m: float
    across_m: float

    @property
    def problem(self) -> str | None:
        """Why the robot did not move as commanded (one line), or None."""
        d = self.commanded_m
        lo, hi = (1.0 - TOLERANCE) * abs(d), (1.0 + TOLERANCE) * abs(d)
        along = math.copysign(1.0, d) * self.along_m
        if lo <= along <= hi and abs(self.across_m) <= TOLERANCE * abs(d):
            return None
        return (
            f"the robot did not move as commanded before takeoff: nudged {d:+.3f} m along its heading "
            f"({NUDGE_SPEED_MPS:g} m/s for {NUDGE_S:g} s), motion capture saw {self.along_m:+.3f} m along "
            f"and {self.across_m:+.3f} m sideways (tolerance {lo:.3f}–{hi:.3f} m along, "
            f"≤ {TOLERANCE * abs(d):.3f} m sideways); nothing took off"
        )


def nudge_direction(x: float, y: float, theta: float, fence_lo_xy: tuple[float, float],
                    fence_hi_xy: tuple[float, float]) -> float | None:  # fmt: skip
    """+1 (forward) or −1 (backward): the nudge whose end, NUDGE_SPEED_MPS·NUDGE_S from (x, y) along
    heading θ (m, rad), lies inside the fence's xy box; None when neither does."""
    d = NUDGE_SPEED_MPS * NUDGE_S
    for sign in (1.0, -1.0):
        ex, ey = x + sign * d * math.cos(theta), y + sign * d * math.sin(theta)
        if fence_lo_xy[0] <= ex <= fence_hi_xy[0] and fence_lo_xy[1] <= ey <= fence_hi_xy[1]:
            return sign
    return None


def check_robot_moves(
    robot: GroundRobot,
    poses: PoseSource,
    clock: Clock,
    step_s: float,
    fence_lo_xy: tuple[float, float],
    fence_hi_xy: tuple[float, float],
    each: Callable[[], None] | None = None,
) -> MotionCheck:
    """Nudge the robot and measure it (module docstring); always leaves it stopped. The set-point is sent
    every step_s (s, the control period) while the clock advances; each() runs every step (the safety
    tick and the guardian's heartbeat). Raises RuntimeError (one line) when the check fails."""
    start = poses.latest(BODY)
    if start is None:
        raise RuntimeError("motion check: motion capture does not see the robot; nothing took off")
    x0, y0, th0 = float(start.pose.p[0]), float(start.pose.p[1]), float(start.pose.theta)
    sign = nudge_direction(x0, y0, th0, fence_lo_xy, fence_hi_xy)
    if sign is None:
        raise RuntimeError(
            f"motion check: the robot at ({x0:.2f}, {y0:.2f}) m cannot be nudged "
            f"{NUDGE_SPEED_MPS * NUDGE_S:g} m either way inside the fence; nothing took off"
        )
    V = np.array([sign * NUDGE_SPEED_MPS, 0.0, 0.0, 0.0])
    try:
        _hold(clock, NUDGE_S, step_s, lambda: robot.send_body_velocity(V), each)
        robot.stop()
        _hold(clock, SETTLE_S, step_s, robot.stop, each)
    finally:
        robot.stop()
    end = poses.latest(BODY)
    if end is None:
        raise RuntimeError("motion check: motion capture lost the robot during its nudge; nothing took off")
    dx, dy = float(end.pose.p[0]) - x0, float(end.pose.p[1]) - y0
    c, s = math.cos(th0), math.sin(th0)
    result = MotionCheck(sign * NUDGE_SPEED_MPS * NUDGE_S, c * dx + s * dy, -s * dx + c * dy)
    if (why := result.problem) is not None:
        if isinstance(robot, ReportsState):  # what the robot itself says it did (its heartbeat's mode)
            why += f" (the robot's own report: {robot.state_line()})"
        raise RuntimeError(why)
    return result


def _hold(
    clock: Clock, seconds: float, step_s: float, send: Callable[[], None], each: Callable[[], None] | None
) -> None:
    """send() then each() every step_s for `seconds` of the clock (virtual or real)."""
    end = clock.now() + seconds
    while clock.now() < end - 1e-9:
        send()
        if each is not None:
            each()
        clock.sleep_until(min(end, clock.now() + step_s))
