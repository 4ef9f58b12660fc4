"""The parts of a flight that the runner and the served world share: the bounded waits of takeoff and
landing on a clock, and the driver of the ground robot's square law.

Times in seconds on the backend's clock (virtual in simulation, so a wait integrates the world).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from flightstack.hal import Backend, Clock, FlightPhase, StampedPose
from flightstack.paper.target_law import TargetLaw, start_phase
from flightstack.runtime.motion_check import MotionCheck, check_robot_moves
from flightstack.safety.pose_check import FreezeWatch, MotionAgreement
from flightstack.safety.rules import EventLog, valid_pose

TAKEOFF_TIMEOUT_S = 25.0  # > the Tello driver's own 20 s bound, so its outcome is collected first
LAND_TIMEOUT_S = 20.0  # > the Tello's own 15 s auto-land, so a drone that lost its link is seen down
POSE_WAIT_S = 3.0  # before takeoff: how long a drone's motion-capture pose may take to be fresh
MAX_OFF_PATH_M = 0.2  # before takeoff: how far the robot may stand from its law's path (m, in the plane)
ROBOT_FROZEN_S = 0.5  # the robot's pose identical under fresh stamps this long while driven: frozen (s)


class TargetDriver:
    """Drives the ground robot on its square law (Mission.target_law) from its motion-capture pose.

    fence_xy: ((x_lo, y_lo), (x_hi, y_hi)) of the fence (m) when the robot's motion is checked before
    takeoff (flightstack.runtime.motion_check; the rigs with a robot device), None when it is not.

    Its pose is checked before each command: a pose that is not finite, frozen (identical under fresh
    stamps for ROBOT_FROZEN_S while the law drove it) or that moved where its commands could not take it
    (flightstack.safety.pose_check) stops the robot for good, logs `robot_pose_suspect` into `log` and sets
    `suspect` (the runner then ends the run with an error: the law cannot drive a robot it cannot see)."""

    def __init__(
        self,
        law: TargetLaw,
        backend: Backend,
        fence_xy: tuple[tuple[float, float], tuple[float, float]] | None = None,
        log: EventLog | None = None,
    ) -> None:
        self.law = law
        self.robot = backend.target()
        self.poses = backend.pose_source()
        self.backend = backend  # its clock stamps robot_pose_suspect
        self.fence_xy = fence_xy
        self.log = log
        self.t0 = 0.0  # s: the lap time at which the law starts (`start_where_it_is`)
        self.suspect: str | None = None
        """Why the robot's pose was not believed (one line), None while it is."""
        self._freeze = FreezeWatch()
        self._motion = MotionAgreement()
        self._last_command: np.ndarray | None = None

    def start_where_it_is(self) -> tuple[float, float, float] | None:
        """On a rig whose robot is a device (the rigs whose robot is nudged), the robot stands where the last
        mode left it, not at the lap's start: start the law at the lap time where it is
        (target_law.start_phase) and return (t0 s, distance m, heading error rad); None when not such a rig.
        Raises RuntimeError (one line) when the robot stands farther than MAX_OFF_PATH_M from the path or
        has no pose."""
        if self.robot is None or self.fence_xy is None:
            return None
        own = self.poses.latest("target")
        if own is None:
            raise RuntimeError("the ground robot has no motion-capture pose: its law cannot start")
        t0, dist, dth = start_phase(self.law, own.pose)
        if dist > MAX_OFF_PATH_M:
            ref = self.law.reference(0.0)[0]
            raise RuntimeError(
                f"the ground robot stands {dist:.2f} m from its square's path (at most "
                f"{MAX_OFF_PATH_M:g} m): place it on the path, e.g. at its start ({ref.p[0]:+.2f}, "
                f"{ref.p[1]:+.2f}) m facing {ref.theta:+.2f} rad, or drive it there (`flightstack target`)"
            )
        self.t0 = t0
        return t0, dist, dth

    def check_moves(
        self, clock: Clock, step_s: float, each: Callable[[], None] | None = None
    ) -> MotionCheck | None:
        """The motion check before takeoff (motion_check.check_robot_moves) when this driver has a robot
        and a fence to check it in (None when not checked); raises RuntimeError (one line) when the robot
        did not move as commanded."""
        if self.robot is None or self.fence_xy is None:
            return None
        return check_robot_moves(self.robot, self.poses, clock, step_s, *self.fence_xy, each)

    def tick(self, t_mission: float) -> None:
        """Command the robot by its law at t_mission (s) from its pose, unless that pose is suspect."""
        own = self.poses.latest("target")
        if own is None or self.robot is None or self.suspect is not None:
            return
        problem = self._pose_problem(own)
        if problem is not None:
            self.suspect = problem
            self.robot.stop()
            if self.log is not None:
                now = self.backend.clock.now()
                self.log.record(now, None, "robot_pose_suspect", f"{problem}: robot stopped")
            return
        cmd = self.law.command(self.t0 + t_mission, own.pose)
        self.robot.send_body_velocity(cmd)
        self._last_command = np.asarray(cmd, dtype=float)

    def _pose_problem(self, own: StampedPose) -> str | None:
        """Why the robot's pose sample cannot be believed, or None (see the class docstring)."""
        if not valid_pose(own):
            return f"the ground robot's pose is not finite ({own})"
        stamp = float(own.stamp)
        self._freeze.sample(stamp, own.pose.as_vector(), self._last_command)
        since = self._freeze.frozen_since
        if since is not None and stamp - since >= ROBOT_FROZEN_S:
            return (
                f"the ground robot's pose identical for {stamp - since:.2f} s under fresh stamps while its "
                "law drove it (frozen motion capture)"
            )
        p = own.pose.p
        d = self._motion.sample(stamp, float(p[0]), float(p[1]), float(own.pose.theta), self._last_command)
        if d is not None:
            return (
                f"the ground robot's pose moved {d:.2f} m off what its commands explain over "
                f"{self._motion.window_s:g} s (a swapped or mislabelled body)"
            )
        return None

    def stop(self) -> None:
        if self.robot is not None:
            self.robot.stop()


def advance_until(
    clock: Clock,
    done: Callable[[], bool],
    timeout: float,
    step: float,
    each: Callable[[], None] | None = None,
) -> bool:
    """Advance the clock in steps until done() or timeout (s); True if done."""
    t_end = clock.now() + timeout
    while not done():
        if clock.now() >= t_end:
            return False
        if each is not None:
            each()
        clock.sleep_until(clock.now() + step)
    return True


def settle_virtual_landing(backend: Backend, ids: list[int], dt: float) -> dict[int, bool]:
    """After backend.close() on a virtual clock: advance it (steps of dt s, at most LAND_TIMEOUT_S) until
    every drone's own state says GROUND. Returns {id: on the ground}."""
    drones = {i: backend.drone(i) for i in ids}

    def grounded(i: int) -> bool:
        return drones[i].state().phase == FlightPhase.GROUND

    advance_until(backend.clock, lambda: all(grounded(i) for i in ids), LAND_TIMEOUT_S, dt)
    return {i: grounded(i) for i in ids}
