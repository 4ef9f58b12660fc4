"""`flightstack target MISSION`: drive the real ground robot on the paper's square law from motion capture.

This is the paper's own set-up (Sec. 6): the robot's body velocity is computed on a computer from its
motion-capture pose by the mission's square law (`Mission.target_law`) and sent over MAVLink. On a
non-holonomic robot (every ArduPilot Rover: a velocity set-point never moves it sideways) that is the
unicycle law (`flightstack.paper.target_law.UnicycleSquareLaw`): forward speed v_x and yaw rate, v_y = 0.
It runs on its own (a separate terminal or computer) while the drones fly their mission, or from a
mission whose `hardware.target` is set.

Safety: a pose older than `stale_stop_s` makes the robot stop (zero set-point) until the pose returns;
lost for `lost_abort_s` ends the run. A lost MAVLink link ends the run. Ctrl-C stops and disarms.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flightstack.config.mission import Mission
from flightstack.drivers.guardian.launcher import Guardian, GuardianConfig
from flightstack.drivers.lab.hardware import body_names, mocap_config, scamper_config
from flightstack.drivers.mocap import MocapPoseSource
from flightstack.drivers.scamper.driver import ScamperDriver
from flightstack.hal import TARGET_BODY, GroundRobot, PoseSource
from flightstack.paper.target_law import TargetLaw


@dataclass
class TargetRunResult:
    """What the robot did: path length (m) measured by motion capture, time (s), reference tracking."""

    duration_s: float = 0.0
    path_length_m: float = 0.0
    max_tracking_error_m: float = 0.0  # ‖p_w0 − p_d(t)‖ over the run
    ticks: int = 0
    stale_ticks: int = 0
    ended_by: str = "duration"
    poses: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, x, y, θ)


def drive_square(
    robot: GroundRobot,
    poses: PoseSource,
    law: TargetLaw,
    duration_s: float,
    body: str = "target",
    rate_hz: float = 20.0,
    stale_stop_s: float = 0.2,
    lost_abort_s: float = 1.0,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    link_alive: Callable[[], bool] | None = None,
    on_tick: Callable[[float, TargetRunResult], None] | None = None,
    robot_ready: Callable[[], bool] | None = None,
) -> TargetRunResult:
    """Run the square law for duration_s (s) of law time; always leaves the robot stopped.

    The law's clock starts at the first fresh pose. Raises nothing on pose or link loss: `ended_by`
    says why the run ended ("duration", "pose lost", "link lost", "robot not ready": its heartbeat shows
    it left GUIDED or disarmed, e.g. an RC switch or a failsafe); KeyboardInterrupt propagates after the
    robot is stopped."""
    res = TargetRunResult()
    period = 1.0 / rate_hz
    t0: float | None = None
    last_fresh = clock()
    prev_p: np.ndarray | None = None
    try:
        while True:
            now = clock()
            if link_alive is not None and not link_alive():
                res.ended_by = "link lost"
                break
            if robot_ready is not None and not robot_ready():
                res.ended_by = "robot not ready (left GUIDED or disarmed)"
                break
            sp = poses.latest(body)
            if sp is None or now - sp.stamp > stale_stop_s:
                robot.send_body_velocity(np.zeros(4))
                res.stale_ticks += 1
                if now - last_fresh > lost_abort_s:
                    res.ended_by = "pose lost"
                    break
            else:
                last_fresh = now
                if t0 is None:
                    t0 = now
                t = now - t0
                if t >= duration_s:
                    break
                robot.send_body_velocity(law.command(t, sp.pose))
                p = np.asarray(sp.pose.p[:2], dtype=float)
                if prev_p is not None:
                    res.path_length_m += float(np.linalg.norm(p - prev_p))
                prev_p = p
                ref, _ = law.reference(t)
                res.max_tracking_error_m = max(res.max_tracking_error_m, float(np.linalg.norm(p - ref.p[:2])))
                res.poses.append((t, float(p[0]), float(p[1]), float(sp.pose.theta)))
                res.duration_s = t
            res.ticks += 1
            if on_tick is not None:
                on_tick(now, res)
            sleep(max(0.0, period - (clock() - now)))
    finally:
        robot.stop()
    return res


def lap_summary(res: TargetRunResult, law: TargetLaw) -> str:
    laps = res.duration_s / law.lap_time
    expected = law.distance(res.duration_s)
    err = 100.0 * (res.path_length_m - expected) / expected if expected > 0 else math.nan
    return (
        f"{laps:.2f} laps in {res.duration_s:.1f} s: path {res.path_length_m:.3f} m measured, "
        f"{expected:.3f} m commanded ({err:+.1f} %), max tracking error {res.max_tracking_error_m:.3f} m, "
        f"ended by {res.ended_by}"
    )


def drive_target(mission: Mission, duration: float) -> int:
    """`flightstack target` on an opened rig: the robot of `mission.hardware.target` driven `duration` s on
    the square law from its motion-capture pose, under a guardian that stops and disarms it if this process
    dies or stalls (drivers/guardian/); progress on stdout, problems on stderr. Exit code: 0 when it drove
    the whole duration, else 1."""
    law = mission.target_law()
    sc = scamper_config(mission)
    assert sc is not None
    mocap = MocapPoseSource(mocap_config(mission))
    body = body_names(mission)[TARGET_BODY]
    robot = ScamperDriver(sc, pose_source=lambda: mocap.latest(body))
    guardian = Guardian.start(GuardianConfig.for_devices([], sc.url))
    robot.set_muted(guardian.taken_over)
    armed = [False]

    def beat(now: float, res: object) -> None:
        if not armed[0]:
            guardian.arm()
            armed[0] = True
        guardian.heartbeat()

    try:
        mocap.start()
        if not _seen_within(mocap, body, 2.0):
            print(f"error: motion capture does not see the robot (body {body!r})", file=sys.stderr)
            return 1
        robot.connect()
        print(f"driving {duration:.1f} s ({duration / law.lap_time:.2f} laps); Ctrl-C stops the robot")
        res = drive_square(
            robot,
            mocap,
            law,
            duration,
            body=body,
            link_alive=robot.link_alive,
            robot_ready=lambda: (
                robot.robot_state().ready and not guardian.taken_over() and guardian.lost() is None
            ),
            on_tick=beat,
        )
        print(lap_summary(res, law))
        if (lost := guardian.lost()) is not None:
            print(f"error: {lost}: the robot was stopped (never driven without it)", file=sys.stderr)
        return 0 if res.ended_by == "duration" else 1
    finally:
        guardian.arm(False)
        robot.close()
        mocap.close()
        guardian.finish()


def _seen_within(poses: PoseSource, body: str, timeout_s: float) -> bool:
    """Whether `body` has a pose within timeout_s (s)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if poses.latest(body) is not None:
            return True
        time.sleep(0.02)
    return False
