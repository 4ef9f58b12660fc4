"""`validate` (and `run` before takeoff) refuse what cannot run: too many drones (refused fast, without the
complete graph's quadratic list), a recording larger than the computer's memory, gains beyond the sampled
loop's divergence bound; every shipped experiment still validates."""

from __future__ import annotations

import itertools
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.cli.app import main
from flightstack.config.mission import MAX_DRONES, MissionError, load_mission, parse_mission
from flightstack.config.rig import resolved_document
from flightstack.paper.gain_analysis import (
    MAX_RATE_DT,
    fastest_error_rate,
    laplacian,
    own_loop_rate,
)
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording, recording_nbytes
from flightstack.runtime import resources
from tests.conftest import MISSIONS, random_recording, run_cli

EXPERIMENTS = sorted(p for p in MISSIONS.glob("*.yaml"))


def paper() -> dict:
    return resolved_document("paper_sim")


def with_drones(doc: dict, n: int) -> dict:
    """paper_sim's document flown by n drones (ids 0..n-1, one band each)."""
    doc["drones"] = [{"id": i, "desired_pose": {"p": [0.5, 0.0, 1.5], "theta": 0.0}} for i in range(n)]
    doc["gp"]["regions"]["edges"] = [float(i) for i in range(n - 1)]
    return doc


# ---- the drone bound and the graph ------------------------------------------------------------------------
def test_9000_drones_are_refused_at_once_with_little_memory() -> None:
    doc = with_drones(paper(), 9000)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(MissionError) as exc:
            parse_mission(doc, "m.yaml")
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert f"drones: 9000 drones; at most {MAX_DRONES}" in str(exc.value)
    assert "scaling missions fly 31" in str(exc.value)
    # the complete graph as a list of 40 M tuples took 4.4 GB; the refusal takes a few MB at most
    print(f"refused in {1e3 * elapsed:.0f} ms, peak {peak / 1e6:.1f} MB")
    assert peak < 20e6, peak


def test_the_largest_mission_validates_without_listing_its_complete_graph() -> None:
    doc = with_drones(paper(), MAX_DRONES)
    doc["gains"]["k_s"] = 0.2  # (261.8 + 0.2 · 1000) · 0.002 < 2
    tracemalloc.start()
    try:
        m = parse_mission(doc, "m.yaml")
        assert m.edge_count() == MAX_DRONES * (MAX_DRONES - 1) // 2
        assert m.laplacian_lambda_max() == MAX_DRONES
        assert m.neighbours(7) == [j for j in range(MAX_DRONES) if j != 7]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 60e6, peak  # the pair list alone: 499,500 tuples, ~ 70 MB


@pytest.mark.parametrize("kind", ["complete", "edges"])
def test_graph_queries_agree_with_the_edge_list(kind: str) -> None:
    """neighbours, edge_count and λ_max(L) equal what the listed pairs give (an independent reference)."""
    rng = np.random.default_rng(3)
    doc = with_drones(paper(), 9)
    for i, d in enumerate(doc["drones"]):
        d["id"] = 10 + 3 * i  # ids that are not indices
    ids = [d["id"] for d in doc["drones"]]
    edges = [[int(a), int(b)] for a, b in rng.choice(ids, size=(14, 2))] + [
        [ids[0], ids[1]],
        [ids[1], ids[0]],
    ]
    doc["graph"] = {"kind": kind, "edges": edges if kind == "edges" else []}
    doc["gains"]["k_s"] = 10.0
    m = parse_mission(doc, "m.yaml")
    pairs = m.edge_index_pairs()
    if kind == "complete":
        assert pairs == list(itertools.combinations(range(9), 2))
    else:
        index = {i: k for k, i in enumerate(ids)}
        assert pairs == sorted({tuple(sorted((index[a], index[b]))) for a, b in edges if a != b})
    assert m.edge_count() == len(pairs)
    for k in range(9):
        assert m.neighbours(k) == sorted({b for a, b in pairs if a == k} | {a for a, b in pairs if b == k})
    assert m.laplacian_lambda_max() == pytest.approx(np.linalg.eigvalsh(laplacian(9, pairs))[-1], abs=1e-12)


# ---- the sampled loop's divergence bound ------------------------------------------------------------------
def test_own_loop_rate_is_the_largest_eigenvalue_of_nt_k_n() -> None:
    """Reference: numpy's eigenvalues of NᵀKN with N = [[I, 0], [−I, I]] (θ_c = 0), K = diag(k_c, k_e)."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        k_c, k_e = rng.uniform(0.1, 500, 4), rng.uniform(0.1, 500, 4)
        N = np.block([[np.eye(4), np.zeros((4, 4))], [-np.eye(4), np.eye(4)]])
        K = np.diag(np.concatenate([k_c, k_e]))
        assert own_loop_rate(k_c, k_e) == pytest.approx(np.linalg.eigvalsh(N.T @ K @ N)[-1], rel=1e-12)


def network_rate(k_c: float, k_e: float, k_s: float, L: np.ndarray, visible: np.ndarray) -> float:
    """λ_max of the linearised network error dynamics of one component, built directly: ė_c = −k_c e_c
    + v k_e (e_e − e_c), ė_e = −v k_e (e_e − e_c) − k_s L e_e (consensus c = L e_e)."""
    n = len(L)
    V = np.diag(visible.astype(float))
    M = np.block([[k_c * np.eye(n) + k_e * V, -k_e * V], [-k_e * V, k_e * V + k_s * L]])
    return float(np.linalg.eigvalsh(M)[-1])


def test_fastest_error_rate_bounds_the_network_and_is_exact_without_consensus() -> None:
    rng = np.random.default_rng(1)
    for n in (2, 3, 7):
        L = laplacian(n, list(itertools.combinations(range(n), 2)))
        for _ in range(20):
            k_c, k_e, k_s = rng.uniform(1, 300), rng.uniform(1, 300), rng.uniform(0, 100)
            visible = rng.random(n) > 0.3
            bound = fastest_error_rate([k_c] * 4, [k_e] * 4, k_s, float(n))
            assert network_rate(k_c, k_e, k_s, L, visible) <= bound * (1 + 1e-12)
            all_seen = network_rate(k_c, k_e, 0.0, L, np.ones(n, bool))
            assert all_seen == pytest.approx(fastest_error_rate([k_c] * 4, [k_e] * 4, 0.0, float(n)))


@pytest.mark.parametrize("path", EXPERIMENTS, ids=lambda p: p.stem)
def test_every_shipped_experiment_validates_and_keeps_its_loop_sampled(
    path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["validate", str(path)]) == 0
    assert capsys.readouterr().out.endswith("valid\n")
    m = load_mission(path)
    g = m.gains
    assert fastest_error_rate(g.k_c, g.k_e, g.k_s, m.laplacian_lambda_max()) * m.dt_s < MAX_RATE_DT


def test_gains_of_a_million_are_refused_naming_the_key_and_the_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = paper()
    doc["gains"] = {"k_c": [1e6] * 4, "k_e": [1e6] * 4, "k_s": 70}
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "gains: the sampled loop diverges" in err
    assert "(2.61803e+06 + 70 · 3) · 0.002 s = 5236, must be < 2" in err


def test_gains_just_below_the_bound_validate_and_just_above_are_refused() -> None:
    k_ok = 0.97 * MAX_RATE_DT / 0.002 / own_loop_rate([1.0] * 4, [1.0] * 4)  # rate ∝ k for k_c = k_e = k
    for k, ok in ((k_ok, True), (k_ok * 1.03 / 0.97, False)):
        doc = paper()
        doc["gains"] = {"k_c": [k] * 4, "k_e": [k] * 4, "k_s": 0.0}
        if ok:
            parse_mission(doc, "m.yaml")
        else:
            with pytest.raises(MissionError, match="gains: the sampled loop diverges"):
                parse_mission(doc, "m.yaml")


# ---- the recording's memory -------------------------------------------------------------------------------
def test_recording_nbytes_is_what_empty_allocates() -> None:
    for n, ticks in ((1, 1), (3, 100), (31, 17)):
        rec = Recording.empty("none", list(range(n)), ticks)
        assert recording_nbytes(n, ticks) == sum(getattr(rec, f).nbytes for f in ARRAY_FIELDS)


def test_available_memory_is_read_from_meminfo(tmp_path: Path) -> None:
    info = tmp_path / "meminfo"
    info.write_text("MemTotal:       16000000 kB\nMemFree:  100 kB\nMemAvailable:    8000000 kB\n")
    assert resources.available_memory_bytes(info) == 8000000 * 1024
    info.write_text("MemTotal:       16000000 kB\n")
    assert resources.available_memory_bytes(info) is None
    assert resources.available_memory_bytes(tmp_path / "missing") is None


def test_a_recording_larger_than_the_available_memory_is_refused_naming_the_numbers() -> None:
    m = load_mission("paper_sim")  # 3 modes × 20,000 ticks × 3 drones, 1003 bytes per tick
    need = resources.recording_memory_bytes(m)
    assert need == 3 * recording_nbytes(3, 20000) == 3 * 20000 * 1003
    resources.check_recording_fits(m, available_bytes=int(need / resources.MEMORY_FRACTION))
    with pytest.raises(MissionError) as exc:
        resources.check_recording_fits(m, available_bytes=int(need / resources.MEMORY_FRACTION) - 1)
    msg = str(exc.value)
    assert msg.startswith("paper_sim: duration_s / dt_s: the recording needs 0.056 GiB of memory")
    assert "3 mode(s) none, local, dgp × 20000 ticks × 3 drone(s), 1003 bytes per tick" in msg
    assert "more than 50% of the 0.112 GiB this computer has available" in msg


def test_a_mode_recording_the_recorder_cannot_close_in_time_is_refused(tmp_path: Path) -> None:
    """dt 1e-4 s for 1000 s on paper_sim (10 GB in one mode) fits a large computer's memory, but its final
    npz would take minutes to compress: refused whatever the memory (and before any memory check)."""
    m = load_mission("paper_sim").model_copy(update={"dt_s": 1e-4, "duration_s": 1000.0})
    assert recording_nbytes(3, 10_000_000) > resources.MAX_MODE_RECORDING_BYTES
    with pytest.raises(MissionError, match=r"one mode's recording would be 10030 MB .* close timeout"):
        resources.check_recording_fits(m, available_bytes=2**50)
    largest_shipped = recording_nbytes(31, 20000)  # scaling_31
    assert largest_shipped < resources.MAX_MODE_RECORDING_BYTES / 3
    resources.check_recording_fits(load_mission("scaling_31"), available_bytes=2**50)


@pytest.mark.parametrize("command", ["validate", "run"])
def test_validate_and_run_refuse_a_recording_the_computer_cannot_hold(
    command: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(resources, "available_memory_bytes", lambda: 100 * 2**20)  # 100 MiB available
    out = tmp_path / "run"
    args = ["validate", "paper_sim"] if command == "validate" else ["run", "paper_sim", "--out", str(out)]
    t0 = time.perf_counter()
    assert main(args) == 2
    assert time.perf_counter() - t0 < 10  # refused before anything flies (a flight takes minutes)
    err = capsys.readouterr().err
    assert "duration_s / dt_s: the recording needs 0.056 GiB of memory" in err
    assert "more than 50% of the 0.0977 GiB this computer has available" in err
    assert not out.exists()  # nothing was created, nothing took off


# ---- the command line end to end --------------------------------------------------------------------------
@pytest.mark.system
def test_cli_refuses_9000_drones_and_a_recording_no_computer_holds(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_text(yaml.safe_dump(with_drones(paper(), 9000), default_flow_style=None))
    t0 = time.perf_counter()
    res = run_cli("validate", str(big), timeout=120)
    assert res.returncode == 2, res.stderr
    assert "drones: 9000 drones; at most 1000" in res.stderr
    assert time.perf_counter() - t0 < 60  # it took 19 s and 4.4 GB before; the YAML parse is most of it now
    doc = resolved_document("scaling_31")
    doc.update(dt_s=1e-4, duration_s=1000.0)  # 1e7 ticks × 31 drones: ~ 280 GB for three modes
    long = tmp_path / "long.yaml"
    long.write_text(yaml.safe_dump(doc))
    for args in (("validate", str(long)), ("run", str(long), "--out", str(tmp_path / "run"))):
        res = run_cli(*args, timeout=120)
        assert res.returncode == 2, res.stderr
        assert "duration_s / dt_s: one mode's recording would be 97670 MB" in res.stderr
        assert "(10000000 ticks × 31 drone(s))" in res.stderr
    assert not (tmp_path / "run").exists()


# ---- absurd physical parameters ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["drones"][0]["desired_pose"].update(p=[0.5, 0.0, 1e300]), "drones.0.desired_pose.p.2"),
        (lambda d: d["target"]["initial_pose"].update(theta=1e9), "target.initial_pose.theta"),
        (lambda d: d["target"]["feature_points"][0].__setitem__(0, -5000.0), "target.feature_points.0.0"),
        (lambda d: d["target"]["duffing"].update(beta=1e6), "target.duffing.beta"),
        (lambda d: d["target"].update(square={"speed_mps": 300.0}), "target.square.speed_mps"),
        (lambda d: d["camera"].update(focal_length=1e300), "camera.focal_length"),
        (lambda d: d["target"].update(robot={"max_speed_mps": 1e9}), "target.robot.max_speed_mps"),
        (lambda d: d["sim"]["tello"].update(time_constant_s=1e12), "sim.tello.time_constant_s"),
        (lambda d: d["sim"]["tello"].update(takeoff_height_m=5000.0), "sim.tello.takeoff_height_m"),
        (lambda d: d["sim"]["mocap"].update(rate_hz=1e9), "sim.mocap.rate_hz"),
        (lambda d: d["drones"][1].update(rc_gains={"xy": 50.0}), "drones.1.rc_gains.xy"),
    ],
)
def test_absurd_physical_parameters_are_refused_naming_the_key(mutate, expected: str) -> None:
    doc = paper()
    doc.setdefault("sim", {}).setdefault("tello", {})
    doc["sim"].setdefault("mocap", {})
    mutate(doc)
    with pytest.raises(MissionError) as exc:
        parse_mission(doc, "m.yaml")
    assert f"{expected}: Input should be" in str(exc.value)


# ---- camera calibrations ----------------------------------------------------------------------------------
def calibration_doc(width: int, height: int, cx: float, cy: float) -> dict:
    return {
        "width": width,
        "height": height,
        "camera_matrix": [[260.0, 0.0, cx], [0.0, 260.0, cy], [0.0, 0.0, 1.0]],
        "dist_coeffs": [0.0, 0.0, 0.0, 0.0, 0.0],
    }


def test_a_principal_point_outside_the_image_is_refused() -> None:
    from flightstack.vision.camera_file import CalibrationError, calibration_from_dict

    calibration_from_dict(calibration_doc(320, 240, 160.0, 120.0))
    calibration_from_dict(calibration_doc(320, 240, -0.5, 239.5))  # the image's outer pixel edges
    for w, h, cx, cy in ((1, 240, 480.0, 120.0), (320, 240, 320.0, 120.0), (320, 240, 160.0, -1.0)):
        with pytest.raises(CalibrationError) as exc:
            calibration_from_dict(calibration_doc(w, h, cx, cy), "cam.yaml")
        assert (
            f"cam.yaml: camera_matrix: the principal point (cx, cy) = ({cx:g}, {cy:g}) px lies outside"
            in (str(exc.value))
        )
        assert f"the {w} × {h} image" in str(exc.value)


def test_validate_refuses_an_experiment_whose_calibration_has_its_principal_point_outside(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal = tmp_path / "cam.yaml"
    cal.write_text(yaml.safe_dump(calibration_doc(1, 240, 480.0, 120.0)))
    doc = resolved_document("paper_experiment")
    for d in doc["drones"]:
        d["camera"]["calibration"] = str(cal)
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "drones.0.camera.calibration: " in err
    assert "principal point (cx, cy) = (480, 120) px lies outside the 1 × 240 image" in err


# ---- a state that diverges at run time --------------------------------------------------------------------
def test_check_rows_names_the_first_diverged_tick_drone_and_quantity() -> None:
    from flightstack.runtime.divergence import (
        DIVERGED_ABOVE,
        DIVERGED_POSITION_M,
        DivergedError,
        check_rows,
    )

    rec = random_recording("none", [4, 7, 9], 50)
    check_rows(rec, 0, 50)  # normal values pass
    rec.V_cmd[30, 2, 3] = np.nan
    rec.u_e[25, 0, 0] = 0.9 * DIVERGED_ABOVE  # fast, not diverged
    rec.g_bar_w[31, 0, 0] = np.inf
    rec.g_wi[20, 1, 1] = 1.5 * DIVERGED_POSITION_M
    check_rows(rec, 0, 20)  # rows before the first bad one
    with pytest.raises(DivergedError, match=r"^diverged at t = 1 s \(drone 7, g_wi y = 1.5e\+04;"):
        check_rows(rec, 0, 50)
    # motion capture's poses are measurements: on hardware only what the stack computes is checked
    with pytest.raises(DivergedError, match=r"^diverged at t = 1.5 s \(drone 9, V_cmd θ = nan;"):
        check_rows(rec, 0, 50, simulated=False)
    rec.g_w0[5, 2] = -np.inf
    with pytest.raises(DivergedError, match=r"^diverged at t = 0.25 s \(g_w0 z = -inf;"):
        check_rows(rec, 0, 50)


def test_metrics_of_a_failed_run_are_written_with_null(tmp_path: Path) -> None:
    import json

    from flightstack.recording.run_dir import RunWriter

    writer = RunWriter(tmp_path / "run")
    try:
        with pytest.raises(ValueError):
            writer.write_metrics({"x": float("inf")})  # a finished run: a non-finite metric is a finding
        written = writer.write_metrics({"x": float("inf"), "y": [1.0, float("nan")]}, strict=False)
    finally:
        writer.close()
    assert written["x"] == float("inf")
    on_disk = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert on_disk["x"] is None and on_disk["y"] == [1.0, None]


def test_a_run_that_diverges_stops_lands_writes_metrics_and_exits_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The issue's gains of 1e6 on the ideal rig, with validation's gain bound switched off in-process."""
    import json

    from flightstack.config.mission import Mission
    from flightstack.recording.run_reader import load_run

    doc = paper()
    doc["gains"] = {"k_c": [1e6] * 4, "k_e": [1e6] * 4, "k_s": 70}
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(doc))
    monkeypatch.setattr(Mission, "_check_sampled_loop", lambda self: None)
    out = tmp_path / "run"
    code = main(["run", str(path), "--out", str(out), "--modes", "none", "--duration", "2"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert "error: diverged at t = 0.004 s (drone " in err and "every drone landed" in err
    metrics = json.loads((out / "metrics.json").read_text())  # strict JSON: non-finite values are null
    assert metrics["modes"]["none"]["error"].startswith("diverged at t = 0.004 s (drone ")
    assert metrics["modes"]["none"]["ticks"] == 3  # stopped on the third tick, not after 1000
    rec = load_run(out)["none"]  # the recording so far stays readable
    assert rec.ticks_done == 3 and np.abs(rec.u_e[2]).max() > 1e6 >= np.abs(rec.u_e[1]).max()
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert any(e.get("event") == "end" and e.get("reason") == "diverged" for e in events)
    assert any(e.get("event") == "landed" for e in events)


def test_the_ideal_rig_diverges_where_the_bound_says(monkeypatch: pytest.MonkeyPatch) -> None:
    """k_c = k_e = k, k_s = 0: 3 % below the bound the validated mission flies with errors of mm; 3 % above
    it (past validation) the ideal rig's errors grow by orders of magnitude. max(k_c, k_e)·dt is only 0.79
    there: that reading of k_max would let it fly."""
    from flightstack.config.mission import Mission
    from tests.conftest import fly_mode

    k_bound = MAX_RATE_DT / 0.002 / own_loop_rate([1.0] * 4, [1.0] * 4)
    monkeypatch.setattr(Mission, "_check_sampled_loop", lambda self: None)
    worst = {}
    for factor in (0.97, 1.03):
        gains = {"k_c": [factor * k_bound] * 4, "k_e": [factor * k_bound] * 4, "k_s": 0.0}
        over = {"duration_s": 3.0, "compare_modes": ["none"], "gains": gains}
        rec = fly_mode(load_mission("paper_sim", overrides=over), "none")
        assert rec.ticks_done == 1500 or (rec.error or "").startswith("diverged at t = ")
        worst[factor] = float(np.abs(rec.e_c[1000 : rec.ticks_done]).max())
    assert worst[0.97] < 0.01 and worst[1.03] > 10.0, worst
