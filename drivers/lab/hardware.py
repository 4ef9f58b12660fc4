"""The hardware backend (`backend: tello`): real Tellos, motion capture and the Scamper, from a mission.

It implements `flightstack.hal.Backend` like the simulated backends, so the runner, agents and safety
layer do not know they fly real drones. Building it connects every device, each with a bounded wait
(`hardware.*.connect_timeout_s`, `heartbeat_timeout_s`); if any device fails, whatever was already
connected is closed again and the error names the device.

Clock: the wall clock `time.monotonic()` (seconds), which is also the time base of every driver's stamps
(Tello state and video, motion-capture receive times), so pose and frame ages are comparable with `now()`.

Bodies: flightstack names the motion-capture bodies `drone<ID>` and `target`; `hardware.mocap.bodies`
maps them to the names used in the motion-capture software.

Raw traffic: given `devices` (the run directory's, flightstack.recording.files.DeviceFiles), every Tello's
commands, replies, state lines and video datagram timing are recorded from before `connect` to after
`close` (drivers/tello/traffic.py), so that a flight can be replayed to the driver; the robot's MAVLink
link, both directions, goes to a pymavlink .tlog (drivers/scamper/tlog.py). The guardian process's
own datagrams (after a takeover) are not among them: it logs what it sends to guardian.log.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.config.derive import derive
from flightstack.config.mission import Mission
from flightstack.drivers.guardian.launcher import Guardian, GuardianConfig
from flightstack.drivers.mocap import MocapConfig, MocapPoseSource
from flightstack.drivers.scamper.driver import ScamperConfig, ScamperDriver
from flightstack.drivers.tello.camera import TelloCamera
from flightstack.drivers.tello.config import TelloConfig
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.rc import RcGains
from flightstack.drivers.tello.traffic import TrafficWriter
from flightstack.hal import TARGET_BODY, DroneIdentity, FlightPhase, StampedPose
from flightstack.paper.geometry import Pose
from flightstack.recording.files import DeviceFiles
from flightstack.vision.camera_file import load_calibration
from flightstack.vision.picture import picture_of

if TYPE_CHECKING:
    from flightstack.runtime.rig import AgentSeat

LOG = logging.getLogger("flightstack.hardware")


class WallClock:
    """hal.Clock on time.monotonic() (s); sleep_until sleeps (returns at once when t is past)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        delay = t - time.monotonic()
        if delay > 0:
            time.sleep(delay)


class NamedPoseSource:
    """hal.PoseSource that maps flightstack body names to motion-capture names (`hardware.mocap.bodies`)."""

    def __init__(self, inner: MocapPoseSource, names: dict[str, str]) -> None:
        self.inner = inner
        self.names = dict(names)

    def latest(self, body: str) -> StampedPose | None:
        return self.inner.latest(self.names.get(body, body))


def tello_config(mission: Mission, drone_id: int) -> TelloConfig:
    """The driver settings of drone `drone_id` from `hardware.drones` (and `hardware.video`) and the
    drone's rc gains and camera."""
    assert mission.hardware is not None
    hw = mission.hardware.drone(drone_id)
    spec = next(d for d in mission.drones if d.id == drone_id)
    return derive(
        TelloConfig,
        hw,
        rename={"ip": "host"},
        # the drone's key; the camera's (flightstack.drivers.tello.camera); merged with the lab's below
        skip={"id", "frame_timeout_s", "video"},
        state_port=mission.hardware.state_port,
        video_settings=mission.hardware.video_settings(drone_id),
        rc_gains=RcGains(**spec.rc_gains.model_dump()),
        min_battery_pct=mission.safety.min_battery_takeoff,
        downward_camera=spec.camera is not None and spec.camera.mount == "down",
    )


def mocap_config(mission: Mission) -> MocapConfig:
    assert mission.hardware is not None
    m = mission.hardware.mocap
    return derive(MocapConfig, m, skip={"bodies"}, settings=dict(m.settings))  # bodies: body_names()


def scamper_config(mission: Mission) -> ScamperConfig | None:
    assert mission.hardware is not None
    t = mission.hardware.target
    if t is None:
        return None
    return derive(ScamperConfig, t)


def body_names(mission: Mission) -> dict[str, str]:
    """flightstack body name → motion-capture body name, for every drone and the target."""
    assert mission.hardware is not None
    names = [who.name for who in mission.identities()] + [TARGET_BODY]
    return {n: mission.hardware.body(n) for n in names}


class _UnknownPose:
    """Recorded for a body motion capture has never seen: NaN in the recording, never used for control."""

    def as_vector(self) -> np.ndarray:
        return np.full(4, np.nan)


UNKNOWN_POSE: Any = _UnknownPose()


class GuardianTakeoverError(RuntimeError):
    """The guardian process took over this process's devices (it had stalled): end the run."""


class GuardianLostError(RuntimeError):
    """This process's guardian is gone (killed, crashed, hung): land now, never fly on without it."""


@dataclass
class LabDrone:
    """One drone this process flies: who it is (names derived from its id) and its devices."""

    identity: DroneIdentity
    driver: TelloDriver
    camera: TelloCamera | None = None
    """Started once the driver is connected."""
    traffic: TrafficWriter | None = None
    """Where its raw traffic is recorded (None: nowhere)."""


class HardwareBackend:
    """hal.Backend of the lab. `truth()` returns the motion-capture poses (the lab's reference)."""

    simulated = False

    def __init__(
        self,
        mission: Mission,
        drone_ids: list[int] | None = None,
        guardian_log: str | None = None,
        devices: DeviceFiles | None = None,
    ) -> None:
        """drone_ids: the drones this process flies (`flightstack agent --id N`); the robot is then left
        to `flightstack target` (None: every drone, and the robot when hardware.target is set).

        A guardian process (drivers/guardian/launcher.py) is started before any device is connected: if this
        process dies or its control loop stops beating (`heartbeat()`, every tick, armed at the first
        one) it hovers and lands these drones and stops and disarms the robot from its own sockets, and
        mutes this process's drivers for good. guardian_log: a file for its log (default: none).
        devices: where each Tello's raw traffic is recorded (module docstring; None: nowhere)."""
        if mission.hardware is None:
            raise ValueError("backend 'tello' needs the mission's hardware section")
        self.mission = mission
        self.drone_ids = [d.id for d in mission.drones] if drone_ids is None else list(drone_ids)
        why = mission.hardware.shared_by(self.drone_ids)
        if why is not None:
            raise ValueError(why)
        self.clock = WallClock()
        self.mocap = MocapPoseSource(mocap_config(mission), clock=self.clock.now)
        self.names = body_names(mission)
        self.poses = NamedPoseSource(self.mocap, self.names)
        self.lab_drones: dict[int, LabDrone] = {}
        """Drone id -> the drone and its devices, in the mission's order (filled as each connects)."""
        self.devices = devices
        sc = scamper_config(mission) if drone_ids is None else None
        self.robot: ScamperDriver | None = None
        if sc is not None:  # its own motion-capture pose goes to its autopilot (external navigation)
            tlog = None if devices is None else devices.scamper()
            self.robot = ScamperDriver(sc, pose_source=lambda: self.poses.latest(TARGET_BODY), tlog_path=tlog)
        self._last_truth: dict[str, Pose] = {}
        self.guardian: Guardian | None = None
        self._armed = False
        self._takeover_reported = False
        self._lost_reported = False
        try:
            self.guardian = Guardian.start(
                GuardianConfig.for_devices(
                    [tello_config(mission, i) for i in self.drone_ids],
                    None if sc is None else sc.url,
                    log_path=guardian_log or "",
                )
            )
            self._connect_all()
        except BaseException:
            self.close()
            raise

    def _connect_all(self) -> None:
        assert self.mission.hardware is not None
        self.mocap.start()
        for d in self.mission.drones:
            if d.id not in self.drone_ids:
                continue
            cfg = tello_config(self.mission, d.id)
            traffic = None if self.devices is None else TrafficWriter(self.devices.tello(d.id), cfg.host)
            try:
                drv = TelloDriver(cfg, traffic)
            except BaseException:  # (once recorded in lab_drones, close() closes its writer)
                if traffic is not None:
                    traffic.close()
                raise
            this = self.lab_drones[d.id] = LabDrone(DroneIdentity(d.id), drv, traffic=traffic)
            if self.guardian is not None:
                drv.set_muted(self.guardian.taken_over)
            drv.connect()
            # a frame is stamped when it was taken: decoded minus the video link's mean delay, latency_s +
            # jitter_s / 2 (config.links; measured on the emulated lab: docs/links.md)
            video = self.mission.links.link("video")
            video_latency_s = video.latency_s + video.jitter_s / 2
            to_picture = None  # frames cut to the calibrated picture (the EDU's downward stream)
            if d.camera is not None and d.camera.calibration is not None:
                to_picture = picture_of(load_calibration(self.mission.resolve(d.camera.calibration)))
            timeout_s = self.mission.hardware.drone(d.id).frame_timeout_s
            this.camera = TelloCamera(drv, timeout_s, video_latency_s, to_picture)
            this.camera.start()
        if self.robot is not None:
            if self.guardian is not None:
                self.robot.set_muted(self.guardian.taken_over)
            self.robot.connect()

    # ---- hal.Backend ------------------------------------------------------------------------------
    def drone(self, drone_id: int) -> TelloDriver:
        return self.lab_drones[drone_id].driver

    def camera(self, drone_id: int) -> TelloCamera:
        cam = self.lab_drones[drone_id].camera
        if cam is None:
            raise KeyError(f"drone {drone_id}: its camera is not started")
        return cam

    def pose_source(self) -> NamedPoseSource:
        return self.poses

    def target(self) -> ScamperDriver | None:
        return self.robot

    def truth(self) -> tuple[Pose, dict[int, Pose]]:
        """Motion-capture poses of the target and the drones (the last one seen while a body is lost)."""
        for name in self.names:
            sp = self.poses.latest(name)
            if sp is not None:
                self._last_truth[name] = sp.pose
        target = self._last_truth.get(TARGET_BODY, UNKNOWN_POSE)
        drones = {i: self._last_truth.get(d.identity.name, UNKNOWN_POSE) for i, d in self.lab_drones.items()}
        return target, drones

    def _seen_down(self, drone: LabDrone) -> bool:
        """Motion capture shows the drone's body on the floor now (fresh pose, z ≤ safety.landed_height)."""
        sp = self.poses.latest(drone.identity.name)
        limit = self.mission.safety.landed_height
        return sp is not None and self.clock.now() - sp.stamp <= 0.3 and float(sp.pose.p[2]) <= limit

    def heartbeat(self) -> None:
        """One control tick, for the guardian (the runner calls it every tick, also in takeoff and landing).

        Raises GuardianTakeoverError once when the guardian has taken over (this process is then muted:
        the run must end), GuardianLostError once when the guardian is gone (the run lands its drones
        itself: nothing would cover it if this process died now); never otherwise."""
        g = self.guardian
        if g is None:
            return
        if not self._armed:
            g.arm()
            self._armed = True
        g.heartbeat()
        if g.taken_over() and not self._takeover_reported:
            self._takeover_reported = True
            raise GuardianTakeoverError(
                "the guardian process took over (this process stalled): it lands the drones; nothing more "
                "is sent from here"
            )
        lost = g.lost()
        if lost is not None and not self._lost_reported:
            self._lost_reported = True
            LOG.error("%s: landing every drone of this process now", lost)
            raise GuardianLostError(f"{lost}: no safety net if this process dies; landing")

    def close(self) -> None:
        """Land every drone still flying, stop video, stop and disarm the robot, close motion capture,
        then tell the guardian the run ended normally.

        Never raises: every failure is logged and the remaining devices are still closed."""
        if self.guardian is not None:
            self.guardian.arm(False)  # the blocking lands below must not read as a stalled loop
        for i, d in self.lab_drones.items():
            if d.driver.state().phase != FlightPhase.GROUND:  # taking off, airborne, landing or unknown
                if self._seen_down(d):  # its telemetry is silent, but motion capture shows it down
                    LOG.info("drone %s: on the floor by motion capture; no land sent while closing", i)
                    continue
                try:
                    d.driver.land()
                except Exception as exc:
                    LOG.error("drone %s: land failed while closing: %s", i, exc)
        for d in self.lab_drones.values():
            if d.camera is not None:
                with contextlib.suppress(Exception):
                    d.camera.stop()
        for d in self.lab_drones.values():
            with contextlib.suppress(Exception):
                d.driver.close()
        if self.robot is not None:
            with contextlib.suppress(Exception):
                self.robot.close()
        self._close_traffic()
        self.mocap.close()
        if self.guardian is not None:
            code = self.guardian.finish()
            if code is None:
                LOG.error("the guardian is still landing after a takeover; it exits when the drones are down")
            self.guardian = None

    def _close_traffic(self) -> None:
        """Close the raw-traffic files (after the drivers and cameras: nothing more arrives); a recording
        that failed or was cut short is logged (the flight went on without it)."""
        for i, d in self.lab_drones.items():
            w, d.traffic = d.traffic, None
            if w is None:
                continue
            w.close()
            if w.errors:
                LOG.warning(
                    "drone %s: raw traffic %s: %d records written; incomplete: %s",
                    i, w.path, w.written, ", ".join(f"{k} {n}" for k, n in sorted(w.errors.items())),
                )  # fmt: skip


def build_tello(mission: Mission, devices: DeviceFiles | None = None) -> HardwareBackend:
    return HardwareBackend(mission, devices=devices)


@contextlib.contextmanager
def agent_backend(mission: Mission, seat: AgentSeat) -> Iterator[HardwareBackend]:
    """The lab rig's agent backend (drivers/lab/rig.py): this agent's drone (with its guardian logging to
    `seat.guardian_log`), motion capture and, where the mission has one, the robot. The run lands and
    closes it (`close()`); if the agent fails before the run takes it over (e.g. keeping the computer
    awake fails), it is closed here so that no armed robot or running guardian is left behind."""
    backend = HardwareBackend(
        mission, drone_ids=[seat.drone_id], guardian_log=seat.guardian_log, devices=seat.devices
    )
    try:
        yield backend
    except BaseException:
        backend.close()  # never raises; a second close after the run's own is a no-op for what is closed
        raise
