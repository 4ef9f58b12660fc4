"""The robot's motion check before takeoff (flightstack.runtime.motion_check): a robot that moves as
commanded passes; one that stays put, drives the wrong way or sideways, or that motion capture loses,
stops the mission with one line; the nudge stays inside the fence and within its bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.hal import ReportsState, StampedPose
from flightstack.paper.geometry import Pose
from flightstack.runtime import motion_check as mc
from flightstack.sim_backend.lab import RobotParams, ScamperSim

FENCE = ((-2.0, -2.0), (2.0, 2.0))


class World:
    """A virtual clock that steps a simulated robot (ScamperSim) and reports its pose as motion capture."""

    def __init__(self, robot: ScamperSim | None, pose: Pose, seen: bool = True) -> None:
        self.t = 0.0
        self.robot = robot
        self.fixed = pose
        self.seen = seen
        self.sent: list[np.ndarray] = []

    def now(self) -> float:
        return self.t

    def sleep_until(self, t: float) -> None:
        while self.t < t - 1e-12:
            h = min(0.005, t - self.t)
            self.t += h
            if self.robot is not None:
                self.robot.step(self.t, h)

    def latest(self, body: str) -> StampedPose | None:
        if not self.seen:
            return None
        return StampedPose(self.t, self.robot.pose if self.robot is not None else self.fixed)


class Recorder:
    """A GroundRobot that records its commands and forwards them (or not: a robot that does not move)."""

    def __init__(self, inner: ScamperSim | None, transform=None) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.transform, self.sent, self.stops = inner, transform, [], 0

    def send_body_velocity(self, V: np.ndarray) -> None:
        self.sent.append(np.array(V))
        if self.inner is not None:
            self.inner.send_body_velocity(self.transform(V) if self.transform else V)

    def stop(self) -> None:
        self.stops += 1
        if self.inner is not None:
            self.inner.stop()


def _run(pose: Pose, transform=None, moving: bool = True, seen: bool = True) -> tuple[Recorder, World]:  # type: ignore[no-untyped-def]
    sim = ScamperSim(pose, RobotParams(kinematics="differential"), lambda: world.t) if moving else None
    world = World(sim, pose, seen)
    robot = Recorder(sim, transform)
    return robot, world


def test_a_robot_that_moves_as_commanded_passes_and_the_nudge_is_bounded() -> None:
    robot, world = _run(Pose.make([0.0, 0.0, 0.0], 0.7))
    res = mc.check_robot_moves(robot, world, world, 0.05, *FENCE)
    assert res.problem is None
    assert res.commanded_m == pytest.approx(0.05)
    assert res.along_m == pytest.approx(0.05, abs=0.005) and abs(res.across_m) < 1e-9
    speeds = [abs(v[0]) for v in robot.sent]
    assert max(speeds) <= 0.1 and all(v[1] == 0 and v[3] == 0 for v in robot.sent)
    assert world.t <= 2.0 and robot.stops >= 1  # ≤ 2 s in all; left stopped
    print(f"moved {res.along_m * 1000:.1f} mm of {res.commanded_m * 1000:.0f} mm in {world.t:.2f} s")


def test_a_robot_that_does_not_move_stops_the_mission_with_one_line() -> None:
    robot, world = _run(Pose.make([0.0, 0.0, 0.0], 0.0), moving=False)
    with pytest.raises(RuntimeError) as err:
        mc.check_robot_moves(robot, world, world, 0.05, *FENCE)
    msg = str(err.value)
    assert "did not move as commanded" in msg and "+0.000 m along" in msg and "\n" not in msg
    assert robot.stops >= 1


class HeldRobot(Recorder):
    """A robot whose own telemetry says a failsafe put it in HOLD (drivers/scamper/driver.py's state_line)."""

    def state_line(self) -> str:
        return "heartbeat shows HOLD (4), armed (0.10 s old); last change by the robot: GUIDED -> HOLD"


def test_a_robot_that_reports_its_own_state_is_quoted_in_the_refusal() -> None:
    """Why it did not move is the robot's to say (its heartbeat's mode), not the check's to guess."""
    assert isinstance(HeldRobot(None), ReportsState) and not isinstance(Recorder(None), ReportsState)
    _, world = _run(Pose.make([0.0, 0.0, 0.0], 0.0), moving=False)
    with pytest.raises(RuntimeError) as err:
        mc.check_robot_moves(HeldRobot(None), world, world, 0.05, *FENCE)
    msg = str(err.value)
    assert "+0.000 m along" in msg and "\n" not in msg
    assert "(the robot's own report: heartbeat shows HOLD (4), armed" in msg and "GUIDED -> HOLD)" in msg


@pytest.mark.parametrize(
    ("transform", "what"),
    [
        (lambda V: -V, "the wrong way"),
        (lambda V: 3.0 * V, "three times as far"),
        (lambda V: 0.3 * V, "a third of the way"),
    ],
)
def test_a_robot_that_moves_otherwise_fails(transform, what: str) -> None:  # type: ignore[no-untyped-def]
    robot, world = _run(Pose.make([0.0, 0.0, 0.0], 0.0), transform)
    with pytest.raises(RuntimeError, match="did not move as commanded"):
        mc.check_robot_moves(robot, world, world, 0.05, *FENCE)


def test_sideways_motion_fails() -> None:
    res = mc.MotionCheck(0.05, 0.05, 0.03)
    assert res.problem is not None and "sideways" in res.problem
    assert mc.MotionCheck(0.05, 0.05, 0.02).problem is None
    assert mc.MotionCheck(-0.05, -0.03, 0.0).problem is None
    assert mc.MotionCheck(-0.05, 0.03, 0.0).problem is not None


def test_the_nudge_stays_inside_the_fence() -> None:
    # facing the fence 3 cm away: it is nudged backwards
    robot, world = _run(Pose.make([1.97, 0.0, 0.0], 0.0))
    res = mc.check_robot_moves(robot, world, world, 0.05, *FENCE)
    assert res.commanded_m == pytest.approx(-0.05) and res.problem is None
    assert world.robot is not None and world.robot.pose.p[0] < 1.97
    # in a corner of a box too small either way: refused, nothing moved
    robot, world = _run(Pose.make([0.0, 0.0, 0.0], math.pi / 4))
    with pytest.raises(RuntimeError, match="inside the fence"):
        mc.check_robot_moves(robot, world, world, 0.05, (-0.02, -0.02), (0.02, 0.02))
    assert robot.sent == []


def test_without_motion_capture_nothing_is_nudged() -> None:
    robot, world = _run(Pose.make([0.0, 0.0, 0.0], 0.0), seen=False)
    with pytest.raises(RuntimeError, match="does not see the robot"):
        mc.check_robot_moves(robot, world, world, 0.05, *FENCE)
    assert robot.sent == []
