"""Hardware abstraction: one Protocol per hardware role (DESIGN §5).

Both `drivers/` (real hardware) and `sim_backend/` implement these; the agent and runner only see them.
Units: SI, radians. Frames: poses are in the world frame Σw (the motion-capture frame); body
velocities are expressed in the body frame of the robot they command.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from flightstack.paper.geometry import Pose


@runtime_checkable
class Clock(Protocol):
    """Mission time in seconds. The sim clock is virtual: sleep_until integrates the world."""

    def now(self) -> float: ...
    def sleep_until(self, t: float) -> None: ...


class FlightPhase(enum.StrEnum):
    """What a drone is doing, decided from its own telemetry (never from a command reply alone).

    The values are the strings the simulated lab and the served world already use.
    """

    GROUND = "ground"  # on the ground, motors off (never flown, or landed)
    TAKING_OFF = "taking_off"  # takeoff sent or seen, not yet confirmed airborne: no rc, no land
    AIRBORNE = "flying"  # airborne at a stable height: velocity commands are obeyed
    LANDING = "landing"  # land sent and descent seen (or awaited): nothing else is sent
    UNKNOWN = "unknown"  # no telemetry yet


@dataclass(frozen=True)
class DroneState:
    """battery in percent, height in metres above ground, link_alive from the drone's own telemetry.

    A landed drone reports height_m ≥ 0. The ideal simulation has no ground: it reports 0.0 once landed
    and, while flying, its world z (the camera's optical axis there, possibly negative), which is not a
    height to compare with the ground (sim_backend/ideal.py).

    `flying` is True when the drone is airborne and obeys velocity commands (phase AIRBORNE). `phase`
    (a FlightPhase value) says more; when a backend does not give it, it is derived from `flying`:
    AIRBORNE, or UNKNOWN (not flying could be on the ground, taking off or landing).
    """

    battery_pct: float
    height_m: float
    link_alive: bool
    flying: bool
    phase: str = ""

    def __post_init__(self) -> None:
        if not self.phase:
            derived = FlightPhase.AIRBORNE if self.flying else FlightPhase.UNKNOWN
            object.__setattr__(self, "phase", str(derived))


@runtime_checkable
class Drone(Protocol):
    """One drone that flies body-velocity commands V = [v_x, v_y, v_z, ω_z] (m/s, rad/s, body frame)."""

    def connect(self) -> None: ...
    def takeoff(self) -> None: ...
    def land(self) -> None: ...
    def emergency_stop(self) -> None: ...
    def send_body_velocity(self, V: np.ndarray) -> None: ...
    def state(self) -> DroneState: ...
    def close(self) -> None: ...


@runtime_checkable
class HoldsLastCommand(Protocol):
    """A drone that flies its last velocity command on by itself until its own timeout ends it (a Tello
    keeps its last `rc` for `own_timeout_s` = 15 s, then lands): the safety layer bounds its climb so that
    this last command cannot carry it through the fence's ceiling (flightstack.safety.rules.climb_cap)."""

    @property
    def own_timeout_s(self) -> float: ...


@dataclass(frozen=True)
class Frame:
    """A camera sample taken at `stamp` (s, mission clock).

    Either `image` (H × W × 3, RGB uint8; H × W grey uint8 from a grey camera, its calibration's
    `image: grey`) from a real or rendered camera, cut to the calibrated picture, or `features` (2m,) in the
    paper's image-plane units (the ideal camera of the paper's simulation), or both; `features` is None
    when the target is not (fully) visible.
    `roi` (x0, y0, x1, y1), pixels, end exclusive: a simulated camera's promise that no pixel of `image`
    outside it shows a marker (flightstack.vision.markers.extract_markers' `roi`; a fiducial's board lies
    inside it); None: no promise.
    `damaged`, `since_loss`: what a camera whose frames come over a lossy stream knows of this frame's
    integrity (the Tello's H.264: drivers/tello/camera.py); a detection from any frame is checked against
    a prediction before it is used (flightstack.vision.gate).
    """

    stamp: float
    image: np.ndarray | None
    features: np.ndarray | None
    roi: tuple[int, int, int, int] | None = None
    damaged: bool = False
    """Decoded through a detected loss of its stream (concealed by the decoder) and no intact keyframe
    since: it may be smeared. False is no proof: a lost middle datagram of a frame is not detectable."""
    since_loss: int | None = None
    """Frames decoded since the stream's last detected loss (0: this frame's own); None: no loss found
    since the stream (re)started."""
    truth_px: np.ndarray | None = None
    """Simulated cameras only: the true pixels (m, 2) of the target's feature points in this frame, in
    the distorted image, for measuring the detector (never used by the loop); None: unknown."""


@runtime_checkable
class Camera(Protocol):
    """One drone's camera: its newest frame (stamped when it was captured), or None before the first."""

    def latest(self) -> Frame | None: ...


FrameTruth = Callable[[np.ndarray], "np.ndarray | None"]
"""Given a decoded image of an emulated camera, the true pixels (m, 2) of the target's feature points in
it (Frame.truth_px), or None when it cannot tell."""
_FRAME_TRUTH: dict[tuple[str, int], FrameTruth] = {}


def register_frame_truth(host: str, video_port: int, truth: FrameTruth | None) -> None:
    """An emulated camera that streams from `host` to UDP `video_port` says how to know the truth of its
    frames (None: forget it). Measurement only: a camera driver attaches it to its frames' `truth_px`,
    the loop never uses it, and a real lab registers nothing."""
    if truth is None:
        _FRAME_TRUTH.pop((host, int(video_port)), None)
    else:
        _FRAME_TRUTH[(host, int(video_port))] = truth


def frame_truth(host: str, video_port: int) -> FrameTruth | None:
    """What `register_frame_truth` registered for (host, video_port), or None."""
    return _FRAME_TRUTH.get((host, int(video_port)))


@runtime_checkable
class StreamCounting(Protocol):
    """A camera whose frames come over a stream it checks (the Tello's H.264 over UDP): what that stream
    did so far, e.g. frames published, damaged frames dropped, resynchronisations (counts)."""

    def stream_counts(self) -> dict[str, int]: ...


@dataclass(frozen=True)
class StampedPose:
    """A pose in Σw and its stamp (s, on the mission clock; motion capture stamps a pose when its frame was
    received: drivers/mocap.py)."""

    stamp: float
    pose: Pose


TARGET_BODY = "target"
"""The ground robot's body name in a PoseSource (its motion-capture body: hardware.mocap.bodies)."""


@dataclass(frozen=True)
class DroneIdentity:
    """One drone's id and every name derived from it, built once per drone (Mission.identities) and passed
    on: `name`, the drone's name wherever one is needed (its body in a PoseSource, which the lab file maps
    to the motion-capture system's own, hardware.mocap.bodies; its topics and keys in a recording);
    `label`, its device label in the emulated lab (its network and link logs); `agent`, its participant
    name on the bus (an agent process's key)."""

    id: int

    @property
    def name(self) -> str:
        return f"drone{self.id}"

    @property
    def label(self) -> str:
        return f"tello{self.id}"

    @property
    def agent(self) -> str:
        return str(self.id)


@runtime_checkable
class PoseSource(Protocol):
    """Latest pose of a named rigid body (motion capture; sim: truth + noise); None if never seen."""

    def latest(self, body: str) -> StampedPose | None: ...


@runtime_checkable
class GroundRobot(Protocol):
    """The pursued ground robot (Scamper), commanded by body velocity [v_x, v_y, 0, ω_z]."""

    def send_body_velocity(self, V: np.ndarray) -> None: ...
    def stop(self) -> None: ...


@runtime_checkable
class ReportsState(Protocol):
    """A device that says in one line what its own telemetry last reported (the robot: its heartbeat's
    mode, armed flag and age, and what it changed on its own), for messages about what it did."""

    def state_line(self) -> str: ...


@runtime_checkable
class Backend(Protocol):
    """Builds the hardware (or simulated) devices of a mission and owns the clock.

    simulated: True when the clock is virtual (the world advances only while the runner sleeps on it), so
    after close() the runner keeps the clock going until every drone's own state says GROUND; False on
    hardware (real time; closing the drivers lands the drones).
    """

    simulated: bool

    @property
    def clock(self) -> Clock: ...  # read-only: a backend's own clock type (VirtualClock, WallClock) is one
    def drone(self, drone_id: int) -> Drone: ...
    def camera(self, drone_id: int) -> Camera: ...
    def pose_source(self) -> PoseSource: ...
    def target(self) -> GroundRobot | None: ...

    def truth(self) -> tuple[Pose, dict[int, Pose]]:
        """(g_w0, {id: g_wi}) in Σw now, for metrics and the recording, never for control: the simulator's
        truth, or on hardware the newest motion-capture poses."""
        ...

    def heartbeat(self) -> None:
        """Once per control tick: proves the loop alive to a watchdog (the guardian process on hardware;
        a no-op in simulation). Raises when the watchdog has taken over (the run must land)."""
        ...

    def close(self) -> None: ...
