"""Did the computer keep the control period? The loop-health part of metrics.json and its plot.

The paper's own experiment names "the slow operating frequency" as a limit; on hardware nothing
recorded it before. Every Python tick of `runtime.runner.run_mode` records, in wall seconds of this
computer (`time.perf_counter`):

- `loop_period[k]`: from the previous tick's start to this one's (NaN for the first tick and after a
  chunk of the compiled loop, which is not timed per tick);
- `loop_compute[k]`: this tick's sensing (image decoding is on the camera's own thread; marker
  extraction is here), fusion, command and recording row;

and per drone, on the mission clock (the same clock as the samples' stamps):

- `frame_age[k, i]`: t − stamp of the camera frame the tick looked at (NaN: no frame);
- `pose_age[k, i]`: t − stamp of the drone's own motion-capture pose it used (NaN: none, a dropout);
  a sample that arrived after the tick's start t (between t and the read) counts as age 0. Both are
  sampled once per tick, so a stream at rate r shows ages spread over [0, 1/r] plus its latency.

A tick is an **overrun** when its period exceeds (1 + OVERRUN_TOLERANCE)·dt: the loop sleeps until its
start + dt, so a period just above dt is the sleep's wake-up jitter (well under 1 ms on Linux; 2 % of
dt at 20 Hz), not a missed deadline. Overruns are counted only for real-time runs (hardware, the emulated
lab); a simulated clock runs as fast as it can and its wall period says how fast, not whether it kept dt.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from flightstack.recording.timeseries import Recording

OVERRUN_TOLERANCE = 0.1
"""A period up to (1 + this)·dt is on time (the sleep's wake-up jitter); beyond it, an overrun."""
KEEPS_DT_MAX_OVERRUN_FRACTION = 0.01
"""`keeps_dt` holds when at most this fraction of the measured ticks overran (and p99 compute < dt)."""


def percentiles(x: np.ndarray) -> dict[str, float | None]:
    """{p50, p99, max, n} of the finite values of x (None each when there is none)."""
    v = np.asarray(x, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {
        "p50": float(np.percentile(v, 50)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
        "n": int(v.size),
    }


def _per_drone(rec: Recording, x: np.ndarray) -> dict[str, dict[str, float | None]]:
    return {str(i): percentiles(x[:, j]) for j, i in enumerate(rec.drone_ids)}


def loop_health(rec: Recording, dt: float, real_time: bool) -> dict[str, Any]:
    """The loop-health summary of a recording with nominal period dt (s).

    period_s / compute_s / frame_age_s / pose_age_s: {p50, p99, max, n} in seconds (frame and pose ages
    also per drone). overruns / overrun_fraction / keeps_dt: for real-time runs only (None otherwise)."""
    k = rec.ticks_done
    period, compute = rec.loop_period[:k], rec.loop_compute[:k]
    measured = period[np.isfinite(period)]
    out: dict[str, Any] = {
        "real_time": bool(real_time),
        "dt_s": float(dt),
        "overrun_above_s": float((1.0 + OVERRUN_TOLERANCE) * dt),
        "period_s": percentiles(period),
        "compute_s": percentiles(compute),
        "frame_age_s": percentiles(rec.frame_age[:k]),
        "pose_age_s": percentiles(rec.pose_age[:k]),
        "frame_age_s_per_drone": _per_drone(rec, rec.frame_age[:k]),
        "pose_age_s_per_drone": _per_drone(rec, rec.pose_age[:k]),
        "overruns": None,
        "overrun_fraction": None,
        "longest_overrun_s": None,
        "keeps_dt": None,
    }
    if real_time and measured.size:
        late = measured > (1.0 + OVERRUN_TOLERANCE) * dt
        frac = float(late.mean())
        p99c = out["compute_s"]["p99"]
        out.update(
            overruns=int(late.sum()),
            overrun_fraction=frac,
            longest_overrun_s=float(measured.max()) if late.any() else 0.0,
            keeps_dt=bool(frac <= KEEPS_DT_MAX_OVERRUN_FRACTION and p99c is not None and p99c < dt),
        )
    return out


def loop_health_line(h: dict[str, Any]) -> str:
    """One line for the terminal: period and compute p50/p99/max (ms), overruns, frame and pose age p99."""

    def ms(d: dict[str, Any], key: str) -> str:
        v = d[key]
        return "-" if v is None else f"{1e3 * v:.1f}"

    p, c = h["period_s"], h["compute_s"]
    parts = [
        f"period p50/p99/max {ms(p, 'p50')}/{ms(p, 'p99')}/{ms(p, 'max')} ms (dt {1e3 * h['dt_s']:.0f} ms)",
        f"compute {ms(c, 'p50')}/{ms(c, 'p99')}/{ms(c, 'max')} ms",
    ]
    if h["overruns"] is not None:
        parts.append(f"overruns {h['overruns']} ({100 * h['overrun_fraction']:.1f} %)")
    fa, pa = ms(h["frame_age_s"], "p99"), ms(h["pose_age_s"], "p99")
    parts.append(f"frame age p99 {fa} ms, pose age p99 {pa} ms")
    return "; ".join(parts)


def plot_loop_health(path: Path, recs: dict[str, Recording], dt: float) -> bool:
    """loop_health.png: per mode the period and compute time per tick against dt, and each drone's frame
    and pose age; False (nothing written) when no tick was timed."""
    timed = {m: r for m, r in recs.items() if np.isfinite(r.loop_period[: r.ticks_done]).any()}
    if not timed:
        return False
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 3.2 * len(timed)))
    axes = fig.subplots(len(timed), 2, squeeze=False)
    for row, (mode, rec) in enumerate(timed.items()):
        k = rec.ticks_done
        t = rec.t[:k] - rec.t[0]
        ax = axes[row, 0]
        ax.plot(t, 1e3 * rec.loop_period[:k], lw=0.7, label="period")
        ax.plot(t, 1e3 * rec.loop_compute[:k], lw=0.7, label="compute")
        ax.axhline(1e3 * dt, color="k", ls="--", lw=0.8, label="dt")
        ax.axhline(1e3 * (1 + OVERRUN_TOLERANCE) * dt, color="tab:red", ls=":", lw=0.8, label="overrun")
        ax.set_ylabel("ms")
        ax.set_title(f"{mode}: control loop")
        ax.legend(fontsize=7, loc="upper right")
        ax = axes[row, 1]
        for j, i in enumerate(rec.drone_ids):
            if np.isfinite(rec.frame_age[:k, j]).any():
                ax.plot(t, 1e3 * rec.frame_age[:k, j], lw=0.7, label=f"frame age, drone {i}")
            if np.isfinite(rec.pose_age[:k, j]).any():
                ax.plot(t, 1e3 * rec.pose_age[:k, j], lw=0.7, ls="--", label=f"pose age, drone {i}")
        ax.set_ylabel("ms")
        ax.set_title(f"{mode}: age of the samples used")
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("time since the first tick [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return True
