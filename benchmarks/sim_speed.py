"""Speed of the tick and of the simulator, measured as ratios in one run (benchmarks/run.py).

* Agent tick (observer, own prediction, publish, fuse, control), per agent, on the ideal backend: against
  M (10, 100, 1000 training points per expert; the paper's model, one kernel per output) and against the
  number of neighbours (2, 10, 30: the paper simulation with 3 drones and the generated 11- and 31-drone
  missions, complete graphs); M = 1000 also with one kernel shared by the four outputs (gp.output_kernel:
  shared), and that option's accuracy against the per-output expert fitted on the same data.
* The paper simulation's flown modes (none, local, dgp; 40 s each) in the compiled loop, and the whole
  `flightstack run paper_sim` command (kernel cache load, training, gain analysis, files and plots) in a
  subprocess; simulation speed against drones (3, 11, 31; mode dgp).
* The whole `flightstack run paper_sim` process, warm, five times as the machine is and five times beside
  two CPU-bound processes: wall and CPU seconds.
* A 20-seed sweep of the paper simulation (`flightstack sweep paper_sim --seeds 20`, 3 modes each) on
  every core of this machine.
* The simulated lab (`paper_experiment --rig lab-sim`): one run's flown modes in sim s per wall s, and a
  20-seed sweep, each with the rendered camera (the default) and with `sim.render.model: centres`, and
  per mode the 20 seeds' mean error both ways with its 95 % CI (the option must stay within them).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flightstack.comms.bus import InProcBus
from flightstack.config.mission import Mission, load_mission
from flightstack.learning.training import one_kernel
from flightstack.paper.gp import GPExpert, GPHyperparameters
from flightstack.paper.gp_fit import LOG_LENGTH_BOUNDS, LOG_SIGMA_F_BOUNDS, fit_hyperparameters
from flightstack.paper.kernels_warmup import warm_up
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch
from flightstack.runtime.fleet import make_agents
from flightstack.runtime.flight import Flight
from flightstack.runtime.rig import build_backend

NOISE_VAR = 0.01  # σ_n², the paper's data specification
LO, HI = np.array([-2.0, -1.5, -0.05, -math.pi]), np.array([1.9, 1.5, 0.05, math.pi])  # the path's box


def field_data(mission: Mission, M: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """M noisy samples (σ_n² = 0.01) of the target's true body-velocity field over its path's box."""
    rng = np.random.default_rng(seed)
    prm = DuffingParams(**mission.target.duffing.model_dump())
    X = rng.uniform(LO, HI, size=(M, 4))
    return X, duffing_body_velocity_batch(X, prm) + math.sqrt(NOISE_VAR) * rng.normal(size=(M, 4))


def field_experts(mission: Mission, M: int, shared: bool = False, seed: int = 0) -> dict[int, GPExpert]:
    """Experts of M points on the target's field for every drone (the trained experts' role at any size);
    per-output length scales (the paper's model) unless `shared` (one kernel for the four outputs)."""
    rows = (
        np.tile([0.8, 0.8, 1.0, 2.0], (4, 1))
        if shared
        else np.array(
            [[0.8, 0.9, 1.0, 2.0], [0.9, 0.8, 1.1, 1.8], [0.7, 1.0, 0.9, 2.2], [1.0, 0.7, 1.2, 1.9]]
        )
    )
    hyper = GPHyperparameters(np.full(4, 0.5), rows, np.full(4, NOISE_VAR))
    return {
        d.id: GPExpert.from_hyperparameters(*field_data(mission, M, seed + k), hyper)
        for k, d in enumerate(mission.drones)
    }


def bench_agent_tick(mission: Mission, experts: dict[int, GPExpert], rounds: int) -> dict[str, float]:
    """Per-agent seconds of sense_and_publish + fuse_control_act (mode dgp), agents built as the runner
    does, the world advanced between ticks (not timed)."""
    backend = build_backend(mission)
    ids = [d.id for d in mission.drones]
    bus = InProcBus(mission.name, set(ids))
    drones = {i: backend.drone(i) for i in ids}
    agents = make_agents(mission, "dgp", backend, drones, bus, experts)
    clock = backend.clock
    samples = []
    for k in range(rounds + 20):
        t = clock.now()
        t0 = time.perf_counter()
        for a in agents:
            a.sense_and_publish(t)
        for a in agents:
            a.fuse_control_act(t)
        if k >= 20:  # warm-up excluded
            samples.append((time.perf_counter() - t0) / len(agents))
        clock.sleep_until(t + mission.dt_s)
    s = np.array(samples)
    return {
        "per_agent_us": float(np.median(s) * 1e6),
        "per_agent_mean_us": float(s.mean() * 1e6),
        "neighbours": len(ids) - 1,
        "dt_over_tick": mission.dt_s / float(np.median(s)),
    }


def bench_ticks(paper: Path, scaling: dict[int, Path]) -> dict[str, dict[str, float]]:
    """Agent tick against M (3 drones) and against neighbours (M = 10), and M = 1000 with one kernel."""
    warm_up()
    m3 = load_mission(paper, {"duration_s": 1.0})
    out = {
        f"M{M}": bench_agent_tick(m3, field_experts(m3, M), r)
        for M, r in ((10, 3000), (100, 2000), (1000, 300))
    }
    out["M1000_shared"] = bench_agent_tick(m3, field_experts(m3, 1000, shared=True), 300)
    for n, path in scaling.items():
        mn = load_mission(path, {"duration_s": 1.0})
        out[f"n{n}"] = bench_agent_tick(mn, field_experts(mn, 10), max(200, 6000 // n))
    return out


def shared_kernel_accuracy(paper: Path, M: int = 1000, fit_M: int = 300, seed: int = 0) -> dict[str, float]:
    """gp.output_kernel: shared against the paper's per-output kernels, both fitted (type-II ML, 2
    restarts, ≤ 60 L-BFGS-B iterations) on the same fit_M points and then conditioned on the same M:
    RMS error of each expert's mean against the true field on 2000 test points, and their RMS difference."""
    m = load_mission(paper)
    X, Y = field_data(m, M, seed)
    _, _, per_output = fit_hyperparameters(
        X[:fit_M], Y[:fit_M], NOISE_VAR, restarts=2, seed=seed, maxiter=60,
        log_sigma_f_bounds=LOG_SIGMA_F_BOUNDS, log_length_bounds=LOG_LENGTH_BOUNDS,
    )  # fmt: skip
    one = one_kernel([X[:fit_M]], [Y[:fit_M]], NOISE_VAR, 2, seed)
    exact, cheap = GPExpert(X, Y, per_output), GPExpert(X, Y, one)
    Xt = np.random.default_rng(seed + 1).uniform(LO, HI, size=(2000, 4))
    truth = duffing_body_velocity_batch(Xt, DuffingParams(**m.target.duffing.model_dump()))
    mu_e, var_e = exact.predict(Xt)
    mu_c, var_c = cheap.predict(Xt)

    def rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(a**2)))

    return {
        "rmse_exact": rms(mu_e - truth),
        "rmse_shared": rms(mu_c - truth),
        "rms_difference": rms(mu_c - mu_e),
        "median_var_ratio": float(np.median(var_c / var_e)),
        "shared_kernel": bool(cheap.shared_kernel),
    }


def bench_paper_sim(paper: Path) -> dict[str, object]:
    """The paper simulation's flown modes (compiled loop, experts of M = 10 on the field), then the whole
    `flightstack run paper_sim` in a subprocess (its own printout gives the loop's share)."""
    warm_up(loop=True)
    m = load_mission(paper)
    experts = field_experts(m, 10)
    modes = {}
    for mode in ("none", "local", "dgp"):
        with Flight(m) as flight:
            rec = flight.fly_mode(mode, None if mode == "none" else experts)
        if rec.error or rec.interrupted:
            raise RuntimeError(f"paper simulation {mode}: {rec.error}")
        modes[mode] = {"wall_s": rec.wall_seconds, "sim_per_wall": m.duration_s / rec.wall_seconds}
    sim = 3 * m.duration_s
    loop = sum(v["wall_s"] for v in modes.values())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cmd = [
            sys.executable,
            "-m",
            "flightstack",
            "run",
            "paper_sim",
            "--out",
            f"{tmp}/run",
            "--no-progress",
        ]
        subprocess.run(cmd, check=True, capture_output=True, timeout=600)
        command = time.perf_counter() - t0
    return {
        "modes": modes,
        "loop_sim_per_wall": sim / loop,
        "command_s": command,
        "command_sim_per_wall": sim / command,
    }


def _whole_run(out: str, *flags: str) -> tuple[float, float, float]:
    """One `flightstack run paper_sim` process: (wall s, CPU s = user + sys of the process and its children,
    GP training's wall s as the run's metrics.json reports it)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "flightstack", "run", "paper_sim", "--out", out, "--force", "--no-progress"]
    subprocess.run([*cmd, *flags], check=True, capture_output=True, timeout=600)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    train = json.loads((Path(out) / "metrics.json").read_text())["gp"]["train_seconds"]
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), float(train)


WHOLE_CASES = (
    ("quiet", (), 0),
    ("quiet_no_live_mcap", ("--no-live-mcap",), 0),
    ("loaded", (), 2),
)
"""The whole-process cases: (name, extra `run` flags, CPU-bound processes beside it)."""


def bench_whole_process(repeats: int = 5, loaded_repeats: int = 10) -> dict[str, dict[str, object]]:
    """The whole `flightstack run paper_sim` process (start, imports, flight, files, plots, the live MCAP's
    follower finishing, exit), warm, for each of WHOLE_CASES: `repeats` runs (`loaded_repeats` beside two
    CPU-bound processes); each: the runs' wall and CPU seconds (the follower's included), GP training's wall
    seconds per run, their medians, the 1-minute load average before and after. On a shared machine "quiet"
    is what the other jobs leave: the load says how quiet it was."""
    out: dict[str, dict[str, object]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        _whole_run(f"{tmp}/run")  # warm: the kernels' cache and the file system
        for case, flags, n_hogs in WHOLE_CASES:
            hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(n_hogs)]
            if hogs:
                time.sleep(2.0)
            try:
                load0 = os.getloadavg()[0]
                runs = [_whole_run(f"{tmp}/run", *flags) for _ in range(loaded_repeats if hogs else repeats)]
                load1 = os.getloadavg()[0]
            finally:
                for h in hogs:
                    h.kill()
                    h.wait()
            walls, cpus, trains = ([r[k] for r in runs] for k in range(3))
            out[case] = {
                "flags": list(flags),
                "wall_s": walls,
                "cpu_s": cpus,
                "train_s": trains,
                "median_wall_s": float(np.median(walls)),
                "median_cpu_s": float(np.median(cpus)),
                "load": [load0, load1],
            }
    return out


def bench_drones(
    paper: Path, scaling: dict[int, Path], duration_s: float = 4.0
) -> dict[str, dict[str, float]]:
    """Simulated seconds per wall second against drones (mode dgp, compiled loop, experts of M = 10)."""
    warm_up(loop=True)
    out = {}
    for n, path in {3: paper, **scaling}.items():
        m = load_mission(path, {"duration_s": duration_s})
        with Flight(m) as flight:
            rec = flight.fly_mode("dgp", field_experts(m, 10))
        if rec.error or rec.interrupted:
            raise RuntimeError(f"{n} drones: {rec.error}")
        out[str(n)] = {"wall_s": rec.wall_seconds, "sim_per_wall": duration_s / rec.wall_seconds}
    return out


LAB_MODELS = ("image", "centres")
"""The simulated lab's camera models benchmarked (`sim.render.model`)."""


def bench_lab_run(duration_s: float = 80.0) -> dict[str, dict[str, float]]:
    """One `paper_experiment` on lab-sim (seed 0, its three modes, GP training included), per camera
    model: wall seconds of Flight.fly and simulated seconds (the flown modes) per wall second."""
    out = {}
    for model in LAB_MODELS:
        m = load_mission("paper_experiment", {"duration_s": duration_s}, rig="lab-sim")
        doc = m.model_dump(mode="json")
        doc["sim"]["render"]["model"] = model
        from flightstack.config.mission import parse_mission

        mission = parse_mission(doc, "bench lab")
        mission._base_dir = m._base_dir
        t0 = time.perf_counter()
        with Flight(mission) as flight:
            res = flight.fly()
        wall = time.perf_counter() - t0
        if res.error or res.interrupted:
            raise RuntimeError(f"lab run ({model}): {res.error}")
        sim = duration_s * len(mission.compare_modes)
        out[model] = {"wall_s": wall, "sim_per_wall": sim / wall}
    return out


def bench_lab_sweep(seeds: int = 20) -> dict[str, dict[str, object]]:
    """`flightstack sweep paper_experiment --rig lab-sim --seeds 20` on every core, per camera model: wall
    seconds of the whole command, its CPU seconds (user + sys, workers included: divided by the jobs, the
    wall it would take on otherwise idle cores, as other work shares the machine), the 1-minute load
    average before and after, and each mode's mean_sq_error over the seeds (mean, 95 % CI)."""
    import json

    jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    out: dict[str, dict[str, object]] = {}
    for model in LAB_MODELS:
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "flightstack", "sweep", "paper_experiment", "--rig", "lab-sim"]
            cmd += ["--seeds", str(seeds), "--jobs", str(jobs), "--set", f"sim.render.model={model}"]
            load0, cpu0, t0 = os.getloadavg()[0], _children_cpu_s(), time.perf_counter()
            subprocess.run([*cmd, "--out", f"{tmp}/sweep"], check=True, capture_output=True, timeout=3600)
            wall, cpu, load1 = time.perf_counter() - t0, _children_cpu_s() - cpu0, os.getloadavg()[0]
            summary = json.loads(Path(f"{tmp}/sweep/summary.json").read_text())
        errors = {
            mode: {k: d["mean_sq_error"][k] for k in ("mean", "ci_low", "ci_high")}
            for mode, d in summary["points"][0]["modes"].items()
        }
        out[model] = {
            "seeds": seeds,
            "jobs": jobs,
            "wall_s": wall,
            "cpu_s": cpu,  # user + sys of the command and its workers
            "idle_wall_s": cpu / jobs,  # what the wall would be on `jobs` otherwise idle cores (≈)
            "load_before": load0,
            "load_after": load1,
            "mean_sq_error": errors,
        }
    return out


def _children_cpu_s() -> float:
    """User + system CPU seconds of this process's finished children (and theirs, once waited for)."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def bench_sweep(seeds: int = 20) -> dict[str, float]:
    """`flightstack sweep paper_sim --seeds 20` on every core, wall seconds of the whole command."""
    jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "flightstack", "sweep", "paper_sim", "--seeds", str(seeds)]
        subprocess.run(
            [*cmd, "--jobs", str(jobs), "--out", f"{tmp}/sweep"],
            check=True,
            capture_output=True,
            timeout=1200,
        )
        wall = time.perf_counter() - t0
    return {"seeds": seeds, "jobs": jobs, "wall_s": wall, "runs_per_s": seeds / wall}
