"""Is a flight stable? A run of a sweep classified from its error envelope: converged, oscillating or
diverged (and the classes of a grid point's seeds combined into one).

The envelope (flightstack.analysis.metrics.error_envelope, metrics.json `error_envelope`) is the largest
true position error norm ‖p_err‖ over the drones in each window of 5 s. Per flown mode:

1. the windows that begin within the transient, min(10 s, 25 % of the mode's length) as for the
   oscillation measures (metrics.default_transient_s), are left out; the rest, w_1 .. w_m, are split into
   an early half A = w_1 .. w_⌊m/2⌋ and a late half B (with m < 2: A = B = the kept windows);
2. **diverged**: a value is missing or not finite (a state that left every bound), the run's error says
   `diverged` (flightstack.runtime.divergence), or the late envelope max(B) exceeds DIVERGED_M (the
   pursuit is lost: the observing drone's camera, 63° wide at 0.85 m above the marker plate, sees
   ±0.52 × ±0.39 m, and a drone the safety layer landed is about 1 m below its desired pose);
3. **oscillating**: else, the envelope grows, growth = max(B) / max(A) > GROWTH_LIMIT;
4. **converged**: otherwise (bounded and not growing; a steady tracking error from the target's motion
   is not an oscillation).

A run's class is the worst over its flown modes (diverged > oscillating > converged); a run with an
error that is not a divergence (e.g. too little GP training data) and no diverged mode is `failed`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from flightstack.analysis.metrics import ENVELOPE_WINDOW_S, default_transient_s

CONVERGED, OSCILLATING, DIVERGED, FAILED = "converged", "oscillating", "diverged", "failed"
CLASSES = (CONVERGED, OSCILLATING, DIVERGED, FAILED)
"""The classes, from best to worst (failed: no verdict on stability)."""
DIVERGED_M = 0.8
"""A late error envelope (m) above this is a divergence: the pursuit is lost (module docstring)."""
GROWTH_LIMIT = 1.5
"""An envelope whose late half peaks this many times above its early half is a growing oscillation."""
STABLE_FRACTION = 0.8
"""A grid point is converged when at least this fraction of its classified seeds converged."""
_RANK = {CONVERGED: 0, OSCILLATING: 1, DIVERGED: 2}


def envelope_growth(
    envelope: Sequence[float | None], window_s: float = ENVELOPE_WINDOW_S
) -> tuple[float, float] | None:
    """(growth max(B)/max(A), late max(B) in m) of an envelope after the transient (module docstring);
    None when a kept value is missing or not finite, or nothing is left."""
    n = len(envelope)
    if n == 0:
        return None
    transient = default_transient_s(n * window_s)
    kept = [v for i, v in enumerate(envelope) if i * window_s >= transient or n == 1]
    kept = kept or list(envelope[-1:])
    if any(v is None or not math.isfinite(float(v)) for v in kept):
        return None
    vals = [float(v) for v in kept]  # type: ignore[arg-type]
    half = len(vals) // 2
    early, late = (vals[:half], vals[half:]) if half >= 1 else (vals, vals)
    a, b = max(early), max(late)
    return (b / a if a > 0 else (1.0 if b == 0 else math.inf)), b


def classify_mode(mode_metrics: Mapping[str, Any]) -> str:
    """converged, oscillating or diverged of one mode's metrics (its `error_envelope`)."""
    env = mode_metrics.get("error_envelope")
    if not isinstance(env, Mapping) or not isinstance(env.get("max_m"), list):
        return FAILED  # no envelope (a recording without the mission's drones): no verdict
    g = envelope_growth(env["max_m"], float(env.get("window_s", ENVELOPE_WINDOW_S)))
    if g is None:
        return DIVERGED
    growth, late = g
    if late > DIVERGED_M:
        return DIVERGED
    return OSCILLATING if growth > GROWTH_LIMIT else CONVERGED


def classify_run(record: Mapping[str, Any]) -> str:
    """The class of one sweep record (flightstack.sweep: `error`, `metrics.modes`): the worst of its
    flown modes; `diverged` for an error that says so; `failed` for another error without a diverged mode."""
    metrics = record.get("metrics") if isinstance(record.get("metrics"), Mapping) else {}
    assert isinstance(metrics, Mapping)
    error = str(record.get("error") or metrics.get("error") or "")
    if "diverged" in error:
        return DIVERGED
    modes = metrics.get("modes") if isinstance(metrics.get("modes"), Mapping) else {}
    assert isinstance(modes, Mapping)
    classes = [classify_mode(m) for m in modes.values() if isinstance(m, Mapping)]
    ranked = [c for c in classes if c in _RANK]
    worst = max(ranked, key=_RANK.__getitem__) if ranked else FAILED
    if worst == DIVERGED:
        return DIVERGED
    if error or metrics.get("interrupted") or not ranked or FAILED in classes:
        return FAILED
    return worst


def point_class(classes: Iterable[str]) -> tuple[str, dict[str, float]]:
    """(class, fraction of each class) of a grid point's seeds: converged when at least STABLE_FRACTION
    of the classified seeds (not failed) converged; else diverged if at least as many diverged as
    oscillated, else oscillating; failed when no seed was classified."""
    cs = list(classes)
    fractions = {c: (cs.count(c) / len(cs) if cs else 0.0) for c in CLASSES}
    rated = [c for c in cs if c != FAILED]
    if not rated:
        return FAILED, fractions
    if rated.count(CONVERGED) >= STABLE_FRACTION * len(rated):
        return CONVERGED, fractions
    return (DIVERGED if rated.count(DIVERGED) >= rated.count(OSCILLATING) else OSCILLATING), fractions


__all__ = [
    "CLASSES",
    "CONVERGED",
    "DIVERGED",
    "DIVERGED_M",
    "FAILED",
    "GROWTH_LIMIT",
    "OSCILLATING",
    "STABLE_FRACTION",
    "classify_mode",
    "classify_run",
    "envelope_growth",
    "point_class",
]
