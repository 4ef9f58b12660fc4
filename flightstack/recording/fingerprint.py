"""SHA-256 fingerprints of what a Recording says about the flight, to tell "recording unchanged" from
"changed" bit for bit (tests/fingerprints.py flies short runs and keeps theirs in
tests/data/fingerprints.json; docs/fingerprints.md says how to re-baseline).

What is fingerprinted, per mode's Recording (only its ticks done):
- every array of FINGERPRINTED_FIELDS: ARRAY_FIELDS except MACHINE_FIELDS, which measure the computer that
  flew, not the flight: `wall_t` (time.time() of each tick), `loop_period` and `loop_compute` (wall time
  between tick starts and of a tick's work). `frame_age` and `pose_age` are kept: they are tick time −
  stamp on the mission clock, which on the simulated rigs (ideal, lab-sim) is the virtual clock, so they
  are as deterministic as the poses (0 in the shipped simulated runs, NaN where no frame or pose was
  used; on hardware the mission clock is time.monotonic() and they vary from run to run like everything);
- `events`: the events with EVENT_MACHINE_KEYS removed from each (wall times), as canonical JSON (keys
  sorted, numpy values and non-finite floats as events.jsonl writes them), in the order of their
  mission time t, ties by content: the order of events.jsonl is partly the computer's (the run
  directory's writer thread polls the safety log every 0.5 s of wall time, so under load a safety event
  of t = 0.55 s can follow a runner event of t = 2.05 s); event kinds, drones, times and details stay;
- `meta`: mode, drone ids and META_FIELDS except `wall_seconds` (ticks done, bus drops, interruption,
  error, vision rejections), as canonical JSON.

An array's fingerprint is SHA-256 of the header `"<dtype.str> <shape>\\n"` (e.g. `"<f8 (160, 2, 4)\\n"`)
followed by its values as C-contiguous little-endian bytes. Values, not bit patterns: every NaN is hashed
as numpy's NaN and −0.0 as 0.0 (x + 0.0), so a computation that reaches the same numbers by another path
keeps its fingerprint.

The fingerprints are as portable as the numbers: tests/fingerprints.py computes them in a process that
pins numpy, OpenBLAS, OpenCV and glibc's libm to their x86-64 baseline code, and says what they still
depend on (the libraries' versions, the platform) and what that was measured to change.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import Counter
from typing import Any

import numpy as np

from flightstack.recording.files import json_safe
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS, Recording

FINGERPRINTED_FIELDS = tuple(f for f in ARRAY_FIELDS if f not in MACHINE_FIELDS)
"""The arrays fingerprinted: every array of a Recording except those that measure the computer."""
EVENT_MACHINE_KEYS = frozenset({"p50_ms", "p99_ms", "max_ms", "wall_t"})
"""Keys of an event that measure the computer, removed before the events are fingerprinted: the safety
tick's wall-time percentiles (ms) of the `safety tick` event (runtime.fleet SafetyTicker.summary) and the
wall clock (s since the epoch) of `recording_stopped` (recording.run_dir)."""
META_MACHINE_KEYS = frozenset({"wall_seconds"})
"""Keys of `Recording.meta()` that measure the computer (wall time the mode took, s)."""
EVENTS = "events"
META = "meta"
"""The names of the two fingerprints that are not of an array (no array has either name)."""
NORM_DIGITS = 6
"""Significant digits of the L2 norm in an array's summary."""


def _canonical(a: np.ndarray) -> np.ndarray:
    """`a` as C-contiguous little-endian values; floats with every NaN numpy's NaN and −0.0 as 0.0."""
    a = np.asarray(a)
    if a.dtype.kind in "fc":
        a = np.where(np.isnan(a), np.nan, a + 0.0).astype(a.dtype)
    return np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))


def array_fingerprint(a: np.ndarray) -> str:
    """SHA-256 (hex) of `a`'s dtype, shape and values (module docstring: the header, then the bytes)."""
    c = _canonical(a)
    h = hashlib.sha256(f"{c.dtype.str} {c.shape}\n".encode())
    h.update(c.tobytes())
    return h.hexdigest()


def array_summary(a: np.ndarray) -> dict[str, Any]:
    """What a person can compare of an array: shape, dtype, the L2 norm of its finite values (NORM_DIGITS
    significant digits) and how many values are not finite (NaN: nothing measured)."""
    a = np.asarray(a)
    x = a.astype(np.float64).ravel()
    finite = np.isfinite(x)
    norm = float(np.linalg.norm(x[finite]))
    return {
        "shape": list(a.shape),
        "dtype": a.dtype.name,
        "norm": float(f"{norm:.{NORM_DIGITS}g}"),
        "nonfinite": int(x.size - finite.sum()),
    }


def _event_key(ev: dict[str, Any]) -> str:
    kind = ev.get("kind")
    return f"{ev.get('event')}/{kind}" if kind is not None else str(ev.get("event"))


def events_canonical(rec: Recording) -> list[dict[str, Any]]:
    """The events of `rec` without EVENT_MACHINE_KEYS, JSON-able as events.jsonl writes them, ordered by
    mission time t (s; an event without one last), ties by content."""
    events = [json_safe({k: v for k, v in ev.items() if k not in EVENT_MACHINE_KEYS}) for ev in rec.events]

    def order(ev: dict[str, Any]) -> tuple[float, str]:
        t = ev.get("t")
        when = float(t) if isinstance(t, int | float) and not isinstance(t, bool) else math.inf
        return when, json.dumps(ev, sort_keys=True)

    return sorted(events, key=order)


def meta_canonical(rec: Recording) -> dict[str, Any]:
    """Mode, drone ids and the META_FIELDS of `rec` that do not measure the computer."""
    meta = {k: v for k, v in rec.meta().items() if k not in META_MACHINE_KEYS}
    return {"mode": rec.mode, "drone_ids": [int(i) for i in rec.drone_ids], **meta}


def _json_fingerprint(obj: Any) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def fingerprints(rec: Recording) -> dict[str, str]:
    """SHA-256 (hex) of every FINGERPRINTED_FIELDS array of `rec` (its ticks done), of its events
    (EVENTS) and of its facts (META), by name."""
    k = rec.ticks_done
    out = {f: array_fingerprint(getattr(rec, f)[:k]) for f in FINGERPRINTED_FIELDS}
    out[EVENTS] = _json_fingerprint(events_canonical(rec))
    out[META] = _json_fingerprint(meta_canonical(rec))
    return out


def summaries(rec: Recording) -> dict[str, dict[str, Any]]:
    """A summary per fingerprint of `fingerprints(rec)`: `array_summary` of each array; for EVENTS their
    count per kind; for META the facts themselves."""
    k = rec.ticks_done
    out = {f: array_summary(getattr(rec, f)[:k]) for f in FINGERPRINTED_FIELDS}
    kinds = Counter(_event_key(ev) for ev in rec.events)
    out[EVENTS] = {"count": len(rec.events), "kinds": dict(sorted(kinds.items()))}
    out[META] = meta_canonical(rec)
    return out


def summaries_agree(stored: dict[str, Any], new: dict[str, Any], rel: float, abs_: float) -> bool:
    """True when two summaries of one fingerprint (`summaries`) agree: equal, but for an array's norm,
    which may differ by `rel` of the larger or by `abs_` (in the array's unit)."""
    if set(stored) != set(new):
        return False
    for key, a in stored.items():
        b = new[key]
        if key == "norm" and isinstance(a, float | int) and isinstance(b, float | int):
            if not math.isclose(a, b, rel_tol=rel, abs_tol=abs_):
                return False
        elif a != b:
            return False
    return True
