"""Mission files: one YAML document validated against a strict schema (DESIGN §8).

Unknown keys are errors; every error names the key path (e.g. `drones.1.desired_pose.p`) and the
reason. `load_mission(path)` raises MissionError with all problems listed, nothing half-loaded.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, cast

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
from flightstack.config.compensation import (
    CompensationSpec,
    stand_in_problem,
    told,
)
from flightstack.config.hardware import HardwareSpec
from flightstack.config.links import LinksSpec, network_in_links
from flightstack.config.rig import problem_list
from flightstack.config.rig_rules import safety_off_problem
from flightstack.config.rigs import RIGS, RigFacts, backends, rig_for
from flightstack.config.sim_specs import RcGainsSpec, RobotSpec, SimSpec
from flightstack.config.types import Angle, Coordinate, Distance, Finite, Mode, Speed
from flightstack.config.types import Strict as _Strict
from flightstack.hal import DroneIdentity
from flightstack.paper.delay_compensation import Compensation
from flightstack.paper.fusion import FUSION_RULES
from flightstack.paper.gain_analysis import (
    MAX_RATE_DT,
    fastest_error_rate,
    laplacian_lambda_max,
    own_loop_rate,
)
from flightstack.paper.geometry import Pose
from flightstack.paper.projection import CameraModel
from flightstack.paper.target_law import TargetLaw, square_law
from flightstack.safe_yaml import Lines, line_of
from flightstack.safety import SafetyLimits

MODES = tuple(m.value for m in Mode)
MAX_TICKS = 10**7  # ticks of one mode (duration_s / dt_s)
MAX_DRONES = 1000
"""At most this many drones in a mission. The scaling missions fly 31; beyond 1000 nothing carries them:
the operator's abort and its acknowledgements name every drone and carry at most 1024 ids
(flightstack.comms.control), the lock-step tick of a complete graph exchanges n(n − 1) messages (10⁶ per
tick at 1000), and `flightstack generate-mission` writes at most 1000. The recording's memory (n × ticks)
is checked against the computer's separately (flightstack.runtime.resources). Checked on the raw list,
before any drone is validated: a 9,000-drone file is refused at once."""

# Camera mounts in the drone's FLU body frame (columns: camera x right, y down, z optical axis).
CAMERA_MOUNTS = {
    "down": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "forward": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
}


class MissionError(ValueError):
    """A mission file that cannot be used; the message lists each bad key path and why."""


class PoseSpec(_Strict):
    """A pose (p in metres, theta in radians)."""

    p: tuple[Coordinate, Coordinate, Coordinate] = (0.0, 0.0, 0.0)
    theta: Angle = 0.0

    def pose(self) -> Pose:
        return Pose.make(self.p, self.theta)


DuffingCoefficient = Annotated[float, Field(ge=-100, le=100, allow_inf_nan=False)]
"""The paper's coefficients are at most 1 in size; the field is cubic in the position, so beyond 100 the
target leaves any arena within a fraction of a second."""


class DuffingSpec(_Strict):
    """Coefficients of the paper's Duffing-like target velocity field (Sec. 5)."""

    alpha: DuffingCoefficient = -1.0
    beta: DuffingCoefficient = 1.0
    gamma: DuffingCoefficient = 0.39
    delta: DuffingCoefficient = 0.1
    omega: DuffingCoefficient = 0.4


class SquareSpec(_Strict):
    """The paper's experiment: a square lap with one rotation per lap (flightstack.paper.target_law).
    `law`: `paper` (eq. scamper_vel, commands sideways velocity: an `omni` robot only), `unicycle` (heading
    along the path, forward speed and turn rate: any robot); unset: the one the rig's robot can follow
    (`paper` for an omni robot, the ideal rig's, else `unicycle`: `Mission.target_law_name`). `gain`
    (1/s) is the paper law's."""

    side_m: Distance = 1.0
    speed_mps: Speed = 0.1
    gain: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.05  # 1/s
    law: Literal["paper", "unicycle"] | None = None


class TargetSpec(_Strict):
    motion: Literal["duffing", "square"] = "duffing"
    initial_pose: PoseSpec = PoseSpec(p=(-0.3, -1.0, 0.0), theta=0.0)
    duffing: DuffingSpec = DuffingSpec()
    square: SquareSpec = SquareSpec()
    robot: RobotSpec = RobotSpec()
    feature_points: list[tuple[Coordinate, Coordinate, Coordinate]] = Field(min_length=4)
    substeps: int = Field(default=1, ge=1, le=1000)


class CameraSpec(_Strict):
    """The ideal camera: focal length λ in image units (1: the normalised image plane; pixels: ~10²–10³)."""

    focal_length: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = 1.0


class DroneCameraSpec(_Strict):
    """A real or rendered camera: calibration file (relative to the mission file), mount, offset (m)."""

    calibration: str | None = None  # required on every rig but the ideal one (its camera is exact)
    mount: Literal["down", "forward"] = "down"
    offset: tuple[Coordinate, Coordinate, Coordinate] = (0.0, 0.0, 0.0)


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
    # per_expert: each expert maximises its own log marginal likelihood (the paper); shared: one set of
    # hyperparameters for all experts maximising the sum of theirs (Deisenroth & Ng 2015; gp_shared_fit.py)
    hyperparameters: Literal["per_expert", "shared"] = "per_expert"
    # separate: one SE-ARD kernel per output (the paper); shared: one σ_f and one set of length scales for
    # the four outputs (maximising the sum of the outputs' log marginal likelihoods), so an expert keeps
    # one Cholesky factor and predicts with one k_* and one L⁻¹k_* (~4× cheaper; for large M:
    # docs/performance.md)
    output_kernel: Literal["separate", "shared"] = "separate"
    fusion: str = "poe"

    @field_validator("fusion")
    @classmethod
    def _rule(cls, v: str) -> str:
        if v not in FUSION_RULES:
            raise ValueError(f"unknown fusion rule {v!r}; valid: {', '.join(FUSION_RULES)}")
        return v


def _safety_spec() -> type[BaseModel]:
    """The `safety:` section: exactly the fields and defaults of flightstack.safety.SafetyLimits (one
    source of truth), plus `enabled`; SafetyLimits' own checks run as the section's validator."""
    hints = typing.get_type_hints(SafetyLimits)
    fields: dict[str, Any] = {"enabled": (bool, True)}
    for f in dataclasses.fields(SafetyLimits):
        fields[f.name] = (hints[f.name], f.default)

    def _limits_valid(self: BaseModel) -> BaseModel:
        SafetyLimits(**self.model_dump(exclude={"enabled"}))  # raises ValueError with the reason
        return self

    return create_model(
        "SafetySpec",
        __base__=_Strict,
        __doc__="flightstack.safety.SafetyLimits; `enabled: false` only for the paper's ideal simulation.",
        __validators__=cast(dict[str, Any], {"_limits_valid": model_validator(mode="after")(_limits_valid)}),
        **fields,
    )


if TYPE_CHECKING:
    # The static view of the model built below: SafetyLimits' fields plus `enabled` (never executed).
    class SafetySpec(_Strict, SafetyLimits):
        enabled: bool = True
else:
    SafetySpec = _safety_spec()


class GainAnalysisSpec(_Strict):
    gamma_sq: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 10.0
    beta: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 2.0
    eta: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.5
    samples: int = Field(default=4000, ge=10, le=10**6)


class Mission(_Strict):
    """An experiment composed with its rig (flightstack.config.rig.compose), validated: what every layer
    below the CLI consumes and every run writes (`mission_resolved.yaml`). Load one with `load_mission`;
    `rig_type` is the rig it flies on."""

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    description: str = ""
    rig: str = ""  # the rig it was composed with (flightstack.config.rig); "" if built without one
    start_emulators: bool = False  # the emulated-lab rig: `run` starts loopback emulators for `hardware`
    backend: str = "sim_ideal"  # the rig's name in flightstack.config.rigs.RIGS
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
    links: LinksSpec = LinksSpec()  # how late and lossy each link is (flightstack.config.links)
    compensation: CompensationSpec = CompensationSpec()  # delay-aware observer and command
    safety: SafetySpec = SafetySpec()
    hardware: HardwareSpec | None = None
    _base_dir: Path = PrivateAttr(default=Path("."))

    @property
    def rig_type(self) -> RigFacts:
        """The rig this mission flies on (flightstack.config.rigs; backend and start_emulators name it)."""
        return rig_for(self.backend, self.start_emulators)

    def robot_kinematics(self) -> str:
        """The ground robot's kinematics (flightstack.paper.target_law.KINEMATICS): the rig file's
        `robot.kinematics`, else the rig's default (`omni` on the ideal rig: the paper's idealised target,
        which the Duffing-like field and eq. scamper_vel move sideways)."""
        k = self.target.robot.kinematics
        if k is not None:
            return k
        return self.rig_type.default_kinematics

    def target_law_name(self) -> str:
        """The square law the robot is driven on (target.square.law; unset: `paper` for an omni robot,
        `unicycle` for any other)."""
        law = self.target.square.law
        if law is not None:
            return law
        return "paper" if self.robot_kinematics() == "omni" else "unicycle"

    def target_law(self) -> TargetLaw:
        """The square law of target.square for this rig's robot (flightstack.paper.target_law)."""
        sq, r = self.target.square, self.target.robot
        return square_law(
            self.target_law_name(),
            self.robot_kinematics(),
            sq.side_m,
            sq.speed_mps,
            sq.gain,
            self.target.initial_pose.theta,
            r.min_turn_radius_m or 0.0,
        )

    def _check_robot(self) -> None:
        """The robot's kinematics and its law: the law must be one the robot can follow (ValueError naming
        the key)."""
        r, kin = self.target.robot, self.robot_kinematics()
        if kin == "ackermann" and r.min_turn_radius_m is None:
            raise ValueError("target.robot.min_turn_radius_m: required for kinematics 'ackermann' (m)")
        if kin != "ackermann" and r.min_turn_radius_m is not None:
            raise ValueError(
                f"target.robot.min_turn_radius_m: only for kinematics 'ackermann' (this: {kin!r})"
            )
        if self.target.motion == "duffing" and kin != "omni":
            raise ValueError(
                f"target.motion: the Duffing-like field moves the target sideways, which a {kin} robot "
                "(target.robot.kinematics) cannot follow; it needs an omni target (the ideal rig)"
            )
        if self.target.motion != "square":
            return
        if kin != "omni" and self.target.square.law == "paper":
            raise ValueError(
                "target.square.law: 'paper' (eq. scamper_vel) commands sideways body velocity, which a "
                f"{kin} robot (target.robot.kinematics) cannot follow: use 'unicycle'"
            )
        try:
            self.target_law()
        except ValueError as exc:
            key = "target.robot.min_turn_radius_m" if kin == "ackermann" else "target.square"
            raise ValueError(f"{key}: {exc}") from None

    def delay_compensation(self) -> Compensation | None:
        """What each agent's delay compensation is told (None: off, the paper's law). Unset latencies
        come from the rig (RigFacts.command_link, drone_response_s); on hardware response_s is required
        (validation)."""
        c = self.compensation
        if not c.enabled:
            return None
        rig = self.rig_type
        return told(c, rig.command_link(self), rig.drone_response_s(self))

    def resolve(self, relative: str) -> Path:
        """A path from the mission file (calibrations, experts) made absolute against its directory."""
        p = Path(relative)
        return p if p.is_absolute() else (self._base_dir / p).resolve()

    @field_validator("drones", mode="before")
    @classmethod
    def _at_most_max_drones(cls, v: object) -> object:
        if isinstance(v, list) and len(v) > MAX_DRONES:
            raise ValueError(
                f"{len(v)} drones; at most {MAX_DRONES} (the operator's abort names at most 1024 "
                "drones and a complete graph's lock-step tick exchanges n(n − 1) messages; the scaling "
                "missions fly 31)"
            )
        return v

    @field_validator("backend")
    @classmethod
    def _known_backend(cls, v: str) -> str:
        if v not in RIGS:
            raise ValueError(f"unknown backend {v!r}; known: {', '.join(backends())}")
        return v

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
        try:
            rig = self.rig_type  # the backend is known (_known_backend): this asks for its emulators
        except ValueError as exc:
            raise ValueError(f"start_emulators: {exc}") from None
        off = safety_off_problem(rig, self.safety.enabled)  # the rig's rule, whatever set the value
        if off is not None:
            raise ValueError(off)
        if self.duration_s / self.dt_s > MAX_TICKS:
            raise ValueError(
                f"duration_s / dt_s: {self.duration_s / self.dt_s:.3g} ticks per mode; at most {MAX_TICKS:g} "
                "(the recording holds every tick in memory)"
            )
        if self.links.network != "clean" and not rig.applies_network_profile:
            raise ValueError(
                f"links.network: profile {self.links.network!r} is applied by the emulated lab's emulators "
                "only (rig emulated-lab); a simulated rig has no packets, only its links' delays"
            )
        ids = [d.id for d in self.drones]
        id_set = set(ids)
        if len(id_set) != len(ids):
            raise ValueError("drones: ids must be unique")
        for a, b in self.graph.edges:
            if a not in id_set or b not in id_set:
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
        self._check_sampled_loop()
        self._check_robot()
        c = self.compensation
        if c.enabled and (why := stand_in_problem(c, rig.command_link(self))) is not None:
            raise ValueError(why)
        if self.hardware is not None and not rig.has_devices:
            raise ValueError(
                f"hardware: only used by a rig of devices (this mission: backend {self.backend!r})"
            )
        rig.check(self)
        return self

    def _check_sampled_loop(self) -> None:
        """Refuse gains the sampled loop cannot carry: (k_max + k_s·λ_max(L))·dt < 2, k_max the fastest
        mode of a drone's own pursuit loop (flightstack.paper.gain_analysis.fastest_error_rate)."""
        g = self.gains
        lam = self.laplacian_lambda_max()
        k_max = own_loop_rate(g.k_c, g.k_e)
        rate_dt = fastest_error_rate(g.k_c, g.k_e, g.k_s, lam) * self.dt_s
        if not rate_dt < MAX_RATE_DT:
            raise ValueError(
                "gains: the sampled loop diverges: (k_max + k_s·λ_max(L))·dt_s = "
                f"({k_max:.6g} + {g.k_s:.6g} · {lam:.6g}) · {self.dt_s:g} s = {rate_dt:.4g}, must be < "
                f"{MAX_RATE_DT:g} (k_max: the fastest mode of a drone's own loop from k_c and k_e; λ_max(L) "
                "of the graph); lower gains.k_c, gains.k_e, gains.k_s or dt_s"
            )

    def identities(self) -> list[DroneIdentity]:
        """Each drone's identity (its id and the names derived from it), in `drones` order."""
        return [DroneIdentity(d.id) for d in self.drones]

    def identity(self, drone_id: int) -> DroneIdentity:
        """The identity of drone `drone_id` (KeyError: not one of the mission's drones)."""
        if drone_id not in self.drone_ids():
            raise KeyError(f"drone {drone_id} is not one of the mission's drones {self.drone_ids()}")
        return DroneIdentity(drone_id)

    def drone_ids(self) -> list[int]:
        """The drones' ids, in `drones` order."""
        return [d.id for d in self.drones]

    def flown_modes(self) -> list[str]:
        """The modes a run flies, in order: the data run `none` first when a GP mode needs experts that
        are not given (gp.experts_file)."""
        modes = list(self.compare_modes)
        if self.gp.experts_file is None and any(Mode(m).uses_gp for m in modes):
            modes = [Mode.NONE.value] + [m for m in modes if m != Mode.NONE]
        return modes

    @property
    def n_ticks(self) -> int:
        """Ticks of pursuit per mode: duration_s / dt_s, rounded (the one place it is computed)."""
        return round(self.duration_s / self.dt_s)

    @property
    def simulated(self) -> bool:
        """A simulated clock and physics (RigFacts.simulated)."""
        return self.rig_type.simulated

    def camera_model(self, index: int) -> CameraModel:
        """The camera model of drone `index` (its observer's and, on the ideal rig, its exact camera's): the
        normalised image plane (λ = 1) with the mount extrinsic and offset for a drone with a camera (the
        lab rigs give image features in normalised coordinates), else `camera.focal_length` (paper Sec. 5)."""
        d = self.drones[index]
        if d.camera is None:
            return CameraModel(focal_length=self.camera.focal_length)
        return CameraModel(1.0, CAMERA_MOUNTS[d.camera.mount].copy(), np.array(d.camera.offset, dtype=float))

    def k_c_xy_unequal(self) -> bool:
        return self.gains.k_c[0] != self.gains.k_c[1] or self.gains.k_e[0] != self.gains.k_e[1]

    def edge_index_pairs(self) -> list[tuple[int, int]]:
        """Graph edges as sorted 0-based index pairs into `drones` (complete graph when kind is 'complete').
        A complete graph's list has n(n − 1)/2 pairs: use `edge_count` and `neighbours` where the list
        itself is not needed."""
        n = len(self.drones)
        if self.graph.kind == "complete":
            return [(a, b) for a in range(n) for b in range(a + 1, n)]
        return sorted(self._edge_pair_set())

    def _edge_pair_set(self) -> set[tuple[int, int]]:
        """The `edges` graph's distinct pairs (a < b) of 0-based indices; self-loops dropped."""
        index = {d.id: k for k, d in enumerate(self.drones)}
        return {(min(index[a], index[b]), max(index[a], index[b])) for a, b in self.graph.edges if a != b}

    def edge_count(self) -> int:
        """Number of distinct undirected edges of the graph, without listing a complete graph's."""
        n = len(self.drones)
        return n * (n - 1) // 2 if self.graph.kind == "complete" else len(self._edge_pair_set())

    def neighbours(self, index: int) -> list[int]:
        """0-based indices of the neighbours of drone `index` (linear in the drones and the edges)."""
        if self.graph.kind == "complete":
            return [j for j in range(len(self.drones)) if j != index]
        out = set()
        for a, b in self._edge_pair_set():
            if a == index:
                out.add(b)
            elif b == index:
                out.add(a)
        return sorted(out)

    def laplacian_lambda_max(self) -> float:
        """λ_max(L) of the graph's Laplacian: n for a complete graph (n ≥ 2), else from its edges."""
        n = len(self.drones)
        if self.graph.kind == "complete":
            return float(n) if n > 1 else 0.0
        return laplacian_lambda_max(n, sorted(self._edge_pair_set()))


_NAMES_ITS_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_]+)*: ")


def _format_errors(err: ValidationError, where: Lines | None = None) -> list[str]:
    lines = []
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        line = line_of(where, e["loc"]) if where else None
        if not e["loc"] and _NAMES_ITS_KEY.match(msg):  # a mission-wide rule that names its key
            lines.append(msg + (f" (line {line})" if line else ""))
            continue
        lines.append(f"{path}: {msg}" + (f" (line {line})" if line else ""))
    return lines


def with_overrides(data: dict[str, Any], overrides: dict[str, object]) -> dict[str, Any]:
    """`overrides` on a mission document: each replaces a top-level key, or with a dot (`links.network`)
    one key of a section. Replacing `links` keeps the section's `network` unless the new one sets it:
    the radio is under the links, not one of them (`--links` and `--network` are independent)."""
    out = dict(data)
    for key, value in overrides.items():
        head, _, tail = key.partition(".")
        section = out.get(head)
        if tail:
            out[head] = {**(section if isinstance(section, dict) else {}), tail: value}
        elif (
            key == "links" and isinstance(value, dict) and isinstance(section, dict) and "network" in section
        ):
            out[key] = {"network": section["network"], **value}
        else:
            out[key] = value
    return out


def parse_mission(data: object, source: str = "<mission>", where: Lines | None = None) -> Mission:
    """Validate an already-parsed YAML/JSON document; `where`: key path → line, for the messages."""
    if not isinstance(data, dict):
        raise MissionError(f"{source}: (top level): a mission must be a mapping of keys")
    try:
        data = network_in_links(data, source)
    except ValueError as exc:
        raise MissionError(str(exc)) from None
    try:
        return Mission.model_validate(data)
    except ValidationError as err:
        raise MissionError(problem_list(f"{source}: invalid mission", _format_errors(err, where))) from None


def load_mission(
    path: str | Path,
    overrides: dict[str, object] | None = None,
    check_files: bool = True,
    rig: str | Path | None = None,
) -> Mission:
    """Read and validate a mission: an experiment on `rig` (a built-in name or a rig file; default: the
    experiment's own `rig:`) or a resolved mission written by a run.
    `path` may be a built-in experiment name. `overrides` replace keys (e.g. duration_s, or a section's
    `links.network`) of the resolved mission first (`with_overrides`).

    Referenced files must exist (calibrations, experts); each camera calibration is parsed and checked
    (flightstack.vision.camera_file: intrinsics, image size, principal point in the image).
    check_files=False skips these checks so that `flightstack preflight` can report them as rows of its
    table instead of stopping at the first one."""
    from flightstack.config.rig import RigError, load_composed

    try:  # one hardened loader (safe_load.py): regular files only, bounded, UTF-8, no aliases, ...
        data, path, where, label = load_composed(path, rig)
    except RigError as exc:
        raise MissionError(str(exc)) from None
    if overrides:
        try:
            data = with_overrides(network_in_links(data, label), overrides)
        except ValueError as exc:
            raise MissionError(str(exc)) from None
    m = parse_mission(data, label, where)
    m._base_dir = Path(path).resolve().parent
    if not check_files:
        return m
    from flightstack.vision.camera_file import CalibrationError, load_calibration

    checked: set[Path] = set()
    for k, d in enumerate(m.drones):
        if d.camera is None or d.camera.calibration is None:
            continue
        cal = m.resolve(d.camera.calibration)
        if not cal.is_file():
            raise MissionError(f"{label}: drones.{k}.camera.calibration: file not found: {cal}")
        if cal not in checked:  # parsed and checked (intrinsics, image size, fiducial) once per file
            try:
                fid = load_calibration(cal).fiducial
            except CalibrationError as exc:
                raise MissionError(f"{label}: drones.{k}.camera.calibration: {exc}") from None
            if fid is not None:  # its corners must be the target's feature points
                from flightstack.vision.fiducial import placement_problem

                why = placement_problem(fid, np.array(m.target.feature_points, dtype=float))
                if why is not None:
                    raise MissionError(f"{label}: drones.{k}.camera.calibration: {cal}: fiducial: {why}")
            checked.add(cal)
    if m.gp.experts_file is not None and not m.resolve(m.gp.experts_file).is_file():
        raise MissionError(f"{label}: gp.experts_file: file not found: {m.resolve(m.gp.experts_file)}")
    return m


def mission_to_dict(m: Mission) -> dict[str, Any]:
    """The resolved mission (defaults filled in), JSON/YAML-serialisable."""
    return m.model_dump(mode="json")
