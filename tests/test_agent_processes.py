"""Agents in separate processes over Zenoh on loopback (issue 6): `flightstack world` serves the paper
simulation, one `flightstack agent` process per drone. Killing an agent makes the others drop it from
fusion within 1 s and finish safely; `flightstack status` sees every agent; `flightstack abort` lands all.
Every process is bounded (timeouts, kill in finally)."""

from __future__ import annotations

import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.gp import GPExpert, GPHyperparameters
from flightstack.target_motion import DuffingParams, duffing_body_velocity_batch
from flightstack.training import save_experts
from tests.conftest import MISSIONS, REPO

pytest.importorskip("zenoh")

IDS = (1, 2, 3)


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_mission(tmp: Path, duration_s: float) -> Path:
    """paper_sim at dt = 10 ms over Zenoh (world + one endpoint per agent), with trained-looking experts."""
    m = yaml.safe_load((MISSIONS / "paper_sim.yaml").read_text())
    m["name"] = "dry_run"
    m["duration_s"] = duration_s
    m["dt_s"] = 0.01
    endpoints = {"world": f"tcp/127.0.0.1:{free_tcp_port()}"}
    endpoints.update({str(d["id"]): f"tcp/127.0.0.1:{free_tcp_port()}" for d in m["drones"]})
    m["bus"] = {"kind": "zenoh", "stale_after_s": 0.5, "zenoh": {"endpoints": endpoints, "lease_ms": 500}}
    experts = {}
    for k, d in enumerate(m["drones"]):
        rng = np.random.default_rng(k)
        X = np.column_stack([rng.uniform(-1.5, 1.5, (40, 2)), np.zeros(40), rng.uniform(-np.pi, np.pi, 40)])
        Y = duffing_body_velocity_batch(X, DuffingParams()) + 0.05 * rng.normal(size=(40, 4))
        hyper = GPHyperparameters(np.full(4, 0.5), np.full((4, 4), 1.0), np.full(4, 0.01))
        experts[d["id"]] = GPExpert.from_hyperparameters(X, Y, hyper)
    save_experts(tmp / "experts.npz", experts)
    m["gp"]["experts_file"] = str(tmp / "experts.npz")
    path = tmp / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


def cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "flightstack.cli", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


class Lines:
    """Reads a process's output lines on a thread, so the test can wait for one with a timeout."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.q.put(line)

    def wait_for(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.1)
            except queue.Empty:
                continue
            self.seen.append(line)
            if text in line:
                return True
        return False

    def rest(self) -> str:
        while not self.q.empty():
            self.seen.append(self.q.get())
        return "".join(self.seen)


def start(mission: Path, out: Path) -> tuple[subprocess.Popen[str], Lines, dict[int, subprocess.Popen[str]]]:
    world = cli("world", str(mission))
    agents = {
        i: cli("agent", str(mission), "--id", str(i), "--mode", "dgp", "--out", str(out / f"a{i}"))
        for i in IDS
    }
    return world, Lines(world), agents


def stop_all(procs: list[subprocess.Popen[str]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(timeout=10)


def test_killed_agent_is_dropped_from_fusion_within_1s(tmp_path: Path) -> None:
    mission = write_mission(tmp_path, duration_s=8.0)
    world, wlines, agents = start(mission, tmp_path)
    try:
        assert wlines.wait_for("tick 300", 60), wlines.rest()
        agents[3].send_signal(signal.SIGKILL)
        t_kill = time.time()
        codes = {i: agents[i].wait(timeout=90) for i in (1, 2)}
        world.wait(timeout=30)
        wout = wlines.rest()
    finally:
        stop_all([world, *agents.values()])
    assert codes == {1: 0, 2: 0}, {i: agents[i].stdout.read() if agents[i].stdout else "" for i in (1, 2)}
    assert world.returncode == 0, wout
    assert "agent 3 left" in wout and "1: landed, 2: landed, 3: landed" in wout
    for i in (1, 2):
        rec = np.load(tmp_path / f"a{i}" / "timeseries_dgp.npz")
        n_fused, wall = rec["n_fused"][:, 0], rec["wall_t"]
        assert rec["t"].shape[0] == 800  # the whole mission was flown
        before, after = wall < t_kill, wall > t_kill + 1.0
        assert np.all(n_fused[before] == 3) and before.sum() > 100
        assert np.all(n_fused[after] == 2) and after.sum() > 0, "agent 3 still fused 1 s after its death"
        first_drop = wall[np.argmax(n_fused == 2)]
        print(f"agent {i}: dropped agent 3 from fusion {first_drop - t_kill:.3f} s after the kill")
        assert first_drop - t_kill < 1.0


def test_status_then_abort_lands_everyone(tmp_path: Path) -> None:
    mission = write_mission(tmp_path, duration_s=120.0)
    world, wlines, agents = start(mission, tmp_path)
    try:
        assert wlines.wait_for("tick 200", 60), wlines.rest()
        status = subprocess.run(
            [sys.executable, "-m", "flightstack.cli", "status", str(mission), "--once"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=30,
        )
        t0 = time.monotonic()
        abort = subprocess.run(
            [sys.executable, "-m", "flightstack.cli", "abort", str(mission)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=30,
        )
        codes = {i: a.wait(timeout=30) for i, a in agents.items()}
        elapsed = time.monotonic() - t0
        world.wait(timeout=30)
        wout = wlines.rest()
    finally:
        stop_all([world, *agents.values()])
    assert status.returncode == 0, status.stdout + status.stderr
    rows = [ln.split() for ln in status.stdout.splitlines()[1:]]
    assert [(int(r[0]), r[1]) for r in rows] == [(1, "yes"), (2, "yes"), (3, "yes")], status.stdout
    assert abort.returncode == 0 and "agents present [1, 2, 3]" in abort.stdout, abort.stdout + abort.stderr
    assert codes == {1: 1, 2: 1, 3: 1}  # ended by the operator, not by the mission's end
    assert elapsed < 10.0
    for i in IDS:
        summary = (tmp_path / f"a{i}" / "summary.json").read_text()
        assert "operator abort" in summary
    assert "1: landed, 2: landed, 3: landed" in wout
