"""The rows of `flightstack faults` with agents in separate processes over Zenoh (loopback): one agent
process killed, and a bus partition (an agent unreachable without closing its links).

Both fly the paper simulation (3 agents, `mission_configs/paper_sim.yaml` at dt = 10 ms, mode dgp with
fixed GP experts) served by `flightstack world`, one `flightstack agent` process per drone. The lab
mission is not used here: serving it would stream 960×720 camera frames through Zenoh every tick.
Wall-clock times (time.time(), shared by the processes) measure how fast the survivors react.
"""

from __future__ import annotations

import queue
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from flightstack.comms.factory import free_loopback_endpoints
from flightstack.config.rig import MISSION_CONFIGS, resolved_document
from flightstack.faults.result import Checks, FaultResult, FaultRow
from flightstack.faults.rows_cli import cli_command, cli_env

if TYPE_CHECKING:
    from flightstack.sim_backend.emulators.bus_proxies import BusProxies

PAPER_SIM = MISSION_CONFIGS / "paper_sim.yaml"
PROCESS_TIMEOUT_S = 90.0
DROP_WITHIN_S = 1.0  # the others drop a dead agent from fusion within 1 s


def drone_ids_of(mission: Path) -> tuple[int, ...]:
    """The drones of a mission file, in its order."""
    from flightstack.config.mission import load_mission

    return tuple(load_mission(mission, check_files=False).drone_ids())


def served_ids() -> tuple[int, ...]:
    """The drones `served_mission` flies (paper_sim's)."""
    return drone_ids_of(PAPER_SIM)


def served_mission(
    workdir: Path, duration_s: float, name: str = "dry_run", security: str = "plaintext"
) -> Path:
    """paper_sim over Zenoh on loopback (world + one endpoint per agent, free ports), dt = 10 ms with the
    gains scaled to it, one fixed GP expert per drone fitted to its own samples of the paper's target
    field. `security` "mtls": tls/ endpoints and the mission's certificates in workdir/certs."""
    from flightstack.learning.training import save_experts
    from flightstack.paper.gp import GPExpert, GPHyperparameters
    from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch

    workdir.mkdir(parents=True, exist_ok=True)
    m = resolved_document("paper_sim")
    m["name"] = name
    m["duration_s"] = duration_s
    m["dt_s"] = 0.01
    # paper_sim's gains (100) are stable for its dt of 2 ms (k·dt ≤ 0.62 for the fastest error mode);
    # at 10 ms they are not: the served drones reached 1e37 m within 0.25 s (seen once a test
    # bounded positions, not only their finiteness). Scaled by dt: 20 keeps k·dt at 0.62.
    m["gains"] = {"k_c": [20.0] * 4, "k_e": [20.0] * 4, "k_s": 14.0}
    names = ["world"] + [str(d["id"]) for d in m["drones"]]
    proto = "tls/" if security == "mtls" else "tcp/"
    eps = [e.replace("tcp/", proto, 1) for e in free_loopback_endpoints(len(names))]
    endpoints = dict(zip(names, eps, strict=True))
    m["bus"] = {
        "kind": "zenoh",
        "stale_after_s": 0.5,
        "zenoh": {"endpoints": endpoints, "lease_ms": 500, "security": security},
    }
    if security == "mtls":
        from flightstack.comms.certs import create_mission_certs, participants

        ids = [int(d["id"]) for d in m["drones"]]
        create_mission_certs(name, participants(ids, endpoints), workdir / "certs")
    experts = {}
    for k, d in enumerate(m["drones"]):
        rng = np.random.default_rng(k)
        X = np.column_stack([rng.uniform(-1.5, 1.5, (40, 2)), np.zeros(40), rng.uniform(-np.pi, np.pi, 40)])
        Y = duffing_body_velocity_batch(X, DuffingParams()) + 0.05 * rng.normal(size=(40, 4))
        hyper = GPHyperparameters(np.full(4, 0.5), np.full((4, 4), 1.0), np.full(4, 0.01))
        experts[d["id"]] = GPExpert.from_hyperparameters(X, Y, hyper)
    save_experts(workdir / "experts.npz", experts)
    # absolute: the mission resolves a relative path from its own folder (a relative workdir was doubled)
    m["gp"]["experts_file"] = str((workdir / "experts.npz").resolve())
    path = workdir / "mission.yaml"
    path.write_text(yaml.safe_dump(m))
    return path


class Lines:
    """A process's output lines, read on a thread, so a caller can wait for one with a timeout."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.q: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self.eof = False
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.q.put(line)
        self.eof = True

    def wait_for(self, text: str, timeout: float) -> bool:
        """True when a line containing `text` arrives; False after timeout s or when the output ended."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.1)
            except queue.Empty:
                if self.eof:
                    return False
                continue
            self.seen.append(line)
            if text in line:
                return True
        return False

    def rest(self, timeout: float = 2.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                self.seen.append(self.q.get(timeout=0.05))
            except queue.Empty:
                break
        return "".join(self.seen)


def popen(*args: str) -> subprocess.Popen[str]:
    out, err = subprocess.PIPE, subprocess.STDOUT
    return subprocess.Popen(cli_command(*args), env=cli_env(), stdout=out, stderr=err, text=True)


class ServedRun:
    """`flightstack world` + one `flightstack agent` per drone; everything killed on exit.

    network: a flightstack.netem profile for the Zenoh links between the processes: not "clean", each
    participant's endpoint gets a TcpImpairProxy in front of it (sim_backend/emulators/bus_proxies.py,
    seeded by `seed`) and each process flies its own copy of the mission (`<stem>_<participant>.yaml`
    beside it) naming the others' proxies; `proxies` holds them (None on a clean network). The proxies
    close after the processes have been stopped."""

    def __init__(
        self,
        mission: Path,
        out: Path,
        ids: tuple[int, ...] | None = None,
        mode: str = "dgp",
        agent_args: dict[int, tuple[str, ...]] | None = None,
        network: str = "clean",
        seed: int = 0,
    ) -> None:
        """ids: the agents to start (None: one per drone of the mission); agent_args: extra arguments of some
        agents' command lines (e.g. --viewer), by drone id."""
        self.out = out
        self.ids = drone_ids_of(mission) if ids is None else ids
        self.proxies = None if network == "clean" else _bus_proxies(mission, network, seed)
        try:
            self._start(mission, self.ids, mode, agent_args or {})
        except BaseException:
            if self.proxies is not None:  # (a process started before the failure stops by its timeouts)
                self.proxies.close()
            raise

    def _start(
        self, mission: Path, ids: tuple[int, ...], mode: str, extra: dict[int, tuple[str, ...]]
    ) -> None:
        views = {"world": mission, **{str(i): mission for i in ids}}
        if self.proxies is not None:
            views = {name: mission_view(mission, self.proxies, name) for name in views}
        self.world = popen("world", str(views["world"]))
        self.world_lines = Lines(self.world)
        out = self.out
        self.agents = {
            i: popen(
                "agent", str(views[str(i)]), "--id", str(i), "--mode", mode, "--out", str(out / f"agent{i}"),
                *extra.get(i, ()),
            )
            for i in ids
        }  # fmt: skip
        self.agent_lines = {i: Lines(p) for i, p in self.agents.items()}

    def __enter__(self) -> ServedRun:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            for p in [self.world, *self.agents.values()]:
                if p.poll() is None:
                    if p.pid and _stopped(p.pid):
                        p.send_signal(signal.SIGCONT)
                    p.kill()
                p.wait(timeout=10)
        finally:
            if self.proxies is not None:
                self.proxies.close()

    def wait(self) -> tuple[dict[int, int | None], int | None]:
        """Exit codes of the agents and the world (None: still running after the timeout)."""
        deadline = time.monotonic() + PROCESS_TIMEOUT_S
        codes: dict[int, int | None] = {}
        for i, p in self.agents.items():
            try:
                codes[i] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                codes[i] = None
        try:
            world = self.world.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            world = None
        return codes, world


def _bus_proxies(mission: Path, network: str, seed: int) -> BusProxies:
    """Started proxies in front of every endpoint of the mission file's `bus.zenoh.endpoints`."""
    from flightstack.sim_backend.emulators.bus_proxies import BusProxies

    endpoints = yaml.safe_load(mission.read_text())["bus"]["zenoh"]["endpoints"]
    return BusProxies(endpoints, network, seed)


def mission_view(mission: Path, proxies: BusProxies, participant: str) -> Path:
    """A copy of the mission file beside it in which `participant` reaches the others through their
    proxies (BusProxies.view)."""
    doc = yaml.safe_load(mission.read_text())
    doc["bus"]["zenoh"]["endpoints"] = proxies.view(participant)
    path = mission.with_name(f"{mission.stem}_{participant}.yaml")
    path.write_text(yaml.safe_dump(doc))
    return path


def _stopped(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "T"
    except OSError:
        return False


def _survivor_checks(
    run: ServedRun, victim: int, survivors: list[int], t_fault: float, c: Checks
) -> list[str]:
    """Each surviving agent: full recording, finite, fused every agent's prediction before the fault and all
    but the victim's from ≤ 1 s after."""
    notes, n = [], len(run.ids)
    for i in survivors:
        path = run.out / f"agent{i}" / "timeseries_dgp.npz"
        if not c.check(path.is_file(), f"agent {i} wrote no recording"):
            continue
        with np.load(path) as z:
            n_fused, wall, t = z["n_fused"][:, 0], z["wall_t"], z["t"]
            finite = all(np.all(np.isfinite(z[f])) for f in ("g_wi", "g_bar_w", "V_cmd", "mu_used"))
        c.check(finite, f"agent {i}: non-finite values in its recording")
        before = wall < t_fault
        c.check(bool(np.all(n_fused[before] == n)) and before.any(), f"agent {i} did not fuse {n} before")
        events = (run.out / f"agent{i}" / "events.jsonl").read_text()
        c.check(f'"dropped": [{victim}]' in events, f"agent {i} logged no neighbours event dropping {victim}")
        dropped = np.flatnonzero(n_fused == n - 1)
        if c.check(dropped.size > 0, f"agent {i} never dropped agent {victim}"):
            delay = float(wall[dropped[0]] - t_fault)
            c.check(delay < DROP_WITHIN_S, f"agent {i} dropped agent {victim} only {delay:.3f} s after")
            notes.append(f"agent {i} dropped {victim} after {delay:.3f} s, flew {t.shape[0]} ticks")
    return notes


def _world_landed(out: str, ids: tuple[int, ...], c: Checks) -> bool:
    ok = ", ".join(f"{i}: landed" for i in ids) in out
    c.check(ok, "the world did not report every drone landed")
    return ok


@dataclass
class _Served:
    """What a served fault row saw: the run, its victim and the others, the world's and the victim's
    output, the checks so far."""

    run: ServedRun
    victim: int
    survivors: list[int]
    world_out: str
    victim_out: str
    c: Checks
    crash: Checks
    notes: list[str]
    safe: bool


def _served_fault(workdir: Path, name: str, inject: Callable[[ServedRun, int], float]) -> _Served:
    """Fly the served mission, call inject(run, victim) 3 s into it (the victim: its last drone's agent;
    inject returns the fault's `time.time()`), wait for every process, and make the checks every such row
    makes."""
    c, crash = Checks(), Checks()
    mission = served_mission(workdir, duration_s=8.0, name=f"fault_{name}")
    with ServedRun(mission, workdir) as run:
        victim = run.ids[-1]
        crash.check(run.world_lines.wait_for("tick 300", 60), "the served run never reached t = 3 s")
        t_fault = inject(run, victim)
        codes, world = run.wait()
        wout = run.world_lines.rest()
        vout = run.agent_lines[victim].rest()
    survivors = [i for i in run.ids if i != victim]
    crash.check(all(codes[i] == 0 for i in survivors), f"surviving agents exited {codes}")
    crash.check(world == 0, f"world exited {world}")
    c.check(f"agent {victim} left" in wout, f"the world never saw agent {victim} leave")
    notes = _survivor_checks(run, victim, survivors, t_fault, c)
    return _Served(run, victim, survivors, wout, vout, c, crash, notes, _world_landed(wout, run.ids, c))


def _result(
    name: str, expected: str, sv: _Served, recorded: list[int], observed: str, wall0: float
) -> FaultResult:
    """The row's result; `recorded`: the agents that must have written their recording."""
    return FaultResult(
        name,
        expected,
        "; ".join([*sv.notes, observed]),
        all_safe=sv.safe,
        recording_complete=all((sv.run.out / f"agent{i}" / "timeseries_dgp.npz").is_file() for i in recorded),
        crashed=not sv.crash.ok,
        seconds=time.perf_counter() - wall0,
        reaction_ok=sv.c.ok,
        problems=[*sv.c.failed, *sv.crash.failed],
    )


def _agents(ids: list[int]) -> str:
    return ", ".join(str(i) for i in ids)


def agent_killed(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGKILL to the last drone's agent during pursuit."""
    wall0 = time.perf_counter()

    def kill(run: ServedRun, victim: int) -> float:
        run.agents[victim].send_signal(signal.SIGKILL)
        return time.time()

    sv = _served_fault(workdir / "agent_killed", "killed", kill)
    v = sv.victim
    expected = (
        f"agent {v}'s liveliness token vanishes (TCP closed); agents {_agents(sv.survivors)} drop it from "
        f"fusion and consensus within {DROP_WITHIN_S:g} s and fly to the end; the world lands drone {v} "
        "at once"
    )
    left = f"world: agent {v} left → drone {v} landed" if f"agent {v} left" in sv.world_out else "?"
    return _result("agent_killed", expected, sv, sv.survivors, left, wall0)  # the killed agent writes nothing


def bus_partition(mission_path: Path, workdir: Path) -> FaultResult:
    """The last drone's agent unreachable for 3 s without closing its links (SIGSTOP, then SIGCONT): a
    partition."""
    wall0 = time.perf_counter()

    def freeze(run: ServedRun, victim: int) -> float:
        run.agents[victim].send_signal(signal.SIGSTOP)
        t_fault = time.time()
        time.sleep(3.0)
        run.agents[victim].send_signal(signal.SIGCONT)
        return t_fault

    sv = _served_fault(workdir / "bus_partition", "partition", freeze)
    v = sv.victim
    expected = (
        f"after the 0.5 s lease agents {_agents(sv.survivors)} and the world see agent {v} gone: they drop "
        f"it from fusion within {DROP_WITHIN_S:g} s and fly on; the world lands drone {v}; agent {v}, back, "
        "finds no world: it lands (requested) and exits 1 with its partial recording"
    )
    code, aout = sv.run.agents[v].returncode, sv.victim_out
    sv.crash.check(code == 1 and "Traceback" not in aout, f"agent {v} exited {code}: {aout[-300:]}")
    sv.c.check("WorldLostError" in aout, f"agent {v} did not report the lost world")
    recorded = (sv.run.out / f"agent{v}" / "timeseries_dgp.npz").is_file()
    sv.c.check(recorded, f"agent {v} wrote no partial recording")
    observed = f"world: agent {v} left → drone {v} landed; agent {v}: world lost, exit 1"
    return _result("bus_partition", expected, sv, list(sv.run.ids), observed, wall0)


ROWS: dict[str, FaultRow] = {"agent_killed": agent_killed, "bus_partition": bus_partition}
