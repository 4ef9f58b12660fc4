"""Mission files: one YAML document validated against a strict schema (DESIGN §8).

Unknown keys are errors; every error names the key path (e.g. `drones.1.desired_pose.p`) and the
reason. `load_mission(path)` raises MissionError with all problems listed, nothing half-loaded.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from flightstack.fusion import FUSION_RULES

MODES = ("none", "local", "dgp", "oracle")


class MissionError(ValueError):
    """A mission file that cannot be used; the message lists each bad key path and why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Finite = Annotated[float, Field(allow_inf_nan=False)]


class PoseSpec(_Strict):
    """A pose (p in metres, theta in radians)."""

    p: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)
    theta: Finite = 0.0


class DuffingSpec(_Strict):
    """Coefficients of the paper's Duffing-like target velocity field (Sec. 5)."""

    alpha: Finite = -1.0
    beta: Finite = 1.0
    gamma: Finite = 0.39
    delta: Finite = 0.1
    omega: Finite = 0.4


class TargetSpec(_Strict):
    motion: Literal["duffing"] = "duffing"
    initial_pose: PoseSpec = PoseSpec(p=(-0.3, -1.0, 0.0), theta=0.0)
    duffing: DuffingSpec = DuffingSpec()
    feature_points: list[tuple[Finite, Finite, Finite]] = Field(min_length=4)
    substeps: int = Field(default=1, ge=1, le=1000)


class CameraSpec(_Strict):
    focal_length: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0


class DroneSpec(_Strict):
    id: int = Field(ge=0, lt=2**16)
    desired_pose: PoseSpec
    initial_offset: PoseSpec = PoseSpec()
    initial_estimate_error: PoseSpec = PoseSpec()
    sees_target: bool = True

    @field_validator("desired_pose")
    @classmethod
    def _in_front(cls, v: PoseSpec) -> PoseSpec:
        if v.p[2] <= 0:
            raise ValueError("the target must be in front of the camera: desired_pose.p[2] > 0")
        if abs(v.theta) >= math.pi / 2:
            raise ValueError("|theta| must be < pi/2 (Assumption 4 of the paper)")
        return v


class GraphSpec(_Strict):
    kind: Literal["complete", "edges"] = "complete"
    edges: list[tuple[int, int]] = []


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


class BusSpec(_Strict):
    kind: Literal["inproc"] = "inproc"
    stale_after_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 0.5


class GainAnalysisSpec(_Strict):
    gamma_sq: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 10.0
    beta: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 2.0
    eta: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = 0.5
    samples: int = Field(default=4000, ge=10, le=10**6)


class Mission(_Strict):
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    description: str = ""
    backend: Literal["sim_ideal"] = "sim_ideal"
    seed: int = 0
    duration_s: Annotated[float, Field(gt=0, le=86400, allow_inf_nan=False)]
    dt_s: Annotated[float, Field(gt=0, le=1.0, allow_inf_nan=False)]
    compare_modes: list[str] = Field(default=["dgp"], min_length=1)
    target: TargetSpec
    camera: CameraSpec = CameraSpec()
    drones: list[DroneSpec] = Field(min_length=1)
    graph: GraphSpec = GraphSpec()
    gains: GainsSpec
    gp: GPSpec
    bus: BusSpec = BusSpec()
    gain_analysis: GainAnalysisSpec = GainAnalysisSpec()

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
        return self

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


def _format_errors(err: ValidationError) -> list[str]:
    lines = []
    for e in err.errors():
        path = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        lines.append(f"{path}: {msg}")
    return lines


def parse_mission(data: object, source: str = "<mission>") -> Mission:
    """Validate an already-parsed YAML/JSON document."""
    if not isinstance(data, dict):
        raise MissionError(f"{source}: (top level): a mission must be a mapping of keys")
    try:
        return Mission.model_validate(data)
    except ValidationError as err:
        lines = _format_errors(err)
        raise MissionError(
            f"{source}: invalid mission ({len(lines)} problem(s)):\n  " + "\n  ".join(lines)
        ) from None


def load_mission(path: str | Path, overrides: dict[str, object] | None = None) -> Mission:
    """Read and validate a mission file; `overrides` replace top-level keys (e.g. duration_s) first."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise MissionError(f"{path}: cannot read mission file: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise MissionError(f"{path}: not valid YAML: {exc}") from None
    if isinstance(data, dict) and overrides:
        data = {**data, **overrides}
    return parse_mission(data, str(path))


def mission_to_dict(m: Mission) -> dict[str, object]:
    """The resolved mission (defaults filled in), JSON/YAML-serialisable."""
    return m.model_dump(mode="json")
