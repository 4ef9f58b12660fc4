"""CLI conventions of `run`/`sim`/`fly`/`agent`, in process: `--out` refuses a non-empty
directory unless `--force` (which removes exactly the files a run writes), a time-stamped default run
directory, progress bars only on a terminal, a run too short to train refused before anything flies, no
made-up gain condition without experts, and a landed drone of the ideal simulation at a height >= 0."""

from __future__ import annotations

import datetime
import io
import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from flightstack.cli import app as cli
from flightstack.cli.run import default_out_dir, want_progress
from flightstack.config.mission import Mission, load_mission
from flightstack.config.rig import resolved_document
from flightstack.learning.training import bands, predicted_target_path, training_shortfall
from flightstack.paper.geometry import Pose
from flightstack.paper.target_motion import DuffingField, DuffingParams
from flightstack.recording.files import PLOTS, RUN_FILES, is_run_file, run_files
from flightstack.recording.run_reader import read_run, resolved_mission
from flightstack.runtime.flight import Flight
from flightstack.sim_backend.ideal import IdealDrone
from flightstack.sim_backend.world import World
from tests.conftest import MISSIONS, fly_mode

GP_SECONDS = 0.3
"""The GP run's length (s): 150 ticks of paper_sim, the bands placed so that each gets a third."""


def _write(path: Path, doc: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


def _small_mission(tmp_path: Path, duration_s: float = 0.05) -> Path:
    """paper_sim (ideal rig, 500 Hz) flying mode `none` only, for duration_s (s)."""
    doc = resolved_document("paper_sim")
    doc.update(duration_s=duration_s, compare_modes=["none"])
    return _write(tmp_path / "small.yaml", doc)


@pytest.fixture(scope="module")
def gp_mission(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """paper_sim for GP_SECONDS with modes none and dgp, 2 samples per region, one restart, and band
    edges at the target's predicted x after 1/3 and 2/3 of the run: a short run that trains experts."""
    m = load_mission("paper_sim", {"duration_s": GP_SECONDS})
    x = predicted_target_path(m)[:, 0]
    n = len(x)
    doc = resolved_document("paper_sim")
    doc.update(duration_s=GP_SECONDS, compare_modes=["none", "dgp"])
    doc["gp"].update(
        samples_per_region=2,
        restarts=1,
        regions={"axis": "x", "edges": sorted([float(x[n // 3]), float(x[2 * n // 3])])},
    )
    return _write(tmp_path_factory.mktemp("gp") / "gp.yaml", doc)


@pytest.fixture(scope="module")
def gp_run(gp_mission: Path) -> Path:
    """The run directory of `flightstack sim GP_MISSION` (data run, training, dgp, plots)."""
    out = gp_mission.parent / "run"
    assert cli.main(["sim", str(gp_mission), "--out", str(out), "--no-progress"]) == 0
    return out


# ---- --out, --force, the default run directory ------------------------------------------------------------
def test_every_file_a_run_writes_is_in_run_files(gp_run: Path) -> None:
    """RUN_FILES is the one list of what a run writes: a full run (data run, experts, dgp, plots) writes
    nothing else, and --force would remove all of it."""
    names = {p.name for p in gp_run.iterdir()}
    for expected in ("timeseries_none.npz", "timeseries_dgp.npz", "experts.npz", "datasets.npz"):
        assert expected in names
    # loop_health.png only when ticks were timed: this ideal-rig run flies in compiled chunks
    assert set(PLOTS.values()) - {PLOTS["loop_health"]} <= names
    assert {"metrics.json", "events.jsonl", "recording.json", "mission_resolved.yaml"} <= names
    assert sorted(gp_run.iterdir()) == run_files(gp_run)
    assert json.loads((gp_run / "metrics.json").read_text())["gain_condition"]["evaluated"] is True


def test_is_run_file_knows_only_what_a_run_writes() -> None:
    for name in ("timeseries_dgp.npz", "timeseries_x.rows", ".metrics.json.tmp123", "emulated_lab"):
        assert is_run_file(name), name
    for name in ("notes.txt", "timeseries.csv", "my_experts.npz", "README.md", ".git"):
        assert not is_run_file(name), name
    assert "timeseries_*.npz" in RUN_FILES


def test_out_refuses_a_non_empty_directory_unless_force(
    gp_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The motivating bug: a stale timeseries_dgp.npz survived a new run and `train --from-mode dgp`
    read it. Now the reuse is refused; --force removes the earlier run's files and nothing else."""
    out = tmp_path / "run"
    shutil.copytree(gp_run, out)
    (out / "notes.txt").write_text("mine")
    (out / "mine").mkdir()
    (out / "mine" / "timeseries_dgp.npz").write_bytes(b"not ours")  # not at the top: kept
    before = sorted(out.rglob("*"))
    small = _small_mission(tmp_path)
    assert cli.main(["sim", str(small), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: not empty" in err and "--force" in err and "nothing took off" in err
    assert sorted(out.rglob("*")) == before  # nothing touched

    assert cli.main(["sim", str(small), "--out", str(out), "--no-progress", "--force"]) == 0
    assert "--force: removed" in capsys.readouterr().err
    names = {p.name for p in out.iterdir()}
    assert not {"timeseries_dgp.npz", "experts.npz", "datasets.npz"} & names  # the earlier run's: gone
    assert {"notes.txt", "mine", "timeseries_none.npz", "metrics.json"} <= names
    assert (out / "mine" / "timeseries_dgp.npz").read_bytes() == b"not ours"
    assert cli.main(["train", str(out), "--from-mode", "dgp", "--out", str(tmp_path / "e.npz")]) == 2
    assert "no recording of mode 'dgp'" in capsys.readouterr().err


def test_an_empty_out_directory_is_fine(tmp_path: Path) -> None:
    out = tmp_path / "empty"
    out.mkdir()
    assert cli.main(["sim", str(_small_mission(tmp_path)), "--out", str(out), "--no-progress"]) == 0
    assert (out / "timeseries_none.npz").is_file()


def test_without_out_a_time_stamped_directory_under_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    small = _small_mission(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert cli.main(["sim", str(small), "--no-progress"]) == 0
    (run,) = (work / "runs").iterdir()
    assert re.fullmatch(r"paper_sim-\d{8}-\d{6}", run.name), run.name
    assert (run / "metrics.json").is_file()
    assert f"run directory: runs/{run.name}" in capsys.readouterr().err


def test_default_out_dir_is_new_and_file_name_safe(tmp_path: Path) -> None:
    now = datetime.datetime(2020, 1, 2, 3, 4, 5)
    first = default_out_dir("paper sim/2", now, tmp_path)
    assert first == tmp_path / "paper_sim_2-20200102-030405"
    first.mkdir()
    assert default_out_dir("paper sim/2", now, tmp_path) == tmp_path / "paper_sim_2-20200102-030405-2"


def test_agent_out_refuses_a_non_empty_directory_unless_force(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_bus(*args: object, **kwargs: object) -> None:
        raise RuntimeError("no bus in this test")

    monkeypatch.setattr("flightstack.comms.factory.make_bus", no_bus)
    doc = yaml.safe_load(_small_mission(tmp_path).read_text())
    eps = {p: f"tcp/127.0.0.1:{7400 + int(p)}" for p in "123"}
    doc["bus"] = {"kind": "zenoh", "zenoh": {"endpoints": eps, "security": "plaintext"}}
    mission = _write(tmp_path / "zenoh.yaml", doc)
    out = tmp_path / "a1"
    out.mkdir()
    (out / "timeseries_dgp.npz").write_bytes(b"stale")  # a mode this agent does not fly
    (out / "notes.txt").write_text("mine")
    args = ["agent", str(mission), "--id", "1", "--mode", "none", "--out", str(out)]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: not empty" in err and "--force" in err
    assert (out / "timeseries_dgp.npz").read_bytes() == b"stale"
    assert cli.main([*args, "--force"]) == 1  # past the check: the (patched) bus fails
    assert "no bus in this test" in capsys.readouterr().err
    assert not (out / "timeseries_dgp.npz").exists() and (out / "notes.txt").read_text() == "mine"


# ---- progress bars --------------------------------------------------------------------------------------
class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_want_progress_follows_the_terminal_unless_told() -> None:
    assert want_progress(None, _Tty()) is True
    assert want_progress(None, io.StringIO()) is False
    assert want_progress(True, io.StringIO()) is True
    assert want_progress(False, _Tty()) is False


@pytest.mark.parametrize(("flag", "bars"), [(None, False), ("--progress", True), ("--no-progress", False)])
def test_progress_bars_only_on_a_terminal_or_with_progress(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str | None, bars: bool
) -> None:
    """Under pytest stderr is not a terminal: no bars unless --progress. The summary of a run without
    experts says the gain condition was not evaluated (no `L_mu = 0.000`)."""
    extra = [flag] if flag else []
    assert cli.main(["sim", str(_small_mission(tmp_path)), "--out", str(tmp_path / "run"), *extra]) == 0
    cap = capsys.readouterr()
    assert ("mode none" in cap.err) is bars, cap.err
    assert "gain condition: not evaluated (no GP expert" in cap.out and "L_mu =" not in cap.out


# ---- a run too short to train ---------------------------------------------------------------------------
def test_paper_sim_for_2_s_is_too_short_to_train() -> None:
    msg = training_shortfall(load_mission("paper_sim", {"duration_s": 2.0}))
    assert msg is not None
    assert "duration_s = 2 s is too short to train" in msg
    assert "drone 3's band x >= 0.6: 0 ticks" in msg and "gp.samples_per_region = 10" in msg
    assert re.search(r"fly at least \d+(\.\d)? s \(--duration, or duration_s\)", msg), msg
    assert "lower gp.samples_per_region" in msg


def test_long_enough_runs_and_runs_that_train_nothing_pass() -> None:
    assert training_shortfall(load_mission("paper_sim")) is None  # 40 s
    assert training_shortfall(load_mission("paper_sim", {"duration_s": 40.0})) is None
    assert training_shortfall(load_mission("paper_experiment")) is None  # the square, 80 s
    assert (
        training_shortfall(load_mission("paper_sim", {"duration_s": 2.0, "compare_modes": ["none"]})) is None
    )
    m = load_mission("paper_sim", {"duration_s": 2.0})
    with_experts = m.model_copy(update={"gp": m.gp.model_copy(update={"experts_file": "experts.npz"})})
    assert training_shortfall(with_experts) is None


def test_the_suggested_duration_is_enough() -> None:
    msg = training_shortfall(load_mission("paper_sim", {"duration_s": 2.0}))
    assert msg is not None
    match = re.search(r"fly at least (\d+(?:\.\d)?) s", msg)
    assert match is not None
    assert training_shortfall(load_mission("paper_sim", {"duration_s": float(match.group(1))})) is None


def test_the_predicted_path_is_the_simulators() -> None:
    """duffing: the ideal world's own step (World.step); square: on the 1 m square, every band filled."""
    m = load_mission("paper_sim", {"duration_s": 1.0})
    path = predicted_target_path(m)
    p0 = m.target.initial_pose
    world = World(
        Pose.make(list(p0.p), p0.theta), DuffingField(DuffingParams(**m.target.duffing.model_dump())), {}
    )
    for k in range(len(path)):
        assert np.allclose(path[k], world.target.pose.as_vector(), atol=1e-12), k
        world.step(m.dt_s)
    sq = load_mission("paper_experiment")
    path = predicted_target_path(sq)
    assert len(path) == round(sq.duration_s / sq.dt_s) and np.abs(path[:, :2]).max() <= 0.5 + 1e-9
    for lo, hi in bands(sq):
        assert ((path[:, 0] >= lo) & (path[:, 0] < hi)).sum() >= sq.gp.samples_per_region


def test_a_ctrl_c_while_a_mode_is_assembled_still_writes_an_interrupted_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A SIGINT can arrive before the runner's handlers are in place (the kernels loading on a busy
    computer): the flight ends as interrupted and metrics.json says so, and the mode's recording is closed
    (no tick, its end event), so that the recording is complete with what there is."""
    calls: list[str] = []

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        calls.append(args[1])
        raise KeyboardInterrupt

    monkeypatch.setattr("flightstack.runtime.flight.assemble_fleet", interrupted)
    out = tmp_path / "run"
    code = cli.main(
        ["sim", "paper_sim", "--duration", "0.1", "--modes", "none", "--out", str(out), "--no-progress"]
    )
    assert code == 130 and calls == ["none"]
    m = json.loads((out / "metrics.json").read_text())
    assert m["interrupted"] is True and m["modes"] == {}
    assert m["recording"]["complete"] is True, m["recording"]
    state = json.loads((out / "recording.json").read_text())["modes"]["none"]
    assert state["state"] == "closed" and state["ticks_done"] == 0, state
    ends = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines() if '"end"' in x]
    assert [(e["mode"], e["reason"], e["before_takeoff"]) for e in ends] == [("none", "interrupted", True)]


def test_a_mode_that_fails_while_landing_keeps_its_flown_rows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An exception after the mode has flown (here in finish_recording, after the landing): the error ends
    the run, and the recording is still closed with every flown tick, never as an unflown mode."""

    def broken(*args: Any, **kwargs: Any) -> None:
        raise RuntimeError("broken after the landing")

    monkeypatch.setattr("flightstack.runtime.runner.finish_recording", broken)
    out = tmp_path / "run"
    code = cli.main(
        ["sim", "paper_sim", "--duration", "1", "--modes", "none", "--out", str(out), "--no-progress"]
    )
    assert code != 0
    mission, _ = resolved_mission(out)
    state = json.loads((out / "recording.json").read_text())["modes"]["none"]
    assert state["state"] == "closed" and state["final"] == "timeseries_none.npz", state
    recs = read_run(out, mission).recordings
    assert recs["none"].ticks_done == round(1.0 / mission.dt_s), recs["none"].ticks_done
    assert not any(e.get("before_takeoff") for e in recs["none"].events), recs["none"].events


def test_cli_refuses_a_run_too_short_to_train_before_flying(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_flight(*args: object, **kwargs: object) -> None:
        raise AssertionError("took off")

    monkeypatch.setattr("flightstack.runtime.flight.Flight.fly", no_flight)
    out = tmp_path / "run"
    assert cli.main(["sim", "paper_sim", "--duration", "2", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "too short to train" in err and "drone 3's band" in err and "nothing took off" in err
    assert not out.exists()


def test_a_data_run_that_still_comes_up_short_says_so_and_evaluates_no_gain_condition() -> None:
    """The check after the data run stays (the prediction ignores the estimates' transient); without
    experts metrics.json says the gain condition was not evaluated instead of L_mu = 0."""
    with Flight(load_mission("paper_sim", {"duration_s": 0.05})) as flight:
        res = flight.fly()
    assert res.error is not None and res.error.startswith("GP training data: drone")
    assert list(res.recordings) == ["none"] and not res.experts
    gc = res.metrics["gain_condition"]
    assert isinstance(gc, dict) and gc["evaluated"] is False and "no GP expert" in gc["reason"]
    assert "kappa" not in gc and "L_mu" not in gc and "satisfied" not in gc


# ---- the ideal simulation's landed height ---------------------------------------------------------------
def _mission(duration_s: float) -> Mission:
    return load_mission(MISSIONS / "paper_sim.yaml", {"duration_s": duration_s, "compare_modes": ["none"]})


def test_landed_drones_of_the_ideal_sim_report_a_height_of_at_least_0() -> None:
    rec = fly_mode(_mission(0.05), "none")
    landed = [e for e in rec.events if e["event"] == "landed"]
    assert {e["drone"] for e in landed} == {1, 2, 3}
    assert all(e["height_m"] >= 0.0 for e in landed), landed


def test_ideal_drone_reports_its_world_z_while_flying_and_0_once_landed() -> None:
    world = World(
        Pose.make([0.0, 0.0, 0.0], 0.0), lambda g: np.zeros(4), {1: Pose.make([0.0, 0.0, -1.5], 0.0)}
    )
    drone = IdealDrone(world, 1)
    assert drone.state().flying and drone.state().height_m == -1.5  # z is the optical axis here
    drone.land()
    assert not drone.state().flying and drone.state().height_m == 0.0


def test_set_changes_a_dotted_key_after_the_rig_and_bad_ones_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from flightstack.cli.run import with_sets

    m = load_mission("paper_experiment", rig="lab-sim")
    changed = with_sets(m, ["compensation.enabled=true", "gains.k_e=[6,6,6,6]", "sim.render.model=centres"])
    assert changed.compensation.enabled and list(changed.gains.k_e) == [6.0] * 4
    assert changed.sim.render.model == "centres" and changed.rig == m.rig
    assert changed.drones == m.drones  # the rest untouched (calibration paths made absolute, same files)
    assert with_sets(m, ["seed=7"]).seed == 7  # a mission key here; only a sweep sets it itself (--seeds)
    for bad, says in [
        ("seed=", "--set seed: empty value"),  # it pointed to --seeds, an option of sweep, not of run
        ("compensation.enabled=maybe", "compensation.enabled"),
        ("compensation.enabld=true", "compensation.enabld: unknown key"),
        ("gains.k_s=1,4", "one value"),
        ("gains.k_s", "KEY=V"),
    ]:
        code = cli.main(
            ["run", "paper_experiment", "--rig", "lab-sim", "--set", bad, "--out", str(tmp_path / "x")]
        )
        assert code == 2, bad
        assert says in capsys.readouterr().err, bad
    assert not (tmp_path / "x").exists()  # nothing flew, nothing written
