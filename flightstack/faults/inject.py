"""Fault injection by wrapping a backend and a bus (used by `flightstack faults`).

Every wrapper delegates to the real object and changes only what its fault changes, inside a time window
of the mission clock (`backend.clock.now()`, seconds since the backend was built; on `sim_lab` the
drones take off at t = 0 and pursuit starts at t ≈ 2.05 s). Nothing here imports sim_backend/: the
wrapped backend is any hal.Backend with a `clock` (and `truth()` on simulators, passed through).

- `FaultyDrone`: link loss (telemetry frozen with `link_alive=False`, commands dropped, land/takeoff
  raise `LinkLostError` like a driver that gets no reply) and a forced battery level.
- `DropoutPoses`: motion capture returns None (no pose) for some or all bodies.
- `OccludedCamera`: frames are black (nothing visible: the target is occluded).
- `FaultyBus`: a neighbour's messages carry NaN, and/or a foreign mission's messages are injected.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from flightstack.comms.messages import PredictionMessage, encode
from flightstack.events import Event
from flightstack.hal import DroneState, Frame, StampedPose
from flightstack.paper.geometry import Pose

__all__ = [
    "DropoutPoses",
    "FaultSpec",
    "FaultyBackend",
    "FaultyBus",
    "FaultyDrone",
    "LinkLostError",
    "OccludedCamera",
    "Window",
]


class LinkLostError(ConnectionError):
    """A command that needs the drone's reply was sent while its link is down (no reply)."""


@dataclass(frozen=True)
class Window:
    """The half-open interval [start, end) of mission-clock seconds during which a fault is active."""

    start: float
    end: float = math.inf

    def active(self, t: float) -> bool:
        return self.start <= t < self.end


@dataclass(frozen=True)
class FaultSpec:
    """Which faults a `FaultyBackend` injects (all times in mission-clock seconds).

    link_loss: drone id -> window of lost link. battery: drone id -> (from t, battery %), the level the
    drone reports from then on. mocap_dropout: window without motion capture for `mocap_bodies` (None: every
    body). occlusion: window during which every camera sees nothing. mocap_frozen: body -> (from t, from z m
    or None): the body's pose freezes (the same pose under fresh stamps, a stuck capture pipeline) from the
    first sample at or after t whose z is at least the given z. mocap_shifted: body -> (from t, (dx, dy, dz)
    m): the body's pose moved by that offset from t on (a mislabelled or swapped body).
    """

    link_loss: dict[int, Window] = field(default_factory=dict)
    battery: dict[int, tuple[float, float]] = field(default_factory=dict)
    mocap_dropout: Window | None = None
    mocap_bodies: frozenset[str] | None = None
    occlusion: Window | None = None
    mocap_frozen: dict[str, tuple[float, float | None]] = field(default_factory=dict)
    mocap_shifted: dict[str, tuple[float, tuple[float, float, float]]] = field(default_factory=dict)


class FaultyDrone:
    """hal.Drone around another one; link loss and battery faults per `FaultSpec`.

    While the link is down: state() repeats the last telemetry received with `link_alive=False`;
    send_body_velocity is dropped (the drone keeps flying its last command, like a Tello that hears
    nothing); land(), takeoff() and emergency_stop() raise LinkLostError; close() does nothing. Other
    attributes (a simulator's `phase`, `pose`) are read from the wrapped drone.
    """

    def __init__(
        self, inner: Any, now: Callable[[], float], link: Window | None, battery: tuple[float, float] | None
    ) -> None:
        self.inner = inner
        self._now = now
        self._link = link
        self._battery = battery
        self._last_state: DroneState | None = None
        self.dropped_commands = 0
        self.sent: list[tuple[float, np.ndarray]] = []
        """Every velocity command that reached the drone: (mission s, V)."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def link_down(self) -> bool:
        return self._link is not None and self._link.active(self._now())

    def _need_link(self, what: str) -> None:
        if self.link_down():
            raise LinkLostError(f"{what}: no reply, the drone's link is down")

    def connect(self) -> None:
        self._need_link("connect")
        self.inner.connect()

    def takeoff(self) -> None:
        self._need_link("takeoff")
        self.inner.takeoff()

    def land(self) -> None:
        self._need_link("land")
        self.inner.land()

    def emergency_stop(self) -> None:
        self._need_link("emergency")
        self.inner.emergency_stop()

    def sent_after(self, t: float) -> list[tuple[float, np.ndarray]]:
        """The commands that reached the drone at or after mission time t (s)."""
        return [(ts, v) for ts, v in self.sent if ts >= t]

    def send_body_velocity(self, V: np.ndarray) -> None:
        if self.link_down():
            self.dropped_commands += 1
            return
        self.sent.append((self._now(), np.array(V, dtype=float)))
        self.inner.send_body_velocity(V)

    def state(self) -> DroneState:
        if self.link_down():
            last = self._last_state or DroneState(math.nan, math.nan, False, True)
            return replace(last, link_alive=False)
        st = self.inner.state()
        if self._battery is not None and self._now() >= self._battery[0]:
            st = replace(st, battery_pct=float(self._battery[1]))
        self._last_state = st
        return st

    def close(self) -> None:
        if not self.link_down():
            self.inner.close()


class DropoutPoses:
    """hal.PoseSource that returns None for `bodies` (None: all) while `window` is active."""

    def __init__(
        self, inner: Any, now: Callable[[], float], window: Window, bodies: Iterable[str] | None
    ) -> None:
        self.inner = inner
        self._now = now
        self.window = window
        self.bodies = None if bodies is None else frozenset(bodies)
        self.withheld = 0

    def latest(self, body: str) -> StampedPose | None:
        if self.window.active(self._now()) and (self.bodies is None or body in self.bodies):
            self.withheld += 1
            return None
        return self.inner.latest(body)


class LyingPoses:
    """hal.PoseSource whose poses lie from a mission time on, under the fresh stamps of the real samples.

    frozen: body -> (from t s, from z m or None): the pose of the first sample at or after t (and at or
    above that z) repeated in every later one (a stuck capture pipeline). shifted: body -> (from t s,
    (dx, dy, dz) m): every pose from t on moved by that offset (a mislabelled or swapped body). `began`
    holds the mission time (s) each body's lie began."""

    def __init__(
        self,
        inner: Any,
        now: Callable[[], float],
        frozen: dict[str, tuple[float, float | None]],
        shifted: dict[str, tuple[float, tuple[float, float, float]]],
    ) -> None:
        self.inner = inner
        self._now = now
        self.frozen = dict(frozen)
        self.shifted = dict(shifted)
        self.began: dict[str, float] = {}
        self._held: dict[str, Pose] = {}

    def latest(self, body: str) -> StampedPose | None:
        sp = self.inner.latest(body)
        if sp is None:
            return sp
        now = self._now()
        if body in self.frozen and body not in self._held:
            t0, z0 = self.frozen[body]
            if now >= t0 and (z0 is None or sp.pose.p[2] >= z0):
                self._held[body] = sp.pose
                self.began[body] = now
        if body in self._held:
            return StampedPose(sp.stamp, self._held[body])
        if body in self.shifted and now >= self.shifted[body][0]:
            self.began.setdefault(body, now)
            offset = np.asarray(self.shifted[body][1], dtype=float)
            return StampedPose(sp.stamp, Pose(sp.pose.p + offset, sp.pose.theta))
        return sp


class OccludedCamera:
    """hal.Camera whose frames are black (the target is hidden from the camera) while `window` is active."""

    def __init__(self, inner: Any, now: Callable[[], float], window: Window) -> None:
        self.inner = inner
        self._now = now
        self.window = window
        self.occluded_frames = 0

    def latest(self) -> Frame | None:
        frame = self.inner.latest()
        if frame is None or not self.window.active(self._now()):
            return frame
        self.occluded_frames += 1
        image = None if frame.image is None else np.zeros_like(frame.image)
        return Frame(frame.stamp, image, None)


class FaultyBackend:
    """A hal.Backend that wraps another and injects the faults of `spec` (see the module docstring).

    The same wrapper object is returned on every call for a given drone or camera, as the runner expects.
    `truth()` and `clock` are the wrapped backend's. close() closes each drone through its wrapper (a drone
    whose link is down is not reached, as on hardware) and stops the ground robot.
    """

    def __init__(self, inner: Any, spec: FaultSpec, drone_ids: Iterable[int]) -> None:
        self.inner = inner
        self.spec = spec
        self.clock = inner.clock
        self.simulated: bool = inner.simulated
        self.ids = list(drone_ids)
        now = self.clock.now
        self._drones = {
            i: FaultyDrone(inner.drone(i), now, spec.link_loss.get(i), spec.battery.get(i)) for i in self.ids
        }
        src = inner.pose_source()
        lies = spec.mocap_frozen or spec.mocap_shifted
        self._lies = LyingPoses(src, now, spec.mocap_frozen, spec.mocap_shifted) if lies else None
        src = self._lies or src
        self._poses = (
            src
            if spec.mocap_dropout is None
            else DropoutPoses(src, now, spec.mocap_dropout, spec.mocap_bodies)
        )
        self._cams: dict[int, Any] = {}

    def drone(self, drone_id: int) -> FaultyDrone:
        return self._drones[drone_id]

    def camera(self, drone_id: int) -> Any:
        if drone_id not in self._cams:
            cam = self.inner.camera(drone_id)
            occ = self.spec.occlusion
            self._cams[drone_id] = cam if occ is None else OccludedCamera(cam, self.clock.now, occ)
        return self._cams[drone_id]

    def pose_source(self) -> Any:
        return self._poses

    def pose_lies_began(self) -> dict[str, float]:
        """Mission time (s) at which each frozen or shifted body's pose began to lie (FaultSpec)."""
        return {} if self._lies is None else dict(self._lies.began)

    def target(self) -> Any:
        return self.inner.target()

    def truth(self) -> Any:
        return self.inner.truth()

    def heartbeat(self) -> None:
        self.inner.heartbeat()

    def close(self) -> None:
        if not any(d.link_down() for d in self._drones.values()):
            self.inner.close()
            return
        for d in self._drones.values():
            d.close()
        robot = self.inner.target()
        if robot is not None:
            robot.stop()


# ---- the bus ---------------------------------------------------------------------------------------------
_F64 = struct.Struct("<4d")


def nan_bytes(msg: PredictionMessage) -> bytes:
    """`msg` encoded, then its ḡ_w and μ overwritten with NaN (what a broken neighbour would send)."""
    data = bytearray(encode(msg))
    body = len(data) - 16 * 8  # the 16 doubles end the message: ḡ_w (4), μ (4), var (4), prior_var (4)
    _F64.pack_into(data, body, *([math.nan] * 4))
    _F64.pack_into(data, body + 32, *([math.nan] * 4))
    return bytes(data)


def foreign_copy(msg: PredictionMessage, mission: str, shift_m: float = 1.0) -> PredictionMessage:
    """A valid message of another mission: same sender id, much newer seq, ḡ_w shifted by shift_m in x."""
    g = np.array(msg.g_bar_w, dtype=float)
    g[0] += shift_m
    return replace(msg, mission=mission, seq=msg.seq + 100_000, g_bar_w=g)


class FaultyBus:
    """A Bus around another (e.g. InProcBus) that corrupts or adds messages on publish.

    nan_sender / nan_window: that sender's messages published inside the window (by message stamp, s)
    go out with NaN estimate and prediction instead. foreign_mission: every published message is
    preceded by a valid copy from that other mission (same sender id, newer seq, estimate shifted 1 m).
    """

    def __init__(
        self,
        inner: Any,
        *,
        nan_sender: int | None = None,
        nan_window: Window | None = None,
        foreign_mission: str | None = None,
    ) -> None:
        self.inner = inner
        self.nan_sender = nan_sender
        self.nan_window = nan_window or Window(0.0)
        self.foreign_mission = foreign_mission
        self.injected: Counter[str] = Counter()

    @property
    def dropped(self) -> Counter[str]:
        return self.inner.dropped

    def publish(self, msg: PredictionMessage) -> None:
        if self.foreign_mission is not None:
            self.inner.publish_raw(encode(foreign_copy(msg, self.foreign_mission)))
            self.injected["foreign"] += 1
        if msg.sender == self.nan_sender and self.nan_window.active(msg.stamp):
            self.inner.publish_raw(nan_bytes(msg))
            self.injected["nan"] += 1
            return
        self.inner.publish(msg)

    def publish_raw(self, data: bytes) -> None:
        self.inner.publish_raw(data)

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        return self.inner.latest(sender, now, stale_after)

    def wait_alive(self, senders: set[int], timeout_s: float) -> set[int]:
        return self.inner.wait_alive(senders, timeout_s)

    def wait_for_stamp(self, senders: set[int], stamp: float, timeout_s: float) -> set[int]:
        return self.inner.wait_for_stamp(senders, stamp, timeout_s)

    def control_events(self) -> list[Any]:
        return self.inner.control_events()

    def publish_control(self, kind: str, payload: dict[str, Any]) -> None:
        self.inner.publish_control(kind, payload)

    @property
    def presence_events(self) -> list[Event]:
        return self.inner.presence_events

    def close(self) -> None:
        self.inner.close()
