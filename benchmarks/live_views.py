"""What the live MCAP and the live Foxglove view cost the flight, measured side by side in one run.

    python benchmarks/live_views.py [--repeats 5] [--lab-seconds 20]

1. `flightstack run paper_sim`, with the live MCAP (the default) and with `--no-live-mcap`, interleaved:
   the flown modes' wall seconds (metrics.json: each mode's takeoff to landing, summed) and the whole
   process; target: with the writer within 10 % of without (ratio of the medians).
2. `flightstack run paper_experiment --rig emulated-lab --modes none`, with and without `--viewer
   foxglove:PORT` (and without the live MCAP in both, to see the view alone): the loop period's median and
   99th percentile (the recording's `loop_period`) and the ticks that overran dt.

Prints one JSON object and writes it to benchmarks/live_views.json; docs/performance.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "live_views.json"


def _run(args: list[str], out: Path) -> tuple[float, dict]:
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "flightstack", "run", *args, "--out", str(out), "--force", "--no-progress"]
    subprocess.run(cmd, check=True, capture_output=True, timeout=1200, cwd=REPO)
    wall = time.perf_counter() - t0
    return wall, json.loads((out / "metrics.json").read_text())


def _flown_s(metrics: dict) -> float:
    return float(sum(m.get("wall_seconds", 0.0) for m in metrics["modes"].values()))


def bench_mcap(repeats: int) -> dict[str, object]:
    res: dict[str, dict[str, list[float]]] = {
        c: {"flown_s": [], "process_s": []} for c in ("with", "without")
    }
    with tempfile.TemporaryDirectory() as tmp:
        _run(["paper_sim"], Path(tmp) / "warm")
        for _ in range(repeats):
            for case, extra in (("with", []), ("without", ["--no-live-mcap"])):
                wall, m = _run(["paper_sim", *extra], Path(tmp) / case)
                res[case]["flown_s"].append(_flown_s(m))
                res[case]["process_s"].append(wall)
    med = {c: {k: statistics.median(v) for k, v in d.items()} for c, d in res.items()}
    return {
        "runs": res,
        "median": med,
        "flown_ratio": med["with"]["flown_s"] / med["without"]["flown_s"],
        "process_ratio": med["with"]["process_s"] / med["without"]["process_s"],
        "target_flown_ratio": 1.10,
    }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def bench_view(seconds: float) -> dict[str, object]:
    out: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case in ("without", "with"):
            args = ["paper_experiment", "--rig", "emulated-lab", "--modes", "none",
                    "--duration", str(seconds), "--no-live-mcap", "--yes"]  # fmt: skip
            if case == "with":
                args += ["--viewer", f"foxglove:{_free_port()}"]
            run = Path(tmp) / case
            _run(args, run)
            with np.load(run / "timeseries_none.npz") as z:
                period = z["loop_period"][np.isfinite(z["loop_period"])]
            dt = json.loads((run / "metrics.json").read_text()).get("dt_s")
            out[case] = {
                "ticks": int(period.size),
                "median_ms": float(np.median(period) * 1e3),
                "p99_ms": float(np.percentile(period, 99) * 1e3),
                "max_ms": float(period.max() * 1e3),
                "dt_ms": None if dt is None else float(dt) * 1e3,
            }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--lab-seconds", type=float, default=20.0)
    ap.add_argument("--only", choices=("mcap", "view"), default=None)
    args = ap.parse_args(argv)
    result: dict[str, object] = {"load_before": os.getloadavg()[0]}
    if args.only in (None, "mcap"):
        result["live_mcap_paper_sim"] = bench_mcap(args.repeats)
    if args.only in (None, "view"):
        result["foxglove_view_emulated_lab"] = bench_view(args.lab_seconds)
    result["load_after"] = os.getloadavg()[0]
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
