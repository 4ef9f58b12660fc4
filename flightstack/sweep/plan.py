"""The plan of a sweep: the --set grid, its combinations (seed × grid point) and their stable ids.

A `--set KEY=V1,V2,...` names a dotted path into the resolved mission (`gains.k_s`, `gp.fusion`,
`drones.0.desired_pose.p`; an integer segment indexes a list) and its values, split at the commas outside
brackets, braces and quotes and each parsed as YAML (`gains.k_s=10,70` → 10, 70;
`compare_modes=[none,oracle]` → one list). Every grid point is validated against the mission schema
before anything runs; a bad key or value raises SweepError naming it and the reason.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flightstack.config.mission import Mission, MissionError, parse_mission
from flightstack.config.rig_rules import beyond_rig
from flightstack.safe_yaml import MAX_DEPTH, LoadError, parse_yaml

KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_]+)*$")
RESERVED = {"seed": "set by --seeds (seed = 0 .. N-1)"}
"""Keys a sweep sets itself (`parse_grid`); `run --set` may set them."""


class SweepError(ValueError):
    """Bad sweep input (a --set, the seeds, the output directory); the CLI exits 2 with the message."""


@dataclass(frozen=True)
class Combination:
    """One run of the sweep: `seed` at grid point `point` (index into the cartesian product)."""

    id: str
    seed: int
    point: int
    values: dict[str, Any]
    mission: dict[str, Any]  # the resolved mission of this run (seed and values applied), JSON-able


@dataclass
class Plan:
    """The combinations of a sweep and the facts that define it (compared on a resume)."""

    seeds: int
    grid: list[tuple[str, list[Any]]]
    base: dict[str, Any]
    points: list[dict[str, Any]] = field(default_factory=list)
    combinations: list[Combination] = field(default_factory=list)

    def labels(self) -> list[str]:
        """Each grid point's label: the keys with more than one value (all --set keys if none has)."""
        varying = [k for k, v in self.grid if len(v) > 1] or [k for k, _ in self.grid]
        return [point_label(v, varying) for v in self.points]

    def record(self) -> dict[str, Any]:
        """What sweep.json keeps as the plan: a rerun with another record conflicts (unless --force)."""
        return canonical(
            {"seeds": self.seeds, "grid": [[k, v] for k, v in self.grid], "base_mission": self.base}
        )


def canonical(obj: Any) -> Any:
    """`obj` as JSON would read it back (tuples → lists, keys → strings): for comparisons with files."""
    return json.loads(json.dumps(obj))


def split_values(text: str) -> list[str]:
    """Split at the commas outside [], {} and quotes: `1,[2,3],'a,b'` → ['1', '[2,3]', "'a,b'"]."""
    out: list[str] = []
    cur: list[str] = []
    depth, quote = 0, ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur))
    return out


def parse_set(text: str) -> tuple[str, list[Any]]:
    """`KEY=V1,V2,...` → (KEY, [values parsed as YAML]); SweepError naming what is wrong."""
    key, sep, rest = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise SweepError(f"--set {text!r}: expected KEY=V1,V2,... (e.g. gains.k_s=10,70)")
    if not KEY_RE.match(key):
        raise SweepError(f"--set {text!r}: {key!r} is not a dotted key path (e.g. gp.fusion)")
    if key.count(".") >= MAX_DEPTH:
        raise SweepError(f"--set {key[:40]}...: a key nested deeper than {MAX_DEPTH} levels")
    values = []
    for token in split_values(rest):
        if not token.strip():
            raise SweepError(f"--set {key}: empty value in {rest!r}")
        try:  # the hardened loader of every file: no huge integers, deep nesting, aliases, ...
            values.append(parse_yaml(token, f"--set {key}")[0])
        except LoadError as exc:
            raise SweepError(str(exc)) from None
    return key, values


def parse_grid(sets: list[str]) -> list[tuple[str, list[Any]]]:
    """Every --set of a sweep in order; a key the sweep sets itself (RESERVED), given twice, or inside
    another one, is an error."""
    grid = [parse_set(s) for s in sets]
    keys = [k for k, _ in grid]
    for key in keys:
        if key in RESERVED:
            raise SweepError(f"--set {key}: {RESERVED[key]}")
    for a, b in itertools.permutations(keys, 2):
        if a == b or b.startswith(a + "."):
            raise SweepError(
                f"--set {b}: given twice (or inside --set {a}); give all its values in one --set"
            )
    return grid


def set_path(doc: dict[str, Any], key: str, value: Any) -> None:
    """doc[key] = value for a dotted key (in place; missing sections are created, the schema checks them)."""
    node: Any = doc
    parts = key.split(".")
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        where = ".".join(parts[: i + 1])
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise SweepError(f"--set {key}: {where}: no item {part} (the list has {len(node)} items)")
            if last:
                node[int(part)] = value
            else:
                node = node[int(part)]
            continue
        if not isinstance(node, dict):
            raise SweepError(f"--set {key}: {'.'.join(parts[:i])} is a value, not a section")
        if last:
            node[part] = value
        else:
            if node.get(part) is None:
                node[part] = {}
            node = node[part]


def point_label(values: dict[str, Any], shown: Sequence[str] | None = None) -> str:
    """`gains.k_s=10 gp.fusion=poe` (values as compact JSON unless strings) of the keys `shown` (default all);
    `(base)` when there are none."""
    keys = [k for k in values if shown is None or k in shown]
    if not keys:
        return "(base)"
    return " ".join(f"{k}={_compact(values[k])}" for k in keys)


def _compact(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v, separators=(",", ":"))


def combination_id(seed: int, values: dict[str, Any]) -> str:
    """`s0003-<10 hex digits of the values>`: stable across runs and argument orders."""
    digest = hashlib.sha256(json.dumps(values, sort_keys=True).encode()).hexdigest()[:10]
    return f"s{seed:04d}-{digest}"


def mission_for(base: dict[str, Any], values: dict[str, Any], seed: int) -> dict[str, Any]:
    """The base mission with `values` (dotted keys) and `seed` applied (a new dict)."""
    doc = copy.deepcopy(base)
    for key, value in values.items():
        set_path(doc, key, value)
    doc["seed"] = seed
    return doc


def check_mission(
    doc: dict[str, Any], values: dict[str, Any], base_dir: Path, rig: Mission | None = None
) -> Mission:
    """Validate one grid point's mission (schema, what the base mission `rig`'s rig allows:
    flightstack.config.rig_rules, and referenced files); SweepError naming the key."""
    label = f"--set {point_label(values)}" if values else "the base mission"
    try:
        m = parse_mission(doc, label)
    except MissionError as exc:
        raise SweepError(str(exc)) from None
    why = None if rig is None else beyond_rig(rig, m)
    if why is not None:
        raise SweepError(f"{label}: {why}")
    m._base_dir = base_dir
    files = [
        (f"drones.{i}.camera.calibration", d.camera.calibration) for i, d in enumerate(m.drones) if d.camera
    ]
    files.append(("gp.experts_file", m.gp.experts_file))
    for key, path in files:
        if path is not None and not m.resolve(path).is_file():
            raise SweepError(f"{label}: {key}: file not found: {m.resolve(path)}")
    if not m.simulated:
        raise SweepError(
            f"{label}: a sweep flies simulated rigs only (ideal, lab-sim), not {m.rig or m.backend!r}"
        )
    if m.bus.kind != "inproc":
        raise SweepError(
            f"{label}: bus.kind: a sweep runs its missions on the in-process bus, not {m.bus.kind!r}"
        )
    return m


def build_plan(base: dict[str, Any], grid: list[tuple[str, list[Any]]], seeds: int, base_dir: Path) -> Plan:
    """Every seed 0 .. seeds-1 × every point of the cartesian product of the grid's values, each point
    validated (SweepError on the first bad one); combinations ordered by point, then seed."""
    if seeds < 1:
        raise SweepError(f"--seeds {seeds}: give at least 1")
    plan = Plan(seeds, grid, canonical(base))
    keys = [k for k, _ in grid]
    rig = check_mission(plan.base, {}, base_dir)
    for p, combo in enumerate(itertools.product(*(v for _, v in grid))):
        values = canonical(dict(zip(keys, combo, strict=True)))
        check_mission(mission_for(plan.base, values, 0), values, base_dir, rig)
        plan.points.append(values)
        for s in range(seeds):
            doc = canonical(mission_for(plan.base, values, s))
            plan.combinations.append(Combination(combination_id(s, values), s, p, values, doc))
    ids = [c.id for c in plan.combinations]
    if len(set(ids)) != len(ids):
        raise SweepError("--set: two grid points have the same values (a value repeated in one --set?)")
    return plan


def plan_differences(recorded: Any, plan: Plan) -> list[str]:
    """What differs between sweep.json's recorded plan and this one (the top-level names); [] if equal."""
    if not isinstance(recorded, dict):
        return ["sweep.json has no readable plan"]
    now = plan.record()
    return [k for k in now if recorded.get(k) != now[k]]
