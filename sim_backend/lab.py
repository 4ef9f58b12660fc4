"""Simulated lab of the paper's experiment (Sec. 6): Tello-like drones, motion capture, a Scamper-like
ground robot and rendered cameras, each behind the flightstack.hal Protocols.

Frames: Σw is the motion-capture frame, z up. Drones and robot have yaw-only poses (the Tello's tilt while
accelerating is not modelled: the camera stays level). Drone body frame FLU (x forward, y left, z up).
Time: the world's virtual clock (seconds); models advance in `LabWorld.step`. Links (the rig's `links:`,
flightstack.config.links) make rc commands take effect late, camera frames arrive late (rendered at their
capture time, stamped with it), motion-capture samples and the drones' telemetry arrive late and the robot
acts on its commands late, each drawn from its own seeded generator; a link that is neither late nor lossy
draws nothing. (The bus between agents is delayed on the same clock: build_lab.LabSimBackend.delay_bus.)
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np

from flightstack.config.links import LinkDelays, LinkSpec
from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.drivers.tello.config import TELLO_OWN_TIMEOUT_S
from flightstack.drivers.tello.rc import RcGains, rc_to_velocity, velocity_to_rc
from flightstack.events import Event
from flightstack.hal import TARGET_BODY, DroneIdentity, DroneState, Frame, StampedPose
from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose, relative
from flightstack.vision.camera_file import CameraCalibration


@dataclass(frozen=True)
class TelloParams:
    """Physics of the simulated Tello (the truth) and the driver-side rc mapping (the calibration)."""

    true_gains: RcGains = field(default_factory=RcGains)  # what one rc unit really does
    cmd_gains: RcGains = field(default_factory=RcGains)  # what the driver believes (mission calibration)
    time_constant_s: float = 0.25  # first-order velocity response
    max_speed_xy: float = 1.0  # m/s
    max_speed_z: float = 0.5
    max_yaw_rate: float = 1.75  # rad/s
    takeoff_height_m: float = 1.0
    climb_rate: float = 0.5  # m/s during takeoff
    descent_rate: float = 0.4  # m/s during landing
    battery_pct: float = 90.0
    battery_drain_pct_per_s: float = 0.12  # ~12 min of flight from full
    auto_land_s: float = TELLO_OWN_TIMEOUT_S  # the real Tello lands by itself without a command


T = TypeVar("T")

RC_LINK = LinkSpec(latency_s=0.05)
"""A command's delay when none is given: the `perfect` profile's."""

UNKNOWN_STATE = DroneState(math.nan, 0.0, False, False, "unknown")
"""What a drone's telemetry says before its first sample has arrived (no link yet, phase unknown)."""


class LateSamples(Generic[T]):
    """Samples of a device taken on the world's clock and seen through a link (LinkDelays): each taken at
    most rate_hz times per second (None: every time one is offered), late by link.delay(), lost with the
    link's loss; `newest(now)` is the newest sample (by the time it was taken) that has arrived by `now`
    (s). Jitter may reorder arrivals: an older sample arriving after a newer one is never shown."""

    def __init__(self, link: LinkDelays) -> None:
        self.link = link
        self._next_t = -math.inf  # the earliest time (s) of the next sample
        self._pending: deque[tuple[float, float, T]] = deque()  # (arrival, taken, value)
        self._shown: tuple[float, T] | None = None  # (taken, value)

    def offer(self, t: float, value: T) -> None:
        """The device's value at time t (s): taken when a sample is due, then lost or sent on its way."""
        rate = self.link.spec.rate_hz
        if t + 1e-12 < self._next_t:
            return
        if rate is not None:
            self._next_t = (math.floor(t * rate + 1e-9) + 1) / rate
        if not self.link.lost():
            self._pending.append((t + self.link.delay(), t, value))

    def newest(self, now: float) -> tuple[float, T] | None:
        """(taken, value) of the newest sample arrived by `now` (s), None before the first."""
        keep: deque[tuple[float, float, T]] = deque()
        for arrival, taken, value in self._pending:
            if arrival > now:
                keep.append((arrival, taken, value))
            elif self._shown is None or taken > self._shown[0]:
                self._shown = (taken, value)
        self._pending = keep
        return self._shown


class PoseState:
    """A simulated body's pose, kept as the vector [x, y, z, θ] (m, rad) the kernels integrate: a Pose
    object is made only when `pose` is read (the world steps every 5 ms; its pose is read far less often).
    The numbers are those of integrating Poses (geometry.integrate_body_velocity) step by step."""

    def __init__(self, pose: Pose) -> None:
        self._g = np.empty(4)
        self._next = np.empty(4)
        self._pose: Pose | None = None
        self.set(pose)

    @property
    def pose(self) -> Pose:
        if self._pose is None:
            g = self._g
            self._pose = Pose(g[:3].copy(), float(g[3]))
        return self._pose

    def set(self, pose: Pose) -> None:
        self._g[:3] = pose.p
        self._g[3] = pose.theta
        self._pose = pose

    def copy_to(self, out: np.ndarray) -> None:
        """Write [x, y, z, θ] (m, rad) into out (4,)."""
        out[:] = self._g

    @property
    def z(self) -> float:
        """Height (m)."""
        return float(self._g[2])

    def integrate(self, V: np.ndarray, dt: float) -> None:
        """Move with body velocity V (float64 (4,), m/s and rad/s) held for dt seconds."""
        kern.integrate4(self._g, V, dt, self._next)
        self._g, self._next = self._next, self._g
        self._pose = None

    def lag_integrate(self, V: np.ndarray, V_target: np.ndarray, a: float, dt: float) -> None:
        """V += a (V_target − V) in place (first-order lag, a = 1 − exp(−dt/τ)), then `integrate`(V, dt)."""
        kern.lag_integrate4(self._g, V, V_target, a, dt, self._next)
        self._g, self._next = self._next, self._g
        self._pose = None


def _clip(x: float, limit: float) -> float:
    """x clipped to [−limit, limit] (np.clip's result for a float)."""
    return min(max(x, -limit), limit)


class TelloSim:
    """A Tello-like drone (hal.Drone, hal.HoldsLastCommand). Commands arrive as the integer rc values the
    real driver sends."""

    GROUND, TAKING_OFF, FLYING, LANDING = "ground", "taking_off", "flying", "landing"

    def __init__(
        self,
        drone_id: int,
        pose: Pose,
        params: TelloParams,
        clock_now,
        rc_link: LinkDelays | None = None,
        state_link: LinkDelays | None = None,
    ) -> None:
        """rc_link: how late (and lossy) each rc command is (default RC_LINK). state_link: the telemetry
        `state()` reports, sampled after each world step (None or perfect: the present)."""
        self.id = drone_id
        self.rc_link = rc_link if rc_link is not None else LinkDelays(RC_LINK)
        self.telemetry: LateSamples[DroneState] | None = (
            None if state_link is None or state_link.spec.perfect else LateSamples(state_link)
        )
        self.body = PoseState(pose)
        self.p = params
        self.now = clock_now
        self.phase = self.GROUND
        self.battery = params.battery_pct
        self.v = np.zeros(4)  # actual body velocity
        self._v_target = np.zeros(4)
        self._queue: list[tuple[float, int, tuple[int, int, int, int]]] = []  # (arrival, seq, rc)
        self._seq = 0
        self.last_command_t = -math.inf
        self.rc_log: list[tuple[float, tuple[int, int, int, int]]] = []
        self.events: list[Event] = []  # source lab, on the world's virtual clock (s)
        self.connected = False

    @property
    def pose(self) -> Pose:
        """The true pose in Σw."""
        return self.body.pose

    @pose.setter
    def pose(self, pose: Pose) -> None:
        self.body.set(pose)

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
        self.rc_log.append((t, rc))
        if self.rc_link.lost():  # the drone never hears it: its auto-land timer is not reset either
            return
        self._seq += 1  # arrivals in order of arrival; a later command can overtake with jitter
        bisect.insort(self._queue, (t + self.rc_link.delay(), self._seq, rc))
        self.last_command_t = t

    @property
    def own_timeout_s(self) -> float:
        """How long it flies its last rc on by itself (s; `TelloParams.auto_land_s`)."""
        return self.p.auto_land_s

    def state(self) -> DroneState:
        """The drone's telemetry: the present, or with a state link the newest sample arrived."""
        if self.telemetry is None:
            return self._state_now()
        seen = self.telemetry.newest(self.now())
        return UNKNOWN_STATE if seen is None else seen[1]

    def _state_now(self) -> DroneState:
        return DroneState(self.battery, self.body.z, self.connected, self.phase == self.FLYING, self.phase)

    def close(self) -> None:
        self.land()

    # ---- physics ----------------------------------------------------------------------------------
    def _flying_step(self, t: float, dt: float) -> bool:
        """`step` while flying with nothing to change (no auto-land, battery left, above the floor, no
        telemetry link): the velocity's lag and the pose's step in one kernel call. False (nothing done)
        otherwise."""
        p = self.p
        if t - self.last_command_t > p.auto_land_s or self.battery <= 0.0 or self.telemetry is not None:
            return False
        body = self.body
        body.lag_integrate(self.v, self._v_target, 1.0 - math.exp(-dt / p.time_constant_s), dt)
        self.battery = max(0.0, self.battery - p.battery_drain_pct_per_s * dt)
        if body.z < 0.0:
            pose = body.pose
            self.pose = Pose(np.array([pose.p[0], pose.p[1], 0.0]), pose.theta)
        return True

    def step(self, t: float, dt: float) -> None:
        """Advance dt seconds ending at t (deliver due commands, first-order response, phases)."""
        while self._queue and self._queue[0][0] <= t:
            rc = self._queue.pop(0)[2]
            v = rc_to_velocity(rc, self.p.true_gains)
            sp = math.hypot(v[0], v[1])
            if sp > self.p.max_speed_xy:
                v[:2] *= self.p.max_speed_xy / sp
            v[2] = _clip(float(v[2]), self.p.max_speed_z)
            v[3] = _clip(float(v[3]), self.p.max_yaw_rate)
            self._v_target = v
        if self.phase == self.FLYING and self._flying_step(t, dt):
            return
        airborne = self.phase != self.GROUND
        if self.phase == self.FLYING:
            if t - self.last_command_t > self.p.auto_land_s:
                self.events.append(Event(t, self.id, "auto_land_no_command", source="lab"))
                self.phase = self.LANDING
            elif self.battery <= 0.0:
                self.events.append(Event(t, self.id, "battery_empty", source="lab"))
                self.phase = self.LANDING
        if self.phase == self.FLYING:  # v += a (v_target − v), then the pose moves with v
            self.body.lag_integrate(self.v, self._v_target, 1.0 - math.exp(-dt / self.p.time_constant_s), dt)
        else:
            if self.phase == self.TAKING_OFF:
                self.v = np.array([0.0, 0.0, self.p.climb_rate, 0.0])
            elif self.phase == self.LANDING:
                self.v = np.array([0.0, 0.0, -self.p.descent_rate, 0.0])
            else:
                self.v = np.zeros(4)
            if airborne:
                self.body.integrate(self.v, dt)
        if airborne:
            self.battery = max(0.0, self.battery - self.p.battery_drain_pct_per_s * dt)
        z = self.body.z
        if self.phase == self.TAKING_OFF and z >= self.p.takeoff_height_m:
            self.phase = self.FLYING
            self.v = np.zeros(4)
            self._v_target = np.zeros(4)
        if self.phase == self.LANDING and z <= 0.0:
            self.phase = self.GROUND
        if z < 0.0:
            self.pose = Pose(np.array([self.pose.p[0], self.pose.p[1], 0.0]), self.pose.theta)
        if self.telemetry is not None:
            self.telemetry.offer(t, self._state_now())


@dataclass(frozen=True)
class RobotParams:
    time_constant_s: float = 0.2
    max_speed: float = 0.5  # m/s
    max_yaw_rate: float = 1.0  # rad/s
    command_timeout_s: float = 3.0  # stops without a fresh command (ArduPilot Rover behaviour)
    kinematics: str = "omni"  # flightstack.paper.target_law.KINEMATICS
    min_turn_radius_m: float = 0.0  # m, ackermann only


_STILL = np.zeros(4)
"""The robot's target velocity without a fresh command (read only)."""


class ScamperSim:
    """A ground robot (hal.GroundRobot) commanded by body velocity [v_x, v_y, 0, ω].

    `omni`: it follows [v_x, v_y, ω] (speed clamped). `differential`/`ackermann` (params.kinematics): it
    never moves sideways; a set-point is taken as ArduPilot Rover takes one with velocity and yaw rate
    (`GCS_MAVLINK_Rover::handle_set_position_target_local_ned`, Rover/GCS_MAVLink_Rover.cpp): forward
    speed sign(v_x)·|(v_x, v_y)| at turn rate ω; an Ackermann robot's turn rate is further limited to
    |v| / min_turn_radius_m (it cannot turn tighter, nor in place).

    With a `link` (the rig's `robot` link, not perfect) each command is acted on link.delay() s after it
    was sent, in order of arrival (jitter may let a later one overtake), or never when lost; the command
    timeout counts from the arrival. `stop()` acts at once (as `land` does on the drone)."""

    def __init__(self, pose: Pose, params: RobotParams, clock_now, link: LinkDelays | None = None) -> None:
        self.body = PoseState(pose)
        self.p = params
        self.now = clock_now
        self.link = None if link is None or link.spec.perfect else link
        self.v = np.zeros(4)
        self._cmd = np.zeros(4)
        self._cmd_t = -math.inf
        self._queue: list[tuple[float, int, np.ndarray]] = []  # (arrival, seq, command) on their way
        self._seq = 0

    @property
    def pose(self) -> Pose:
        """The true pose in Σw."""
        return self.body.pose

    @pose.setter
    def pose(self, pose: Pose) -> None:
        self.body.set(pose)

    def send_body_velocity(self, V: np.ndarray) -> None:
        V = np.nan_to_num(np.asarray(V, dtype=float))
        if self.p.kinematics != "omni":
            V[0], V[1] = math.copysign(math.hypot(V[0], V[1]), V[0]), 0.0
        sp = math.hypot(V[0], V[1])
        if sp > self.p.max_speed:
            V[:2] *= self.p.max_speed / sp
        V[2] = 0.0
        V[3] = _clip(float(V[3]), self.p.max_yaw_rate)
        if self.p.kinematics == "ackermann":
            V[3] = _clip(float(V[3]), abs(float(V[0])) / self.p.min_turn_radius_m)
        if self.link is None:
            self._cmd, self._cmd_t = V, self.now()
        elif not self.link.lost():
            self._seq += 1
            bisect.insort(self._queue, (self.now() + self.link.delay(), self._seq, V))

    def stop(self) -> None:
        self._cmd = np.zeros(4)
        self._queue.clear()

    def step(self, t: float, dt: float) -> None:
        while self._queue and self._queue[0][0] <= t:
            arrival, _, self._cmd = self._queue.pop(0)
            self._cmd_t = arrival
        target = self._cmd if t - self._cmd_t <= self.p.command_timeout_s else _STILL
        self.body.lag_integrate(self.v, target, 1.0 - math.exp(-dt / self.p.time_constant_s), dt)


@dataclass(frozen=True)
class MocapParams:
    rate_hz: float = 120.0
    noise_pos_m: float = 0.0005
    noise_yaw_rad: float = 0.002
    dropout_prob: float = 0.0  # probability that a body is missing from a frame


class NormalStream:
    """The standard normals of a generator, drawn in blocks and handed out in order: the very numbers
    (bit for bit) that drawing them one call at a time would give (numpy's Generator draws each normal on
    its own from the bit stream), for a fraction of the calls' cost. Only for a generator nothing else
    draws from: it runs ahead of what has been handed out."""

    BLOCK = 4096

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self._block = np.empty(0)
        self._at = 0

    def take(self, n: int) -> tuple[np.ndarray, int]:
        """(block, offset): the next n normals are block[offset : offset + n]."""
        if self._at + n > self._block.size:
            rest = self._block[self._at :]
            self._block = np.concatenate((rest, self.rng.standard_normal(max(n, self.BLOCK))))
            self._at = 0
        at = self._at
        self._at += n
        return self._block, at


class MocapSim:
    """Motion capture (hal.PoseSource): truth sampled at rate_hz, Gaussian noise, random dropouts; with
    a late `link`, each sample becomes visible link.delay() after it was taken (stamped when taken).

    Without dropouts the noise is drawn in blocks (NormalStream: the same numbers) and, without a late
    link, a frame's noisy poses are computed only when `latest` asks for them (the world samples at
    120 Hz, the agents read at 20 Hz)."""

    def __init__(
        self,
        params: MocapParams,
        rng: np.random.Generator,
        link: LinkDelays | None = None,
        now: Callable[[], float] | None = None,
    ) -> None:
        self.p = params
        self.rng = rng
        self.link = link if link is not None and not link.spec.perfect else None
        self.now = now
        self._pending: deque[tuple[float, str, StampedPose]] = deque()  # (arrival, body, sample)
        self._latest: dict[str, StampedPose] = {}
        self._noise = NormalStream(rng) if params.dropout_prob <= 0 else None
        # the newest frame, not yet read: (t, bodies, their poses (B, 4), normals, offset)
        self._unread: tuple[float, tuple[str, ...], np.ndarray, np.ndarray, int] | None = None
        self._next_t = 0.0
        self.frames = 0
        self.dropped = 0

    def due(self, t: float) -> bool:
        """Whether a frame is taken at time t (s): a sample time has passed."""
        return t + 1e-12 >= self._next_t

    def capture(self, t: float, bodies: dict[str, Pose]) -> None:
        """Called by the world after each step; takes a frame whenever a sample time has passed."""
        if self.due(t):
            G = np.array([(g.p[0], g.p[1], g.p[2], g.theta) for g in bodies.values()], dtype=float)
            self.capture_vectors(t, tuple(bodies), G.reshape(-1, 4))

    def capture_vectors(self, t: float, names: tuple[str, ...], G: np.ndarray) -> None:
        """`capture` of the bodies `names` at the poses G (B, 4) = [x, y, z, θ] (m, rad) in Σw (G is
        kept: pass a fresh array)."""
        if t + 1e-12 < self._next_t:
            return
        self._next_t += 1.0 / self.p.rate_hz * max(1, math.floor((t - self._next_t) * self.p.rate_hz) + 1)
        self.frames += 1
        if self._noise is None:
            self._capture_with_dropouts(t, names, G)
            return
        z, at = self._noise.take(4 * len(names))  # per body: 3 for the position, 1 for the yaw
        if self.link is None:
            self._unread = (t, names, G, z, at)
            return
        for k, name in enumerate(names):
            if not self.link.lost():
                sample = StampedPose(t, self._noisy(G[k], z, at + 4 * k))
                self._pending.append((t + self.link.delay(), name, sample))

    def _noisy(self, g: np.ndarray, z: np.ndarray, at: int) -> Pose:
        """Pose g = [x, y, z, θ] with the noise of normals z[at : at + 4] (0.0 + σ·z: what
        Generator.normal(0.0, σ) gives)."""
        dp = 0.0 + self.p.noise_pos_m * z[at : at + 3]
        return Pose.make(g[:3] + dp, float(g[3]) + (0.0 + self.p.noise_yaw_rad * float(z[at + 3])))

    def _capture_with_dropouts(self, t: float, names: tuple[str, ...], G: np.ndarray) -> None:
        for name, g in zip(names, G, strict=True):
            if self.rng.random() < self.p.dropout_prob:
                self.dropped += 1
                continue
            noisy = Pose.make(
                g[:3] + self.rng.normal(0.0, self.p.noise_pos_m, 3),
                float(g[3]) + self.rng.normal(0.0, self.p.noise_yaw_rad),
            )
            if self.link is None:
                self._latest[name] = StampedPose(t, noisy)
            elif not self.link.lost():
                self._pending.append((t + self.link.delay(), name, StampedPose(t, noisy)))

    def latest(self, body: str) -> StampedPose | None:
        if self._unread is not None:
            t, names, G, z, at = self._unread
            self._unread = None
            for k, name in enumerate(names):
                self._latest[name] = StampedPose(t, self._noisy(G[k], z, at + 4 * k))
        if self.link is not None and self.now is not None:
            now = self.now()
            keep: deque[tuple[float, str, StampedPose]] = deque()
            for arrival, name, sample in self._pending:  # jitter may reorder: the newest stamp wins
                if arrival > now:
                    keep.append((arrival, name, sample))
                elif name not in self._latest or sample.stamp > self._latest[name].stamp:
                    self._latest[name] = sample
            self._pending = keep
        return self._latest.get(body)


MOUNTS = CAMERA_MOUNTS


class RenderedCamera:
    """hal.Camera that renders the target's markers (or its fiducial, over the floor the render options
    name) as seen by a drone's camera (image only; grey for a grey camera).

    Without a video link (or a perfect one) every call renders the present. With one, frames are taken
    at k / rate_hz, each rendered from the world as it was then (LabWorld.history) and stamped with that
    capture time, and arrives link.delay() later unless lost; `latest` is the newest frame arrived (None
    before the first)."""

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
        self.link: LinkDelays | None = None
        self._rate_hz = 30.0
        self._next_k = 0
        self._in_flight: list[tuple[float, float]] = []  # (arrival, capture time) of frames on their way
        self._shown: Frame | None = None
        self.centre_noise_px: float | None = None  # None: images; else features only (centres_only)

    def centres_only(self, noise_px: float) -> None:
        """Give frames without an image: the markers' exact normalised centres (the lab's λ = 1 image
        features) plus Gaussian noise of noise_px pixels (divided by fx, fy), or no features unless every
        disc lies inside the image (its projected centre ± its radius in pixels, a fiducial's corners ±
        its quiet zone, at least 1 pixel from the border, each centre at least 0.05 m in front). Much
        cheaper than rendering and extraction; results differ from theirs within the measurement noise
        (docs/performance.md)."""
        self.centre_noise_px = noise_px

    def delay_frames(self, link: LinkDelays, rate_hz: float) -> None:
        """Take frames at rate_hz (Hz) and deliver them through `link` (the world keeps its history)."""
        self.link, self._rate_hz = link, rate_hz
        self.world.keep_history(link.spec.latency_s + link.spec.jitter_s + 2.0 / rate_hz)

    def latest(self) -> Frame | None:
        if self.link is None:
            return self._render(self.world.t, self.world.drones[self.id].pose, self.world.robot.pose)
        now = self.world.t
        while self._next_k / self._rate_hz <= now + 1e-12:  # frames taken by now, in order
            taken = self._next_k / self._rate_hz
            self._next_k += 1
            if not self.link.lost():
                self._in_flight.append((taken + self.link.delay(), taken))
        arrived = [c for a, c in self._in_flight if a <= now]
        if arrived:
            newest = max(arrived)
            self._in_flight = [(a, c) for a, c in self._in_flight if a > now and c > newest]
            if self._shown is None or newest > self._shown.stamp:
                drone, robot = self.world.poses_at(newest, self.id)
                self._shown = self._render(newest, drone, robot)
        return self._shown

    def _render(self, taken: float, drone: Pose, robot: Pose) -> Frame:
        """The image of the markers seen from `drone` with the robot at `robot`, stamped `taken` (s)."""
        from flightstack.sim_backend.scene.floor import floor_view
        from flightstack.sim_backend.scene.render import (
            marker_centres_in_camera,
            markers_in_camera,
            render_markers_region,
            true_pixels,
        )

        g_i0 = relative(drone, robot)
        if self.centre_noise_px is not None:
            centres_c = marker_centres_in_camera(g_i0, self.P0, self.R_ic, self.t_ic)
            self.frames += 1
            return Frame(taken, None, self._centres(centres_c, self.centre_noise_px))
        centres_c, normal_c = markers_in_camera(g_i0, self.P0, self.R_ic, self.t_ic)
        floor = floor_view(drone, self.R_ic, self.t_ic) if self.opts.floor != "plain" else None
        image, _, _, roi = render_markers_region(self.cal, centres_c, normal_c, self.opts, self.rng, floor)
        self.frames += 1
        return Frame(taken, image, None, roi, truth_px=true_pixels(self.cal, centres_c))

    def _centres(self, centres_c: np.ndarray, noise_px: float) -> np.ndarray | None:
        """(2m,) noisy normalised centres of the markers at centres_c (m, 3) in Σc, or None (centres_only)."""
        import cv2

        from flightstack.sim_backend.scene.render import MIN_IN_VIEW_DEPTH_M

        cal, z = self.cal, centres_c[:, 2]
        z_min = z.min()
        if z_min <= MIN_IN_VIEW_DEPTH_M:
            return None
        px, _ = cv2.projectPoints(centres_c, _ZERO3, _ZERO3, cal.camera_matrix, cal.dist_coeffs)
        px = px.reshape(-1, 2)
        # how far the target's print reaches beyond its points: a disc's radius, a fiducial's quiet zone
        reach_m = self.opts.marker_radius_m if cal.fiducial is None else cal.fiducial.quiet_zone_m
        r_px = max(cal.fx, cal.fy) * reach_m / z_min  # (px)
        lo, hi = px.min(axis=0) - r_px, px.max(axis=0) + r_px
        if lo[0] < 0.5 or lo[1] < 0.5 or hi[0] > cal.width - 1.5 or hi[1] > cal.height - 1.5:
            return None
        xy = centres_c[:, :2] / z[:, None]
        if noise_px > 0:
            xy = xy + self.rng.normal(0.0, noise_px, xy.shape) / np.array([cal.fx, cal.fy])
        return xy.reshape(-1)


_ZERO3 = np.zeros(3)


class LabWorld:
    """Truth of the lab simulation, advanced in steps of at most world_dt by the virtual clock."""

    def __init__(self, robot: ScamperSim, drones: dict[int, TelloSim], mocap: MocapSim) -> None:
        self.t = 0.0
        self.robot = robot
        self.drones = drones
        self.mocap = mocap
        self._horizon_s = 0.0  # how far back `poses_at` must reach (s); 0: no history kept
        self._times: deque[float] = deque()
        self._history: deque[np.ndarray] = deque()  # the bodies' poses (B, 4) at each of _times
        # the bodies, as motion capture names them: the drones (drone<id>), then the target
        self._names = (*(DroneIdentity(i).name for i in drones), TARGET_BODY)
        self._bodies = (*(d.body for d in drones.values()), robot.body)
        self._row = {i: k for k, i in enumerate(drones)}  # drone id -> its row in a snapshot

    def keep_history(self, horizon_s: float) -> None:
        """Keep at least horizon_s (s) of the drones' and the robot's poses for `poses_at`."""
        self._horizon_s = max(self._horizon_s, horizon_s)

    def poses_at(self, t: float, drone_id: int) -> tuple[Pose, Pose]:
        """(drone pose, robot pose) as they were at time t (s): the last world step at or before t."""
        k = bisect.bisect_right(self._times, t) - 1
        if k < 0:
            return self.drones[drone_id].pose, self.robot.pose
        G = self._history[k]
        d = G[self._row[drone_id]]
        return Pose(d[:3].copy(), float(d[3])), Pose(G[-1, :3].copy(), float(G[-1, 3]))

    def _snapshot(self) -> np.ndarray:
        """The bodies' poses now, (B, 4) = [x, y, z, θ] per body in the order of `_names` (a new array)."""
        G = np.empty((len(self._bodies), 4))
        for k, s in enumerate(self._bodies):
            s.copy_to(G[k])
        return G

    def step(self, dt: float) -> None:
        t = self.t + dt
        self.robot.step(t, dt)
        for d in self.drones.values():
            d.step(t, dt)
        self.t = t
        keep, due = self._horizon_s > 0, self.mocap.due(t)
        if not (keep or due):
            return
        G = self._snapshot()  # shared by the history and motion capture: neither writes to it
        if keep:
            self._times.append(t)
            self._history.append(G)
            while self._times and self._times[0] < t - self._horizon_s:
                self._times.popleft()
                self._history.popleft()
        if due:
            self.mocap.capture_vectors(t, self._names, G)

    def target_pose(self) -> Pose:
        return self.robot.pose


def camera_extrinsic(mount: str, offset: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(R_ic, t_ic) of a named mount with an offset (m) in the drone body frame."""
    if mount not in MOUNTS:
        raise ValueError(f"unknown camera mount {mount!r}; known: {', '.join(MOUNTS)}")
    return MOUNTS[mount].copy(), np.array(offset, dtype=float)
