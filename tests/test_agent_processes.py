"""Agents in separate processes over Zenoh on loopback: `flightstack world` serves the paper
simulation, one `flightstack agent` process per drone; `flightstack status` sees every agent and
`flightstack abort` lands them all. (A killed agent and a bus partition are rows of `flightstack faults`,
tests/test_faults.py.) Every process is bounded (timeouts, killed on exit)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.comms.factory import free_loopback_endpoints
from flightstack.config.rig import resolved_document
from flightstack.faults.rows_processes import ServedRun, served_ids, served_mission
from tests.conftest import MISSIONS, REPO

IDS = served_ids()
"""The served mission's drones (its agents)."""

pytest.importorskip("zenoh")


def test_status_then_abort_lands_everyone(tmp_path: Path) -> None:
    mission = served_mission(tmp_path, duration_s=120.0)
    with ServedRun(mission, tmp_path) as run:
        world, wlines, agents = run.world, run.world_lines, run.agents
        assert wlines.wait_for("tick 200", 60), wlines.rest()
        status = subprocess.run(
            # --once returns once every agent is heard; a loaded machine may need more than the default 3 s
            [sys.executable, "-m", "flightstack.cli.app", "status", str(mission), "--once", "--wait", "15"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=30,
        )
        t0 = time.monotonic()
        abort = subprocess.run(
            # the abort is published at once; --timeout bounds only the wait for acknowledgements, which a
            # fresh operator session on a loaded machine may need more than the default 2 s to connect for
            [sys.executable, "-m", "flightstack.cli.app", "abort", str(mission), "--timeout", "10"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=30,
        )
        codes = {i: a.wait(timeout=30) for i, a in agents.items()}
        elapsed = time.monotonic() - t0
        world.wait(timeout=30)
        wout = wlines.rest()
    assert status.returncode == 0, status.stdout + status.stderr
    rows = [ln.split() for ln in status.stdout.splitlines()[1:]]
    assert [(int(r[0]), r[1]) for r in rows] == [(1, "yes"), (2, "yes"), (3, "yes")], status.stdout
    assert all(float(r[3]) < 2.0 for r in rows), status.stdout  # predictions arrive (wall s since the last)
    assert all(r[4] == "dgp" for r in rows), status.stdout
    assert abort.returncode == 0 and "agents present [1, 2, 3]" in abort.stdout, abort.stdout + abort.stderr
    assert codes == {1: 1, 2: 1, 3: 1}  # ended by the operator, not by the mission's end
    print(f"abort to every agent ended: {elapsed:.1f} s")
    for i in IDS:
        summary = (tmp_path / f"agent{i}" / "summary.json").read_text()
        assert "operator abort" in summary
    assert "1: landed, 2: landed, 3: landed" in wout


def test_served_lab_streams_camera_images(tmp_path: Path) -> None:
    """The simulated lab served to two agent processes: rendered camera images go through Zenoh, the
    observing drone extracts the markers from them and pursues; both drones land."""
    m = resolved_document("paper_experiment")
    m["duration_s"] = 3.0
    names = ("world", "1", "2")
    endpoints = dict(zip(names, free_loopback_endpoints(3), strict=True))
    m["bus"] = {
        "kind": "zenoh",
        "stale_after_s": 0.5,
        "zenoh": {"endpoints": endpoints, "security": "plaintext"},
    }
    for d in m["drones"]:
        d["camera"]["calibration"] = str(MISSIONS / d["camera"]["calibration"])
    mission = tmp_path / "lab.yaml"
    mission.write_text(yaml.safe_dump(m))
    live = tmp_path / "agent1_live.rrd"  # agent 1 also streams its flight to a Rerun file (--viewer)
    viewer = importlib.util.find_spec("rerun") is not None  # the `viewer` extra (CI installs it)
    extra = {1: ("--viewer", f"save:{live}")} if viewer else {}
    with ServedRun(mission, tmp_path, ids=(1, 2), mode="none", agent_args=extra) as run:
        codes = {i: a.wait(timeout=90) for i, a in run.agents.items()}
        run.world.wait(timeout=30)
        wout = run.world_lines.rest()
    assert codes == {1: 0, 2: 0}, wout
    assert "drones 1: landed, 2: landed" in wout
    rec = np.load(tmp_path / "agent1" / "timeseries_none.npz")
    assert rec["t"].shape[0] == 60 and rec["visible"][:, 0].mean() > 0.9  # drone 1 saw the markers
    height = rec["g_wi"][:, 0, 2] - rec["g_w0"][:, 2]
    assert np.all(np.abs(height - 1.0) < 0.1)  # and held 1 m above the target
    if viewer:
        from flightstack.viewer import layout
        from tests.test_viewer import Rrd

        rrd = Rrd(live)
        assert rrd.rows[layout.drone("none", 1)] > 0 and rrd.rows[layout.image("none", 1)] >= 1
        assert rrd.rows[layout.markers("none", 1)] >= 1  # what agent 1 detected in the served images


def test_agent_without_a_world_fails_clearly(tmp_path: Path) -> None:
    """No `flightstack world` running: the agent gives up after start_timeout_s with a one-line error."""
    mission = served_mission(tmp_path, duration_s=5.0)
    m = yaml.safe_load(mission.read_text())
    m["bus"]["zenoh"]["start_timeout_s"] = 2.0
    mission.write_text(yaml.safe_dump(m))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "flightstack.cli.app",
            "agent",
            str(mission),
            "--id",
            "1",
            "--out",
            str(tmp_path / "a"),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1, r.stderr
    assert "WorldLostError: no tick from the served world within 2 s" in r.stderr
    assert "Traceback" not in r.stderr


def test_the_served_mission_loads_from_a_relative_work_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`flightstack faults` passes its relative --out (runs/faults/...): the experts file the served mission
    names must load from there, not be looked for under that folder a second time."""
    from flightstack.config.mission import load_mission

    monkeypatch.chdir(tmp_path)
    path = served_mission(Path("runs") / "faults" / "row", duration_s=1.0)
    mission = load_mission(path)  # checks that gp.experts_file exists
    assert mission.resolve(mission.gp.experts_file) == (tmp_path / "runs/faults/row/experts.npz").resolve()
