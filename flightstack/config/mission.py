"""Mission files: one YAML document validated against a strict schema (DESIGN §8).

Unknown keys are errors; every error names the key path (e.g. `drones.1.desired_pose.p`) and the
reason. `load_mission(path)` raises MissionError with all problems listed, nothing half-loaded.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import typing
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import (
    BaseModel,
    Field,
    PrivateAttr,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)

from flightstack.config.bus import BusSpec
from flightstack.config.safe_load import Lines, LoadError, line_of, load_yaml
from flightstack.config.types import Finite, NonNegative, Positive
from flightstack.config.types import Strict as _Strict
from flightstack.paper.fusion import FUSION_RULES
from flightstack.paper.geometry import Pose
from flightstack.safety import SafetyLimits

MODES = ("none", "local", "dgp", "oracle")
MAX_TICKS = 10**7  # ticks of one mode (duration_s / dt_s)

# Camera mounts in the drone's FLU body frame (columns: camera x right, y down, z optical axis).
CAMERA_MOUNTS = {
    "down": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "forward": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}


class MissionError(ValueError):
    """A mission file that cannot be used; the message lists each bad key path and why."""


class PoseSpec(_Strict):
    """A pose (p in metres, theta in radians)."""

    p: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)
    theta: Finite = 0.0

    def pose(self) -> Pose:
        return Pose.make(self.p, self.theta)


class DuffingSpec(_Strict):
    """Coefficients of the paper's Duffing-like target velocity field (Sec. 5)."""

    alpha: Finite = -1.0
    beta: Finite = 1.0
    gamma: Finite = 0.39
    delta: Finite = 0.1
    omega: Finite = 0.4


class SquareSpec(_Strict):
    """The paper's experiment law (eq. scamper_vel): a square lap with one rotation per lap."""

    side_m: Positive = 1.0
    speed_mps: Positive = 0.1
    gain: NonNegative = 0.05


class RobotSpec(_Strict):
    """Simulated ground robot (sim_lab only)."""

    time_constant_s: Positive = 0.2
    max_speed_mps: Positive = 0.5
    max_yaw_rate: Positive = 1.0
    command_timeout_s: Positive = 3.0


class TargetSpec(_Strict):
    motion: Literal["duffing", "square"] = "duffing"
    initial_pose: PoseSpec = PoseSpec(p=(-0.3, -1.0, 0.0), theta=0.0)
    duffing: DuffingSpec = DuffingSpec()
    square: SquareSpec = SquareSpec()
    robot: RobotSpec = RobotSpec()
    feature_points: list[tuple[Finite, Finite, Finite]] = Field(min_length=4)
    substeps: int = Field(default=1, ge=1, le=1000)


class CameraSpec(_Strict):
    focal_length: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0


class DroneCameraSpec(_Strict):
    """A real or rendered camera: calibration file (relative to the mission file), mount, offset (m)."""

    calibration: str
    mount: Literal["down", "forward"] = "down"
    offset: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)


class RcGainsSpec(_Strict):
    """Velocity per Tello rc unit (m/s, rad/s)."""

    xy: Positive = 0.01
    z: Positive = 0.01
    yaw: Positive = 0.0175


class DroneSpec(_Strict):
    id: int = Field(ge=0, lt=2**16)
    desired_pose: PoseSpec
    initial_offset: PoseSpec = PoseSpec()
    initial_estimate_error: PoseSpec = PoseSpec()
    sees_target: bool = True
    camera: DroneCameraSpec | None = None
    rc_gains: RcGainsSpec = RcGainsSpec()

    @field_validator("desired_pose")
    @classmethod
    def _yaw(cls, v: PoseSpec) -> PoseSpec:
        if abs(v.theta) >= math.pi / 2:
            raise ValueError("|theta| must be < pi/2 (Assumption 4 of the paper)")
        return v

    @model_validator(mode="after")
    def _in_front(self) -> DroneSpec:
        if not self.sees_target:
            return self
        if self.camera is None:
            depth = self.desired_pose.p[2]
        else:
            R = CAMERA_MOUNTS[self.camera.mount]
            depth = float((np.array(self.desired_pose.p) - np.array(self.camera.offset)) @ R[:, 2])
        if depth <= 0:
            raise ValueError("desired_pose: the target must be in front of the drone's camera (depth > 0)")
        return self


class GraphSpec(_Strict):
    kind: Literal["complete", "edges"] = "complete"
    edges: list[tuple[int, int]] = Field(default_factory=list)


class GainsSpec(_Strict):
    k_c: Annotated[
        list[Annotated[float, Field(gt=0, allow_inf_nan=False)]], Field(min_length=4, max_length=4)
    ]
    k_e: Annotated[
        list[Annotated[float, Field(gt=0, allow_inf_nan=False)]], Field(min_length=4, max_length=4)
    ]
    k_s: Annotated[float, Field(ge=0, allow_inf_nan=False)]


class RegionsSpec(_Strict):
    """Expert regions: bands of the xy plane along `axis`, split at `edges` (n − 1 increasing values)."""

    axis: Literal["x", "y"] = "x"
    edges: list[Finite]

    @field_validator("edges")
    @classmethod
    def _increasing(cls, v: list[float]) -> list[float]:
        if any(b <= a for a, b in itertools.pairwise(v)):
            raise ValueError("edges must be strictly increasing")
        return v


class GPSpec(_Strict):
    experts_file: str | None = None  # trained experts (flightstack train); None: train on the `none` run
    noise_var: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 0.01
    samples_per_region: int = Field(default=10, ge=2, le=100000)
    regions: RegionsSpec
    restarts: int = Field(default=5, ge=1, le=100)
    fusion: str = "poe"

    @field_validator("fusion")
    @classmethod
    def _rule(cls, v: str) -> str:
        if v not in FUSION_RULES:
            raise ValueError(f"unknown fusion rule {v!r}; valid: {', '.join(FUSION_RULES)}")
        return v


class TelloSimSpec(_Strict):
    """Physics of the simulated Tellos (sim_lab).

    The rc gains here are the truth; drones.N.rc_gains are what the driver believes (its calibration)."""

    true_rc_gains: RcGainsSpec = RcGainsSpec()
    time_constant_s: Positive = 0.25
    latency_s: NonNegative = 0.05
    max_speed_xy: Positive = 1.0
    max_speed_z: Positive = 0.5
    max_yaw_rate: Positive = 1.75
    takeoff_height_m: Positive = 1.0
    battery_pct: Annotated[float, Field(ge=0, le=100)] = 90.0
    battery_drain_pct_per_s: NonNegative = 0.12
    auto_land_s: Positive = 15.0


class MocapSimSpec(_Strict):
    rate_hz: Positive = 120.0
    noise_pos_m: NonNegative = 0.0005
    noise_yaw_rad: NonNegative = 0.002
    dropout_prob: Annotated[float, Field(ge=0, lt=1)] = 0.0


class RenderSpec(_Strict):
    marker_radius_m: Positive = 0.03
    noise_std: NonNegative = 2.0
    blur_px: NonNegative = 0.0


class SimSpec(_Strict):
    """Settings of the simulated lab (backend sim_lab)."""

    world_dt_s: Annotated[float, Field(gt=0, le=0.1)] = 0.005
    tello: TelloSimSpec = TelloSimSpec()
    mocap: MocapSimSpec = MocapSimSpec()
    render: RenderSpec = RenderSpec()


def _safety_spec() -> type[BaseModel]:
    """The `safety:` section: exactly the fields and defaults of flightstack.safety.SafetyLimits (one
    source of truth), plus `enabled`; SafetyLimits' own checks run as the section's validator."""
    hints = typing.get_type_hints(SafetyLimits)
    fields: dict[str, object] = {"enabled": (bool, True)}
    for f in dataclasses.fields(SafetyLimits):
        fields[f.name] = (hints[f.name], f.default)

    def _limits_valid(self: BaseModel) -> BaseModel:
        SafetyLimits(**self.model_dump(exclude={"enabled"}))  # raises ValueError with the reason
        return self

    return create_model(
        "SafetySpec",
        __base__=_Strict,
        __doc__="flightstack.safety.SafetyLimits; `enabled: false` only for the paper's ideal simulation.",
        __validators__={"_limits_valid": model_validator(mode="after")(_limits_valid)},
        **fields,
    )


SafetySpec = _safety_spec()


MOCAP_SYSTEMS = ("mock", "vicon", "optitrack", "qualisys", "vrpn")


class TelloHardwareSpec(_Strict):
    """One real Tello (backend `tello`). `ip`: its address (192.168.10.1 in access-point mode; the
    router's lease in station mode). Ports: 8889 (commands) on a real drone; `video_port` is where it
    streams on this computer (station mode with several drones: one port each, needs SDK 3.0).
    `loop_hover_s`/`loop_land_s`: the driver's loop watchdog: a control loop silent this long (s) makes
    the drone hover, then land by itself (README "Failsafe")."""

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
    body names (`drone<ID>`, `target`) to the names of the rigid bodies in the mocap software; a name
    not listed is looked up as is."""

    system: Literal["mock", "vicon", "optitrack", "qualisys", "vrpn"]
    settings: dict[str, str] = Field(default_factory=dict)
    bodies: dict[str, str] = Field(default_factory=dict)
    connect_timeout_s: Positive = 5.0
    stale_after_s: Positive = 0.1
    max_tilt_rad: Annotated[float, Field(gt=0, le=math.pi / 2)] = 0.35


class TargetHardwareSpec(_Strict):
    """The ground robot over MAVLink (`drivers/scamper.py`); `url` is a pymavlink connection string."""

    url: str = Field(min_length=1)
    heartbeat_timeout_s: Positive = 5.0
    ack_timeout_s: Positive = 2.0
    stream_hz: Annotated[float, Field(ge=1, le=100)] = 10.0
    link_timeout_s: Positive = 3.0


class HardwareSpec(_Strict):
    """The lab (backend `tello`). `target: null` when the robot is driven elsewhere (`flightstack target`
    on another computer, or by hand): the mission then only reads its motion-capture pose.
    `max_frame_age_s`: a camera frame older than this is treated as no frame (stalled video).

    `topology` (README "Flying the real lab"): `access_point` (default) — each Tello is its own Wi-Fi
    access point at 192.168.10.1, one computer per drone runs `flightstack agent --id N`, the agents talk
    over Zenoh on another interface; works with SDK 2.0 and the default video port. `station` — every
    Tello joins the lab Wi-Fi, one process may fly them all; several drones' video needs per-drone ports,
    which need SDK 3.0 (preflight checks). `state_port`: the local UDP port the drones' state streams
    arrive at (8890 on real Tellos; the tests use a free one)."""

    topology: Literal["access_point", "station"] = "access_point"
    state_port: int = Field(default=8890, ge=1, le=65535)
    drones: list[TelloHardwareSpec] = Field(min_length=1)
    mocap: MocapHardwareSpec
    target: TargetHardwareSpec | None = None
    max_frame_age_s: Positive = 0.5

    @model_validator(mode="after")
    def _unique(self) -> HardwareSpec:
        ids = [d.id for d in self.drones]
        if len(set(ids)) != len(ids):
            raise ValueError("drones: ids must be unique")
        if self.topology == "station":
            ips = [(d.ip, d.control_port) for d in self.drones]
            if len(set(ips)) != len(ips):
                raise ValueError("drones: two drones share an ip and port (station mode: one address each)")
            ports = [d.video_port for d in self.drones]
            if len(set(ports)) != len(ports):
                raise ValueError("drones: each drone needs its own video_port in station mode")
        return self

    def shared_by(self, drone_ids: list[int]) -> str | None:
        """Why these drones cannot be flown from one process (same address or video port), or None."""
        ds = [self.drone(i) for i in drone_ids]
        if len({(d.ip, d.control_port) for d in ds}) < len(ds) or len({d.video_port for d in ds}) < len(ds):
            return (
                f"drones {drone_ids} share an address or video port ({self.topology} mode): in "
                "access-point mode each drone needs its own computer; run `flightstack agent MISSION "
                "--id N` (and `preflight --id N`) on each"
            )
        return None

    def drone(self, drone_id: int) -> TelloHardwareSpec:
        return next(d for d in self.drones if d.id == drone_id)

    def body(self, name: str) -> str:
        """The motion-capture name of flightstack body `name` (`drone<ID>` or `target`)."""
        return self.mocap.bodies.get(name, name)


class GainAnalysisSpec(_Strict):
    gamma_sq: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 10.0
    beta: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 2.0
    eta: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.5
    samples: int = Field(default=4000, ge=10, le=10**6)


class Mission(_Strict):
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    description: str = ""
    backend: Literal["sim_ideal", "sim_lab", "tello"] = "sim_ideal"
    seed: int = Field(default=0, ge=0, le=2**32 - 1)  # numpy's generators take 0 .. 2³²−1
    duration_s: Annotated[float, Field(gt=0, le=86400, allow_inf_nan=False)]
    dt_s: Annotated[float, Field(ge=1e-4, le=1.0, allow_inf_nan=False)]  # 0.1 ms .. 1 s
    compare_modes: list[str] = Field(default=["dgp"], min_length=1)
    target: TargetSpec
    camera: CameraSpec = CameraSpec()
    drones: list[DroneSpec] = Field(min_length=1)
    graph: GraphSpec = GraphSpec()
    gains: GainsSpec
    gp: GPSpec
    bus: BusSpec = BusSpec()
    gain_analysis: GainAnalysisSpec = GainAnalysisSpec()
    sim: SimSpec = SimSpec()
    safety: SafetySpec = SafetySpec()  # type: ignore[valid-type]
    hardware: HardwareSpec | None = None
    _base_dir: Path = PrivateAttr(default=Path("."))

    def resolve(self, relative: str) -> Path:
        """A path from the mission file (calibrations, experts) made absolute against its directory."""
        p = Path(relative)
        return p if p.is_absolute() else (self._base_dir / p).resolve()

    @field_validator("compare_modes")
    @classmethod
    def _modes(cls, v: list[str]) -> list[str]:
        for m in v:
            if m not in MODES:
                raise ValueError(f"unknown mode {m!r}; valid: {', '.join(MODES)}")
        if len(set(v)) != len(v):
            raise ValueError("modes must not repeat")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Mission:
        if self.duration_s / self.dt_s > MAX_TICKS:
            raise ValueError(
                f"duration_s / dt_s: {self.duration_s / self.dt_s:.3g} ticks per mode; at most {MAX_TICKS:g} "
                "(the recording holds every tick in memory)"
            )
        ids = [d.id for d in self.drones]
        if len(set(ids)) != len(ids):
            raise ValueError("drones: ids must be unique")
        for a, b in self.graph.edges:
            if a not in ids or b not in ids:
                raise ValueError(f"graph.edges: edge ({a}, {b}) names a drone id that is not in drones")
        if self.graph.kind == "edges" and not self.graph.edges and len(ids) > 1:
            raise ValueError("graph.edges: kind 'edges' needs at least one edge")
        if len(self.gp.regions.edges) != len(self.drones) - 1:
            raise ValueError(
                f"gp.regions.edges: {len(self.drones)} drones need {len(self.drones) - 1} band edges, "
                f"got {len(self.gp.regions.edges)}"
            )
        if not any(d.sees_target for d in self.drones):
            raise ValueError("drones: at least one drone must see the target (Assumption 3)")
        if self.k_c_xy_unequal():
            raise ValueError("gains: k_c and k_e must have equal x and y components")
        if self.backend == "sim_lab":
            if self.target.motion != "square":
                raise ValueError("target.motion: the sim_lab backend drives the robot on the 'square' law")
            for d in self.drones:
                if d.camera is None:
                    raise ValueError(f"drones: drone {d.id} needs a camera (calibration, mount) on sim_lab")
        if self.backend == "tello":
            self._check_hardware(ids)
        elif self.hardware is not None:
            raise ValueError(f"hardware: only used by backend 'tello' (this mission: {self.backend!r})")
        if self.backend == "sim_ideal" and self.target.motion != "duffing":
            raise ValueError("target.motion: the sim_ideal backend implements the 'duffing' field")
        return self

    def _check_hardware(self, ids: list[int]) -> None:
        if self.hardware is None:
            raise ValueError("hardware: backend 'tello' needs a hardware section (drone IPs, mocap, robot)")
        hw_ids = sorted(d.id for d in self.hardware.drones)
        if hw_ids != sorted(ids):
            raise ValueError(f"hardware.drones: ids {hw_ids} must be exactly the drones' ids {sorted(ids)}")
        if self.target.motion != "square":
            raise ValueError("target.motion: real robots are driven on the 'square' law")
        for d in self.drones:
            if d.camera is None:
                raise ValueError(f"drones: drone {d.id} needs a camera (calibration, mount) on real hardware")
        if not self.safety.enabled:
            raise ValueError("safety.enabled: must be true on real hardware")
        z = self.bus.zenoh
        if self.bus.kind == "zenoh" and z is not None and z.security != "mtls":
            raise ValueError(
                "bus.zenoh.security: real drones fly only on an authenticated bus (mtls with the "
                "certificates of `flightstack certs`); plaintext is for simulations on one computer"
            )

    @property
    def simulated(self) -> bool:
        return self.backend != "tello"

    def k_c_xy_unequal(self) -> bool:
        return self.gains.k_c[0] != self.gains.k_c[1] or self.gains.k_e[0] != self.gains.k_e[1]

    def edge_index_pairs(self) -> list[tuple[int, int]]:
        """Graph edges as 0-based index pairs into `drones` (complete graph when kind is 'complete')."""
        ids = [d.id for d in self.drones]
        if self.graph.kind == "complete":
            return [(a, b) for a in range(len(ids)) for b in range(a + 1, len(ids))]
        return sorted({tuple(sorted((ids.index(a), ids.index(b)))) for a, b in self.graph.edges if a != b})

    def neighbours(self, index: int) -> list[int]:
        """0-based indices of the neighbours of drone `index`."""
        out = set()
        for a, b in self.edge_index_pairs():
            if a == index:
                out.add(b)
            elif b == index:
                out.add(a)
        return sorted(out)


def _format_errors(err: ValidationError, where: Lines | None = None) -> list[str]:
    lines = []
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        line = line_of(where, e["loc"]) if where else None
        lines.append(f"{path}: {msg}" + (f" (line {line})" if line else ""))
    return lines


def parse_mission(data: object, source: str = "<mission>", where: Lines | None = None) -> Mission:
    """Validate an already-parsed YAML/JSON document; `where`: key path → line, for the messages."""
    if not isinstance(data, dict):
        raise MissionError(f"{source}: (top level): a mission must be a mapping of keys")
    try:
        return Mission.model_validate(data)
    except ValidationError as err:
        lines = _format_errors(err, where)
        raise MissionError(
            f"{source}: invalid mission ({len(lines)} problem(s)):\n  " + "\n  ".join(lines)
        ) from None


def load_mission(
    path: str | Path, overrides: dict[str, object] | None = None, check_files: bool = True
) -> Mission:
    """Read and validate a mission file; `overrides` replace top-level keys (e.g. duration_s) first.

    check_files=False skips the existence checks of referenced files (calibrations, experts) so that
    `flightstack preflight` can report them as rows of its table instead of stopping at the first one."""
    path = Path(path)
    try:  # one hardened loader (safe_load.py): regular files only, bounded, UTF-8, no aliases, ...
        data, where = load_yaml(path, "mission file")
    except LoadError as exc:
        raise MissionError(str(exc)) from None
    if isinstance(data, dict) and overrides:
        data = {**data, **overrides}
    m = parse_mission(data, str(path), where)
    m._base_dir = path.resolve().parent
    if not check_files:
        return m
    for d in m.drones:
        if d.camera is not None and not m.resolve(d.camera.calibration).is_file():
            raise MissionError(
                f"{path}: drones.{m.drones.index(d)}.camera.calibration: file not found: "
                f"{m.resolve(d.camera.calibration)}"
            )
    if m.gp.experts_file is not None and not m.resolve(m.gp.experts_file).is_file():
        raise MissionError(f"{path}: gp.experts_file: file not found: {m.resolve(m.gp.experts_file)}")
    return m


def mission_to_dict(m: Mission) -> dict[str, object]:
    """The resolved mission (defaults filled in), JSON/YAML-serialisable."""
    return m.model_dump(mode="json")
