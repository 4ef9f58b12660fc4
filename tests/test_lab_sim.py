"""The paper's experiment on the simulated lab, end to end (issue 3 acceptance), plus safety in the loop."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.config.mission import load_mission
from flightstack.config.rig import resolved_document
from tests.conftest import MISSIONS, fly_mode, interrupt_cli_sim, run_cli, terminal_lines

LAB = MISSIONS / "paper_experiment.yaml"


def mission_copy(tmp_path: Path, **changes: object) -> Path:
    """A copy of the lab mission with top-level keys replaced, calibration paths made absolute."""
    d = resolved_document(LAB)  # the experiment on its lab-sim rig, calibration paths absolute
    d.update(changes)
    out = tmp_path / "mission.yaml"
    out.write_text(yaml.safe_dump(d))
    return out


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lab")
    r = run_cli("sim", str(LAB), "--out", str(out), "--duration", "45", "--no-progress")
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def test_lab_mission_keeps_target_in_view_and_inside_the_fence(lab_run: Path) -> None:
    m = json.loads((lab_run / "metrics.json").read_text())
    for mode in ("none", "local", "dgp"):
        mm = m["modes"][mode]
        assert mm["ticks"] == 900 and mm["error"] is None
        assert mm["visible_fraction"]["1"] >= 0.9  # the observing drone
        assert mm["visible_fraction"]["2"] == 0.0  # the other one never sees the target
        assert mm["max_fence_excursion_m"] == 0.0
        assert 0.0 < mm["mean_position_error_m"] < 0.3
        assert np.isfinite(mm["mean_sq_error"])
    assert m["modes"]["none"]["mean_sq_error"] > m["modes"]["dgp"]["mean_sq_error"]
    assert isinstance(m["safety_events"], list) and m["safety_events"]
    assert {e["kind"] for e in m["safety_events"]} >= {"takeoff", "land"}
    assert m["gain_condition"]["kappa"] < 0  # the paper's experiment violates Theorem 1 (its Sec. 6)


def test_lab_mission_lands_every_drone_each_mode(lab_run: Path) -> None:
    events = [json.loads(x) for x in (lab_run / "events.jsonl").read_text().splitlines()]
    for mode in ("none", "local", "dgp"):
        landed = [e for e in events if e["event"] == "landed" and e["mode"] == mode]
        assert {e["drone"] for e in landed} == {1, 2}
        assert all(e["height_m"] == 0.0 for e in landed)
    assert not [e for e in events if e["event"] == "NOT LANDED"]
    # clean: no pose judged stale, frozen or disagreeing with the drone's own height (pose_check)
    suspect = {"pose_stale_hover", "pose_stale_land", "pose_frozen", "pose_disagrees", "robot_pose_suspect"}
    assert not [e for e in events if e.get("kind") in suspect]
    ts = np.load(lab_run / "timeseries_dgp.npz")
    assert ts["g_wi"][:, :, 2].min() > 0.5  # flying during the whole pursuit


def test_train_then_fly_with_saved_experts(lab_run: Path, tmp_path: Path) -> None:
    experts = tmp_path / "experts.npz"
    r = run_cli("train", str(lab_run), "--out", str(experts))
    assert r.returncode == 0, r.stderr
    assert "drone 1: 10 samples" in r.stdout and experts.is_file()
    mission = mission_copy(
        tmp_path,
        compare_modes=["dgp"],
        duration_s=10.0,
        gp={**resolved_document(LAB)["gp"], "experts_file": str(experts)},
    )
    out = tmp_path / "run"
    r = run_cli("sim", str(mission), "--out", str(out), "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert list(m["modes"]) == ["dgp"] and m["modes"]["dgp"]["ticks"] == 200
    assert not (out / "timeseries_none.npz").exists()  # no data run: the experts came from the file
    # the experts used are the ones trained (same data, same hyperparameters)
    saved, used = np.load(experts), np.load(out / "experts.npz")
    assert set(saved.files) == set(used.files)
    for k in saved.files:
        assert np.array_equal(saved[k], used[k])


def test_train_reports_missing_recording(tmp_path: Path) -> None:
    r = run_cli("train", str(tmp_path), "--mission", str(LAB), "--out", str(tmp_path / "e.npz"))
    assert r.returncode == 2 and "no recording" in r.stderr
    assert not (tmp_path / "e.npz").exists()


def test_tight_geofence_stops_the_pursuit_at_the_fence() -> None:
    """The target drives to x = +0.5 m; a soft fence at x = 0.2 m must hold drone 1 back."""
    m = load_mission(
        LAB,
        {
            "duration_s": 25.0,
            "safety": {"fence_lo": [-2.0, -2.0, 0.3], "fence_hi": [0.2, 2.0, 2.0], "hard_margin": 0.3},
        },
    )
    rec = fly_mode(m, "none")
    assert rec.error is None
    x = rec.g_wi[:, 0, 0]
    assert x.max() < 0.2 + 0.3  # never reaches the hard fence
    assert x.max() > 0.1  # it did pursue up to the fence
    kinds = [e.get("kind") for e in rec.events if e["event"] == "safety"]
    assert "fence_soft" in kinds and "fence_hard_land" not in kinds


def test_exception_in_an_agent_lands_everyone_and_keeps_the_data() -> None:
    m = load_mission(LAB, {"duration_s": 10.0})

    class Exploding:
        calls = 0

        def predict_one(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            Exploding.calls += 1
            if Exploding.calls > 100:
                raise RuntimeError("GP blew up")
            return np.zeros(4), np.ones(4)

        def prior_var(self) -> np.ndarray:
            return np.ones(4)

    rec = fly_mode(m, "local", {1: Exploding(), 2: Exploding()})
    assert rec.error == "RuntimeError: GP blew up"
    assert 40 <= rec.ticks_done <= 60 and rec.t.shape[0] == rec.ticks_done
    landed = [e for e in rec.events if e["event"] == "landed"]
    assert {e["drone"] for e in landed} == {1, 2} and all(e["height_m"] == 0.0 for e in landed)


def test_sigint_mid_flight_lands_and_leaves_a_readable_recording(tmp_path: Path) -> None:
    """Also what the console shows: each safety line on a line of its own above the progress bar (the
    takeoffs are logged while the bar is drawn), and stdout ending on the interrupt, not on a complete
    run's "recording complete"."""
    out = tmp_path / "run"
    code, stderr, stdout = interrupt_cli_sim(LAB, out, run_seconds=2.0)
    assert code == 130, stderr[-2000:]
    screen = terminal_lines(stderr)
    logged = [ln for ln in screen if "flightstack.safety:" in ln]
    assert any("takeoff" in ln for ln in logged), screen
    assert all(ln.startswith(("info: ", "warning: ")) for ln in logged), logged
    assert any(ln.startswith("mode none") for ln in screen), screen
    lines = stdout.splitlines()
    assert "  recording complete" not in lines, stdout
    ends = [ln for ln in lines if ln.startswith("  INTERRUPTED")]
    assert ends and ends[0].startswith("  INTERRUPTED (Ctrl-C or another signal) in mode none after"), stdout
    assert lines[lines.index(ends[0]) - 1] == "  recording complete up to the interrupt", stdout
    events = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines()]
    landed = [e for e in events if e["event"] == "landed"]
    assert {e["drone"] for e in landed} == {1, 2} and all(e["height_m"] == 0.0 for e in landed)
    ts = np.load(out / "timeseries_none.npz")
    assert ts["t"].shape[0] > 0 and np.all(np.isfinite(ts["g_wi"]))
    assert json.loads((out / "metrics.json").read_text())["interrupted"] is True
