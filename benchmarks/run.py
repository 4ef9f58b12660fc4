"""Core speed benchmarks, printed as ratios measured in one run (machines are shared and noisy).

    python benchmarks/run.py            # prints a table, writes benchmarks/results.json

Measured: GP predict_one (mean + variance, one point) against scikit-learn's predict(return_std=True)
on the same hyperparameters, one full lock-step tick of the three-drone paper simulation per mode, and
simulation speed (sim-seconds per wall-second). Issue 8 extends this suite.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from flightstack.experiment import TruthPredictor  # noqa: E402
from flightstack.gp import GPExpert, GPHyperparameters  # noqa: E402
from flightstack.mission import load_mission  # noqa: E402
from flightstack.runner import run_mode  # noqa: E402
from flightstack.target_motion import DuffingParams  # noqa: E402


def best_of(fn, repeat: int = 5, number: int = 200) -> float:
    """Best mean seconds per call over `repeat` batches of `number` calls."""
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


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
    t_ours = best_of(lambda: ours.predict_one(x))
    t_skl = best_of(lambda: [g.predict(x[None], return_std=True) for g in skl], number=50)
    return {"ours_us": t_ours * 1e6, "sklearn_us": t_skl * 1e6, "speedup": t_skl / t_ours}


def bench_sim() -> dict[str, dict[str, float]]:
    m = load_mission(REPO / "mission_configs" / "paper_sim.yaml", {"duration_s": 4.0})
    n_ticks = round(m.duration_s / m.dt_s)
    out = {}
    rec = run_mode(m, "none")
    out["none"] = {
        "tick_ms": rec.wall_seconds / n_ticks * 1e3,
        "sim_per_wall": m.duration_s / rec.wall_seconds,
    }
    # experts on synthetic data of the right size (M = 10) stand in for trained ones
    rng = np.random.default_rng(0)
    experts = {}
    for d in m.drones:
        X = rng.uniform(-1, 1, size=(10, 4))
        experts[d.id] = GPExpert.from_hyperparameters(
            X, rng.normal(size=(10, 4)), GPHyperparameters(np.ones(4), np.ones((4, 4)), np.full(4, 0.01))
        )
    for mode in ("local", "dgp"):
        rec = run_mode(m, mode, experts)
        out[mode] = {
            "tick_ms": rec.wall_seconds / n_ticks * 1e3,
            "sim_per_wall": m.duration_s / rec.wall_seconds,
        }
    rec = run_mode(m, "oracle", {d.id: TruthPredictor(DuffingParams()) for d in m.drones})
    out["oracle"] = {
        "tick_ms": rec.wall_seconds / n_ticks * 1e3,
        "sim_per_wall": m.duration_s / rec.wall_seconds,
    }
    return out


def main() -> int:
    results: dict[str, object] = {"gp_predict_one": {str(M): bench_gp_predict(M) for M in (10, 100, 1000)}}
    results["paper_sim_tick_3_drones"] = bench_sim()
    print(f"{'benchmark':40s} {'value':>12s} {'reference':>12s} {'ratio':>8s}")
    for M, r in results["gp_predict_one"].items():
        print(
            f"{'GP predict_one M=' + M + ' [us]':40s} {r['ours_us']:12.1f} {r['sklearn_us']:12.1f} "
            f"{r['speedup']:7.1f}x  (sklearn / ours)"
        )
    for mode, r in results["paper_sim_tick_3_drones"].items():
        print(
            f"{'sim tick, 3 drones, mode ' + mode + ' [ms]':40s} {r['tick_ms']:12.3f} {'':12s} "
            f"{r['sim_per_wall']:7.2f}x  (sim s / wall s)"
        )
    (REPO / "benchmarks" / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
