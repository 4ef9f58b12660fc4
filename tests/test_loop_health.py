"""Loop health: the summary against hand-computed values, the recording's new arrays on both
paths, old files without them, and `bench-loop`'s refusal of rigs it must not fly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flightstack.analysis.loop_health import OVERRUN_TOLERANCE, loop_health, percentiles, plot_loop_health
from flightstack.cli.app import main
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording
from tests.conftest import MISSIONS


def _rec(period: list[float], compute: list[float]) -> Recording:
    rec = Recording.empty("none", [1, 2], len(period))
    rec.t[:] = 0.05 * np.arange(len(period))
    rec.loop_period[:] = period
    rec.loop_compute[:] = compute
    rec.frame_age[:, 0] = 0.01
    rec.frame_age[:, 1] = np.nan  # drone 2 never had a frame
    rec.pose_age[:] = 0.004
    rec.ticks_done = len(period)
    return rec


def test_summary_matches_numpy_and_counts_overruns_beyond_the_jitter_allowance() -> None:
    dt = 0.05
    period = [math.nan] + [0.0501] * 97 + [dt * (1 + OVERRUN_TOLERANCE) + 1e-4, 0.2]
    compute = [0.003] * 99 + [0.04]
    h = loop_health(_rec(period, compute), dt, real_time=True)
    measured = np.array(period[1:])
    assert h["period_s"]["n"] == 99 and h["compute_s"]["n"] == 100
    assert h["period_s"]["p50"] == pytest.approx(np.percentile(measured, 50))
    assert h["period_s"]["p99"] == pytest.approx(np.percentile(measured, 99))
    assert h["period_s"]["max"] == 0.2
    assert h["overruns"] == 2 and h["overrun_fraction"] == pytest.approx(2 / 99)
    assert h["longest_overrun_s"] == 0.2
    assert h["keeps_dt"] is False  # 2 % of the ticks overran (> 1 %)
    assert h["frame_age_s_per_drone"]["2"] == {"p50": None, "p99": None, "max": None, "n": 0}
    assert h["frame_age_s"]["n"] == 100 and h["pose_age_s"]["max"] == pytest.approx(0.004)


def test_a_loop_that_keeps_dt_and_a_simulated_clock_that_is_not_judged() -> None:
    dt = 0.05
    period = [math.nan] + [0.0502] * 99
    rec = _rec(period, [0.004] * 100)
    h = loop_health(rec, dt, real_time=True)
    assert h["overruns"] == 0 and h["keeps_dt"] is True
    sim = loop_health(rec, dt, real_time=False)
    assert sim["overruns"] is None and sim["keeps_dt"] is None and sim["period_s"]["n"] == 99
    slow = loop_health(_rec(period, [0.06] * 100), dt, real_time=True)  # on time, but compute > dt
    assert slow["overruns"] == 0 and slow["keeps_dt"] is False


def test_percentiles_of_nothing_measured() -> None:
    assert percentiles(np.full(5, np.nan)) == {"p50": None, "p99": None, "max": None, "n": 0}


def test_plot_only_when_ticks_were_timed(tmp_path: Path) -> None:
    untimed = Recording.empty("dgp", [1], 10)
    untimed.ticks_done = 10
    assert not plot_loop_health(tmp_path / "a.png", {"dgp": untimed}, 0.05)
    assert not (tmp_path / "a.png").exists()
    assert plot_loop_health(tmp_path / "b.png", {"none": _rec([math.nan, 0.05, 0.05], [0.01] * 3)}, 0.05)
    assert (tmp_path / "b.png").stat().st_size > 5000


def test_old_recordings_load_with_loop_health_not_measured(tmp_path: Path) -> None:
    rec = _rec([math.nan, 0.05], [0.01, 0.01])
    rec.save(tmp_path / "new.npz")
    back = Recording.load(tmp_path / "new.npz")
    np.testing.assert_array_equal(back.loop_compute, rec.loop_compute)
    old = {
        f: getattr(rec, f)
        for f in ARRAY_FIELDS
        if f not in ("loop_period", "loop_compute", "frame_age", "pose_age")
    }
    np.savez(tmp_path / "old.npz", mode="none", drone_ids=np.array([1, 2]), **old)
    back = Recording.load(tmp_path / "old.npz")
    assert (
        np.isnan(back.loop_period).all() and np.isnan(back.pose_age).all() and back.pose_age.shape == (2, 2)
    )


def test_the_ideal_rig_records_sample_ages_but_not_a_wall_clock_verdict(tmp_path: Path) -> None:
    """The ideal rig's samples are stamped with the tick's time (age 0) on both the compiled and the Agent
    path; its metrics carry loop health without an overrun verdict (a simulated clock)."""
    import json

    out = tmp_path / "run"
    argv = ["sim", str(MISSIONS / "paper_sim.yaml"), "--modes", "none", "--duration", "1"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    h = json.loads((out / "metrics.json").read_text())["modes"]["none"]["loop_health"]
    assert h["real_time"] is False and h["overruns"] is None
    assert h["frame_age_s"]["max"] == 0.0 and h["pose_age_s"]["n"] == 3 * 500


@pytest.mark.parametrize("rig", ["ideal", "lab"])
def test_bench_loop_refuses_rigs_other_than_the_emulated_lab(
    rig: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench-loop", "paper_experiment", "--rig", rig, "--seconds", "1"]) == 2
    err = capsys.readouterr().err
    assert "emulated lab only" in err and "never flies real drones" in err
