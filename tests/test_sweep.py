"""Both readings of the paper's error metric, the oscillation measures, and `flightstack sweep`
(plan, statistics against closed forms and scipy, end-to-end sweeps, resume, conflicts, Dask).

Unit tier: the metrics on synthetic Recordings, the plan, the statistics. System tier (marked): the CLI
end to end in child processes, each bounded well under a minute."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sps

from flightstack.analysis.metrics import build_metrics, default_transient_s, mode_metrics, oscillation
from flightstack.config.mission import Mission, load_mission
from flightstack.paper.geometry import compose_arrays, inverse_arrays
from flightstack.recording.timeseries import Recording
from flightstack.sweep.plan import (
    SweepError,
    build_plan,
    combination_id,
    mission_for,
    parse_grid,
    parse_set,
    split_values,
)
from flightstack.sweep.stats import describe, ordering_fraction, ratio_values, summarise
from tests.conftest import REPO, run_cli

# ---- metrics ------------------------------------------------------------------------------------------


def _sinusoid_recording(mode: str, c: float, a: float, n_per: int = 40, periods: int = 3) -> Recording:
    """Drone 1's e_c x-component c + a sin(2π t) over whole 1 s periods (every other component 0)."""
    n = n_per * periods
    rec = Recording.empty(mode, [1, 2, 3], n)
    rec.t[:] = np.arange(n) / n_per
    rec.e_c[:, 0, 0] = c + a * np.sin(2 * np.pi * rec.t)
    rec.ticks_done = n
    return rec


def test_sq_mean_error_and_mean_sq_error_closed_forms() -> None:
    # e(t) = c + a sin ωt over whole periods: mean of ‖e‖² = c² + a²/2, ‖mean of e‖² = c²
    rec = _sinusoid_recording("none", c=0.3, a=0.2)
    m = mode_metrics(rec)
    assert m["sq_mean_error"] == pytest.approx(0.3**2, rel=1e-12)
    assert m["mean_sq_error"] == pytest.approx(0.3**2 + 0.2**2 / 2, rel=1e-12)
    assert m["sq_mean_error"] <= m["mean_sq_error"]  # Jensen
    # a zero-mean oscillation: no bias at all, but a mean square
    m0 = mode_metrics(_sinusoid_recording("none", c=0.0, a=0.2))
    assert m0["sq_mean_error"] == pytest.approx(0.0, abs=1e-30)
    assert m0["mean_sq_error"] == pytest.approx(0.02, rel=1e-12)


def _mission() -> Mission:
    return load_mission("paper_sim")


def _oscillating_recording(mission: Mission, amplitudes: list[float], c: float = 0.5) -> Recording:
    """True relative error δ_i(t) = [r_i(t), 0, 0, 0] per drone: r = 5 m during the first second, then
    c + a_i sin(2π(t − 1)) for 3 whole periods (t = k/40 s, k = 0..160: a 4 s run, transient 1 s)."""
    g_d = np.array([[*d.desired_pose.p, d.desired_pose.theta] for d in mission.drones])
    k = np.arange(161)
    t = k / 40
    n = len(mission.drones)
    rec = Recording.empty("dgp", [d.id for d in mission.drones], t.size)
    rec.t[:] = t
    delta = np.zeros((t.size, n, 4))
    for j, a in enumerate(amplitudes):
        delta[:, j, 0] = np.where(k < 40, 5.0, c + a * np.sin(2 * np.pi * (t - 1.0)))
    # g_i0 = g_wi⁻¹ g_w0 with g_w0 = identity: g_wi = (g_d δ)⁻¹ gives g_d⁻¹ g_i0 = δ
    rec.g_wi[:] = inverse_arrays(compose_arrays(g_d[None], delta))
    rec.ticks_done = t.size
    return rec


def test_oscillation_std_and_total_variation_closed_forms() -> None:
    mission = _mission()
    amps = [0.1, 0.2, 0.05]
    rec = _oscillating_recording(mission, amps)
    rel = rec.true_relative_error(
        np.array([[*d.desired_pose.p, d.desired_pose.theta] for d in mission.drones])
    )
    assert np.linalg.norm(rel[40:, 0, :3], axis=1) == pytest.approx(
        0.5 + 0.1 * np.sin(2 * np.pi * (rec.t[40:] - 1))
    )
    m = mode_metrics(rec, mission)
    assert m["oscillation_transient_s"] == pytest.approx(1.0)  # 25 % of the 4 s run (< 10 s)
    # 121 samples over 3 periods of 40 (both ends at sin = 0): var = a² (3·40/2) / 121; TV = 4a per period
    for j, a in enumerate(amps):
        std = a * math.sqrt(60 / 121)
        assert m["position_error_std_per_drone_m"][str(j + 1)] == pytest.approx(std, rel=1e-9)
        assert m["position_error_tv_per_drone_mps"][str(j + 1)] == pytest.approx(4 * a / 1.0, rel=1e-9)
    assert m["position_error_std_m"] == pytest.approx(np.mean([a * math.sqrt(60 / 121) for a in amps]))
    assert m["position_error_tv_mps"] == pytest.approx(4 * np.mean(amps))
    # without the transient, the 5 m start dominates both
    m_all = mode_metrics(rec, mission, transient_s=0.0)
    assert m_all["position_error_std_m"] > 1.0 and m_all["position_error_tv_mps"] > 1.0


def test_default_transient_and_short_windows() -> None:
    assert default_transient_s(80.0) == 10.0 and default_transient_s(40.0) == 10.0
    assert default_transient_s(8.0) == 2.0 and default_transient_s(0.0) == 0.0
    t = np.arange(5) * 0.1
    assert oscillation(t, np.zeros((5, 2)), transient_s=1.0) is None  # nothing left after the transient
    assert oscillation(t[:1], np.zeros((1, 2))) is None
    res = oscillation(t, np.array([[0.0], [1.0], [0.0], [1.0], [0.0]]), transient_s=0.0)
    assert res is not None
    std, tv, tr = res
    assert std[0] == pytest.approx(np.std([0, 1, 0, 1, 0])) and tv[0] == pytest.approx(4 / 0.4) and tr == 0.0


def test_build_metrics_reports_the_ratios_of_both_readings() -> None:
    mission = _mission()
    recordings = {}
    # (c, a) per mode: mean_sq = c² + a²/2, sq_mean = c²
    for mode, (c, a) in {"none": (0.4, 0.2), "local": (0.2, 0.2), "dgp": (0.1, 0.1)}.items():
        recordings[mode] = _sinusoid_recording(mode, c, a)
    m = build_metrics(mission, recordings, {}, {}, 1.0)
    ms = {
        k: c**2 + a**2 / 2
        for k, (c, a) in {"none": (0.4, 0.2), "local": (0.2, 0.2), "dgp": (0.1, 0.1)}.items()
    }
    assert m["ratios"]["mean_sq_error"]["none/dgp"] == pytest.approx(ms["none"] / ms["dgp"])
    assert m["ratios"]["mean_sq_error"]["local/dgp"] == pytest.approx(ms["local"] / ms["dgp"])
    assert m["ratios"]["sq_mean_error"]["none/dgp"] == pytest.approx(16.0)
    assert m["ratios"]["sq_mean_error"]["local/dgp"] == pytest.approx(4.0)
    assert {k: v["ours"] for k, v in m["paper"]["ratios"].items()} == m["ratios"]["sq_mean_error"]
    assert m["paper"]["modes"]["none"] == {"ours": pytest.approx(0.16), "paper": 3.0e-7}


# ---- plan ---------------------------------------------------------------------------------------------


def test_set_values_are_split_outside_brackets_and_parsed_as_yaml() -> None:
    assert split_values("1,[2,3],'a,b',{x: 1, y: 2}") == ["1", "[2,3]", "'a,b'", "{x: 1, y: 2}"]
    assert parse_set("gains.k_s=10,70") == ("gains.k_s", [10, 70])
    assert parse_set("compare_modes=[none,oracle]") == ("compare_modes", [["none", "oracle"]])
    assert parse_set("gp.fusion=poe,rbcm") == ("gp.fusion", ["poe", "rbcm"])
    for bad, word in [
        ("gains.k_s", "KEY=V1"),
        ("k=1,,2", "empty"),
        ("a b=1", "dotted"),
    ]:
        with pytest.raises(SweepError, match=word):
            parse_set(bad)
    with pytest.raises(SweepError, match="--seeds"):
        parse_grid(["seed=1,2"])
    with pytest.raises(SweepError, match="twice"):
        parse_grid(["gains.k_s=1", "gains.k_s=2"])
    with pytest.raises(SweepError, match="twice"):
        parse_grid(["gains=x", "gains.k_s=2"])


def _base() -> tuple[dict, Path]:
    import yaml

    from flightstack.runtime.flight import resolved_mission_yaml

    m = _mission()
    return yaml.safe_load(resolved_mission_yaml(m)), m.resolve(".")


def test_plan_is_grid_times_seeds_with_stable_ids() -> None:
    base, base_dir = _base()
    grid = parse_grid(["gains.k_s=10,70", "gp.fusion=poe,rbcm,bcm"])
    plan = build_plan(base, grid, 3, base_dir)
    assert len(plan.points) == 6 and len(plan.combinations) == 18
    assert len({c.id for c in plan.combinations}) == 18
    assert plan.points[0] == {"gains.k_s": 10, "gp.fusion": "poe"}
    assert plan.points[5] == {"gains.k_s": 70, "gp.fusion": "bcm"}
    c = plan.combinations[4]  # point 1, seed 1
    assert (c.point, c.seed, c.values) == (1, 1, {"gains.k_s": 10, "gp.fusion": "rbcm"})
    assert c.mission["seed"] == 1 and c.mission["gains"]["k_s"] == 10 and c.mission["gp"]["fusion"] == "rbcm"
    assert c.id == combination_id(1, {"gp.fusion": "rbcm", "gains.k_s": 10})  # independent of key order
    again = build_plan(base, parse_grid(["gains.k_s=10,70", "gp.fusion=poe,rbcm,bcm"]), 3, base_dir)
    assert [x.id for x in again.combinations] == [x.id for x in plan.combinations]
    assert plan.labels()[1] == "gains.k_s=10 gp.fusion=rbcm"
    assert build_plan(base, [], 2, base_dir).labels() == ["(base)"]
    assert mission_for(base, {"drones.1.desired_pose.p": [0, 0, 2]}, 5)["drones"][1]["desired_pose"]["p"] == [
        0,
        0,
        2,
    ]


@pytest.mark.parametrize(
    ("sets", "words"),
    [
        (["gains.k_x=1"], ["gains.k_x", "unknown key"]),
        (["gains.k_s=10,-1"], ["gains.k_s", "greater than or equal to 0"]),
        (["gp.fusion=poe,nope"], ["gp.fusion", "unknown fusion rule"]),
        (["duration_s.x=1"], ["duration_s", "not a section"]),
        (["drones.5.id=1"], ["drones.5", "no item"]),
    ],
)
def test_invalid_grid_point_names_the_key(sets: list[str], words: list[str]) -> None:
    base, base_dir = _base()
    with pytest.raises(SweepError) as err:
        build_plan(base, parse_grid(sets), 1, base_dir)
    for w in words:
        assert w in str(err.value)


# ---- statistics ---------------------------------------------------------------------------------------


def test_describe_against_closed_form_and_scipy() -> None:
    d = describe([1.0, 3.0])  # mean 2, s = √2, s/√n = 1, t_{0.975,1} = 12.7062...
    assert d["n"] == 2 and d["mean"] == 2.0 and d["median"] == 2.0 and d["std"] == pytest.approx(math.sqrt(2))
    # closed form: Student's t with one degree of freedom is Cauchy, t_{0.975,1} = tan(π (0.975 − 1/2));
    # SciPy 1.13 (the lowest bound) computes it 2e-11 off, newer releases to 1e-16
    assert d["ci_high"] - 2.0 == pytest.approx(math.tan(math.pi * 0.475), rel=1e-10)
    rng = np.random.default_rng(3)
    x = rng.normal(1.0, 0.3, size=20)
    d = describe(x)
    lo, hi = sps.t.interval(0.95, 19, loc=x.mean(), scale=sps.sem(x))
    assert (d["ci_low"], d["ci_high"]) == pytest.approx((lo, hi), rel=1e-12)
    assert d["median"] == pytest.approx(np.median(x))
    one = describe([5.0, None, float("nan")])
    assert one["n"] == 1 and one["mean"] == 5.0 and one["ci_low"] is None
    assert describe([])["mean"] is None


def _record(seed: int, point: int, errs: dict[str, float], error: str | None = None) -> dict:
    modes = {m: {"mean_sq_error": v, "sq_mean_error": v / 2} for m, v in errs.items()}
    gc = {"kappa": 1.0 + seed, "L_mu": 2.0 * seed, "lambda_H": 38.0, "satisfied": seed % 2 == 0}
    metrics = {"modes": modes, "gain_condition": gc, "error": None, "interrupted": False}
    return {"id": f"s{seed}", "seed": seed, "point": point, "values": {}, "error": error, "metrics": metrics}


def test_ratios_ordering_and_gain_condition_over_seeds() -> None:
    recs = [
        _record(0, 0, {"none": 8.0, "local": 4.0, "dgp": 1.0}),
        _record(1, 0, {"none": 6.0, "local": 1.0, "dgp": 2.0}),  # local < dgp: ordering fails
        _record(2, 0, {"none": 9.0, "local": 6.0, "dgp": 3.0}),
        _record(3, 0, {"none": 1.0, "local": 1.0, "dgp": 1.0}, error="GP training data: too few"),
    ]
    ok = recs[:3]
    assert ratio_values(ok, "mean_sq_error", "none", "dgp") == [8.0, 3.0, 3.0]
    assert ordering_fraction(ok, "mean_sq_error") == {"n": 3, "fraction": pytest.approx(2 / 3)}
    (p,) = summarise([{}], recs)
    assert p["seeds"] == [0, 1, 2] and p["failed"] == ["s3"] and p["errors"] == ["GP training data: too few"]
    r = p["ratios"]["mean_sq_error"]["none/dgp"]
    assert r["mean"] == pytest.approx(14 / 3) and r["median"] == 3.0
    assert p["ratios"]["sq_mean_error"]["local/dgp"]["mean"] == pytest.approx((4 + 0.5 + 2) / 3)
    assert p["modes"]["dgp"]["sq_mean_error"]["mean"] == pytest.approx(1.0)
    gc = p["gain_condition"]
    assert gc["kappa"]["mean"] == pytest.approx(2.0) and gc["L_mu"]["mean"] == pytest.approx(2.0)
    assert gc["satisfied_fraction"] == pytest.approx(2 / 3)
    assert "position_error_std_m" not in p["modes"]["none"]  # absent metrics are not described


# ---- the CLI end to end (system tier) -----------------------------------------------------------------

GP_SHORT = [  # paper_sim for 1 s: every drone's band is crossed, 3 samples each, one restart (~1 s a run)
    "--set",
    "duration_s=1",
    "--set",
    "gp.samples_per_region=3",
    "--set",
    "gp.restarts=1",
    "--set",
    "gp.regions.edges=[-0.6,-0.4]",
]
NO_GP = ["--set", "duration_s=0.2", "--set", "compare_modes=[none,oracle]"]


def _sweep(out: Path, *args: str, timeout: float = 150) -> subprocess.CompletedProcess:
    return run_cli("sweep", "paper_sim", "--out", str(out), *args, timeout=timeout)


@pytest.fixture(scope="module")
def gp_sweep(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("sweep") / "gp"
    r = _sweep(out, "--seeds", "2", "--jobs", "2", *GP_SHORT, "--set", "gains.k_s=10,70")
    return out, r


@pytest.mark.system
def test_tiny_real_sweep_writes_summary(gp_sweep: tuple[Path, subprocess.CompletedProcess]) -> None:
    out, r = gp_sweep
    assert r.returncode == 0, r.stderr[-3000:]
    assert "4 to run" in r.stdout and "gains.k_s=10" in r.stdout and "none/dgp" in r.stdout
    assert "[1/4]" not in r.stdout  # progress lines only on a terminal
    runs = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*.json"))]
    assert len(runs) == 4 and {(x["seed"], x["values"]["gains.k_s"]) for x in runs} == {
        (s, k) for s in (0, 1) for k in (10, 70)
    }
    assert all(x["mission"]["seed"] == x["seed"] and x["mission"]["duration_s"] == 1 for x in runs)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and [p["label"] for p in summary["points"]] == ["gains.k_s=10", "gains.k_s=70"]
    p0 = summary["points"][0]
    vals = [x["metrics"]["modes"]["dgp"]["sq_mean_error"] for x in runs if x["point"] == 0]
    d = p0["modes"]["dgp"]["sq_mean_error"]
    lo, hi = sps.t.interval(0.95, 1, loc=np.mean(vals), scale=sps.sem(vals))
    assert d["n"] == 2 and d["mean"] == pytest.approx(np.mean(vals)) and d["ci_low"] == pytest.approx(lo)
    assert d["ci_high"] == pytest.approx(hi)
    ratios = [
        x["metrics"]["modes"]["none"]["mean_sq_error"] / x["metrics"]["modes"]["dgp"]["mean_sq_error"]
        for x in runs
        if x["point"] == 0
    ]
    assert p0["ratios"]["mean_sq_error"]["none/dgp"]["mean"] == pytest.approx(np.mean(ratios))
    assert set(p0["ordering"]) == {"mean_sq_error", "sq_mean_error"}
    assert p0["gain_condition"]["lambda_H"]["mean"] > 0 and "position_error_tv_mps" in p0["modes"]["dgp"]
    csv = (out / "summary.csv").read_text().splitlines()
    assert csv[0].startswith("point,label,") and "gains.k_s" in csv[0]
    assert any(",ratio,none/dgp,sq_mean_error," in line for line in csv)
    for png in ("errors.png", "ratios.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    sj = json.loads((out / "sweep.json").read_text())
    assert sj["plan"]["seeds"] == 2 and sj["plan"]["grid"][-1] == ["gains.k_s", [10, 70]]
    assert (
        sj["wall_seconds"] > 0
        and sj["finished"]
        and {"numpy", "scipy", "numba", "flightstack"} <= set(sj["versions"])
    )
    assert sj["plan"]["base_mission"]["name"] == "paper_sim" and "sweep" in sj["command"]


@pytest.mark.system
def test_rerun_skips_finished_and_reruns_a_deleted_result(
    gp_sweep: tuple[Path, subprocess.CompletedProcess], tmp_path: Path
) -> None:
    out = tmp_path / "copy"
    shutil.copytree(gp_sweep[0], out)
    args = ["--seeds", "2", "--jobs", "2", *GP_SHORT, "--set", "gains.k_s=10,70"]
    r = _sweep(out, *args)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "4 finished already, skipped; 0 to run" in r.stdout
    victim = sorted((out / "runs").glob("*.json"))[1]
    before = json.loads(victim.read_text())
    victim.unlink()
    r = _sweep(out, *args)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "3 finished already, skipped; 1 to run" in r.stdout
    after = json.loads(victim.read_text())
    assert (
        after["metrics"]["modes"]["dgp"]["mean_sq_error"]
        == before["metrics"]["modes"]["dgp"]["mean_sq_error"]
    )
    sj = json.loads((out / "sweep.json").read_text())
    assert sj["ran"] == 1 and len(sj["history"]) == 2
    # another plan in the same directory: refused (exit 2) unless --force, which keeps the finished runs
    r = _sweep(out, *args[:1], "3", *args[2:])
    assert r.returncode == 2 and "another plan" in r.stderr and "seeds" in r.stderr
    r = _sweep(out, "--seeds", "3", *args[2:], "--force")
    assert r.returncode == 0 and "4 finished already, skipped; 2 to run" in r.stdout, r.stderr[-3000:]


@pytest.mark.system
def test_invalid_set_exits_2_naming_the_key_before_anything_runs(tmp_path: Path) -> None:
    out = tmp_path / "bad"
    r = _sweep(out, "--seeds", "2", "--set", "gains.k_s=10,-5")
    assert r.returncode == 2 and "gains.k_s" in r.stderr and "greater than or equal to 0" in r.stderr
    r = _sweep(out, "--seeds", "2", "--set", "gp.no_such_key=1")
    assert r.returncode == 2 and "gp.no_such_key: unknown key" in r.stderr
    r = _sweep(out, "--seeds", "1", "--rig", "lab-sim")  # paper_sim has no cameras for the lab rig
    assert r.returncode == 2
    assert not out.exists()


@pytest.mark.system
def test_dask_scheduler_path(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "dask"
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        r = _sweep(out, "--seeds", "2", *NO_GP, "--keep-runs", "--scheduler", cluster.scheduler_address)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Dask cluster" in r.stdout
    runs = sorted((out / "runs").glob("*.json"))
    assert len(runs) == 2
    for p in runs:
        assert (out / "runs" / p.stem / "metrics.json").is_file()  # --keep-runs: the run's directory
    s = json.loads((out / "summary.json").read_text())
    assert s["points"][0]["modes"]["oracle"]["mean_sq_error"]["mean"] < 1e-20


@pytest.mark.system
def test_ctrl_c_keeps_finished_runs_and_exits_130(tmp_path: Path) -> None:
    out = tmp_path / "int"
    cmd = [sys.executable, "-m", "flightstack", "sweep", "paper_sim", "--seeds", "40", "--jobs", "2"]
    cmd += ["--out", str(out), "--set", "duration_s=30", "--set", "compare_modes=[none,oracle]"]
    proc = subprocess.Popen(
        cmd,
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: Ctrl-C reaches the sweep and its workers
    )
    try:
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and not list((out / "runs").glob("*.json")) and proc.poll() is None:
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-3000:]
    kept = list((out / "runs").glob("*.json"))
    assert 1 <= len(kept) < 40 and not list((out / "runs").glob(".*tmp*"))
    assert json.loads((out / "sweep.json").read_text())["interrupted"] is True
