"""The real lab's devices (`hardware:` of a lab rig file; backend `tello`): Tellos, motion capture, the
ground robot, the topology. Used by flightstack.config.mission."""

from __future__ import annotations

import math
import re
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, model_validator

from flightstack.config.tello_video import TelloVideoSpec, video_settings
from flightstack.config.types import Positive
from flightstack.config.types import Strict as _Strict
from flightstack.drivers.tello.sdk_video import VideoSetting

MOCAP_SYSTEMS = ("mock", "vicon", "optitrack", "qualisys", "vrpn")


def _body_name(name: str) -> str:
    """A rigid body's name as the mocap software spells it: not empty, not only blanks."""
    if not name.strip():
        raise ValueError(f"{name!r}: a rigid body's name in the motion-capture software, not empty or blank")
    return name


BodyName = Annotated[str, AfterValidator(_body_name)]
INTERFACE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,14}")


def _interface_name(name: str) -> str:
    """A Linux network interface's name as `ip link` lists it: 1 to 15 letters, digits, `_`, `.`, `-`."""
    if not INTERFACE_NAME.fullmatch(name):
        raise ValueError(
            f"{name!r}: a network interface's name as `ip link` lists it (1 to 15 letters, digits, _ . -)"
        )
    return name


InterfaceName = Annotated[str, AfterValidator(_interface_name)]


class TelloHardwareSpec(_Strict):
    """One real Tello (backend `tello`). `ip`: its address (192.168.10.1 in access-point mode; the
    router's lease in station mode). Ports: 8889 (commands) on a real drone; `video_port` is where it
    streams on this computer (station mode with several drones: one port each, needs SDK 3.0).
    `loop_hover_s`/`loop_land_s`: the driver's loop watchdog: a control loop silent this long (s) makes
    the drone hover, then land by itself (docs/safety.md). `video`: this drone's SDK 3.0 video settings,
    over the lab's `hardware.video` key by key (flightstack.config.tello_video). `interface`: the network
    interface of this computer the drone is reached through (e.g. the Wi-Fi adapter joined to its access
    point); every socket that talks to it is bound to it (drivers/netif.py). None: the routing table's
    choice."""

    id: int = Field(ge=0, lt=2**16)
    ip: str = Field(pattern=r"^\d{1,3}\.\d{1,3}\.\d{1,3}\.\d{1,3}$")
    control_port: int = Field(default=8889, ge=1, le=65535)
    video_port: int = Field(default=11111, ge=1, le=65535)
    connect_timeout_s: Positive = 5.0
    command_timeout_s: Positive = 3.0
    link_timeout_s: Positive = 1.0
    keepalive_s: Annotated[float, Field(gt=0, lt=15)] = 5.0
    loop_hover_s: Annotated[float, Field(gt=0, lt=15)] = 0.5
    loop_land_s: Annotated[float, Field(gt=0, lt=15)] = 2.0
    max_temperature_c: Positive = 85.0
    frame_timeout_s: Positive = 5.0
    video: TelloVideoSpec | None = None
    interface: InterfaceName | None = None

    @model_validator(mode="after")
    def _loop_watchdog_order(self) -> TelloHardwareSpec:
        if not self.loop_hover_s < self.loop_land_s:
            raise ValueError(
                f"loop_hover_s ({self.loop_hover_s} s) must be below loop_land_s ({self.loop_land_s} s)"
            )
        return self


class MocapHardwareSpec(_Strict):
    """Motion capture through libmotioncapture (`drivers/mocap.py`). `system: mock` with
    settings.rigid_bodies is the bench option (fixed bodies, no server). `bodies` maps flightstack's
    body names (`drone<ID>`, `target`) to the names of the rigid bodies in the mocap software (not empty
    or blank); a name not listed is looked up as is."""

    system: Literal["mock", "vicon", "optitrack", "qualisys", "vrpn"]
    settings: dict[str, str] = Field(default_factory=dict)
    bodies: dict[str, BodyName] = Field(default_factory=dict)
    connect_timeout_s: Positive = 5.0
    stale_after_s: Positive = 0.1
    max_tilt_rad: Annotated[float, Field(gt=0, le=math.pi / 2)] = 0.35


class TargetHardwareSpec(_Strict):
    """The ground robot over MAVLink (`drivers/scamper/driver.py`); `url` is a pymavlink connection string.
    `origin_*`: the EKF origin the driver sets (WGS84 degrees, m above MSL; docs/drivers.md "Ground
    robot"); `vision_hz`, `vision_max_age_s`: the motion-capture pose sent as external navigation."""

    url: str = Field(min_length=1)
    heartbeat_timeout_s: Positive = 5.0
    ack_timeout_s: Positive = 2.0
    stream_hz: Annotated[float, Field(ge=1, le=100)] = 10.0
    link_timeout_s: Positive = 3.0
    origin_lat_deg: Annotated[float, Field(ge=-90, le=90)] = 52.0
    origin_lon_deg: Annotated[float, Field(ge=-180, le=180)] = 4.0
    origin_alt_m: Annotated[float, Field(ge=-1000, le=10000)] = 0.0
    origin_timeout_s: Positive = 5.0
    vision_hz: Annotated[float, Field(ge=4, le=50)] = 20.0
    vision_max_age_s: Annotated[float, Field(gt=0, le=1)] = 0.2


class HardwareSpec(_Strict):
    """The lab (backend `tello`). `target: null` when the robot is driven elsewhere (`flightstack target`
    on another computer, or by hand): the mission then only reads its motion-capture pose.
    `max_frame_age_s`: a camera frame older than this is treated as no frame (stalled video).

    `topology` (docs/real-lab.md): `access_point` (default) — each Tello is its own Wi-Fi
    access point at 192.168.10.1: one computer reaches each through a Wi-Fi adapter of its own
    (`interface:` per drone) and one process flies them all, or one computer per drone runs `flightstack
    agent --id N` and the agents talk over Zenoh on another interface; works with SDK 2.0 and the default
    video port. `station` — every
    Tello joins the lab Wi-Fi, one process may fly them all; several drones' video needs per-drone ports,
    which need SDK 3.0 (preflight checks). `state_port`: the local UDP port the drones' state streams
    arrive at (8890 on real Tellos; the tests use a free one). `video`: SDK 3.0 video settings of every
    drone (`setfps`, `setresolution`, `setbitrate`; flightstack.config.tello_video), sent at connect.

    Interfaces (`drones[].interface`): every drone names the interface it is reached through, or none
    does (a socket bound to no interface holds its port on all of them). Drones behind different
    interfaces may share an address and ports: one computer with one Wi-Fi adapter per access-point Tello
    flies them all from one process (`shared_by`)."""

    topology: Literal["access_point", "station"] = "access_point"
    state_port: int = Field(default=8890, ge=1, le=65535)
    drones: list[TelloHardwareSpec] = Field(min_length=1)
    mocap: MocapHardwareSpec
    target: TargetHardwareSpec | None = None
    max_frame_age_s: Positive = 0.5
    video: TelloVideoSpec | None = None

    @model_validator(mode="after")
    def _unique(self) -> HardwareSpec:
        ids = [d.id for d in self.drones]
        if len(set(ids)) != len(ids):
            raise ValueError("drones: ids must be unique")
        named = [d.interface is not None for d in self.drones]
        if any(named) and not all(named):
            n = named.index(False)
            raise ValueError(
                f"drones.{n}.interface: every drone names the interface it is reached through, or none "
                "does (a socket bound to no interface holds its port on all of them)"
            )
        if self.topology == "station":
            ips = [(d.interface, d.ip, d.control_port) for d in self.drones]
            if len(set(ips)) != len(ips):
                raise ValueError("drones: two drones share an ip and port (station mode: one address each)")
            ports = [(d.interface, d.video_port) for d in self.drones]
            if len(set(ports)) != len(ports):
                raise ValueError("drones: each drone needs its own video_port in station mode")
        return self

    def shared_by(self, drone_ids: list[int]) -> str | None:
        """Why these drones cannot be flown from one process, or None: two of them reached through the
        same interface (or through none) with the same address or video port."""
        ds = [self.drone(i) for i in drone_ids]
        addresses = {(d.interface, d.ip, d.control_port) for d in ds}
        video = {(d.interface, d.video_port) for d in ds}
        if len(addresses) < len(ds) or len(video) < len(ds):
            return (
                f"drones {drone_ids} share an address or video port through one interface ({self.topology} "
                "mode): give each drone its own Wi-Fi adapter (`interface:` in its hardware.drones entry), "
                "or its own computer: `flightstack agent MISSION --id N` (and `preflight --id N`) on each"
            )
        return None

    def drone(self, drone_id: int) -> TelloHardwareSpec:
        return next(d for d in self.drones if d.id == drone_id)

    def video_settings(self, drone_id: int) -> tuple[VideoSetting, ...]:
        """The SDK 3.0 video settings of drone `drone_id`: its own `video` keys over the lab's."""
        return video_settings(self.video, self.drone(drone_id).video, drone_id)

    def body(self, name: str) -> str:
        """The motion-capture name of flightstack body `name` (`drone<ID>` or `target`)."""
        return self.mocap.bodies.get(name, name)
