"""The latency study's machinery: the run classification (flightstack.analysis.stability), the error
envelope, what κ > 0 would take (flightstack.analysis.kappa_needs) and the report of
benchmarks/latency_study.py on synthetic sweep results; one short system-tier study that runs and resumes."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from flightstack.analysis.kappa_needs import kappa_needs, loop_rate
from flightstack.analysis.metrics import error_envelope
from flightstack.analysis.stability import (
    CLASSES,
    CONVERGED,
    DIVERGED,
    FAILED,
    OSCILLATING,
    classify_mode,
    classify_run,
    envelope_growth,
    point_class,
)
from flightstack.paper.control import Gains
from flightstack.paper.gain_analysis import MAX_RATE_DT, gain_condition

REPO = Path(__file__).resolve().parents[1]


def _study() -> Any:
    spec = importlib.util.spec_from_file_location("latency_study", REPO / "benchmarks" / "latency_study.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["latency_study"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _mode(envelope: list[float | None], error_m: float = 0.1) -> dict[str, Any]:
    return {
        "error_envelope": {"window_s": 5.0, "max_m": envelope},
        "mean_position_error_m": error_m,
        "ticks": 10,
    }


FLAT = [0.6, 0.3] + [0.2] * 14  # 80 s: the takeoff transient, then a steady tracking error
GROWING = [0.3] + [0.05 + 0.02 * i for i in range(15)]  # grows from 0.07 to 0.33 m, never above 0.5 m


# ------------------------------------------------------------------------------------ classification


def test_error_envelope_takes_the_largest_error_per_window_over_the_drones() -> None:
    t = np.arange(0.0, 12.0, 0.05)
    err = np.stack([np.sin(t) ** 2, 0.5 * np.ones_like(t)], axis=1)
    err[10, 0] = 3.0  # t = 0.5 s, first window
    env = error_envelope(t, err)
    assert len(env) == 3 and env[0] == 3.0 and env[1] == pytest.approx(1.0, abs=1e-3) and env[2] >= 0.5
    assert error_envelope(t[:0], err[:0]) == []
    bad = err.copy()
    bad[150, 1] = np.nan  # t = 7.5 s
    assert math.isnan(error_envelope(t, bad)[1])


def test_envelope_growth_leaves_out_the_transient_and_compares_the_halves() -> None:
    growth, late = envelope_growth(FLAT)  # type: ignore[misc]
    assert growth == pytest.approx(1.0) and late == pytest.approx(0.2)  # the 0.6 m takeoff is left out
    g2 = envelope_growth(GROWING)
    assert g2 is not None and g2[0] > 1.5
    assert envelope_growth([0.1, None, 0.1, 0.1]) is None  # kept value missing
    assert envelope_growth([]) is None
    assert envelope_growth([0.2]) == (1.0, 0.2)  # one window: nothing to compare, no growth


def test_classify_mode_converged_oscillating_diverged() -> None:
    assert classify_mode(_mode(FLAT)) == CONVERGED
    assert classify_mode(_mode(GROWING)) == OSCILLATING
    assert classify_mode(_mode([0.2] * 8 + [0.3, 0.6, 0.9] + [1.0] * 5)) == DIVERGED  # late above 0.8 m
    big_but_bounded = [0.5, 0.6, 0.4, 0.47, 0.3, 0.56, 0.36, 0.37, 0.42, 0.46, 0.37, 0.3, 0.5, 0.4, 0.45, 0.4]
    assert classify_mode(_mode(big_but_bounded)) == CONVERGED  # a steady large error does not grow
    assert classify_mode(_mode([*FLAT[:-1], float("inf")])) == DIVERGED
    assert classify_mode(_mode([*FLAT[:-1], None])) == DIVERGED  # metrics write non-finite values as null
    assert classify_mode({"ticks": 3}) == FAILED  # no envelope: no verdict


def _record(modes: dict[str, Any], error: str | None = None, **extra: Any) -> dict[str, Any]:
    return {"seed": 0, "error": error, "metrics": {"modes": modes, "error": error, **extra}}


def test_classify_run_is_the_worst_mode_and_divergence_errors_are_data() -> None:
    assert classify_run(_record({"none": _mode(FLAT), "dgp": _mode(FLAT)})) == CONVERGED
    assert classify_run(_record({"none": _mode(GROWING), "dgp": _mode(FLAT)})) == OSCILLATING
    assert (
        classify_run(_record({"none": _mode(FLAT)}, "diverged at t = 3.2 s (drone 1, V_cmd x = 2e6)"))
        == DIVERGED
    )
    # another error (too little training data) without a diverged mode: no verdict
    assert classify_run(_record({"none": _mode(FLAT)}, "too little GP training data")) == FAILED
    # ... but a mode that diverged says why the data was missing
    assert (
        classify_run(_record({"none": _mode([0.2] * 6 + [2.0] * 10)}, "too little GP training data"))
        == DIVERGED
    )
    assert classify_run({"error": "boom", "metrics": None}) == FAILED


def test_point_class_needs_most_seeds_converged() -> None:
    assert point_class([CONVERGED] * 4 + [OSCILLATING])[0] == CONVERGED  # 80 %
    assert point_class([CONVERGED] * 3 + [OSCILLATING] * 2)[0] == OSCILLATING
    assert point_class([CONVERGED] * 3 + [OSCILLATING, DIVERGED])[0] == DIVERGED  # ties: the worse
    assert point_class([CONVERGED, CONVERGED, FAILED])[0] == CONVERGED  # failed runs are not rated
    cls, fr = point_class([FAILED])
    assert cls == FAILED and fr[FAILED] == 1.0 and set(fr) == set(CLASSES)


# ------------------------------------------------------------------------------------ κ > 0 would take

PAPER = ([13.0, 13.0, 13.0, 7.0], [8.0] * 4, 1.0)


def _kappa(k_c: list[float], k_e: list[float], k_s: float, L_mu: float) -> float:
    gc = gain_condition(
        Gains.make(k_c, k_e, k_s), 2, [(0, 1)], [True, False], [], np.zeros((1, 4)), 10.0, 2.0, 0.5
    )
    return gc.lambda_H - 0.5 * math.pi * L_mu * gc.lambda_P - 1.0 / 20.0


def test_kappa_needs_each_change_alone_brings_kappa_to_zero() -> None:
    L = 24.35  # the simulated lab's mean L_μ (docs/results.md)
    k = kappa_needs(*PAPER, 2, [(0, 1)], [True, False], L, 10.0, 0.05)
    assert k.kappa == pytest.approx(_kappa(*PAPER, L)) and k.kappa < 0
    assert k.kappa == pytest.approx(-45.5, abs=0.1)  # the lab's reported κ at that L_μ
    assert k.L_mu_max is not None and _kappa(*PAPER, k.L_mu_max) == pytest.approx(0.0, abs=1e-9)
    s = k.gain_scale
    assert s is not None and s > 1
    scaled = ([s * x for x in PAPER[0]], [s * x for x in PAPER[1]], s * PAPER[2])
    assert _kappa(*scaled, L) == pytest.approx(0.0, abs=1e-6)
    assert k.gain_scale_dt_max_s == pytest.approx(MAX_RATE_DT / loop_rate(*scaled, 2.0))
    assert k.gain_scale_dt_max_s < 0.05  # out of reach at 20 Hz
    assert k.slow_k_c is not None and k.slow_k_e is not None and k.slow_k_s is not None
    assert _kappa(k.slow_k_c, k.slow_k_e, k.slow_k_s, L) == pytest.approx(0.0, abs=1e-6)
    assert k.slow_dt_max_s is not None and k.slow_dt_max_s >= k.gain_scale_dt_max_s
    assert k.rate_dt == pytest.approx(loop_rate(*PAPER, 2.0) * 0.05) and k.rate_dt < MAX_RATE_DT


def test_kappa_needs_when_kappa_is_already_positive() -> None:
    k = kappa_needs(*PAPER, 2, [(0, 1)], [True, False], 0.0, 10.0, 0.05)
    assert k.kappa > 0 and k.gain_scale is not None and k.gain_scale < 1 and k.L_mu_max is not None


# ------------------------------------------------------------------------------------ the report


def _metrics(err: float, envelope: list[float | None], kappa: float, L_mu: float) -> dict[str, Any]:
    return {
        "modes": {"none": _mode(envelope, 2 * err), "dgp": _mode(envelope, err)},
        "gain_condition": {"evaluated": True, "kappa": kappa, "L_mu": L_mu, "lambda_H": 0.68},
        "error": None,
        "interrupted": False,
    }


def _write_part(
    root: Path,
    part: str,
    points: list[tuple[dict[str, Any], list[dict[str, Any]]]],
    error: str | None = None,
    first: int = 0,
) -> None:
    """The runs of `points` as a sweep writes them, numbered from `first` (added to what is there)."""
    runs = root / part / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    for i, (mission, metrics) in enumerate(points, start=first):
        for seed, m in enumerate(metrics):
            rec = {
                "id": f"s{seed}-{part}{i}",
                "seed": seed,
                "point": i,
                "values": {},
                "mission": mission,
                "error": m.get("error"),
                "metrics": m,
            }
            (runs / f"{rec['id']}.json").write_text(json.dumps(rec))
    del error


def _synthetic_study(root: Path, mod: Any, comp_error: float) -> None:
    """gains: paper's and k_c × 2 under perfect and tello, compensation off/on; k_c × 2 under tello
    oscillates without compensation; video ×2; hyper shared. With compensation under tello the error is
    `comp_error` at the paper's gains (0.1 m without)."""
    grid = mod.Grid((1.0, 2.0, 4.0), (1.0,), ("perfect", "tello"), (2.0,), 3, 80.0)
    (root / "study.json").write_text(
        json.dumps(
            {
                "grid": grid.record(),
                "invocations": [{"jobs": 2, "wall_s": 120.0, "load_before": 2.0, "parts": {}}],
            }
        )
    )
    pts = []
    for lat in ("perfect", "tello"):
        for comp in (False, True):
            for sc in (1.0, 2.0):
                mission = {
                    "gains": mod.gains_of(sc, 1.0),
                    "links": mod.links_of(lat),
                    "compensation": {"enabled": comp},
                    "gp": {"hyperparameters": "per_expert"},
                }
                base = 0.1 if lat == "tello" else 0.05
                err = comp_error if (lat == "tello" and comp and sc == 1.0) else base
                env = GROWING if (lat == "tello" and not comp and sc == 2.0) else FLAT
                pts.append(
                    (mission, [_metrics(err * (1 + 0.05 * s), env, -45.0 - s, 24.0 + s) for s in range(3)])
                )
    _write_part(root, "gains", pts)
    vid = [
        (
            {
                "gains": mod.gains_of(1, 1),
                "links": mod.links_of("tello", 2.0),
                "compensation": {"enabled": c},
            },
            [_metrics(0.2, FLAT, -50.0, 26.0)] * 2,
        )
        for c in (False, True)
    ]
    _write_part(root, "video", vid)
    hyp = [
        (
            {"gains": mod.gains_of(1, 1), "links": mod.links_of(lat), "gp": {"hyperparameters": "shared"}},
            [_metrics(0.1, FLAT, 0.2, 0.3)] * 2,
        )
        for lat in ("perfect", "tello")
    ]
    _write_part(root, "hyper", hyp)


def test_report_of_a_synthetic_study(tmp_path: Path) -> None:
    mod = _study()
    _synthetic_study(tmp_path, mod, comp_error=0.04)
    _, points = mod.read_study(tmp_path)
    gains = [p for p in points if p.part == "gains"]
    assert len(gains) == 2 * 2 * 3  # 2 flown + 1 not flown (k_c × 4) per latency × compensation
    not_flown = [p for p in gains if not p.flyable]
    assert {p.kc_scale for p in not_flown} == {4.0} and all(p.verdict()[0] == DIVERGED for p in not_flown)
    b = mod.boundary(points, "tello", False)
    assert b["kc"] == 1.0 and b["ke"] is None  # k_c × 2 oscillates; k_e was not swept
    assert (
        mod.boundary(points, "tello", True)["kc"] == 2.0
        and mod.boundary(points, "perfect", False)["kc"] == 2.0
    )
    g = mod.goal(points)
    assert g["met"] and g["ratio"] == pytest.approx(0.1 / 0.04, rel=1e-6)
    assert mod.identical_compensation(points) == (5, 3)  # perfect × 2 and video: compensation changed nothing
    page = tmp_path / "page.md"
    shutil.copy(mod.PAGE, page)
    text = mod.report(tmp_path, True, "cmd", page=page, plot=tmp_path / "plot.png")
    assert "**met**" in text and "not flown (rate·dt" in text and "**oscillating**" in text
    assert (
        "Gains alone (best stable without compensation, k_c × 1, k_e × 1, k_s 1)" in text
        and "Compensation alone" in text
    )
    assert "tello, video ×2" in text and "shared" in text and "never (κ does not depend on dt)" in text
    assert "| tello, video ×2 | off | 1 | not swept |" in text  # its k_c axis: 1 flown, 2 not in the data
    written = page.read_text()
    for key in ("setup", "goal", "boundary", "errors", "kappa", "table"):
        assert f"<!-- latency-study:{key}:start" in written
    assert "0.100 [" in written and (tmp_path / "plot.png").read_bytes()[:4] == b"\x89PNG"
    # the kappa table: κ at the paper's gains from the measured L_μ, L_μ alone needs < 0.33
    assert "| tello | per_expert | 25 |" in written and "0.33" in written


def test_report_says_not_met_with_the_numbers(tmp_path: Path) -> None:
    mod = _study()
    _synthetic_study(tmp_path, mod, comp_error=0.08)
    _, points = mod.read_study(tmp_path)
    g = mod.goal(points)
    assert not g["met"] and g["ratio"] == pytest.approx(0.1 / 0.08, rel=1e-6)  # best stable with it: 0.08 m
    md = mod.goal_md(points)
    assert "**not met**" in md and "ratio" in md and "needs ≥ 2" in md


def test_study_grids_fly_only_what_the_sampled_loop_carries() -> None:
    mod = _study()
    sets = mod.sweep_sets(mod.FULL)
    assert set(sets) == {"gains", "video", "hyper"}
    gains = next(s for s in sets["gains"] if s.startswith("gains="))
    from flightstack.sweep.plan import parse_set

    _, values = parse_set(gains)
    assert values and all(loop_rate(v["k_c"], v["k_e"], v["k_s"], 2.0) * 0.05 < MAX_RATE_DT for v in values)
    assert mod.gains_of(1.0, 1.0) in values  # the paper's gains are flown
    assert "sim.render.model=centres" in sets["gains"] and "compensation.enabled=false,true" in sets["gains"]
    n = sum(mod._runs_of(mod.FULL, p) for p in sets)
    # gains: 16 of the 3 × 3 × 2 (k_c, k_e, k_s) points fly; video: the k_c axis at k_s 1, 3 points
    assert n == (16 * 2 * 2 + 3 * 2 * 2 + 2) * mod.FULL.seeds


# ------------------------------------------------------------------------------------ system tier


@pytest.mark.system
def test_a_tiny_study_runs_and_resumes(tmp_path: Path) -> None:
    """2 seeds × 2 points (compensation off/on) × 8 s flights: the study runs its sweep, classifies every
    run, and a rerun of the same study skips what finished."""
    mod = _study()
    grid = mod.Grid((1.0,), (1.0,), ("perfect",), (), 2, 8.0, hyper=False)  # 8 s: the target reaches x ≥ 0
    t0 = time.monotonic()
    study = mod.run_study(grid, tmp_path, jobs=2, timeout_s=300.0)
    first = time.monotonic() - t0
    assert study["invocations"][0]["parts"]["gains"]["exit_code"] in (0, 1)
    _, points = mod.read_study(tmp_path)
    assert len(points) == 2 and all(len(p.records) == 2 for p in points)
    classes = [c for p in points for c in p.classes()]
    assert all(c in CLASSES for c in classes) and FAILED not in classes, classes  # both modes flew
    study = mod.run_study(grid, tmp_path, jobs=2, timeout_s=300.0)
    assert len(study["invocations"]) == 2
    log = (tmp_path / "gains.log").read_text()
    assert "4 finished already, skipped; 0 to run" in log
    text = mod.report(tmp_path, False, "cmd")
    assert "latency-study" not in text and (tmp_path / "latency_study.png").exists()
    print(f"tiny study: {first:.0f} s, rerun {study['invocations'][1]['wall_s']:.0f} s")


def test_a_consensus_gain_point_is_a_candidate_for_best_not_the_papers(tmp_path: Path) -> None:
    """A point at k_s = 4 (otherwise the paper's gains) with the lowest error is the best stable point,
    and the paper's point and the stability boundary stay at the paper's k_s."""
    mod = _study()
    _synthetic_study(tmp_path, mod, comp_error=0.08)
    mission = {
        "gains": mod.gains_of(1.0, 1.0, 4.0),
        "links": mod.links_of("tello"),
        "compensation": {"enabled": True},
        "gp": {"hyperparameters": "per_expert"},
    }
    _write_part(
        tmp_path, "gains", [(mission, [_metrics(0.03 * (1 + 0.05 * s), FLAT, -44.0, 24.0) for s in range(3)])]
    )
    _, points = mod.read_study(tmp_path)
    best = mod.best_stable(points, "tello", True)
    assert best is not None and best.k_s == 4.0 and best.error()["mean"] < 0.035
    paper = mod.paper_point(points, "tello", True)
    assert paper is not None and paper.k_s == 1.0 and paper.error()["mean"] == pytest.approx(0.084)
    assert mod.boundary(points, "tello", True)["kc"] == 2.0  # the k_s = 4 point is off the boundary's axes
    assert mod.goal(points)["met"]  # 0.1 m against 0.03 m
    assert "| gains | 1 | 1 | 4 | tello | on |" in mod.table_md(points)
