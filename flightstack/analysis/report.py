"""PNG plots like the paper's Figs. 3–5 from an experiment's recordings (matplotlib, Agg backend), and
`rebuild_run`: metrics.json and the plots of any run directory again (`flightstack report RUN_DIR`)."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure  # no pyplot: no backend, no global figure list (and 0.1 s less import)
from matplotlib.ticker import LogFormatter

from flightstack.analysis.loop_health import plot_loop_health
from flightstack.analysis.metrics import build_metrics
from flightstack.config.mission import Mission, load_mission
from flightstack.learning.training import ExpertData, bands, load_datasets, load_experts
from flightstack.paper.gp import GPExpert
from flightstack.recording.files import (
    DATASETS_FILE,
    EXPERTS_FILE,
    METRICS_FILE,
    MISSION_FILE,
    PLOTS,
    RunDirError,
    atomic_write_json,
    read_json_object,
)
from flightstack.recording.run_reader import read_run
from flightstack.recording.timeseries import Recording

MODE_STYLE = {
    "none": ("tab:gray", "without GP"),
    "local": ("tab:orange", "local GP"),
    "dgp": ("tab:blue", "distributed GP"),
    "oracle": ("tab:green", "true velocity"),
}
DRONE_COLOURS = ("tab:red", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
PLOT_POINTS = 2000
"""Most points a plotted line keeps (`envelope`, `thinned`): a 40 s run at 500 Hz has 20 000 a line, which
cost most of the plots' time and are more than a 7-inch figure at 120 dpi (840 px) can show."""
MARGINS = {"left": 0.12, "right": 0.97, "bottom": 0.12, "top": 0.92}
"""Fixed margins of a plot (fractions of the figure), wide enough for its tick labels and titles: the
layout pass of `tight_layout` measured every text once more and cost about a third of the plots' time."""


def envelope(t: np.ndarray, y: np.ndarray, max_points: int = PLOT_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """A time series drawn with at most `max_points` points that keeps what a reader looks for: the samples
    are cut into max_points // 2 consecutive buckets and each keeps its smallest and largest value, in
    their time order (a spike or a dip stays drawn at its height). Shorter series come back unchanged."""
    n = len(y)
    if n <= max_points:
        return t, y
    edges = np.linspace(0, n, max_points // 2 + 1).astype(int)
    keep = np.empty(2 * (len(edges) - 1), dtype=int)
    for b, (i0, i1) in enumerate(itertools.pairwise(edges)):
        lo, hi = i0 + int(np.argmin(y[i0:i1])), i0 + int(np.argmax(y[i0:i1]))
        keep[2 * b], keep[2 * b + 1] = min(lo, hi), max(lo, hi)
    return t[keep], y[keep]


def thinned(xy: np.ndarray, max_points: int = PLOT_POINTS) -> np.ndarray:
    """Every k-th row of a path (rows: samples), k the smallest stride that leaves at most `max_points`,
    the last row always kept; a smooth path sampled at the tick rate looks the same."""
    k = -(-len(xy) // max_points)
    if k <= 1:
        return xy
    return np.concatenate([xy[::k], xy[-1:]]) if (len(xy) - 1) % k else xy[::k]


def plot_trajectory(
    path: Path, mission: Mission, rec: Recording, data: list[ExpertData], show_drones: bool = False
) -> None:
    """Fig. 3: target xy trajectory, expert bands, training points (○ start, □ end)."""
    k = rec.ticks_done
    xy = rec.g_w0[:k, :2]
    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    axis = mission.gp.regions.axis
    lo_all, hi_all = xy.min(axis=0) - 0.3, xy.max(axis=0) + 0.3
    if show_drones:
        pts = rec.g_wi[:k, :, :2].reshape(-1, 2)
        lo_all, hi_all = np.minimum(lo_all, pts.min(axis=0) - 0.2), np.maximum(hi_all, pts.max(axis=0) + 0.2)
    for j, (lo, hi) in enumerate(bands(mission)):
        c = DRONE_COLOURS[j % len(DRONE_COLOURS)]
        a0 = max(lo, lo_all[0 if axis == "x" else 1])
        a1 = min(hi, hi_all[0 if axis == "x" else 1])
        label = f"region of drone {rec.drone_ids[j]}"
        if axis == "x":
            ax.axvspan(a0, a1, color=c, alpha=0.08, label=label)
        else:
            ax.axhspan(a0, a1, color=c, alpha=0.08, label=label)
    line = thinned(xy)
    ax.plot(line[:, 0], line[:, 1], "k-", lw=1, label="target")
    if show_drones:
        for j, i in enumerate(rec.drone_ids):
            c = DRONE_COLOURS[j % len(DRONE_COLOURS)]
            line = thinned(rec.g_wi[:k, j, :2])
            ax.plot(line[:, 0], line[:, 1], "-", color=c, lw=0.6, alpha=0.7, label=f"drone {i}")
    ax.plot(*xy[0], "ko", mfc="none", ms=9)
    ax.plot(*xy[-1], "ks", mfc="none", ms=9)
    for j, d in enumerate(data):
        c = DRONE_COLOURS[j % len(DRONE_COLOURS)]
        ax.plot(d.X[:, 0], d.X[:, 1], "x", color=c, ms=7, label=f"data of drone {d.drone_id}")
    ax.set_xlim(lo_all[0], hi_all[0])
    ax.set_ylim(lo_all[1], hi_all[1])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Target trajectory, expert regions and training data")
    ax.legend(fontsize=7, loc="best")
    fig.subplots_adjust(**MARGINS)
    fig.savefig(path, dpi=120)


def plot_error_norms(path: Path, recs: dict[str, Recording], which: str) -> None:
    """Figs. 4/5: ‖e_c‖ or ‖e_e‖ (network-wide, R^{4n}) over time, one line per mode, log scale."""
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    floor = np.inf
    for mode, rec in recs.items():
        k = rec.ticks_done
        e = rec.e_c[:k] if which == "c" else rec.e_e[:k]
        norm = np.sqrt((e**2).sum(axis=(1, 2)))
        colour, label = MODE_STYLE.get(mode, ("k", mode))
        ax.semilogy(*envelope(rec.t[:k], np.maximum(norm, 1e-16)), color=colour, lw=1, label=label)
        positive = norm[norm > 0]
        if positive.size:
            floor = min(floor, float(np.percentile(positive, 1)))
    if np.isfinite(floor):  # an exact e(0) = 0 would otherwise stretch the axis down to 1e-16
        ax.set_ylim(bottom=floor / 3)
    # tick labels as plain text (1e-03): the default 10^-3 is typeset by mathtext, whose parser costs
    # more than the rest of the figure
    ax.yaxis.set_major_formatter(LogFormatter())
    ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(1, 0.4)))
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"norm of e_{which}, all drones")
    ax.set_title("Control error" if which == "c" else "Estimation error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.subplots_adjust(**MARGINS)
    fig.savefig(path, dpi=120)


def write_plots(
    out: Path, mission: Mission, recs: dict[str, Recording], data: list[ExpertData]
) -> list[Path]:
    """trajectory.png, error_ec.png, error_ee.png and, when ticks were timed, loop_health.png
    (flightstack.recording.files.PLOTS) in `out`
    (recordings without ticks are left out; no plot without any tick); returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    recs = {m: r for m, r in recs.items() if r.ticks_done > 0}
    if not recs:
        return paths
    ref = recs.get("none") or next(iter(recs.values()))
    p = out / PLOTS["trajectory"]
    plot_trajectory(p, mission, ref, data, show_drones=mission.rig_type.plots_drones)
    paths.append(p)
    shown = {m: r for m, r in recs.items() if m in mission.compare_modes}
    for which in ("c", "e"):
        p = out / PLOTS[f"e_{which}"]
        plot_error_norms(p, shown, which)
        paths.append(p)
    p = out / PLOTS["loop_health"]
    if plot_loop_health(p, recs, mission.dt_s):
        paths.append(p)
    return paths


def rebuild_run(
    run_dir: Path, mission: Mission | None = None, plots: bool = True
) -> tuple[dict[str, Any], list[Path], list[str]]:
    """Rebuild metrics.json (atomically) and, if `plots`, the plots of a run directory from its
    recording: the final npz files, or the row streams of a run cut short by a kill, a crash or a full
    disk (flightstack.recording.run_reader.read_run). mission: default RUN_DIR/mission_resolved.yaml.
    The GP facts, the run's wall time (else the sum of the modes') and its thread limits are kept from an
    earlier metrics.json when there is one. Returns (metrics, plot paths, skipped: `<file>: <what>` for
    each damaged optional file or row stream tail left out, files.OPTIONAL_FILES). RunDirError (naming
    the file) when the directory, its mission or a mode's recording is missing or damaged
    (files.REQUIRED_FILES)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirError(run_dir, "no such run directory")
    for out in [METRICS_FILE, *(PLOTS.values() if plots else ())]:
        if (run_dir / out).exists() and not (run_dir / out).is_file():
            raise RunDirError(run_dir / out, "not a file, so it cannot be rebuilt")
    if mission is None:
        mission = run_mission(run_dir)
    contents = read_run(run_dir, mission)
    recs, skipped = contents.recordings, list(contents.skipped)
    if not recs:
        raise RunDirError(run_dir, "no recording (timeseries_<mode>.npz or .rows) in it")
    old = _old_metrics(run_dir / METRICS_FILE, skipped)
    datasets: list[ExpertData] = []
    experts: dict[int, GPExpert] = {}
    try:
        datasets = load_datasets(run_dir / DATASETS_FILE)
    except RunDirError as exc:
        skipped.append(f"{DATASETS_FILE}: {exc.what}")
    if (run_dir / EXPERTS_FILE).exists():
        try:
            experts = load_experts(run_dir / EXPERTS_FILE)
        except RunDirError as exc:
            skipped.append(f"{EXPERTS_FILE}: {exc.what}")
    interrupted = any(r.interrupted for r in recs.values()) or old.get("interrupted") is True
    error = next((r.error for r in recs.values() if r.error), None) or old.get("error")  # e.g. GP data
    wall = old.get("wall_seconds")
    if not isinstance(wall, int | float):
        wall = float(sum(r.wall_seconds for r in recs.values()))
    metrics = build_metrics(
        mission, recs, experts, old.get("gp") or {}, float(wall), interrupted=interrupted, error=error
    )
    if _thread_limits(old.get("threads")):
        metrics["threads"] = old["threads"]  # what the flight's process ran with: not in the recording
    metrics["recording"] = contents.status
    atomic_write_json(run_dir / METRICS_FILE, metrics)
    paths = write_plots(run_dir, mission, recs, datasets) if plots else []
    return metrics, paths, skipped


def run_mission(run_dir: Path) -> Mission:
    """The mission of a run directory, its mission_resolved.yaml (its files need not exist here);
    RunDirError when it is missing or does not load."""
    path = Path(run_dir) / MISSION_FILE
    if not path.exists():
        raise RunDirError(path, "not found (pass --mission)")
    try:
        return load_mission(path, check_files=False)
    except (OSError, ValueError) as exc:  # MissionError is a ValueError
        raise RunDirError(path, f"does not load ({str(exc).removeprefix(f'{path}: ')})") from None


def _thread_limits(value: object) -> bool:
    """`value` is a metrics.json `threads` entry (flightstack.threads.ThreadLimits.as_dict): four counts."""
    keys = {"cpus", "workers", "blas", "numba"}
    return (
        isinstance(value, dict)
        and set(value) == keys
        and all(type(v) is int and 0 <= v <= 1 << 20 for v in value.values())
    )


def _old_metrics(path: Path, skipped: list[str]) -> dict[str, Any]:
    """The facts an earlier metrics.json keeps for the rebuilt one ({} without one; a damaged one is
    skipped and listed in `skipped`)."""
    if not path.exists():
        return {}
    try:
        old = read_json_object(path)
        if not isinstance(old.get("gp", {}), dict | None) or not isinstance(old.get("error"), str | None):
            raise RunDirError(path, "gp / error: not an object / a text")
    except RunDirError as exc:
        skipped.append(f"{METRICS_FILE}: {exc.what}; its GP facts and wall time are not kept")
        return {}
    return old
