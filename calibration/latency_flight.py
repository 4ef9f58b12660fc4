"""The latency calibration flight over a rig (`flightstack calibrate latency --rig RIG`): one drone with a
downward camera takes off, flies over the still target (motion capture), checks that it sees the
markers, yaws one way at a varying rate while its frames and the poses are kept, flies yaw-rate steps
while its yaw is kept (flightstack.calibration.latency_record), and lands, whatever ends it (Ctrl-C, a
signal, a lost link, the safety layer, an exception: flightstack.runtime.flight.Flight.fly_procedure).

The flight is the rig's: the hardware backend (the real lab, or the emulated lab, whose devices the
flight starts on loopback) or the simulated lab on its virtual clock. Frames are timed when they become
available on this computer: on the hardware backend by their decode time, so the camera driver is told
explicitly not to subtract the rig's video latency (`stamping_decode_time`); on the simulated lab, which
stamps a frame with its capture time, when the recorder first sees it. Motion capture is the reference:
the hardware backend stamps a pose when it is received, so the session's pose times are taken back by
the rig's `mocap` link (its mean, latency_s + jitter_s / 2: a few ms on a wired OptiTrack, which NatNet
reports per frame) to the times they were taken; the simulated lab stamps them when taken.

Units: s, m, rad; the motion capture's world Σw; body velocities FLU.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from flightstack.calibration.latency_record import (
    Geometry,
    Station,
    decode_stamp,
    first_seen,
    rc_levels,
    record_rc,
    record_video,
    settle,
)
from flightstack.calibration.latency_session import RcRecord, VideoRecord
from flightstack.config.links import LinkSpec
from flightstack.config.mission import Mission
from flightstack.hal import TARGET_BODY, Backend, Frame
from flightstack.runtime.fleet import Fleet
from flightstack.runtime.flight import Flight
from flightstack.runtime.runner import SafePause
from flightstack.vision.camera_file import CameraCalibration, load_calibration
from flightstack.vision.detect import detect_markers


class CalibrationFlightError(RuntimeError):
    """The calibration flight could not record (markers not in view, the station not reached); the drone
    has landed."""


@dataclass(frozen=True)
class FlightPlan:
    """How the calibration flies: video_s (s) of the yaw pattern at a mean rate of yaw_rate_rad_s
    (rad/s; the pattern reaches 1.9 × it), rc_steps yaw-rate levels of step_s (s) each, at most
    rc_amplitude_rad_s (rad/s); the station is reached within tolerance_m (m) or settle_s (s); the
    markers must be seen within see_s (s)."""

    video_s: float = 10.0
    yaw_rate_rad_s: float = 0.5
    rc_steps: int = 30
    step_s: float = 0.6
    rc_amplitude_rad_s: float = 0.6
    tolerance_m: float = 0.05
    settle_s: float = 15.0
    see_s: float = 3.0
    seed: int = 0

    @classmethod
    def within(cls, max_yaw_rate: float | None, **kw: float) -> FlightPlan:
        """A plan whose yaw rates stay below the safety layer's max_yaw_rate (rad/s; None: no limit): a
        saturated command would not be the one recorded."""
        plan = cls(**kw)  # type: ignore[arg-type]
        if max_yaw_rate is None:
            return plan
        return cls(
            **{
                **plan.__dict__,
                "yaw_rate_rad_s": min(plan.yaw_rate_rad_s, 0.5 * max_yaw_rate),
                "rc_amplitude_rad_s": min(plan.rc_amplitude_rad_s, 0.9 * max_yaw_rate),
            }
        )

    @property
    def seconds(self) -> float:
        """The patterns' own length (s): without takeoff, the station, the marker check and landing."""
        return self.video_s + self.rc_steps * self.step_s + 0.3


def one_drone(mission: Mission, drone_id: int | None) -> Mission:
    """The mission with only the calibrated drone (default: the first with a downward camera); ValueError
    when it has no calibrated downward camera (the yaw pattern keeps the target in view only below)."""
    drones = mission.drones
    if drone_id is None:
        down = [d for d in drones if d.camera is not None and d.camera.mount == "down"]
        if not down:
            raise ValueError("no drone with a downward camera (camera.mount: down) to calibrate with")
        d = down[0]
    else:
        found = [d for d in drones if d.id == drone_id]
        if not found:
            raise ValueError(f"--drone {drone_id}: the mission's drones are {[d.id for d in drones]}")
        d = found[0]
    if d.camera is None or d.camera.mount != "down" or d.camera.calibration is None:
        raise ValueError(
            f"drone {d.id}: the calibration needs a downward camera with a calibration file (it yaws above "
            "the target, which a forward camera would lose)"
        )
    regions = mission.gp.regions.model_copy(update={"edges": []})  # one drone, one band (the schema's rule)
    return mission.model_copy(
        update={"drones": [d], "gp": mission.gp.model_copy(update={"regions": regions})}
    )


def stamping_decode_time(mission: Mission) -> Mission:
    """The mission the hardware backend is built from during the calibration: its camera driver stamps
    a frame with its decode time minus the rig's video latency (latency_s + jitter_s / 2 of the `video`
    link, drivers/lab/hardware.py); measuring that latency needs the plain decode time, so the video link's
    latency and jitter are set to 0 here (its rate and loss kept), explicitly. The robot is left out
    (hardware.target: null): the target stands still; motion capture still reports it."""
    video = mission.links.link("video")
    links = mission.links.model_copy(
        update={"video": LinkSpec(latency_s=0.0, jitter_s=0.0, rate_hz=video.rate_hz, loss=video.loss)}
    )
    update: dict[str, object] = {"links": links}
    if mission.hardware is not None:
        update["hardware"] = mission.hardware.model_copy(update={"target": None})
    return mission.model_copy(update=update)


def marker_finder(cal: CameraCalibration) -> Callable[[Frame], np.ndarray | None]:
    """A frame's markers' distorted pixels (m, 2), or None unless all were found: extracted from its image,
    or projected from its normalised centres (the simulated lab's `centres` model)."""

    def find(frame: Frame) -> np.ndarray | None:
        if frame.image is not None:
            det = detect_markers(frame.image, cal, roi=frame.roi)
            return det.pixels if det.ok else None
        if frame.features is None:
            return None
        xy = np.asarray(frame.features, float).reshape(-1, 2)
        pts = np.column_stack([xy, np.ones(len(xy))])
        px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
        return px.reshape(-1, 2)

    return find


@dataclass
class CalibrationFlight:
    """The procedure flown between takeoff and landing (Flight.fly_procedure): station, marker check,
    the yaw pattern, the rc steps. `seconds` is how long it flew (s, the rig's clock)."""

    mission: Mission
    plan: FlightPlan
    say: Callable[[str], None]
    pose_latency_s: float = 0.0
    """How late the pose source's stamps are behind the poses' capture (s): subtracted from them."""
    seconds: float = 0.0

    def geometry(self) -> tuple[Geometry, CameraCalibration]:
        d = self.mission.drones[0]
        assert d.camera is not None and d.camera.calibration is not None  # one_drone
        path = self.mission.resolve(d.camera.calibration)
        cam = self.mission.camera_model(0)
        P0 = np.array(self.mission.target.feature_points, dtype=float)
        geo = Geometry(str(path), cam.R_ic, cam.t_ic, P0, self.mission.identity(d.id).name, TARGET_BODY)
        return geo, load_calibration(path)

    def __call__(self, f: Fleet, pause: SafePause) -> tuple[VideoRecord, RcRecord]:
        d, plan, clock = self.mission.drones[0], self.plan, f.clock
        geo, cal = self.geometry()
        drone, camera, poses = f.drones[d.id], f.backend.camera(d.id), f.backend.pose_source()
        find = marker_finder(cal)
        t0 = clock.now()
        station = Station(poses, geo, d.desired_pose.pose())
        left = settle(drone, station, clock.now, pause, plan.tolerance_m, plan.settle_s)
        if not left <= 2 * plan.tolerance_m:
            raise CalibrationFlightError(
                f"drone {d.id} did not reach its station over the target ({left:.2f} m away after "
                f"{plan.settle_s:g} s): is the target where motion capture says?"
            )
        self.say(f"drone {d.id} over the target ({1e3 * left:.0f} mm from its station)")
        self._check_markers(camera, find, clock.now, pause, d.id)
        frame_time = first_seen if f.backend.simulated else decode_stamp
        self.say(f"yaw pattern: {plan.video_s:g} s at {plan.yaw_rate_rad_s:g} rad/s mean")
        video = record_video(
            drone, camera, poses, geo, find, clock.now, pause, plan.video_s,
            mean_rad_s=plan.yaw_rate_rad_s, frame_time=frame_time, station=station,
        )  # fmt: skip
        levels = rc_levels(plan.rc_steps, plan.rc_amplitude_rad_s, plan.seed)
        self.say(
            f"yaw-rate steps: {plan.rc_steps} of {plan.step_s:g} s, up to {plan.rc_amplitude_rad_s:g} rad/s"
        )
        rc = record_rc(drone, poses, geo.drone_body, clock.now, pause, levels, plan.step_s, station=station)
        self.seconds = clock.now() - t0
        video.t_pose = video.t_pose - self.pose_latency_s  # when taken (the session's convention)
        rc.t_yaw = rc.t_yaw - self.pose_latency_s
        return video, rc

    def _check_markers(
        self,
        camera: object,
        find: Callable[[Frame], np.ndarray | None],
        now: Callable[[], float],
        pause: Callable[[float], None],
        drone_id: int,
    ) -> None:
        """CalibrationFlightError unless a frame shows every marker within plan.see_s (s)."""
        t_end, last = now() + self.plan.see_s, None
        while now() < t_end:
            frame = camera.latest()  # type: ignore[attr-defined]
            if frame is not None and frame.stamp != last:
                last = frame.stamp
                if find(frame) is not None:
                    return
            pause(0.02)
        raise CalibrationFlightError(
            f"drone {drone_id}'s camera does not show every marker within {self.plan.see_s:g} s (the "
            "calibration's marker colours, the light, the height?)"
        )


def fly_latency_calibration(
    mission: Mission,
    drone_id: int | None = None,
    plan: FlightPlan | None = None,
    say: Callable[[str], None] = print,
    wrap_backend: Callable[[Backend], Backend] | None = None,
) -> tuple[VideoRecord, RcRecord, float, float]:
    """Fly the calibration on the mission's rig: (video part, rc part, the procedure's seconds on the rig's
    clock, the whole flight's wall seconds with takeoff, landing and the emulated lab's start).
    wrap_backend: wraps the backend the flight builds (an observer: the tests' true capture times)."""
    m = one_drone(mission, drone_id)
    if plan is None:
        plan = FlightPlan.within(m.safety.max_yaw_rate if m.safety.enabled else None)
    mocap = m.links.link("mocap")
    pose_latency = 0.0 if m.simulated else mocap.latency_s + mocap.jitter_s / 2  # stamped when received
    proc = CalibrationFlight(m, plan, say, pose_latency)
    wall0 = time.perf_counter()
    with Flight(m, None, modes=["none"], say=say, wrap_backend=wrap_backend) as flight:
        flown = flight.mission if flight.mission.simulated else stamping_decode_time(flight.mission)
        video, rc = flight.fly_procedure(proc, mission=flown)
    return video, rc, proc.seconds, time.perf_counter() - wall0


__all__ = [
    "CalibrationFlight",
    "CalibrationFlightError",
    "FlightPlan",
    "fly_latency_calibration",
    "marker_finder",
    "one_drone",
    "stamping_decode_time",
]
