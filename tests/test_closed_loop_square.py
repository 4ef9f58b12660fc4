"""Closed loop on loopback: rover emulator (ArduPilot Rover's GUIDED semantics) → NatNet emulator →
motioncapture → MocapPoseSource → UnicycleSquareLaw → ScamperDriver → MAVLink → rover emulator. One lap of
the paper's square as a differential robot drives it (sides at the speed, corners turned in place),
time-scaled to keep CI fast, run by `flightstack.drivers.lab.target_run.drive_square` (what `flightstack
target` runs). The driver streams the robot's pose to the emulator (its position estimate) and sets the
EKF origin, without which ArduPilot would not move.

Time scaling by TIME_SCALE = 3: speed 0.3 m/s and turns at 1.5 rad/s (inside the emulator's cruise speed,
0.5 m/s, and its 120 °/s turn-rate limit), k_x and k_θ × 3 (1/s), k_y unchanged (1/m², its term is
multiplied by v_d); lap 52.6 s / 3 = 17.5 s. Everything else is the stack's own code.

Frames: the rover emulator integrates in its own local NED frame starting at the origin; `pose_flu()` gives
x forward, y left, yaw counter-clockwise. The mocap world pose is that pose composed with a fixed world
offset that puts the start at the square's corner (-0.5, -0.5), θ = 0, as mission_configs/
paper_experiment.yaml's target initial pose.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

pytest.importorskip("motioncapture")
pytest.importorskip("pymavlink")

from flightstack.drivers.lab.target_run import drive_square
from flightstack.drivers.mocap import MocapConfig, MocapPoseSource
from flightstack.drivers.scamper.driver import ScamperConfig, ScamperDriver
from flightstack.paper.geometry import Pose, compose
from flightstack.paper.target_law import UnicycleSquareLaw
from flightstack.sim_backend.emulators.natnet import NatNetEmulator
from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator

TIME_SCALE = 3.0  # the paper's experiment, 3x faster
_LAB = UnicycleSquareLaw()  # the gains and speeds of the lab's law, time-scaled below
LAW = UnicycleSquareLaw(
    side=1.0,
    speed=_LAB.speed * TIME_SCALE,
    turn_rate=_LAB.turn_rate * TIME_SCALE,
    k_x=_LAB.k_x * TIME_SCALE,
    k_y=_LAB.k_y,
    k_theta=_LAB.k_theta * TIME_SCALE,
)
WORLD_FROM_ROVER = Pose.make([-LAW.side / 2, -LAW.side / 2, 0.0], 0.0)  # rover start = square corner
REFERENCE_BOUND_M = 0.05  # issue acceptance: the path stays within 5 cm of its reference over a lap
CONTROL_HZ = 50.0
MOCAP_HZ = 100.0


def yaw_quaternion(theta: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation by theta (rad) about world z."""
    return (math.cos(theta / 2.0), 0.0, 0.0, math.sin(theta / 2.0))


def rover_mocap_pose(rover: MavlinkRoverEmulator) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The rover's pose in the mocap world frame: (position (3,) m, quaternion (w, x, y, z))."""
    g = compose(WORLD_FROM_ROVER, rover.pose_flu())
    return g.p, yaw_quaternion(g.theta)


def distance_to_square(p: np.ndarray, side: float) -> float:
    """Distance (m) from the planar point p to the perimeter of the axis-aligned square of `side` at 0."""
    h = side / 2.0
    ax, ay = abs(float(p[0])), abs(float(p[1]))
    if ax <= h and ay <= h:
        return min(h - ax, h - ay)
    return math.hypot(max(ax - h, 0.0), max(ay - h, 0.0))


def test_closed_loop_square_lap() -> None:
    rover = MavlinkRoverEmulator()
    natnet = NatNetEmulator(rate_hz=MOCAP_HZ)
    src: MocapPoseSource | None = None
    drv: ScamperDriver | None = None
    try:
        p0, q0 = rover_mocap_pose(rover)
        natnet.set_body("target", p0, q0)
        natnet.set_pose_provider("target", lambda: rover_mocap_pose(rover))
        natnet.start()
        src = MocapPoseSource(
            MocapConfig(
                system="optitrack", settings=natnet.settings(), connect_timeout_s=2.0, stale_after_s=0.1
            )
        )
        src.start()
        cfg = ScamperConfig(url=rover.url, heartbeat_timeout_s=3.0, stream_hz=20.0)
        drv = ScamperDriver(cfg, pose_source=lambda: src.latest("target"))
        drv.connect()

        res = drive_square(drv, src, LAW, LAW.lap_time, rate_hz=CONTROL_HZ, link_alive=drv.link_alive)
        samples, misses = res.poses, res.stale_ticks  # (t s, x m, y m, θ rad) from mocap
        assert res.ended_by == "duration"
        time.sleep(2.0 / MOCAP_HZ)
        end = src.latest("target")
        assert end is not None
    finally:
        if drv is not None:
            drv.close()
        if src is not None:
            src.close()
        natnet.close()
        rover.close()

    xy = np.array([s[1:3] for s in samples])
    theta = np.unwrap([s[3] for s in samples])
    path = float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))
    lap = LAW.path_length
    deviation = max(distance_to_square(p, LAW.side) for p in xy)
    start = np.array([-LAW.side / 2, -LAW.side / 2])
    ref_err = max(np.linalg.norm(np.array([x, y]) - LAW.reference(t)[0].p[:2]) for t, x, y, _ in samples)
    print(
        f"\nclosed loop: {len(samples)} mocap samples, {misses} misses, path {path:.4f} m "
        f"({100 * (path - lap) / lap:+.2f} % of {lap:g} m), max deviation from the square {deviation:.4f} m, "
        f"max distance to the reference {ref_err:.4f} m, end {np.linalg.norm(end.pose.p[:2] - start):.4f} m "
        f"from the start, yaw turned {theta[-1] - theta[0]:.3f} rad"
    )
    assert misses <= 2  # the mocap feed never went stale during the lap
    assert len(samples) > 0.8 * LAW.lap_time * CONTROL_HZ
    # the lap completes: back at the starting corner, having turned once
    assert np.linalg.norm(end.pose.p[:2] - start) < REFERENCE_BOUND_M
    assert theta[-1] - theta[0] == pytest.approx(2 * math.pi, rel=0.05)
    assert abs(path - lap) / lap < 0.10
    assert deviation < REFERENCE_BOUND_M and ref_err < REFERENCE_BOUND_M
