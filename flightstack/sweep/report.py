"""A sweep's outputs: summary.json, summary.csv, the plots (errors.png, ratios.png) and the printed table.

summary.csv is long-form, one row per statistic: the grid point (its index, label and one column per
--set key), `section` (mode, ratio, ordering, gain_condition), `subject` (the mode, `none/dgp`,
`none>local>dgp`, `gain_condition`), `quantity` (the metric) and n, mean, median, ci_low, ci_high.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from flightstack.analysis.metrics import PAPER_RATIOS
from flightstack.recording.files import atomic_write_bytes, atomic_write_json
from flightstack.sweep.stats import ERROR_METRICS, GAIN_KEYS, MODE_METRICS, succeeded

STAT_COLUMNS = ("n", "mean", "median", "ci_low", "ci_high")
PAPER_METRIC = "sq_mean_error"
"""The metric the paper's numbers are values of (flightstack.analysis.metrics.PAPER_SQ_MEAN_ERROR)."""


def csv_rows(
    summary: Sequence[dict[str, Any]],
) -> Iterator[tuple[dict[str, Any], str, str, str, dict[str, Any]]]:
    """(point summary, section, subject, quantity, statistics) for every statistic of the summary."""
    for p in summary:
        for mode, metrics in p["modes"].items():
            for q, d in metrics.items():
                yield p, "mode", mode, q, d
        for metric, ratios in p["ratios"].items():
            for name, d in ratios.items():
                yield p, "ratio", name, metric, d
        for metric, o in p["ordering"].items():
            yield p, "ordering", "none>local>dgp", metric, {"n": o["n"], "mean": o["fraction"]}
        gc = p.get("gain_condition")
        if gc:
            for k in GAIN_KEYS:
                yield p, "gain_condition", "gain_condition", k, gc[k]
            yield (
                p,
                "gain_condition",
                "gain_condition",
                "satisfied_fraction",
                {
                    "n": gc["n"],
                    "mean": gc["satisfied_fraction"],
                },
            )


def write_summary(
    out: Path, summary: Sequence[dict[str, Any]], keys: Sequence[str], meta: dict[str, Any]
) -> None:
    """DIR/summary.json ({meta..., "points": summary}) and DIR/summary.csv, each written atomically."""
    atomic_write_json(out / "summary.json", {**meta, "points": list(summary)}, strict=False)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["point", "label", *keys, "section", "subject", "quantity", *STAT_COLUMNS])
    for p, section, subject, quantity, d in csv_rows(summary):
        vals = [v if isinstance(v, str) else json.dumps(v) for v in (p["values"].get(k) for k in keys)]
        stats = ["" if d.get(c) is None else d[c] for c in STAT_COLUMNS]
        w.writerow([p["point"], p["label"], *vals, section, subject, quantity, *stats])
    atomic_write_bytes(out / "summary.csv", buf.getvalue().encode())


def _fmt(d: dict[str, Any] | None, digits: int = 2) -> str:
    """`1.2e-04 [1.0e-04, 1.4e-04]` (mean and CI), or `-`."""
    if not d or d.get("mean") is None:
        return "-"
    if d.get("ci_low") is None:
        return f"{d['mean']:.{digits}e}"
    return f"{d['mean']:.{digits}e} [{d['ci_low']:.{digits}e}, {d['ci_high']:.{digits}e}]"


def format_table(summary: Sequence[dict[str, Any]]) -> str:
    """The short table printed at the end: per point and mode both error metrics (mean [95 % CI]),
    the ratios, the ordering fractions and κ."""
    lines = []
    for p in summary:
        failed = f", {len(p['failed'])} failed" if p["failed"] else ""
        lines.append(f"{p['label']}  ({len(p['seeds'])} seeds{failed})")
        lines += [f"  failed: {e}" for e in p.get("errors", [])[:3]]
        for mode, m in p["modes"].items():
            cols = "   ".join(f"{k} {_fmt(m.get(k))}" for k in ERROR_METRICS)
            lines.append(f"  {mode:7s} {cols}")
        for metric, ratios in p["ratios"].items():
            cols = "   ".join(f"{k} {_ratio(d)}" for k, d in ratios.items())
            if metric == PAPER_METRIC:
                cols += "   (paper: " + ", ".join(f"{k} {PAPER_RATIOS[k]:.2f}" for k in ratios) + ")"
            lines.append(f"  ratios of {metric}: {cols}")
        for metric, o in p["ordering"].items():
            lines.append(f"  none > local > dgp ({metric}): {o['fraction'] * 100:.0f} % of {o['n']} seeds")
        gc = p.get("gain_condition")
        if gc and gc["kappa"]["mean"] is not None:
            lines.append(
                f"  gain condition: kappa {gc['kappa']['mean']:.3g}, L_mu {gc['L_mu']['mean']:.3g}, "
                f"lambda_H {gc['lambda_H']['mean']:.3g}, satisfied {gc['satisfied_fraction'] * 100:.0f} %"
            )
    return "\n".join(lines)


def _ratio(d: dict[str, Any]) -> str:
    if d.get("ci_low") is None:
        return f"{d['mean']:.2f}"
    return f"{d['mean']:.2f} [{d['ci_low']:.2f}, {d['ci_high']:.2f}]"


def write_plots(
    out: Path, summary: Sequence[dict[str, Any]], records: Sequence[dict[str, Any]]
) -> list[Path]:
    """errors.png (per mode metric: each seed's value and the mean with its CI, per grid point) and, when
    there are ratios, ratios.png (mean and CI per grid point, the paper's ratios dashed); the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    labels = [p["label"] for p in summary]
    x = list(range(len(summary)))
    metrics = [k for k in MODE_METRICS if any(k in m for p in summary for m in p["modes"].values())]
    modes = list(dict.fromkeys(m for p in summary for m in p["modes"]))
    if metrics and modes:
        fig, axes = plt.subplots(len(metrics), 1, figsize=(max(6.0, 1.2 * len(x) + 3), 3.0 * len(metrics)))
        axes = [axes] if len(metrics) == 1 else list(axes)
        width = 0.6 / max(len(modes), 1)
        for ax, metric in zip(axes, metrics, strict=True):
            shown: list[float] = []
            for j, mode in enumerate(modes):
                off = (j - (len(modes) - 1) / 2) * width
                for r in records:
                    v = r["metrics"].get("modes", {}).get(mode, {}).get(metric) if succeeded(r) else None
                    if isinstance(v, int | float):
                        ax.plot(r["point"] + off, v, ".", color=f"C{j}", alpha=0.35)
                        shown.append(float(v))
                stats = [p["modes"].get(mode, {}).get(metric) for p in summary]
                shown += _errorbars(ax, stats, x, off, f"C{j}", mode)
            _axis(ax, metric, x, labels, shown)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        written.append(_save(fig, out / "errors.png"))
        plt.close(fig)
    ratio_metrics = [k for k in ERROR_METRICS if any(k in p["ratios"] for p in summary)]
    if ratio_metrics:
        fig, axes = plt.subplots(
            len(ratio_metrics), 1, figsize=(max(6.0, 1.2 * len(x) + 3), 3.0 * len(ratio_metrics))
        )
        axes = [axes] if len(ratio_metrics) == 1 else list(axes)
        for ax, metric in zip(axes, ratio_metrics, strict=True):
            shown = []
            for j, name in enumerate(PAPER_RATIOS):
                off = (j - 0.5) * 0.2
                stats = [p["ratios"].get(metric, {}).get(name) for p in summary]
                shown += _errorbars(ax, stats, x, off, f"C{j}", name)
                if metric == PAPER_METRIC:  # the paper's value of this very quantity, nothing else
                    shown.append(PAPER_RATIOS[name])
                    ax.axhline(PAPER_RATIOS[name], color=f"C{j}", ls="--", lw=0.8, label=f"{name} (paper)")
            _axis(ax, f"ratio of {metric}", x, labels, shown)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        written.append(_save(fig, out / "ratios.png"))
        plt.close(fig)
    return written


def _errorbars(
    ax: Any, stats: Sequence[dict[str, Any] | None], x: Sequence[int], off: float, color: str, label: str
) -> list[float]:
    """Mean with its CI (a bare mean when n < 2) at x + off, for the points that have the statistic; the
    means drawn."""
    pts = [(xi + off, d) for xi, d in zip(x, stats, strict=True) if d and d.get("mean") is not None]
    if not pts:
        return []
    xs = [p for p, _ in pts]
    means = [d["mean"] for _, d in pts]
    lo = [d["mean"] - d["ci_low"] if d.get("ci_low") is not None else 0.0 for _, d in pts]
    hi = [d["ci_high"] - d["mean"] if d.get("ci_high") is not None else 0.0 for _, d in pts]
    ax.errorbar(xs, means, yerr=[lo, hi], fmt="o", color=color, capsize=4, label=label)
    return means


def _axis(ax: Any, title: str, x: Sequence[int], labels: Sequence[str], shown: Sequence[float]) -> None:
    """Title, point labels, grid; a log scale when every value shown (seeds, means) is > 0 (a CI that
    reaches below 0 is clipped there)."""
    ax.set_title(title, fontsize=10)
    ax.set_xticks(list(x), list(labels), rotation=20, ha="right", fontsize=8)
    if shown and min(shown) > 0:
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)


def _save(fig: Any, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())
    return path
