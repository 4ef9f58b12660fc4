"""Statistics of a sweep over its seeds, per grid point (pure functions of the runs' records).

For each quantity: the number of seeds n, the mean, the median, the sample standard deviation and the 95 %
confidence interval of the mean, mean ± t_{0.975, n−1} · s / √n (Student t, scipy.stats.t; none for n < 2).
Ratios none/dgp and local/dgp are formed per seed, then described. A run recorded with an error (or
without metrics) is counted as failed and left out of every statistic.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from scipy import stats

from flightstack.sweep.plan import point_label

ERROR_METRICS = ("mean_sq_error", "sq_mean_error")
"""The two readings of the paper's 'squared mean of e' (flightstack.analysis.metrics)."""
MODE_METRICS = (*ERROR_METRICS, "position_error_std_m", "position_error_tv_mps")
"""Per-mode metrics described when present (the oscillation measures need the mission's drones)."""
RATIOS = (("none", "dgp"), ("local", "dgp"))
ORDER = ("none", "local", "dgp")
GAIN_KEYS = ("kappa", "L_mu", "lambda_H")
CONFIDENCE = 0.95


def describe(values: Iterable[float | None], confidence: float = CONFIDENCE) -> dict[str, Any]:
    """n, mean, median, std (ddof 1) and the Student-t confidence interval of the mean of the finite
    values (None and non-finite ones are left out); None for what n does not allow."""
    a = np.array([float(v) for v in values if v is not None and math.isfinite(float(v))])
    n = int(a.size)
    out: dict[str, Any] = {"n": n, "mean": None, "median": None, "std": None, "ci_low": None, "ci_high": None}
    if n == 0:
        return out
    mean = float(a.mean())
    out.update(mean=mean, median=float(np.median(a)))
    if n >= 2:
        s = float(a.std(ddof=1))
        half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * s / math.sqrt(n)
        out.update(std=s, ci_low=mean - half, ci_high=mean + half)
    return out


def succeeded(record: dict[str, Any]) -> bool:
    """A run that returned metrics and no error (a failed data run, an interrupted mode: not)."""
    m = record.get("metrics")
    return isinstance(m, dict) and not record.get("error") and not m.get("error") and not m.get("interrupted")


def _error_of(record: dict[str, Any]) -> str:
    m = record.get("metrics")
    m = m if isinstance(m, dict) else {}
    return str(
        record.get("error") or m.get("error") or ("interrupted" if m.get("interrupted") else "no metrics")
    )


def _mode_value(record: dict[str, Any], mode: str, key: str) -> float | None:
    v = record["metrics"].get("modes", {}).get(mode, {}).get(key)
    return float(v) if isinstance(v, int | float) else None


def ratio_values(records: Sequence[dict[str, Any]], metric: str, num: str, den: str) -> list[float]:
    """Per seed: metric(num) / metric(den), for the seeds that flew both with metric(den) > 0."""
    out = []
    for r in records:
        a, b = _mode_value(r, num, metric), _mode_value(r, den, metric)
        if a is not None and b is not None and b > 0:
            out.append(a / b)
    return out


def ordering_fraction(records: Sequence[dict[str, Any]], metric: str) -> dict[str, Any] | None:
    """The fraction of seeds with none > local > dgp for `metric` (of the seeds that flew all three)."""
    held = []
    for r in records:
        v = [_mode_value(r, m, metric) for m in ORDER]
        if all(x is not None for x in v):
            held.append(v[0] > v[1] > v[2])  # type: ignore[operator]
    return {"n": len(held), "fraction": sum(held) / len(held)} if held else None


def gain_summary(records: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """κ, L_μ, λ_min(H) described over seeds, and the fraction of seeds whose condition is satisfied (of
    the runs that evaluated it: a run without experts says "evaluated": false)."""
    gcs = [
        r["metrics"]["gain_condition"]
        for r in records
        if isinstance(r["metrics"].get("gain_condition"), dict)
        and r["metrics"]["gain_condition"].get("evaluated", True)
    ]
    if not gcs:
        return None
    out: dict[str, Any] = {k: describe(g.get(k) for g in gcs) for k in GAIN_KEYS}
    out["satisfied_fraction"] = sum(bool(g.get("satisfied")) for g in gcs) / len(gcs)
    out["n"] = len(gcs)
    return out


def summarise_point(
    point: int, values: dict[str, Any], records: Sequence[dict[str, Any]], label: str | None = None
) -> dict[str, Any]:
    """Everything summary.json holds for one grid point (its runs' records, any order); `label` names the
    point in tables and plots (default: every value)."""
    ok = sorted((r for r in records if succeeded(r)), key=lambda r: int(r["seed"]))
    modes: list[str] = []
    for r in ok:
        modes += [m for m in r["metrics"].get("modes", {}) if m not in modes]
    out: dict[str, Any] = {
        "point": point,
        "label": point_label(values) if label is None else label,
        "values": values,
        "runs": len(records),
        "seeds": [int(r["seed"]) for r in ok],
        "failed": sorted(str(r["id"]) for r in records if not succeeded(r)),
        "errors": sorted({_error_of(r) for r in records if not succeeded(r)}),
        "modes": {},
        "ratios": {},
        "ordering": {},
    }
    for mode in modes:
        per = {k: describe(_mode_value(r, mode, k) for r in ok) for k in MODE_METRICS}
        out["modes"][mode] = {k: d for k, d in per.items() if d["n"] > 0}
    for metric in ERROR_METRICS:
        ratios = {f"{a}/{b}": describe(ratio_values(ok, metric, a, b)) for a, b in RATIOS}
        ratios = {k: d for k, d in ratios.items() if d["n"] > 0}
        if ratios:
            out["ratios"][metric] = ratios
        order = ordering_fraction(ok, metric)
        if order is not None:
            out["ordering"][metric] = order
    gain = gain_summary(ok)
    if gain is not None:
        out["gain_condition"] = gain
    return out


def summarise(
    points: Sequence[dict[str, Any]], records: Iterable[dict[str, Any]], labels: Sequence[str] | None = None
) -> list[dict[str, Any]]:
    """One summary per grid point (in plan order) of the records that belong to it (by their `point`)."""
    by_point: dict[int, list[dict[str, Any]]] = {p: [] for p in range(len(points))}
    for r in records:
        by_point.setdefault(int(r["point"]), []).append(r)
    return [
        summarise_point(p, dict(points[p]), by_point[p], None if labels is None else labels[p])
        for p in range(len(points))
    ]
