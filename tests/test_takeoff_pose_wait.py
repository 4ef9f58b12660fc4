"""Takeoff waits, bounded, for a fresh motion-capture pose (runner.wait_for_poses).

On a loaded computer the last clean-clone CI saw the emulated lab refuse takeoff because one motion-capture
frame was late at the one instant SafeDrone looked ("pose of 'drone1' never seen"), although preflight had
seen the body at 108 Hz. A pose that is fresh within POSE_WAIT_S lets the mission fly; one that never comes
still stops it before any drone leaves the ground."""

from __future__ import annotations

from pathlib import Path

import pytest

from flightstack.faults.fly import fly_with_faults
from flightstack.faults.inject import FaultSpec, Window
from flightstack.runtime.phases import POSE_WAIT_S
from tests.conftest import MISSIONS

MISSION = MISSIONS / "paper_experiment.yaml"
pytestmark = pytest.mark.unit


def test_a_pose_that_arrives_late_delays_the_takeoff_instead_of_refusing_it(tmp_path: Path) -> None:
    late = 1.0
    assert late < POSE_WAIT_S
    spec = FaultSpec(mocap_dropout=Window(0.0, late), mocap_bodies=["drone1"])
    run = fly_with_faults(MISSION, tmp_path / "late", spec, duration_s=1.0)
    assert run.crashed is None, run.crashed
    assert run.rec is not None and run.rec.ticks_done == run.n_ticks
    takeoffs = run.events("takeoff")
    assert {e.get("drone") for e in takeoffs} == {1, 2}
    assert all(float(e["t"]) >= late for e in takeoffs)  # type: ignore[arg-type]
    assert not run.events("pose_refuse_takeoff")


def test_a_pose_that_never_arrives_stops_the_mission_before_any_takeoff(tmp_path: Path) -> None:
    spec = FaultSpec(mocap_dropout=Window(0.0, 1e9), mocap_bodies=["drone2"])
    run = fly_with_faults(MISSION, tmp_path / "never", spec, duration_s=1.0)
    assert run.crashed is None, run.crashed  # the runner ends the run itself, lands and records why
    assert run.rec is not None
    end = [e for e in run.rec.events if e.get("event") == "end"]
    assert len(end) == 1
    assert f"no fresh motion-capture pose of ['drone2'] within {POSE_WAIT_S:g} s" in str(end[0]["reason"])
    assert not run.events("takeoff")
    assert run.rec is None or run.rec.ticks_done == 0
    assert not run.backend.inner.drone(1).state().flying and not run.backend.inner.drone(2).state().flying


def test_a_pose_source_that_raises_counts_as_no_pose_and_never_crashes_the_wait() -> None:
    from types import SimpleNamespace

    from flightstack.runtime.runner import wait_for_poses

    class Broken:
        def latest(self, body: str) -> None:
            raise OSError("motion capture socket closed")

    class Clock:
        t = 0.0

        def now(self) -> float:
            return self.t

        def sleep_until(self, t: float) -> None:
            self.t = t

    ticks: list[float] = []
    clock = Clock()
    f = SimpleNamespace(
        safe={1: SimpleNamespace(poses=Broken(), body="drone1")},
        clock=clock,
        loop=SimpleNamespace(dt_s=0.05),
        ticker=SimpleNamespace(tick=lambda: ticks.append(clock.t)),
    )
    with pytest.raises(RuntimeError, match=r"no fresh motion-capture pose of \['drone1'\]"):
        wait_for_poses(f)  # type: ignore[arg-type]
    assert clock.t >= POSE_WAIT_S and len(ticks) >= POSE_WAIT_S / 0.05 - 1  # the safety timers kept ticking
