"""Simulated lab of the paper's experiment (Sec. 6): Tello-like drones, motion capture, a Scamper-like
ground robot and rendered cameras, each behind the flightstack.hal Protocols.

Frames: Σw is the motion-capture frame, z up. Drones and robot have yaw-only poses (the Tello's tilt while
accelerating is not modelled: the camera stays level). Drone body frame FLU (x forward, y left, z up).
Time: the world's virtual clock (seconds); models advance in `LabWorld.step`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.drivers.tello_rc import RcGains, rc_to_velocity, velocity_to_rc
from flightstack.events import Event
from flightstack.hal import DroneState, Frame, StampedPose
from flightstack.paper.geometry import Pose, integrate_body_velocity, relative
from flightstack.vision.camera_file import CameraCalibration


@dataclass(frozen=True)
class TelloParams:
    """Physics of the simulated Tello (the truth) and the driver-side rc mapping (the calibration)."""

    true_gains: RcGains = field(default_factory=RcGains)  # what one rc unit really does
    cmd_gains: RcGains = field(default_factory=RcGains)  # what the driver believes (mission calibration)
    time_constant_s: float = 0.25  # first-order velocity response
    latency_s: float = 0.05  # command → effect
    max_speed_xy: float = 1.0  # m/s
    max_speed_z: float = 0.5
    max_yaw_rate: float = 1.75  # rad/s
    takeoff_height_m: float = 1.0
    climb_rate: float = 0.5  # m/s during takeoff
    descent_rate: float = 0.4  # m/s during landing
    battery_pct: float = 90.0
    battery_drain_pct_per_s: float = 0.12  # ~12 min of flight from full
    auto_land_s: float = 15.0  # the real Tello lands after 15 s without a command


class TelloSim:
    """A Tello-like drone (hal.Drone). Commands arrive as the integer rc values the real driver sends."""

    GROUND, TAKING_OFF, FLYING, LANDING = "ground", "taking_off", "flying", "landing"

    def __init__(self, drone_id: int, pose: Pose, params: TelloParams, clock_now) -> None:
        self.id = drone_id
        self.pose = pose
        self.p = params
        self.now = clock_now
        self.phase = self.GROUND
        self.battery = params.battery_pct
        self.v = np.zeros(4)  # actual body velocity
        self._v_target = np.zeros(4)
        self._queue: deque[tuple[float, tuple[int, int, int, int]]] = deque()
        self.last_command_t = -math.inf
        self.rc_log: list[tuple[float, tuple[int, int, int, int]]] = []
        self.events: list[Event] = []  # source lab, on the world's virtual clock (s)
        self.connected = False

    # ---- hal.Drone ------------------------------------------------------------------------------
    def connect(self) -> None:
        self.connected = True

    def takeoff(self) -> None:
        """Starts the climb; state().flying becomes true at the takeoff height."""
        if self.phase == self.GROUND:
            self.phase = self.TAKING_OFF
            self.last_command_t = self.now()

    def land(self) -> None:
        if self.phase in (self.FLYING, self.TAKING_OFF):
            self.phase = self.LANDING
            self._queue.clear()

    def emergency_stop(self) -> None:
        self.phase = self.GROUND  # motors off: it drops (no crash model)
        self.pose = Pose(np.array([self.pose.p[0], self.pose.p[1], 0.0]), self.pose.theta)
        self.v[:] = 0.0

    def send_body_velocity(self, V: np.ndarray) -> None:
        rc = velocity_to_rc(V, self.p.cmd_gains)
        t = self.now()
        self._queue.append((t + self.p.latency_s, rc))
        self.rc_log.append((t, rc))
        self.last_command_t = t

    def state(self) -> DroneState:
        return DroneState(
            self.battery, float(self.pose.p[2]), self.connected, self.phase == self.FLYING, self.phase
        )

    def close(self) -> None:
        self.land()

    # ---- physics ----------------------------------------------------------------------------------
    def step(self, t: float, dt: float) -> None:
        """Advance dt seconds ending at t (deliver due commands, first-order response, phases)."""
        while self._queue and self._queue[0][0] <= t:
            rc = self._queue.popleft()[1]
            v = rc_to_velocity(rc, self.p.true_gains)
            sp = math.hypot(v[0], v[1])
            if sp > self.p.max_speed_xy:
                v[:2] *= self.p.max_speed_xy / sp
            v[2] = float(np.clip(v[2], -self.p.max_speed_z, self.p.max_speed_z))
            v[3] = float(np.clip(v[3], -self.p.max_yaw_rate, self.p.max_yaw_rate))
            self._v_target = v
        airborne = self.phase != self.GROUND
        if self.phase == self.FLYING:
            if t - self.last_command_t > self.p.auto_land_s:
                self.events.append(Event(t, self.id, "auto_land_no_command", source="lab"))
                self.phase = self.LANDING
            elif self.battery <= 0.0:
                self.events.append(Event(t, self.id, "battery_empty", source="lab"))
                self.phase = self.LANDING
        if self.phase == self.FLYING:
            a = 1.0 - math.exp(-dt / self.p.time_constant_s)
            self.v += a * (self._v_target - self.v)
        elif self.phase == self.TAKING_OFF:
            self.v = np.array([0.0, 0.0, self.p.climb_rate, 0.0])
        elif self.phase == self.LANDING:
            self.v = np.array([0.0, 0.0, -self.p.descent_rate, 0.0])
        else:
            self.v = np.zeros(4)
        if airborne:
            self.pose = integrate_body_velocity(self.pose, self.v, dt)
            self.battery = max(0.0, self.battery - self.p.battery_drain_pct_per_s * dt)
        z = float(self.pose.p[2])
        if self.phase == self.TAKING_OFF and z >= self.p.takeoff_height_m:
            self.phase = self.FLYING
            self.v = np.zeros(4)
            self._v_target = np.zeros(4)
        if self.phase == self.LANDING and z <= 0.0:
            self.phase = self.GROUND
        if z < 0.0:
            self.pose = Pose(np.array([self.pose.p[0], self.pose.p[1], 0.0]), self.pose.theta)


@dataclass(frozen=True)
class RobotParams:
    time_constant_s: float = 0.2
    max_speed: float = 0.5  # m/s
    max_yaw_rate: float = 1.0  # rad/s
    command_timeout_s: float = 3.0  # stops without a fresh command (ArduPilot Rover behaviour)


class ScamperSim:
    """A holonomic ground robot (hal.GroundRobot) commanded by body velocity [v_x, v_y, 0, ω]."""

    def __init__(self, pose: Pose, params: RobotParams, clock_now) -> None:
        self.pose = pose
        self.p = params
        self.now = clock_now
        self.v = np.zeros(4)
        self._cmd = np.zeros(4)
        self._cmd_t = -math.inf

    def send_body_velocity(self, V: np.ndarray) -> None:
        V = np.nan_to_num(np.asarray(V, dtype=float))
        sp = math.hypot(V[0], V[1])
        if sp > self.p.max_speed:
            V[:2] *= self.p.max_speed / sp
        V[2] = 0.0
        V[3] = float(np.clip(V[3], -self.p.max_yaw_rate, self.p.max_yaw_rate))
        self._cmd, self._cmd_t = V, self.now()

    def stop(self) -> None:
        self._cmd = np.zeros(4)

    def step(self, t: float, dt: float) -> None:
        target = self._cmd if t - self._cmd_t <= self.p.command_timeout_s else np.zeros(4)
        self.v += (1.0 - math.exp(-dt / self.p.time_constant_s)) * (target - self.v)
        self.pose = integrate_body_velocity(self.pose, self.v, dt)


@dataclass(frozen=True)
class MocapParams:
    rate_hz: float = 120.0
    noise_pos_m: float = 0.0005
    noise_yaw_rad: float = 0.002
    dropout_prob: float = 0.0  # probability that a body is missing from a frame


class MocapSim:
    """Motion capture (hal.PoseSource): truth sampled at rate_hz, Gaussian noise, random dropouts."""

    def __init__(self, params: MocapParams, rng: np.random.Generator) -> None:
        self.p = params
        self.rng = rng
        self._latest: dict[str, StampedPose] = {}
        self._next_t = 0.0
        self.frames = 0
        self.dropped = 0

    def capture(self, t: float, bodies: dict[str, Pose]) -> None:
        """Called by the world after each step; takes a frame whenever a sample time has passed."""
        if t + 1e-12 < self._next_t:
            return
        self._next_t += 1.0 / self.p.rate_hz * max(1, math.floor((t - self._next_t) * self.p.rate_hz) + 1)
        self.frames += 1
        for name, g in bodies.items():
            if self.p.dropout_prob > 0 and self.rng.random() < self.p.dropout_prob:
                self.dropped += 1
                continue
            noisy = Pose.make(
                g.p + self.rng.normal(0.0, self.p.noise_pos_m, 3),
                g.theta + self.rng.normal(0.0, self.p.noise_yaw_rad),
            )
            self._latest[name] = StampedPose(t, noisy)

    def latest(self, body: str) -> StampedPose | None:
        return self._latest.get(body)


MOUNTS = CAMERA_MOUNTS


class RenderedCamera:
    """hal.Camera that renders the target's markers as seen by a drone's camera (image only)."""

    def __init__(
        self,
        world: LabWorld,
        drone_id: int,
        cal: CameraCalibration,
        R_ic: np.ndarray,
        t_ic: np.ndarray,
        P0: np.ndarray,
        render_opts,
        rng: np.random.Generator,
    ) -> None:
        self.world, self.id, self.cal = world, drone_id, cal
        self.R_ic, self.t_ic, self.P0 = R_ic, t_ic, P0
        self.opts, self.rng = render_opts, rng
        self.frames = 0

    def latest(self) -> Frame:
        from flightstack.sim_backend.render import markers_in_camera, render_markers

        g_i0 = relative(self.world.drones[self.id].pose, self.world.robot.pose)
        centres_c, normal_c = markers_in_camera(g_i0, self.P0, self.R_ic, self.t_ic)
        image, _, _ = render_markers(self.cal, centres_c, normal_c, self.opts, self.rng)
        self.frames += 1
        return Frame(self.world.t, image, None)


class LabWorld:
    """Truth of the lab simulation, advanced in steps of at most world_dt by the virtual clock."""

    def __init__(self, robot: ScamperSim, drones: dict[int, TelloSim], mocap: MocapSim) -> None:
        self.t = 0.0
        self.robot = robot
        self.drones = drones
        self.mocap = mocap

    def step(self, dt: float) -> None:
        t = self.t + dt
        self.robot.step(t, dt)
        for d in self.drones.values():
            d.step(t, dt)
        self.t = t
        bodies = {f"drone{i}": d.pose for i, d in self.drones.items()}
        bodies["target"] = self.robot.pose
        self.mocap.capture(t, bodies)

    def target_pose(self) -> Pose:
        return self.robot.pose


def camera_extrinsic(mount: str, offset: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(R_ic, t_ic) of a named mount with an offset (m) in the drone body frame."""
    if mount not in MOUNTS:
        raise ValueError(f"unknown camera mount {mount!r}; known: {', '.join(MOUNTS)}")
    return MOUNTS[mount].copy(), np.array(offset, dtype=float)
