"""The parts of a flight that the runner and the served world share: the bounded waits of takeoff and
landing on a clock, and the driver of the ground robot's square law.

Times in seconds on the backend's clock (virtual in simulation, so a wait integrates the world).
"""

from __future__ import annotations

from collections.abc import Callable

from flightstack.hal import Backend, Clock, FlightPhase
from flightstack.paper.target_law import TargetLaw
from flightstack.runtime.motion_check import MotionCheck, check_robot_moves

TAKEOFF_TIMEOUT_S = 25.0  # > the Tello driver's own 20 s bound, so its outcome is collected first
LAND_TIMEOUT_S = 20.0  # > the Tello's own 15 s auto-land, so a drone that lost its link is seen down
POSE_WAIT_S = 3.0  # before takeoff: how long a drone's motion-capture pose may take to be fresh


class TargetDriver:
    """Drives the ground robot on its square law (Mission.target_law) from its motion-capture pose.

    fence_xy: ((x_lo, y_lo), (x_hi, y_hi)) of the fence (m) when the robot's motion is checked before
    takeoff (flightstack.runtime.motion_check; the rigs with a robot device), None when it is not."""

    def __init__(
        self,
        law: TargetLaw,
        backend: Backend,
        fence_xy: tuple[tuple[float, float], tuple[float, float]] | None = None,
    ) -> None:
        self.law = law
        self.robot = backend.target()
        self.poses = backend.pose_source()
        self.fence_xy = fence_xy

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
        own = self.poses.latest("target")
        if own is None or self.robot is None:
            return
        self.robot.send_body_velocity(self.law.command(t_mission, own.pose))

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
