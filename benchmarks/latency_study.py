"""The latency study: gains × latency × compensation on the simulated lab, seeds with 95 % CIs.

    python benchmarks/latency_study.py --out runs/latency_study       # the full study (≤ ~45 min, 2 cores)
    python benchmarks/latency_study.py --quick --out runs/latency_pilot   # the pilot grid (~4 min)
    python benchmarks/latency_study.py --read runs/latency_study --update-docs   # docs/latency_study.md

What it flies (`paper_experiment --rig lab-sim`, modes none (the data run) and dgp, `sim.render.model:
centres`), as three `flightstack sweep`s in DIR/<part>/ (each resumable: a rerun of the same command skips
what finished; Ctrl-C keeps it):

- `gains`: k_c = s_c · (13, 13, 13, 7) and k_e = s_e · 8 (k_s = 1) for every s_c, s_e of the scales whose
  sampled loop can fly ((k_max + k_s λ_max(L))·dt < 2; the others are in the table as "not flown", they
  diverge by construction), × links profile `perfect` and `tello` × `compensation.enabled` false/true;
- `video`: the k_c axis (k_e at the paper's) under `tello` with the video link's latency and jitter scaled,
  × compensation;
- `hyper`: the paper's gains with `gp.hyperparameters: shared` (perfect, tello; no compensation), for
  the L_μ of "what κ > 0 would take".

Each run is classified converged / oscillating / diverged from its error envelope
(flightstack.analysis.stability; a diverged run is data). `--read DIR` only reads and reports;
`--update-docs` writes the generated blocks of docs/latency_study.md and its plot docs/latency_study.png.
The study is never run in CI (tests/test_latency_study.py checks its machinery on synthetic results and
one tiny system-tier flight).

A script here, not a CLI command: like network_table.py and sweep_tables.py it is one fixed experiment
that writes one docs page; what other studies can reuse is in the package (flightstack.sweep runs it,
flightstack.analysis.stability classifies, flightstack.analysis.kappa_needs computes what κ > 0 takes).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.table import DOCS, write_block  # noqa: E402
from flightstack.analysis.kappa_needs import kappa_needs, loop_rate  # noqa: E402
from flightstack.analysis.stability import (  # noqa: E402
    CONVERGED,
    DIVERGED,
    DIVERGED_M,
    GROWTH_LIMIT,
    STABLE_FRACTION,
    classify_run,
    point_class,
)
from flightstack.paper.gain_analysis import MAX_RATE_DT  # noqa: E402
from flightstack.sweep.stats import describe, succeeded  # noqa: E402

EXPERIMENT, RIG = "paper_experiment", "lab-sim"
PAPER_KC, PAPER_KE, PAPER_KS = (13.0, 13.0, 13.0, 7.0), 8.0, 1.0
N_DRONES, EDGES, VISIBLE, DT_S, GAMMA_SQ = 2, [(0, 1)], [True, False], 0.05, 10.0
"""paper_experiment's fleet (complete graph of 2, only drone 1 sees the target), dt and γ²."""
TELLO_VIDEO = {"latency_s": 0.3, "jitter_s": 0.1, "rate_hz": 30.0, "loss": 0.02}
"""The `tello` profile's video link (flightstack.config.links.PROFILES); `video` scales latency and jitter."""
PAGE = DOCS / "latency_study.md"
PLOT = DOCS / "latency_study.png"
MODE = "dgp"
"""The mode whose error the study reports (the paper's method); `none` is the data run at the same gains."""
ERROR = "mean_position_error_m"
GOAL_FACTOR = 2.0


@dataclass(frozen=True)
class Grid:
    """What a study flies: gain scales, latency profiles, video-latency scales, seeds, flight length."""

    kc_scales: tuple[float, ...]
    ke_scales: tuple[float, ...]
    profiles: tuple[str, ...]
    video_scales: tuple[float, ...]
    seeds: int
    duration_s: float
    hyper: bool = True
    ks_values: tuple[float, ...] = (1.0,)

    def record(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


FULL = Grid((0.5, 1.0, 1.5), (0.5, 1.0, 1.5), ("perfect", "tello"), (0.5, 2.0), 4, 80.0, ks_values=(1.0, 4.0))
"""The full study: the gain scales the sampled loop can fly at dt = 0.05 s (beyond 1.5× few can: 24 of 36
points of 0.5…4× could not), k_s at the paper's 1 and at 4 (the drone that does not see the target
follows the other's estimate through k_s alone), 4 seeds; about 45 min on 2 loaded cores."""
QUICK = Grid((1.0, 2.0), (1.0,), ("perfect", "tello"), (2.0,), 2, 80.0)


def gains_of(sc: float, se: float, ks: float = PAPER_KS) -> dict[str, Any]:
    """The mission's `gains` at scales s_c, s_e of the paper's, and consensus gain k_s."""
    return {
        "k_c": [round(sc * k, 6) for k in PAPER_KC],
        "k_e": [round(se * PAPER_KE, 6)] * 4,
        "k_s": ks,
    }


def rate_dt(sc: float, se: float, ks: float = PAPER_KS) -> float:
    """(k_max + k_s λ_max(L))·dt of the scaled gains: the sampled loop flies only below 2."""
    g = gains_of(sc, se, ks)
    return loop_rate(g["k_c"], g["k_e"], g["k_s"], 2.0) * DT_S


def links_of(profile: str, video_scale: float | None = None) -> dict[str, Any]:
    """The `links` section: a profile, and under `tello` optionally the video link's delay scaled."""
    if video_scale is None:
        return {"profile": profile}
    v = dict(TELLO_VIDEO, latency_s=TELLO_VIDEO["latency_s"] * video_scale)
    v["jitter_s"] = TELLO_VIDEO["jitter_s"] * video_scale
    return {"profile": profile, "video": v}


def latency_label(links: dict[str, Any]) -> str:
    """`perfect`, `tello` or `tello, video ×2` of a `links` section."""
    video = links.get("video")
    if not video:
        return str(links.get("profile"))
    return f"{links.get('profile')}, video ×{video['latency_s'] / TELLO_VIDEO['latency_s']:g}"


def flow(value: Any) -> str:
    """A --set value: JSON (a YAML subset), one value without spaces."""
    return json.dumps(value, separators=(",", ":"))


def sweep_sets(grid: Grid) -> dict[str, list[str]]:
    """The --set arguments of each part (module docstring)."""
    common = [
        "sim.render.model=centres",
        f"compare_modes={flow(['none', MODE])}",
        f"duration_s={grid.duration_s:g}",
    ]
    flyable = [
        (sc, se, ks)
        for sc in grid.kc_scales
        for se in grid.ke_scales
        for ks in grid.ks_values
        if rate_dt(sc, se, ks) < MAX_RATE_DT
    ]
    parts = {
        "gains": [
            *common,
            "gains=" + ",".join(flow(gains_of(sc, se, ks)) for sc, se, ks in flyable),
            "links=" + ",".join(flow(links_of(p)) for p in grid.profiles),
            "compensation.enabled=false,true",
        ]
    }
    if grid.video_scales:
        parts["video"] = [
            *common,
            "gains="
            + ",".join(flow(gains_of(sc, se, ks)) for sc, se, ks in flyable if se == 1.0 and ks == PAPER_KS),
            "links=" + ",".join(flow(links_of("tello", s)) for s in grid.video_scales),
            "compensation.enabled=false,true",
        ]
    if grid.hyper:
        parts["hyper"] = [
            *common,
            "gp.hyperparameters=shared",
            "links=" + ",".join(flow(links_of(p)) for p in grid.profiles),
        ]
    return parts


def sweep_command(grid: Grid, part: str, out: Path, jobs: int) -> list[str]:
    cmd = [sys.executable, "-m", "flightstack", "sweep", EXPERIMENT, "--rig", RIG, "--seeds", str(grid.seeds)]
    for s in sweep_sets(grid)[part]:
        cmd += ["--set", s]
    return [*cmd, "--jobs", str(jobs), "--out", str(out / part)]


def run_study(grid: Grid, out: Path, jobs: int, timeout_s: float | None = None) -> dict[str, Any]:
    """Run (or resume) every part's sweep; study.json gets the grid and each invocation's wall time."""
    out.mkdir(parents=True, exist_ok=True)
    study_json = out / "study.json"
    study = json.loads(study_json.read_text()) if study_json.exists() else {"invocations": []}
    study["grid"] = grid.record()
    inv: dict[str, Any] = {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "jobs": jobs, "parts": {}}
    inv["load_before"] = os.getloadavg()[0]
    for part in sweep_sets(grid):
        cmd = sweep_command(grid, part, out, jobs)
        t0 = time.perf_counter()
        print(f"{part}: {' '.join(cmd[1:])}", flush=True)
        with open(out / f"{part}.log", "a") as log:
            r = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=timeout_s, check=False)
        wall = time.perf_counter() - t0
        inv["parts"][part] = {"exit_code": r.returncode, "wall_s": wall}
        print(f"{part}: exit {r.returncode} in {wall:.0f} s (log {out / f'{part}.log'})", flush=True)
        if r.returncode not in (0, 1):  # 1: some run ended in an error (a divergence is one): data
            inv["stopped"] = f"{part} exited {r.returncode}"
            break
    inv["wall_s"] = sum(p["wall_s"] for p in inv["parts"].values())
    inv["load_after"] = os.getloadavg()[0]
    study["invocations"].append(inv)
    study_json.write_text(json.dumps(study, indent=1) + "\n")
    return study


# --------------------------------------------------------------------------------------------- reading


@dataclass
class Point:
    """One condition of the study: its runs (one per seed) and what they say."""

    part: str
    kc_scale: float
    ke_scale: float
    latency: str
    compensation: bool
    hyper: str = "per_expert"
    records: list[dict[str, Any]] = field(default_factory=list)
    k_s: float = PAPER_KS

    @property
    def flyable(self) -> bool:
        return self.rate_dt < MAX_RATE_DT

    @property
    def rate_dt(self) -> float:
        return rate_dt(self.kc_scale, self.ke_scale, self.k_s)

    @property
    def paper_ks(self) -> bool:
        return self.k_s == PAPER_KS

    def classes(self) -> list[str]:
        return [classify_run(r) for r in self.records]

    def verdict(self) -> tuple[str, dict[str, float]]:
        if not self.flyable:
            return DIVERGED, {DIVERGED: 1.0}
        return point_class(self.classes())

    def error(self, mode: str = MODE, key: str = ERROR) -> dict[str, Any]:
        """The error described over the seeds whose run succeeded (mean, 95 % CI)."""
        vals = [_mode_value(r, mode, key) for r in self.records if succeeded(r)]
        return describe(vals)

    def target_lost(self) -> int:
        """Runs in which the safety layer saw the target lost (target_lost_hover or _land) in any mode."""
        n = 0
        for r in self.records:
            modes = ((r.get("metrics") or {}).get("modes") or {}).values()
            n += any(k.startswith("target_lost") for m in modes for k in (m.get("safety_event_counts") or {}))
        return n

    def gain(self, key: str) -> dict[str, Any]:
        vals = []
        for r in self.records:
            gc = (r.get("metrics") or {}).get("gain_condition") or {}
            if gc.get("evaluated"):
                vals.append(gc.get(key))
        return describe(vals)


def _mode_value(record: dict[str, Any], mode: str, key: str) -> float | None:
    v = ((record.get("metrics") or {}).get("modes") or {}).get(mode, {}).get(key)
    return float(v) if isinstance(v, int | float) and math.isfinite(float(v)) else None


def _scales(gains: dict[str, Any]) -> tuple[float, float, float]:
    """(k_c ×, k_e ×, k_s) of a mission's gains."""
    sc, se = round(float(gains["k_c"][0]) / PAPER_KC[0], 4), round(float(gains["k_e"][0]) / PAPER_KE, 4)
    return sc, se, float(gains.get("k_s", PAPER_KS))


def read_records(part_dir: Path) -> list[dict[str, Any]]:
    """Every finished run of one part (DIR/<part>/runs/*.json)."""
    out = []
    for p in sorted((part_dir / "runs").glob("*.json")):
        try:
            out.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            continue
    return out


def _order(p: Point) -> tuple[Any, ...]:
    return (p.part, _latency_order(p.latency), p.compensation, p.k_s, p.kc_scale, p.ke_scale)


def _latency_order(latency: str) -> tuple[int, float]:
    """perfect, then tello by its video scale (tello itself ×1)."""
    if not latency.startswith("tello"):
        return (0, 0.0)
    return (1, float(latency.rsplit("×", 1)[-1]) if "×" in latency else 1.0)


def points_of(part: str, records: Sequence[dict[str, Any]]) -> list[Point]:
    """The records of one part grouped into points (by gains, links, compensation, hyperparameters)."""
    points: dict[tuple[Any, ...], Point] = {}
    for r in records:
        mission = r.get("mission") or {}
        sc, se, ks = _scales(mission.get("gains") or gains_of(1.0, 1.0))
        lat = latency_label(mission.get("links") or {"profile": "perfect"})
        comp = bool((mission.get("compensation") or {}).get("enabled", False))
        hyper = str((mission.get("gp") or {}).get("hyperparameters", "per_expert"))
        key = (part, sc, se, ks, lat, comp, hyper)
        points.setdefault(key, Point(part, sc, se, lat, comp, hyper, k_s=ks)).records.append(r)
    return sorted(points.values(), key=_order)


def read_study(out: Path) -> tuple[dict[str, Any], list[Point]]:
    study_json = out / "study.json"
    study = json.loads(study_json.read_text()) if study_json.exists() else {"invocations": []}
    points: list[Point] = []
    for part in ("gains", "video", "hyper"):
        if (out / part).is_dir():
            points += points_of(part, read_records(out / part))
    grid = study.get("grid")
    if grid:  # the gain points the sampled loop cannot fly: in the table, not flown
        have = {(p.part, p.kc_scale, p.ke_scale, p.k_s, p.latency, p.compensation) for p in points}
        video = [latency_label(links_of("tello", v)) for v in grid.get("video_scales") or []]
        for sc in grid["kc_scales"]:
            for se in grid["ke_scales"]:
                for ks in grid.get("ks_values") or [PAPER_KS]:
                    if rate_dt(sc, se, ks) < MAX_RATE_DT:
                        continue
                    where = [("gains", lat) for lat in grid["profiles"]]
                    where += [("video", lat) for lat in video if se == 1.0 and ks == PAPER_KS]
                    for part, lat in where:
                        for comp in (False, True):
                            if (part, sc, se, ks, lat, comp) not in have:
                                points.append(Point(part, sc, se, lat, comp, k_s=ks))
    points.sort(key=_order)
    return study, points


# --------------------------------------------------------------------------------------------- report


def _ci(d: dict[str, Any], digits: int = 3) -> str:
    if not d or d.get("mean") is None:
        return "–"
    if d.get("ci_low") is None:
        return f"{d['mean']:.{digits}f}"
    return f"{d['mean']:.{digits}f} [{d['ci_low']:.{digits}f}, {d['ci_high']:.{digits}f}]"


def _cls(p: Point) -> str:
    v, fr = p.verdict()
    if not p.flyable:
        return f"not flown (rate·dt {p.rate_dt:.2f} ≥ 2)"
    parts = [f"{c[:4]} {100 * f:.0f} %" for c, f in fr.items() if f > 0]
    return f"**{v}** ({', '.join(parts)})" if v != CONVERGED else f"{v} ({', '.join(parts)})"


def _on(comp: bool) -> str:
    return "on" if comp else "off"


def table_md(points: Sequence[Point]) -> str:
    lines = [
        f"| part | k_c × | k_e × | k_s | links | compensation | seeds | class | target lost (runs) | "
        f"{MODE} mean position error (m) | none (data run) error (m) | κ | L_μ |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in points:
        part = p.part if p.hyper == "per_expert" else f"{p.part} ({p.hyper})"
        lines.append(
            f"| {part} | {p.kc_scale:g} | {p.ke_scale:g} | {p.k_s:g} | {p.latency} | {_on(p.compensation)} | "
            f"{len(p.records)} | {_cls(p)} | {p.target_lost() if p.records else '–'} | {_ci(p.error())} | "
            f"{_ci(p.error('none'))} | "
            f"{_ci(p.gain('kappa'), 1)} | {_ci(p.gain('L_mu'), 1)} |"
        )
    return "\n".join(lines) + "\n"


GRIDDED = ("gains", "video")
"""The parts over gain points (the video part: the k_c axis, k_e at the paper's)."""


def conditions(points: Sequence[Point]) -> list[tuple[str, bool]]:
    keys = {(p.latency, p.compensation) for p in points if p.part in GRIDDED}
    return sorted(keys, key=lambda k: (_latency_order(k[0]), k[1]))


def boundary(points: Sequence[Point], latency: str, comp: bool) -> dict[str, Any]:
    """The largest converged k_c scale (k_e at the paper's), k_e scale (k_c at the paper's) and the
    converged point with the fastest loop, of one latency and compensation, at the paper's k_s."""
    mine = [
        p
        for p in points
        if p.part in GRIDDED and p.latency == latency and p.compensation == comp and p.paper_ks
    ]

    def largest(axis: str) -> float | None:
        if len({getattr(p, axis) for p in mine}) < 2:
            return None  # not swept along this axis
        other = "ke_scale" if axis == "kc_scale" else "kc_scale"
        ok = [getattr(p, axis) for p in mine if getattr(p, other) == 1.0 and p.verdict()[0] == CONVERGED]
        return max(ok) if ok else None

    conv = [p for p in mine if p.verdict()[0] == CONVERGED]
    fastest = max(conv, key=lambda p: p.rate_dt) if conv else None
    return {"kc": largest("kc_scale"), "ke": largest("ke_scale"), "fastest": fastest}


def boundary_md(points: Sequence[Point]) -> str:
    lines = [
        "| links | compensation | largest k_c × converged (k_e 1×) | largest k_e × converged (k_c 1×) | "
        "converged point with the fastest loop (k_c ×, k_e ×; rate·dt) |",
        "|---|---|---|---|---|",
    ]
    for lat, comp in conditions(points):
        b = boundary(points, lat, comp)
        f = b["fastest"]
        fast = "–" if f is None else f"{f.kc_scale:g}, {f.ke_scale:g}; {f.rate_dt:.2f}"
        kc = _axis_md(points, lat, comp, "kc_scale", b["kc"])
        ke = _axis_md(points, lat, comp, "ke_scale", b["ke"])
        lines.append(f"| {lat} | {_on(comp)} | {kc} | {ke} | {fast} |")
    return "\n".join(lines) + "\n"


def _axis_md(points: Sequence[Point], lat: str, comp: bool, axis: str, value: float | None) -> str:
    swept = {
        getattr(p, axis)
        for p in points
        if p.part in GRIDDED and p.latency == lat and p.compensation == comp and p.paper_ks
    }
    if len(swept) < 2:
        return "not swept"
    return "none" if value is None else f"{value:g}"


def paper_point(points: Sequence[Point], latency: str, comp: bool) -> Point | None:
    return next(
        (
            p
            for p in points
            if p.part in GRIDDED
            and p.latency == latency
            and p.compensation == comp
            and p.kc_scale == 1.0
            and p.ke_scale == 1.0
            and p.paper_ks
            and p.hyper == "per_expert"
        ),
        None,
    )


def best_stable(points: Sequence[Point], latency: str, comp: bool) -> Point | None:
    """The converged gain point of lowest mean error of one latency and compensation."""
    ok = [
        p
        for p in points
        if p.part in GRIDDED
        and p.latency == latency
        and p.compensation == comp
        and p.verdict()[0] == CONVERGED
        and p.error()["mean"] is not None
    ]
    return min(ok, key=lambda p: p.error()["mean"]) if ok else None


def errors_md(points: Sequence[Point]) -> str:
    lines = [
        f"| links | compensation | {MODE} error at the paper's gains (m) | "
        "best stable gains (k_c ×, k_e ×, k_s) | "
        f"{MODE} error there (m) |",
        "|---|---|---|---|---|",
    ]
    for lat, comp in conditions(points):
        pp, best = paper_point(points, lat, comp), best_stable(points, lat, comp)
        at = "–" if best is None else f"{best.kc_scale:g}, {best.ke_scale:g}, {best.k_s:g}"
        lines.append(
            f"| {lat} | {_on(comp)} | {_ci(pp.error()) if pp else '–'} ({pp.verdict()[0] if pp else '–'}) | "
            f"{at} | {_ci(best.error()) if best else '–'} |"
        )
    return "\n".join(lines) + "\n"


def _f(v: float | None, fmt: str = ".3g") -> str:
    return "–" if v is None else format(v, fmt)


def kappa_md(points: Sequence[Point]) -> str:
    """What κ > 0 would take at the paper's gains, per latency: from the measured L_μ (per-expert and
    shared hyperparameters), each change alone (flightstack.analysis.kappa_needs)."""
    lines = [
        "| links | hyperparameters | L_μ measured | κ at the paper's gains | L_μ alone: needs L_μ < | "
        "gains alone: × (k_c, k_e, k_s), needs dt < | slowest-loop gains with κ = 0 (k_c, k_e, k_s), "
        "need dt < | dt alone |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for lat in sorted({p.latency for p in points if p.part in ("gains", "hyper")}):
        for hyper, part in (("per_expert", "gains"), ("shared", "hyper")):
            p = next(
                (
                    q
                    for q in points
                    if q.part == part
                    and q.latency == lat
                    and not q.compensation
                    and q.kc_scale == 1.0
                    and q.ke_scale == 1.0
                    and q.paper_ks
                ),
                None,
            )
            L = None if p is None else p.gain("L_mu")["mean"]
            if L is None:
                continue
            k = kappa_needs(
                list(PAPER_KC), [PAPER_KE] * 4, PAPER_KS, N_DRONES, EDGES, VISIBLE, L, GAMMA_SQ, DT_S
            )
            gs = (
                "–"
                if k.gain_scale is None
                else (
                    f"{k.gain_scale:.0f}× ({k.gain_scale * PAPER_KC[0]:.0f}, {k.gain_scale * PAPER_KE:.0f}, "
                    f"{k.gain_scale * PAPER_KS:.0f}); dt < {1e3 * (k.gain_scale_dt_max_s or 0):.2f} ms"
                )
            )
            slow = (
                "–"
                if k.slow_k_c is None
                else (
                    f"{k.slow_k_c[0]:.0f}, {k.slow_k_e[0]:.0f}, {k.slow_k_s:.0f}; "  # type: ignore[index]
                    f"dt < {1e3 * (k.slow_dt_max_s or 0):.2f} ms ({1 / (k.slow_dt_max_s or 1):.0f} Hz)"
                )
            )
            lines.append(
                f"| {lat} | {hyper} | {L:.3g} | {k.kappa:.1f} | {_f(k.L_mu_max)} "
                f"({_f(L / k.L_mu_max if k.L_mu_max else None, '.0f')}× lower) | {gs} | {slow} | "
                "never (κ does not depend on dt) |"
            )
    return "\n".join(lines) + "\n"


def goal(points: Sequence[Point]) -> dict[str, Any]:
    """With compensation under `tello` (its best stable gains, else the paper's), the mean error against
    the paper's gains without compensation: met when at least GOAL_FACTOR× lower."""
    base = paper_point(points, "tello", False)
    comp = best_stable(points, "tello", True) or paper_point(points, "tello", True)
    b = base.error() if base else {"mean": None}
    c = comp.error() if comp else {"mean": None}
    ratio = b["mean"] / c["mean"] if b.get("mean") and c.get("mean") else None
    return {
        "base": base,
        "comp": comp,
        "base_error": b,
        "comp_error": c,
        "ratio": ratio,
        "met": ratio is not None and ratio >= GOAL_FACTOR,
    }


def goal_md(points: Sequence[Point]) -> str:
    g = goal(points)
    if g["ratio"] is None:
        return (
            "Goal: **not evaluated** (the study has no `tello` runs at the paper's gains with and without "
            "compensation).\n"
        )
    c: Point = g["comp"]
    verdict = "**met**" if g["met"] else "**not met**"
    return (
        f"Goal (with compensation, under `tello`, a mean position error ≥ {GOAL_FACTOR:g}× lower than the "
        f"paper's gains without compensation): {verdict}. Paper's gains, compensation off: "
        f"{_ci(g['base_error'])} m; compensation on, gains k_c × {c.kc_scale:g}, k_e × {c.ke_scale:g}, "
        f"k_s {c.k_s:g} "
        f"({c.verdict()[0]}): {_ci(g['comp_error'])} m; ratio {g['ratio']:.2f} (needs ≥ {GOAL_FACTOR:g})."
        + _shares(points, g)
        + "\n"
    )


def _shares(points: Sequence[Point], g: dict[str, Any]) -> str:
    """What the gains alone give (best stable without compensation) and the compensation at the paper's
    gains alone, so that the goal's ratio can be told apart."""
    out = []
    tuned = best_stable(points, "tello", False)
    if tuned is not None and tuned.error()["mean"]:
        ratio = g["base_error"]["mean"] / tuned.error()["mean"]
        out.append(
            f" Gains alone (best stable without compensation, k_c × {tuned.kc_scale:g}, k_e × "
            f"{tuned.ke_scale:g}, k_s {tuned.k_s:g}): {_ci(tuned.error())} m, ratio {ratio:.2f}."
        )
    comp = paper_point(points, "tello", True)
    if comp is not None and comp.error()["mean"]:
        out.append(
            f" Compensation alone (the paper's gains): {_ci(comp.error())} m, ratio "
            f"{g['base_error']['mean'] / comp.error()['mean']:.2f}."
        )
    return "".join(out)


def identical_compensation(points: Sequence[Point]) -> tuple[int, int]:
    """(pairs, identical): of the points flown with compensation on and off at otherwise the same
    settings, how many gave the same metrics in every seed (the compensation changed nothing)."""
    by_key = {(p.part, p.kc_scale, p.ke_scale, p.k_s, p.latency, p.hyper, p.compensation): p for p in points}
    pairs = same = 0
    for (part, sc, se, ks, lat, hyper, comp), p in by_key.items():
        q = by_key.get((part, sc, se, ks, lat, hyper, False))
        if not comp or q is None or not p.records or not q.records:
            continue
        pairs += 1
        mine = sorted(
            (r["seed"], json.dumps((r.get("metrics") or {}).get("modes"), sort_keys=True)) for r in p.records
        )
        theirs = sorted(
            (r["seed"], json.dumps((r.get("metrics") or {}).get("modes"), sort_keys=True)) for r in q.records
        )
        same += _strip_wall(mine) == _strip_wall(theirs)
    return pairs, same


def _strip_wall(rows: list[tuple[int, str]]) -> list[tuple[int, Any]]:
    """The modes' metrics without what the wall clock decides (wall_seconds, loop_health)."""
    out = []
    for seed, text in rows:
        modes = json.loads(text) or {}
        out.append(
            (
                seed,
                {
                    m: {k: v for k, v in d.items() if k not in ("wall_seconds", "loop_health")}
                    for m, d in modes.items()
                },
            )
        )
    return out


def setup_md(study: dict[str, Any], points: Sequence[Point], command: str) -> str:
    inv = study.get("invocations") or []
    wall = sum(i.get("wall_s", 0.0) for i in inv)
    n = sum(len(p.records) for p in points)
    grid = study.get("grid") or {}
    loads = [i.get("load_before") for i in inv if i.get("load_before") is not None]
    pairs, same = identical_compensation(points)
    return (
        f"Generated by `{command}` ({time.strftime('%Y-%m-%d')}) from {n} runs "
        f"({grid.get('seeds', '?')} seeds per point, {grid.get('duration_s', '?')} s flights), flown in "
        f"{wall / 60:.1f} min of wall time over {len(inv)} invocation(s) with "
        f"{', '.join(str(i.get('jobs')) for i in inv) or '?'} worker(s) on a {os.cpu_count()}-core machine"
        + (f" (load average {min(loads):.1f}–{max(loads):.1f} at the starts)" if loads else "")
        + f". Gain scales k_c × {grid.get('kc_scales')}, k_e × {grid.get('ke_scales')}, k_s "
        f"{grid.get('ks_values', [PAPER_KS])}; links "
        f"{grid.get('profiles')}; video-latency scales {grid.get('video_scales')}. Classes: converged "
        f"when ≥ {100 * STABLE_FRACTION:.0f} % of a point's seeds converged "
        f"(late envelope ≤ {DIVERGED_M:g} m "
        f"and growth ≤ {GROWTH_LIMIT:g})."
        + (" This is the `--quick` pilot grid." if grid == QUICK.record() else "")
        + (
            f"\n\n**Compensation on and off gave the same runs** at {same} of {pairs} points: in this build "
            "`compensation.enabled` does not change the flight yet.\n"
            if pairs and same == pairs
            else (
                f"\n\nCompensation on and off gave the same runs at {same} of {pairs} points.\n"
                if pairs
                else "\n"
            )
        )
    )


def write_plot(points: Sequence[Point], path: Path) -> Path:
    """One panel per latency × compensation: each gain point's class (colour) and mean error (label) over
    k_c × and k_e ×; a last panel the error at the paper's gains against the video latency."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = conditions(points)
    video = [p for p in points if p.part == "video"]
    n = max(len(conds) + (1 if video else 0), 1)
    ncol = min(n, 4)
    nrow = -(-n // ncol)
    fig, grid = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 3.4 * nrow), squeeze=False)
    axes = [a for row in grid for a in row]
    for ax in axes[n:]:
        ax.set_visible(False)
    colours = {CONVERGED: "tab:green", "oscillating": "tab:orange", DIVERGED: "tab:red", "failed": "tab:grey"}
    for ax, (lat, comp) in zip(axes, conds, strict=False):
        mine = [
            p
            for p in points
            if p.part in GRIDDED and p.latency == lat and p.compensation == comp and p.paper_ks
        ]
        for p in mine:
            v = p.verdict()[0]
            ax.scatter(
                p.kc_scale,
                p.ke_scale,
                s=260,
                c=colours.get(v, "k"),
                alpha=0.35 if not p.flyable else 0.9,
                marker="s" if p.flyable else "x",
            )
            e = p.error()["mean"]
            if e is not None:
                ax.annotate(f"{e:.2f}", (p.kc_scale, p.ke_scale), ha="center", va="center", fontsize=7)
        xs = sorted({p.kc_scale for p in mine} or {1.0})
        ys = sorted({p.ke_scale for p in mine} or {1.0})
        ax.set_xscale("log", base=2)
        ax.set_yscale("log", base=2)
        ax.set_xlim(xs[0] / 1.4, xs[-1] * 1.4)
        ax.set_ylim(ys[0] / 1.4, ys[-1] * 1.4)
        ax.set_xticks(xs, [f"{v:g}" for v in xs], minor=False)
        ax.set_yticks(ys, [f"{v:g}" for v in ys], minor=False)
        ax.minorticks_off()
        ax.set_xlabel("k_c × paper")
        ax.set_ylabel("k_e × paper")
        ax.set_title(f"{lat}, compensation {_on(comp)}, k_s {PAPER_KS:g}", fontsize=9)
        ax.grid(True, alpha=0.3)
    if video:
        ax = axes[len(conds)]
        for j, comp in enumerate((False, True)):
            vs = [
                p
                for p in points
                if p.part in ("video", "gains")
                and p.compensation == comp
                and p.kc_scale == 1.0
                and p.ke_scale == 1.0
                and p.paper_ks
                and p.latency.startswith("tello")
            ]
            xs, ms, lo, hi = [], [], [], []
            for p in vs:
                d = p.error()
                if d["mean"] is None:
                    continue
                scale = 1.0 if p.part == "gains" else float(p.latency.rsplit("×", 1)[-1])
                xs.append(TELLO_VIDEO["latency_s"] * scale)
                ms.append(d["mean"])
                lo.append(d["mean"] - (d["ci_low"] if d["ci_low"] is not None else d["mean"]))
                hi.append((d["ci_high"] if d["ci_high"] is not None else d["mean"]) - d["mean"])
            order = sorted(range(len(xs)), key=xs.__getitem__)
            ax.errorbar(
                [xs[i] for i in order],
                [ms[i] for i in order],
                yerr=[[lo[i] for i in order], [hi[i] for i in order]],
                fmt="o-",
                color=f"C{j}",
                capsize=3,
                label=f"compensation {_on(comp)}",
            )
        ax.set_xlabel("video latency (s)")
        ax.set_ylabel(f"{MODE} mean position error (m)")
        ax.set_title("paper's gains, tello", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def report(out: Path, update_docs: bool, command: str, page: Path = PAGE, plot: Path = PLOT) -> str:
    """The blocks of the docs page from the study in `out` (printed); with `update_docs` written into
    `page` and the plot to `plot`, else the plot to out/latency_study.png."""
    study, points = read_study(out)
    blocks = {
        "latency-study:setup": setup_md(study, points, command),
        "latency-study:goal": goal_md(points),
        "latency-study:boundary": boundary_md(points),
        "latency-study:errors": errors_md(points),
        "latency-study:kappa": kappa_md(points),
        "latency-study:table": table_md(points),
    }
    text = "\n".join(blocks.values())
    if update_docs:
        for key, block in blocks.items():
            write_block(page, key, block)
        write_plot(points, plot)
    else:
        write_plot(points, out / "latency_study.png")
    return text


def estimate(study: dict[str, Any], out: Path, full: Grid) -> str:
    """The full study's wall time estimated from a finished (pilot) study's runs per wall second."""
    inv = study.get("invocations") or []
    wall = sum(i.get("wall_s", 0.0) for i in inv)
    runs = sum(len(read_records(out / part)) for part in ("gains", "video", "hyper"))
    if not runs or not wall:
        return "no timing to estimate from"
    n_full = sum(_runs_of(full, part) for part in sweep_sets(full))
    return (
        f"{runs} runs in {wall:.0f} s ({wall / runs:.1f} s per run of wall time, parts' start-up included); "
        f"the full study has {n_full} runs: about {n_full * wall / runs / 60:.0f} min at that rate"
    )


def _runs_of(grid: Grid, part: str) -> int:
    n = 1
    for s in sweep_sets(grid)[part]:
        _, _, vals = s.partition("=")
        from flightstack.sweep.plan import split_values

        n *= len(split_values(vals))
    return n * grid.seeds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="the study's directory (created; a rerun resumes it)")
    ap.add_argument("--read", type=Path, help="only report the study in DIR")
    ap.add_argument("--quick", action="store_true", help="the pilot grid (QUICK)")
    ap.add_argument("--seeds", type=int, default=None, help="seeds per point (default: the grid's)")
    ap.add_argument("--duration", type=float, default=None, help="s of pursuit per mode (default: 80)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--timeout", type=float, default=None, help="s per part's sweep before it is stopped")
    ap.add_argument("--update-docs", action="store_true", help="write docs/latency_study.md and its plot")
    args = ap.parse_args()
    grid = QUICK if args.quick else FULL
    if args.seeds is not None or args.duration is not None:
        grid = Grid(
            **{
                **grid.__dict__,
                "seeds": args.seeds or grid.seeds,
                "duration_s": args.duration or grid.duration_s,
            }
        )
    if args.read is None and args.out is None:
        ap.error("give --out DIR (run or resume a study) or --read DIR (report one)")
    out = args.read or args.out
    if args.read is None:
        n = sum(_runs_of(grid, part) for part in sweep_sets(grid))
        print(f"latency study: {n} runs in {len(sweep_sets(grid))} sweeps into {out}", flush=True)
        study = run_study(grid, out, args.jobs, args.timeout)
        print(estimate(study, out, FULL))
    if not any((out / part / "runs").is_dir() for part in ("gains", "video", "hyper")):
        print(f"error: {out} holds no study (no gains/, video/ or hyper/ sweep)", file=sys.stderr)
        return 2
    command = "python benchmarks/latency_study.py --read DIR --update-docs"
    print(report(out, args.update_docs, command))
    return 0


if __name__ == "__main__":
    sys.exit(main())
