"""The paper's simulation for n drones: `n_drone_mission(n)` scales an experiment file.

The result is an experiment document (the schema of mission_configs/paper_sim.yaml, `rig:` included),
checked by composing it with its rig and validating the resolved mission (flightstack.config.mission)
before it is returned. Everything not listed below is copied from the base experiment unchanged
(target, duration, dt, modes, gains k_c and k_e, GP noise, samples per region, restarts, fusion rule).

Drones (ids 1..n). Drone i's desired pose g_d (the target's pose in the drone's camera frame; metres,
radians) is p = (r cos φ_i, r sin φ_i, z_d), θ = 0, with φ_i = 2π (i − 1)/n: the n drones stand evenly
around the target's optical-axis line, drone 1 at φ = 0 as in paper_sim. r and z_d default to the base's
first drone (paper_sim: r = 0.5 m, z_d = 1.5 m along the optical axis). The base's drones must have no
`camera:` (the ideal rig's normalised camera, optical axis = z); per-drone offsets are not copied.

Graph. `complete` ({kind: complete}) or `ring` ({kind: edges}, drone i linked to i + 1 and n to 1); the
schema knows `complete` and `edges` (flightstack.config.mission.GraphSpec).

Expert bands. n bands of equal width along the base's region axis (x for paper_sim), drone i owning band
i (flightstack.learning.training.bands: the outer two are open-ended). The range split is the target
path's extent along that axis, from integrating the base's target law with the ideal world's own
integrator (sim_backend/world.py: exact exponential, zero-order hold) over the base's duration_s
at its dt_s, rounded to RANGE_STEP_M = 0.1 m. For paper_sim that path spans x ∈ [−2.020, 1.894] m, which
rounds to [−2.0, 1.9] m: exactly the range the file's edges imply (three bands of width 1.3 m split at
−0.7 and 0.6) and the one docs/parameters.md states ("the path's x range [−2.0, 1.9] m"), so n = 3 reproduces
paper_sim's edges. Rounding to the nearest, not outward, loses nothing: the 2 cm of path beyond −2.0 m
falls in the open-ended first band. The range comes from the base's duration, not the generated one's,
so that a shortened run (`--duration`) keeps the bands of the full experiment.

Consensus gain. The consensus term c_i sums over the neighbours, so in the stacked error dynamics the
consensus input is k_s (L ⊗ I) e (flightstack.paper.gain_analysis: H = k_s L + D_v) and its fastest mode
has rate k_s λ_max(L); on a complete graph λ_max(L) = n. k_s is scaled so that k_s λ_max(L) stays the
base's: k_s,n = k_s,base λ_max(L_base)/λ_max(L_n) (paper_sim: 70 · 3/n on a complete graph; on a ring
λ_max = 2 − 2 cos(2π⌊n/2⌋/n), at most 4). The sampled loop's fastest error mode has rate
k_max + k_s λ_max(L) (1/s; k_max the largest component of k_c and k_e) and must satisfy
(k_max + k_s λ_max) dt ≤ MAX_K_DT = 0.62, the value paper_sim.yaml states for its dt ("k*dt <= 0.62 for
the fastest error mode": (100 + 70 · 3) · 0.002 s; docs/parameters.md: below 1
keeps the sampled loop monotone). A mission that exceeds it (an explicit k_s, a longer dt_s, a base with
faster gains) is refused with GenerateError naming the largest k_s that passes, or, with
`reduce_k_s=True`, flies with that k_s; it is refused in any case when k_max dt alone exceeds the bound.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from flightstack.config.mission import MAX_DRONES, Mission, TargetSpec, load_mission, parse_mission
from flightstack.config.rig import RigError, Source, builtin_path, compose, find, kind_of, read
from flightstack.paper.target_law import TargetLaw

MAX_K_DT = 0.62
"""Bound on (k_max + k_s λ_max(L)) · dt, the fastest error mode per control period (paper_sim.yaml)."""
RANGE_STEP_M = 0.1
"""The target path's extent is rounded to this (m): the precision of paper_sim's band edges."""
DECIMALS = 6
"""Desired positions and band edges are written to 1 µm (6 decimals of a metre)."""
GRAPHS = ("complete", "ring")
_REL_TOL = 1e-9  # float rounding of (k + k_s λ) dt at the bound (310 · 0.002 is not exactly 0.62)


class GenerateError(ValueError):
    """A mission that cannot be generated (bad n, an unstable gain, an unsuitable base); says why."""


@dataclass(frozen=True)
class Generated:
    """A generated experiment document and how its derived values were chosen (for the file's header)."""

    doc: dict[str, Any]
    base: str
    n: int
    graph: str
    radius_m: float
    depth_m: float
    axis: str
    band_range_m: tuple[float, float]
    path_range_m: tuple[float, float]  # the target path's extent before rounding (m)
    k_s: float
    k_s_base: float
    lambda_max: float
    lambda_max_base: float
    k_dt: float  # (k_max + k_s λ_max) · dt of the generated mission
    max_k_dt: float = MAX_K_DT
    k_s_reduced: bool = False
    notes: list[str] = field(default_factory=list)


def ring_edges(ids: Sequence[int]) -> list[list[int]]:
    """The ring through `ids` in order: [id_k, id_{k+1}] and [id_last, id_first] (n ≥ 3)."""
    n = len(ids)
    return [[ids[k], ids[(k + 1) % n]] for k in range(n)]


def ring_lambda_max(n: int) -> float:
    """Largest Laplacian eigenvalue of the n-cycle (n ≥ 3): 2 − 2 cos(2π⌊n/2⌋/n) (4 for even n)."""
    return 2.0 - 2.0 * math.cos(2.0 * math.pi * (n // 2) / n)


def mission_lambda_max(m: Mission) -> float:
    """λ_max of a mission's graph Laplacian: n for a complete graph, else from its edges."""
    return m.laplacian_lambda_max()


def target_path_range(
    target: TargetSpec, duration_s: float, dt_s: float, axis: str = "x", law: TargetLaw | None = None
) -> tuple[float, float]:
    """(min, max) of the target's world position along `axis` ('x' or 'y'; m) over duration_s seconds at
    dt_s: the ideal world's target (sim_backend/world.py, World.step; sim_backend/build.py): the law's body
    velocity held over each of `substeps` sub-periods, integrated with the exact exponential. `law`: the
    square law (Mission.target_law), required when target.motion is `square`."""
    from flightstack.paper.geometry import integrate_body_velocity
    from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity

    prm = DuffingParams(**target.duffing.model_dump())
    if target.motion == "square" and law is None:
        raise ValueError("target_path_range: a square target needs its law (Mission.target_law)")
    g = target.initial_pose.pose()
    k = 0 if axis == "x" else 1
    lo = hi = float(g.p[k])
    h = dt_s / target.substeps
    for tick in range(round(duration_s / dt_s)):
        t = tick * dt_s  # the world's clock at the start of the tick (the square law reads it)
        for _ in range(target.substeps):
            V = duffing_body_velocity(g, prm) if law is None else law.command(t, g)
            g = integrate_body_velocity(g, V, h)
        v = float(g.p[k])
        lo, hi = min(lo, v), max(hi, v)
    return lo, hi


def band_edges(n: int, lo: float, hi: float) -> list[float]:
    """The n − 1 inner edges of n bands of equal width over [lo, hi] (m), rounded to DECIMALS."""
    w = (hi - lo) / n
    return [round(lo + k * w, DECIMALS) + 0.0 for k in range(1, n)]


def circle_poses(n: int, radius_m: float, depth_m: float) -> list[dict[str, Any]]:
    """Desired poses g_d (camera frame) of n drones on a circle of radius_m (m) at depth_m along the
    optical axis, φ_k = 2π k/n for k = 0..n−1, θ = 0."""
    out = []
    for k in range(n):
        phi = 2.0 * math.pi * k / n
        x = round(radius_m * math.cos(phi), DECIMALS) + 0.0  # + 0.0: no "-0.0" in the file
        y = round(radius_m * math.sin(phi), DECIMALS) + 0.0
        out.append({"p": [x, y, float(depth_m)], "theta": 0.0})
    return out


def _round_step(v: float) -> float:
    return round(round(v / RANGE_STEP_M) * RANGE_STEP_M, 10) + 0.0


def _base(base: str | Path) -> tuple[dict[str, Any], Path, Mission]:
    """The base experiment's raw document, its file and its resolved mission (validated)."""
    try:
        path = find(base, "experiment")
        src = read(path, "mission file")
    except RigError as exc:
        raise GenerateError(str(exc)) from None
    if kind_of(src.data) != "experiment":
        raise GenerateError(
            f"{path}: the base must be an experiment file (no `backend:`; a rig is chosen by its `rig:`)"
        )
    m = load_mission(path)
    if any(d.camera is not None for d in m.drones):
        raise GenerateError(
            f"{path}: the base's drones have cameras; the circle of desired poses is laid out for the ideal "
            "rig's normalised camera (optical axis = z), as in paper_sim"
        )
    return src.data, path, m


def generate(
    n: int,
    *,
    base: str | Path = "paper_sim",
    graph: Literal["complete", "ring"] | str = "complete",
    radius_m: float | None = None,
    k_s: float | None = None,
    dt_s: float | None = None,
    duration_s: float | None = None,
    band_range_m: tuple[float, float] | None = None,
    name: str | None = None,
    reduce_k_s: bool = False,
    max_k_dt: float = MAX_K_DT,
) -> Generated:
    """`n_drone_mission` with the derivation of its values (see the module docstring for the rules).

    k_s: the consensus gain (1/s; default: the base's scaled to keep k_s λ_max(L)). dt_s, duration_s (s):
    default the base's. band_range_m: (lo, hi) of the bands along the region axis (m; default: the target
    path's extent, rounded). name: the mission's name (default `<base name>_<graph>_<n>`)."""
    if isinstance(n, bool) or not isinstance(n, int) or not 2 <= n <= MAX_DRONES:
        raise GenerateError(f"drones: n must be an integer in 2..{MAX_DRONES}, got {n!r}")
    if graph not in GRAPHS:
        raise GenerateError(f"graph: unknown kind {graph!r}; valid: {', '.join(GRAPHS)}")
    if graph == "ring" and n < 3:
        raise GenerateError("graph: a ring needs at least 3 drones (2 drones: use the complete graph)")
    raw, path, bm = _base(base)
    notes: list[str] = []

    first = bm.drones[0].desired_pose.p
    r = math.hypot(first[0], first[1]) if radius_m is None else float(radius_m)
    if not (math.isfinite(r) and r > 0):
        raise GenerateError(f"radius_m: must be a finite distance > 0 m, got {radius_m!r}")
    depth = float(first[2])

    ids = list(range(1, n + 1))
    if graph == "complete":
        graph_doc: dict[str, Any] = {"kind": "complete"}
        lam = float(n)
    else:
        graph_doc = {"kind": "edges", "edges": ring_edges(ids)}
        lam = ring_lambda_max(n)
    lam_base = mission_lambda_max(bm)
    if k_s is None:
        if lam_base == 0.0:
            raise GenerateError(f"{path}: the base has no consensus edges; give k_s explicitly")
        ks = bm.gains.k_s * lam_base / lam
    else:
        ks = float(k_s)
        if not (math.isfinite(ks) and ks >= 0):
            raise GenerateError(f"k_s: must be a finite gain >= 0 (1/s), got {k_s!r}")
    dt = bm.dt_s if dt_s is None else float(dt_s)
    k_max = max(*bm.gains.k_c, *bm.gains.k_e)
    bound = max_k_dt * (1.0 + _REL_TOL)
    if k_max * dt > bound:
        raise GenerateError(
            f"stability: k_max·dt = {k_max:g} · {dt:g} s = {k_max * dt:.4g} > {max_k_dt:g} even without "
            "consensus (k_s = 0); choose a smaller dt_s"
        )
    k_dt = (k_max + ks * lam) * dt
    reduced = False
    if k_dt > bound:
        ks_ok = (max_k_dt / dt - k_max) / lam
        why = (
            f"stability: the fastest error mode (k_max + k_s·λ_max(L))·dt = ({k_max:g} + {ks:.6g} · "
            f"{lam:.6g}) · {dt:g} s = {k_dt:.4g} exceeds {max_k_dt:g} ({n} drones, {graph} graph)"
        )
        if not reduce_k_s:
            raise GenerateError(
                f"{why}; the largest k_s that passes is {ks_ok:.6g} (reduce_k_s / --reduce-k-s uses it), "
                "or choose a smaller dt_s"
            )
        notes.append(f"k_s reduced from {ks:.6g} to {ks_ok:.6g}: {why}")
        ks, k_dt, reduced = ks_ok, (k_max + ks_ok * lam) * dt, True

    axis = bm.gp.regions.axis
    law = bm.target_law() if bm.target.motion == "square" else None
    path_range = target_path_range(bm.target, bm.duration_s, bm.dt_s, axis, law)
    if band_range_m is None:
        lo, hi = _round_step(path_range[0]), _round_step(path_range[1])
    else:
        lo, hi = float(band_range_m[0]), float(band_range_m[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise GenerateError(f"band range: needs lo < hi (m), got [{lo}, {hi}]")
    edges = band_edges(n, lo, hi)
    if any(b <= a for a, b in itertools.pairwise(edges)):
        raise GenerateError(
            f"band range: [{lo}, {hi}] m is too narrow for {n} bands at {10**-DECIMALS:g} m resolution"
        )

    doc = copy.deepcopy(raw)
    base_name = str(raw.get("name", path.stem))
    doc["name"] = name if name is not None else f"{base_name}_{graph}_{n}"
    doc["description"] = f"{base_name} flown by {n} drones on a {graph} graph (generated, for scaling runs)"
    rig_ref = doc.get("rig")
    if isinstance(rig_ref, str) and builtin_path(rig_ref, "rig") is None and not Path(rig_ref).is_absolute():
        doc["rig"] = str((path.resolve().parent / rig_ref).resolve())  # the written file may live elsewhere
    if dt_s is not None:
        doc["dt_s"] = dt
    if duration_s is not None:
        doc["duration_s"] = float(duration_s)
    doc["drones"] = [
        {"id": i, "desired_pose": pose} for i, pose in zip(ids, circle_poses(n, r, depth), strict=True)
    ]
    doc["graph"] = graph_doc
    doc["gains"] = {**doc["gains"], "k_s": ks}
    gp = doc["gp"]
    gp["regions"] = {"axis": axis, "edges": edges}
    if gp.pop("experts_file", None) is not None:
        notes.append("gp.experts_file dropped: the base's trained experts are for its own drones")
    to_mission(doc, f"{doc['name']} (generated from {path})")  # the loader's checks, on its rig
    return Generated(
        doc=doc,
        base=base_name,
        n=n,
        graph=graph,
        radius_m=r,
        depth_m=depth,
        axis=axis,
        band_range_m=(lo, hi),
        path_range_m=path_range,
        k_s=ks,
        k_s_base=bm.gains.k_s,
        lambda_max=lam,
        lambda_max_base=lam_base,
        k_dt=k_dt,
        max_k_dt=max_k_dt,
        k_s_reduced=reduced,
        notes=notes,
    )


def n_drone_mission(
    n: int,
    *,
    base: str | Path = "paper_sim",
    graph: Literal["complete", "ring"] | str = "complete",
    radius_m: float | None = None,
    k_s: float | None = None,
    dt_s: float | None = None,
    duration_s: float | None = None,
    band_range_m: tuple[float, float] | None = None,
    name: str | None = None,
    reduce_k_s: bool = False,
    max_k_dt: float = MAX_K_DT,
) -> dict[str, Any]:
    """The experiment document (paper_sim.yaml's schema) of the base experiment flown by n drones on
    `graph`, validated on its rig; raises GenerateError (or MissionError for a base that does not load).
    Rules and units: the module docstring and `generate`."""
    return generate(
        n,
        base=base,
        graph=graph,
        radius_m=radius_m,
        k_s=k_s,
        dt_s=dt_s,
        duration_s=duration_s,
        band_range_m=band_range_m,
        name=name,
        reduce_k_s=reduce_k_s,
        max_k_dt=max_k_dt,
    ).doc


def to_mission(doc: dict[str, Any], where: str | Path = "<generated>", **overrides: Any) -> Mission:
    """The resolved, validated Mission of an experiment document on the rig its `rig:` names (as
    load_mission would compose it); `overrides` replace top-level keys first (e.g. duration_s=0.05).
    Raises MissionError listing every problem."""
    from flightstack.config.mission import MissionError

    rig_ref = doc.get("rig")
    if not isinstance(rig_ref, str):
        raise MissionError(f"{where}: rig: the experiment must name its rig")
    try:
        rig_src = read(find(rig_ref, "rig"), "rig file")
        resolved = compose(Source(doc, Path(str(where))), rig_src)
    except RigError as exc:
        raise MissionError(str(exc)) from None
    return parse_mission({**resolved, **overrides}, str(where))


def header(g: Generated, command: str) -> str:
    """The YAML comment block of a generated file: how it was made, why, and its derived values."""
    lo, hi = g.band_range_m
    plo, phi = g.path_range_m
    lines = [
        f"Generated by `{command}`",
        "(flightstack/config/generate.py; regenerate rather than edit: its derived values go together).",
        f"Why: the paper's simulation ({g.base}) flown by {g.n} drones on a {g.graph} graph, to measure how",
        'the stack scales with the number of drones (docs/experiments.md, "More drones").',
        f"Drones 1..{g.n}: desired poses on a circle of radius {g.radius_m:g} m around the optical axis, "
        f"target {g.depth_m:g} m deep,",
        f"  drone i at angle 2*pi*(i-1)/{g.n}.",
        f"Expert bands: {g.n} of equal width along {g.axis} over [{lo}, {hi}] m, the target path's "
        f"extent in {g.base}",
        f"  ([{plo:.3f}, {phi:.3f}] m over its duration, rounded to {RANGE_STEP_M:g} m); "
        "drone i owns band i.",
        f"Consensus gain: k_s = {g.k_s:.6g} 1/s (base {g.k_s_base:g}): k_s*lambda_max(L) = "
        f"{g.k_s * g.lambda_max:.6g} (base {g.k_s_base * g.lambda_max_base:.6g}),",
        f"  lambda_max(L) = {g.lambda_max:.6g}; fastest error mode (k + k_s*lambda_max)*dt = {g.k_dt:.4g} "
        f"<= {g.max_k_dt:g}.",
        *g.notes,
    ]
    return "".join(f"# {line}\n" for line in lines)


def _flat(v: object) -> bool:
    return not isinstance(v, dict | list) or (
        isinstance(v, list) and all(not isinstance(x, dict | list) for x in v)
    )


def mission_yaml(g: Generated, command: str) -> str:
    """The generated experiment as YAML text with its comment header (key order kept; mappings of
    scalars and flat lists on one line, as in paper_sim.yaml: `desired_pose: {p: [...], theta: 0.0}`)."""
    import yaml

    class Dumper(yaml.SafeDumper):
        pass

    def mapping(dumper: yaml.SafeDumper, data: dict[str, Any]) -> Any:
        flow = all(_flat(v) for v in data.values())
        return dumper.represent_mapping("tag:yaml.org,2002:map", data, flow_style=flow)

    Dumper.add_representer(dict, mapping)
    body = yaml.dump(
        g.doc, Dumper=Dumper, sort_keys=False, default_flow_style=None, allow_unicode=True, width=110
    )
    return header(g, command) + body
