"""Closed loop on loopback: rover emulator → NatNet emulator → motioncapture → MocapPoseSource → SquareLaw →
ScamperDriver → MAVLink → rover emulator. One lap of the paper's square, time-scaled to keep CI fast, run
by `flightstack.drivers.target_run.drive_square` (what `flightstack target` runs).

Time scaling: the paper's law (1 m side at 0.1 m/s, gain 0.05 s⁻¹, one rotation per 40 s lap) is run 5×
faster: speed 0.5 m/s (lap 8 s), gain 0.25 s⁻¹; SquareLaw ties the yaw rate to the lap time (2π / 8 s), so
the rotation is scaled with it. Everything else is the stack's own code.

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

from flightstack.drivers.mocap import MocapConfig, MocapPoseSource
from flightstack.drivers.scamper import ScamperConfig, ScamperDriver
from flightstack.drivers.target_run import drive_square
from flightstack.paper.geometry import Pose, compose
from flightstack.paper.target_law import SquareLaw
from flightstack.sim_backend.emulators.mavlink_rover import MavlinkRoverEmulator
from flightstack.sim_backend.emulators.natnet import NatNetEmulator

TIME_SCALE = 5.0  # the paper's experiment, 5x faster
LAW = SquareLaw(side=1.0, speed=0.1 * TIME_SCALE, gain=0.05 * TIME_SCALE, theta0=0.0)
WORLD_FROM_ROVER = Pose.make([-LAW.side / 2, -LAW.side / 2, 0.0], LAW.theta0)  # rover start = square corner
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


@pytest.mark.xfail(
    strict=True,
    reason="the square law streams a sideways velocity, which ArduPilot Rover adds to its forward speed "
    "(GCS_MAVLINK_Rover::handle_set_position_target_local_ned): measured 0.77 m from the reference; "
    "passes again with a target law the rover can follow",
)
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
    lap = 4.0 * LAW.side
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
    assert np.linalg.norm(end.pose.p[:2] - start) < 0.05
    assert theta[-1] - theta[0] == pytest.approx(2 * math.pi, rel=0.05)
    assert abs(path - lap) / lap < 0.10
    # Deviation bound: the rover integrates the commanded twist exactly, so the only errors come from the
    # loop delay δ (mocap frame period 10 ms + control period 20 ms + thread wake-ups, say ≤ 60 ms): at the
    # four corners the reference velocity turns by 90° and the rover keeps the old direction for ≈ δ
    # (overshoot ≈ speed·δ ≈ 0.03 m), and the yaw lag ω·δ tilts the world velocity by ≈ 0.05 rad (lateral
    # drift ≤ speed·ω·δ·T_leg ≈ 0.05 m per 2 s leg before the 0.25 s⁻¹ feedback pulls it back).
    # 0.08 m (8 % of the side) covers both with margin while still catching a wrong frame or sign.
    assert deviation < 0.08
    assert ref_err < 0.1
