"""Core speed benchmarks, printed as ratios measured in one run (machines are shared and noisy).

    python benchmarks/run.py                  # table + benchmarks/results.json (< 5 min on 2 cores)
    python benchmarks/run.py --update-docs    # also rewrites docs/performance.md between the bench markers

Every row compares two things measured in the same run (ours vs scikit-learn, 3 experts vs one pooled GP,
M = 1000 vs M = 10, measured vs target), so machine speed cancels in the ratio. Measured:

* GP predict_one (mean + variance, one point, M = 10, 100, 1000) against scikit-learn's
  GaussianProcessRegressor.predict(return_std=True) with the same fixed hyperparameters.
* GP training (one output dimension, SE-ARD with fixed σ_n²): 3 experts on a third of the data each
  against one GP on the pooled data (the paper's O(Σ M_i³) vs O((Σ M_i)³)), per log-marginal-likelihood
  evaluation and per fit; and our fit against scikit-learn's fit (ConstantKernel·RBF(ARD), alpha = σ_n²,
  i.e. a fixed WhiteKernel) with the same start, bounds and L-BFGS-B settings, reporting the time ratio
  and the log marginal likelihood each reached. One restart; N ≥ 1500 stops after a few iterations.
* The agent tick against M and neighbours, the paper simulation's speed (its loop and the whole command),
  the simulator against drones, and a 20-seed sweep: benchmarks/sim_speed.py.
* Marker extraction (flightstack.vision.markers.extract_markers) on 960×720 frames rendered by
  flightstack.sim_backend.scene.render with the tello_front_sim calibration, all four markers in view.
* Bus hop latency: encode → InProcBus.publish (decode, validation) → latest; Zenoh through
  benchmarks/zenoh_hop.py when that file exists.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks import sim_speed  # noqa: E402
from benchmarks.table import (  # noqa: E402
    TARGETS,
    build_rows,
    machine_info,
    markdown_table,
    print_table,
    update_bench_page,
)
from flightstack.comms.bus import InProcBus  # noqa: E402
from flightstack.comms.messages import PredictionMessage  # noqa: E402
from flightstack.config.mission import load_mission  # noqa: E402
from flightstack.paper.geometry import Pose  # noqa: E402
from flightstack.paper.gp import GPExpert, GPHyperparameters  # noqa: E402
from flightstack.paper.gp_kernel import lml_and_grad, pairwise_sq_diff  # noqa: E402
from flightstack.paper.projection import CameraModel, points_in_camera  # noqa: E402
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity_batch  # noqa: E402
from flightstack.vision.camera_file import load_calibration  # noqa: E402
from flightstack.vision.markers import extract_markers  # noqa: E402

PAPER_SIM = REPO / "mission_configs" / "paper_sim.yaml"
SCALING = {n: REPO / "mission_configs" / f"scaling_{n}.yaml" for n in (11, 31)}
FRONT_CAMERA = REPO / "mission_configs" / "cameras" / "tello_front_sim.yaml"
RESULTS = REPO / "benchmarks" / "results.json"

#: GP training benchmark: N (pooled), L-BFGS-B iteration cap (None: run to the tolerances), restarts = 1
TRAIN_SIZES: tuple[tuple[int, int | None], ...] = ((300, None), (1500, 4), (3000, 4))
NOISE_VAR = 0.01  # σ_n², the paper's data specification


def best_of(fn: Callable[[], object], repeat: int = 5, number: int = 200) -> float:
    """Best mean seconds per call over `repeat` batches of `number` calls."""
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def timed(fn: Callable[[], object]) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


# ---- GP predict ---------------------------------------------------------------------------------------
def bench_gp_predict(M: int) -> dict[str, float]:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    rng = np.random.default_rng(M)
    X = rng.uniform(-1, 1, size=(M, 4))
    Y = np.sin(X @ rng.normal(size=(4, 4))) + 0.1 * rng.normal(size=(M, 4))
    ls = np.abs(rng.normal(1.0, 0.2, size=(4, 4))) + 0.3
    sf = np.full(4, 0.8)
    ours = GPExpert.from_hyperparameters(X, Y, GPHyperparameters(sf, ls, np.full(4, 0.01)))
    skl = [
        GaussianProcessRegressor(
            ConstantKernel(sf[d] ** 2, "fixed") * RBF(ls[d], "fixed"), alpha=0.01, optimizer=None
        ).fit(X, Y[:, d])
        for d in range(4)
    ]
    x = rng.uniform(-1, 1, size=4)
    # same numbers first: a speed ratio between different answers would mean nothing
    mu, var = ours.predict_one(x)
    for d, g in enumerate(skl):
        m_s, s_s = g.predict(x[None], return_std=True)
        assert abs(mu[d] - m_s[0]) <= 1e-8 * max(1.0, abs(m_s[0])), "predict_one mean differs from sklearn"
        assert abs(var[d] - s_s[0] ** 2) <= 1e-6 * sf[d] ** 2, "predict_one variance differs from sklearn"
    number = 200 if M <= 100 else 20
    t_ours = best_of(lambda: ours.predict_one(x), number=number)
    t_skl = best_of(lambda: [g.predict(x[None], return_std=True) for g in skl], number=max(5, number // 4))
    return {"ours_us": t_ours * 1e6, "sklearn_us": t_skl * 1e6, "speedup": t_skl / t_ours}


# ---- GP training --------------------------------------------------------------------------------------
def training_data(N: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """N inputs [x, y, z, θ] over the paper's path box, y = first output of the Duffing field + noise."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-2.0, -1.5, -0.3, -math.pi]), np.array([1.9, 1.5, 0.3, math.pi])
    X = rng.uniform(lo, hi, size=(N, 4))
    y = duffing_body_velocity_batch(X, DuffingParams())[:, 0] + math.sqrt(NOISE_VAR) * rng.normal(size=N)
    return X, y[:, None]


def split_bands(X: np.ndarray, Y: np.ndarray, k: int = 3) -> list[tuple[np.ndarray, np.ndarray]]:
    """k experts on equal-count bands along x (the paper splits by region)."""
    order = np.argsort(X[:, 0], kind="stable")
    return [(X[idx], Y[idx]) for idx in np.array_split(order, k)]


def _lml_eval_seconds(X: np.ndarray, y: np.ndarray, repeat: int) -> float:
    """Best time of one log-marginal-likelihood + gradient evaluation (what every optimiser step costs)."""
    sq = pairwise_sq_diff(X)
    theta_l = np.log(X.std(axis=0))
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        lml_and_grad(sq, y, math.log(float(y.std())), theta_l, NOISE_VAR)
        best = min(best, time.perf_counter() - t0)
    return best


def _sklearn_fit(X: np.ndarray, y: np.ndarray, maxiter: int | None):
    """scikit-learn with our model (σ_f² · SE-ARD, σ_n² fixed), start, bounds and L-BFGS-B settings."""
    import scipy.optimize
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    from flightstack.paper.gp_fit import LBFGSB_OPTIONS

    options = dict(LBFGSB_OPTIONS)
    if maxiter is not None:
        options["maxiter"] = maxiter

    def optimizer(obj_func, initial_theta, bounds):
        res = scipy.optimize.minimize(
            obj_func, initial_theta, method="L-BFGS-B", jac=True, bounds=bounds, options=options
        )
        return res.x, res.fun

    y_std = float(y.std())
    kernel = ConstantKernel(y_std**2, (1e-6, 1e6)) * RBF(X.std(axis=0), (1e-2, 1e3))
    gpr = GaussianProcessRegressor(kernel, alpha=NOISE_VAR, optimizer=optimizer, n_restarts_optimizer=0)
    return gpr.fit(X, y[:, 0])


def bench_gp_train(N: int, maxiter: int | None) -> dict[str, float | int | None]:
    X, Y = training_data(N)
    parts = split_bands(X, Y)
    fit = dict(restarts=1, seed=0, maxiter=maxiter)
    # per evaluation of log p(y | X, θ) and its gradient: the cost every optimiser iteration pays
    rep = 3 if N <= 1500 else 1
    t_eval_pooled = _lml_eval_seconds(X, Y[:, 0], rep)
    t_eval_experts = sum(_lml_eval_seconds(Xi, Yi[:, 0], rep) for Xi, Yi in parts)
    # whole fits (same optimiser settings)
    t_pooled, pooled = timed(lambda: GPExpert.fit(X, Y, NOISE_VAR, **fit))
    t_experts = 0.0
    lml_experts = 0.0
    for Xi, Yi in parts:
        t, ex = timed(lambda Xi=Xi, Yi=Yi: GPExpert.fit(Xi, Yi, NOISE_VAR, **fit))
        t_experts += t
        lml_experts += float(ex.log_marginal_likelihood()[0])
    t_skl, skl = timed(lambda: _sklearn_fit(X, Y, maxiter))
    lml_ours = float(pooled.log_marginal_likelihood()[0])
    lml_skl = float(skl.log_marginal_likelihood_value_)
    return {
        "N": N,
        "maxiter": maxiter,
        "restarts": 1,
        "eval_pooled_s": t_eval_pooled,
        "eval_3_experts_s": t_eval_experts,
        "eval_ratio_pooled_over_experts": t_eval_pooled / t_eval_experts,
        "fit_pooled_s": t_pooled,
        "fit_3_experts_s": t_experts,
        "fit_ratio_pooled_over_experts": t_pooled / t_experts,
        "fit_sklearn_s": t_skl,
        "fit_ratio_sklearn_over_ours": t_skl / t_pooled,
        "lml_ours_pooled": lml_ours,
        "lml_sklearn_pooled": lml_skl,
        "lml_ours_minus_sklearn": lml_ours - lml_skl,
        "lml_3_experts_sum": lml_experts,
    }


# ---- vision -------------------------------------------------------------------------------------------
def bench_vision(n_frames: int = 8, number: int = 40) -> dict[str, float]:
    from flightstack.sim_backend.scene.render import RenderOptions, render_markers

    cal = load_calibration(FRONT_CAMERA)
    P0 = np.array(load_mission(PAPER_SIM).target.feature_points, dtype=float)
    rng = np.random.default_rng(0)
    opts = RenderOptions(marker_radius_m=0.025)
    frames = []
    while len(frames) < n_frames:
        z = rng.uniform(0.8, 2.0)
        g_i0 = Pose.make([rng.uniform(-0.3, 0.3) * z, rng.uniform(-0.2, 0.2) * z, z], rng.uniform(-3, 3))
        centres = points_in_camera(g_i0, P0, CameraModel())
        img, _, in_view = render_markers(cal, centres, np.tile([0.0, 0.0, -1.0], (4, 1)), opts)
        if in_view.all() and extract_markers(img, cal).ok:
            frames.append(img)
    t_render = best_of(
        lambda: render_markers(cal, centres, np.tile([0.0, 0.0, -1.0], (4, 1)), opts), repeat=3, number=10
    )
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(number):
            for img in frames:
                extract_markers(img, cal)
        best = min(best, (time.perf_counter() - t0) / (number * len(frames)))
    return {"ms_per_frame": best * 1e3, "fps": 1.0 / best, "render_ms_per_frame": t_render * 1e3}


# ---- bus ----------------------------------------------------------------------------------------------
def measure_inproc_hop_local(n: int = 20000) -> dict[str, float]:
    """encode → InProcBus.publish (decode + validation) → latest, per message; percentiles in ms."""
    bus = InProcBus("bench", {1, 2})
    g = np.array([0.1, -0.2, 1.5, 0.3])
    mu, var, prior = np.full(4, 0.1), np.full(4, 0.05), np.ones(4)
    lat = np.empty(n)
    clock = time.perf_counter
    for k in range(n):
        msg = PredictionMessage("bench", 1, k + 1, k * 0.002, True, g, mu, var, prior)
        t0 = clock()
        bus.publish(msg)
        got = bus.latest(1, k * 0.002, 0.5)
        lat[k] = clock() - t0
        if got is None or got.seq != k + 1:
            raise RuntimeError("in-process bus lost a message")
    return {
        "n": n,
        "p50_ms": float(np.percentile(lat, 50) * 1e3),
        "p99_ms": float(np.percentile(lat, 99) * 1e3),
    }


def bench_bus(n: int = 2000) -> dict[str, object]:
    out: dict[str, object] = {"inproc": measure_inproc_hop_local()}
    path = REPO / "benchmarks" / "zenoh_hop.py"
    if not path.exists():
        out["zenoh"] = None
        out["zenoh_status"] = "zenoh: not available (benchmarks/zenoh_hop.py missing)"
        return out
    try:
        spec = importlib.util.spec_from_file_location("zenoh_hop", path)
        mod = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
        spec.loader.exec_module(mod)  # type: ignore[union-attr]
        out["inproc_zenoh_hop_py"] = mod.measure_inproc_hop(n)
        out["zenoh"] = mod.measure_zenoh_hop(n)
        out["zenoh_status"] = "ok"
    except Exception as exc:  # zenoh not installed / no router: report, do not fail the suite
        out["zenoh"] = None
        out["zenoh_status"] = f"zenoh: not available ({type(exc).__name__}: {exc})"
    return out


# ---- report -------------------------------------------------------------------------------------------
def _commit() -> str:
    """The checkout's short commit (with "+" when it has uncommitted changes), or "unknown"."""
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD"], cwd=REPO, check=False).returncode != 0
        return rev + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--update-docs", action="store_true", help="rewrite docs/performance.md's bench block")
    ap.add_argument(
        "--only",
        metavar="STAGE[,STAGE]",
        help="measure only these stages (e.g. lab_run,lab_sweep); the others' numbers are kept from "
        "benchmarks/results.json, and the table says which rows were measured when",
    )
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    results: dict[str, object] = {"machine": machine_info()}
    only = None if args.only is None else set(args.only.split(","))
    if only is not None:
        kept = {k: v for k, v in json.loads(RESULTS.read_text()).items() if k not in only}
        results = {**kept, "machine": results["machine"]}
        results["remeasured"] = {
            "stages": sorted(only),
            "commit": _commit(),
            "load": os.getloadavg()[0],
            "kept_from": kept.get("remeasured", {}).get("kept_from")
            or (f"commit {kept['commit']}" if "commit" in kept else "an earlier run"),
        }
    else:
        results["commit"] = _commit()

    def stage(name: str, fn: Callable[[], object]) -> None:
        if only is not None and name not in only:
            return
        t0 = time.perf_counter()
        results[name] = fn()
        print(f"  [{name}: {time.perf_counter() - t0:.1f} s]", file=sys.stderr, flush=True)

    stage("gp_predict_one", lambda: {str(M): bench_gp_predict(M) for M in (10, 100, 1000)})
    stage("agent_tick", lambda: sim_speed.bench_ticks(PAPER_SIM, SCALING))
    stage("shared_kernel", lambda: sim_speed.shared_kernel_accuracy(PAPER_SIM))
    stage("paper_sim", lambda: sim_speed.bench_paper_sim(PAPER_SIM))
    stage("whole_process", sim_speed.bench_whole_process)
    stage("drones", lambda: sim_speed.bench_drones(PAPER_SIM, SCALING))
    stage("sweep", sim_speed.bench_sweep)
    stage("lab_run", sim_speed.bench_lab_run)
    stage("lab_sweep", sim_speed.bench_lab_sweep)
    stage("vision", bench_vision)
    stage("bus", bench_bus)
    stage("gp_train", lambda: [bench_gp_train(N, it) for N, it in TRAIN_SIZES])
    results["targets"] = {k: {"target": v[0], "unit": v[1], "kind": v[2]} for k, v in TARGETS.items()}
    results["total_seconds"] = time.perf_counter() - t_start
    rows = build_rows(results)
    print_table(rows)
    print(f"(total {results['total_seconds']:.0f} s; raw numbers in {RESULTS.relative_to(REPO)})")
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    if args.update_docs:
        machine = {**results["machine"], "remeasured": results.get("remeasured")}  # type: ignore[dict-item]
        update_bench_page(markdown_table(rows, machine))
        print("docs/performance.md: bench block rewritten")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
