"""The run's plots: the decimated lines they draw (`envelope`, `thinned`) and the plot process that draws
them beside a simulated flight (flightstack.analysis.plot_process), with the flight's own fallback."""

from __future__ import annotations

import io
import itertools
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from flightstack.analysis.plot_process import PlotProcess, serve
from flightstack.analysis.report import PLOT_POINTS, envelope, thinned, write_plots
from flightstack.config.mission import load_mission
from flightstack.learning.training import ExpertData, save_datasets
from flightstack.recording.files import DATASETS_FILE, MISSION_FILE, PLOTS
from flightstack.recording.run_dir import RunWriter
from flightstack.runtime.flight import Flight, resolved_mission_yaml
from tests.conftest import MISSIONS, random_recording

PNG = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------- envelope
@pytest.mark.parametrize("n", [1, 7, PLOT_POINTS, PLOT_POINTS + 1, 20_000, 123_457])
def test_envelope_keeps_every_extreme_in_time_order(n: int) -> None:
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.001, 0.003, n))
    y = rng.lognormal(size=n)
    spike = int(rng.integers(n))
    y[spike] = 1e6  # one sample far above the rest must stay drawn
    tt, yy = envelope(t, y)
    if n <= PLOT_POINTS:
        assert tt is t and yy is y
        return
    assert len(tt) <= PLOT_POINTS
    kept = np.searchsorted(t, tt)  # a subsequence of the samples, in time order
    assert np.array_equal(t[kept], tt) and np.array_equal(y[kept], yy) and np.all(np.diff(kept) > 0)
    assert yy.max() == y.max() == 1e6 and yy.min() == y.min()
    # independent check: every sample lies inside the [min, max] of the kept samples of its bucket
    edges = np.linspace(0, n, PLOT_POINTS // 2 + 1).astype(int)
    for i0, i1 in itertools.pairwise(edges):
        inside = (kept >= i0) & (kept < i1)
        assert inside.sum() == 2
        assert yy[inside].min() == y[i0:i1].min() and yy[inside].max() == y[i0:i1].max()


@pytest.mark.parametrize("n", [1, 5, PLOT_POINTS, PLOT_POINTS + 1, 20_000, 20_001])
def test_thinned_keeps_both_ends_within_the_budget(n: int) -> None:
    xy = np.column_stack([np.arange(n), -np.arange(n)]).astype(float)
    out = thinned(xy)
    assert len(out) <= PLOT_POINTS + 1
    assert np.array_equal(out[0], xy[0]) and np.array_equal(out[-1], xy[-1])
    step = np.diff(out[:-1, 0])
    assert len(set(step)) <= 1  # one stride (the last row may come sooner)
    if n <= PLOT_POINTS:
        assert out is xy


# ---------------------------------------------------------------------------------------------- run dir
N_TICKS = 80


def _run_dir(out: Path) -> Path:
    """A run directory of the ideal rig's mission with the final npz of `none` and `dgp` and datasets."""
    mission = load_mission(MISSIONS / "paper_sim.yaml", {"compare_modes": ["none", "dgp"]})
    ids = [d.id for d in mission.drones]
    out.mkdir(parents=True)
    (out / MISSION_FILE).write_text(resolved_mission_yaml(mission))
    run = RunWriter(out, block_period_s=0.0)
    for mode, seed in (("none", 1), ("dgp", 2)):
        rec = random_recording(mode, ids, N_TICKS, seed)
        run.mode(mode, ids, N_TICKS).close(rec, stream=False)
    assert run.drain()
    run.close()
    rng = np.random.default_rng(0)
    data = [
        ExpertData(i, (0.0, 1.0), rng.normal(size=(5, 4)), rng.normal(size=(5, 4)), np.arange(5)) for i in ids
    ]
    save_datasets(out / DATASETS_FILE, data)
    return out


def test_write_plots_only_draws_the_plots_asked_for(tmp_path: Path) -> None:
    from flightstack.analysis.report import run_mission
    from flightstack.recording.timeseries import Recording

    run = _run_dir(tmp_path / "run")
    recs = {m: Recording.load(run / f"timeseries_{m}.npz") for m in ("none", "dgp")}
    paths = write_plots(run, run_mission(run), recs, [], only={"e_c"})
    assert [p.name for p in paths] == [PLOTS["e_c"]]
    assert not (run / PLOTS["trajectory"]).exists() and not (run / PLOTS["e_e"]).exists()


def test_serve_answers_each_request_in_order_and_never_raises(tmp_path: Path) -> None:
    run = _run_dir(tmp_path / "run")
    requests = [
        {"run_dir": str(run), "plots": ["trajectory"], "modes": ["none"]},
        {"run_dir": str(run), "plots": ["e_c", "e_e", "loop_health"], "modes": ["none", "dgp"]},
        {"run_dir": str(run), "plots": ["e_c"], "modes": ["local"]},  # no such recording
        {"run_dir": str(tmp_path / "nowhere"), "plots": ["e_c"], "modes": ["none"]},
        "not a request",
        {"run_dir": str(run), "plots": ["e_c", "../../etc"], "modes": ["none"]},
        {"run_dir": str(run), "plots": ["e_c"], "modes": ["../none"]},
    ]
    stdin = io.StringIO("".join(json.dumps(r) + "\n" for r in requests) + "{broken\n")
    stdout = io.StringIO()
    serve(stdin, stdout)
    replies = [json.loads(line) for line in stdout.getvalue().splitlines()]
    assert len(replies) == len(requests) + 1
    assert replies[0] == {"written": [PLOTS["trajectory"]], "error": None}
    drawn = [PLOTS["e_c"], PLOTS["e_e"], PLOTS["loop_health"]]  # random rows: the ticks look timed
    assert replies[1] == {"written": drawn, "error": None}
    for r in replies[2:]:
        assert r["written"] == [] and r["error"], r
    print("\n".join(r["error"] for r in replies[2:]))
    assert "timeseries_local.npz" in replies[2]["error"]
    for name in PLOTS:
        assert (run / PLOTS[name]).read_bytes().startswith(PNG)


# ------------------------------------------------------------------------------------ the child process
@pytest.mark.system
def test_plot_process_draws_in_a_child_and_reports_a_dead_one(tmp_path: Path) -> None:
    run = _run_dir(tmp_path / "run")
    with PlotProcess() as child:
        child.request(run, ["trajectory"], ["none"])
        child.request(run, ["e_c", "e_e"], ["none", "dgp"])
        drawn = child.finish(timeout_s=120)
    assert child.problem is None and drawn == {"trajectory", "e_c", "e_e"}
    with PlotProcess([sys.executable, "-c", "pass"]) as dead:  # ends before it answers
        dead.request(run, ["e_c"], ["none"])
        assert dead.finish(timeout_s=30) == set()
    print(f"a dead child: {dead.problem}")
    assert dead.problem is not None


@pytest.mark.system
@pytest.mark.parametrize("child", ["works", "dies"])
def test_a_simulated_flight_gets_every_plot_whatever_its_plot_process_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, child: str
) -> None:
    import flightstack.runtime.flight as flight_module

    if child == "dies":
        monkeypatch.setattr(flight_module, "PlotProcess", lambda: PlotProcess([sys.executable, "-c", "pass"]))
    mission = load_mission(MISSIONS / "paper_sim.yaml", {"duration_s": 12.0})
    said: list[str] = []
    with Flight(mission, tmp_path / "run", plots=True, say=said.append) as flight:
        flight.fly()
    for name in ("trajectory", "e_c", "e_e"):
        assert (tmp_path / "run" / PLOTS[name]).read_bytes().startswith(PNG)
    notes = [s for s in said if "plot" in s]
    print(notes)
    assert notes == [] if child == "works" else len(notes) == 1 and notes[0].startswith("note: plot process")
