"""A run whose state diverges stops: one vectorised look at the rows just recorded, per tick or chunk.

`validate` refuses gains beyond the sampled loop's divergence bound (Mission._check_sampled_loop), but a
world can still diverge (a linearisation that does not hold, a backend's own dynamics). After every
recorded tick (and every compiled chunk) the runner calls `check_rows`; a value of the state that is not
finite or exceeds its bound (DIVERGED_POSITION_M for poses, DIVERGED_ABOVE for velocities)
raises DivergedError, "diverged at t = … s (drone N, quantity)", and the
run ends as after any error: every drone lands, the recording so far is kept, metrics are written (their
non-finite values as null) and `run` exits 1.
"""

from __future__ import annotations

import numpy as np

from flightstack.config.types import MAX_DISTANCE_M
from flightstack.recording.timeseries import Recording

DIVERGED_ABOVE = 1e6
"""No velocity (m/s, rad/s) of a flight reaches 10⁶ in size: a state that does has left
every arena, long before floats overflow to inf and NaN."""
DIVERGED_POSITION_M = 10 * MAX_DISTANCE_M
"""No position (m) of a flight leaves 10 km: the mission's own positions are within MAX_DISTANCE_M. It
bounds the whole pose vector: its θ is wrapped to (−π, π]."""
ESTIMATE_FIELDS = ("g_bar_w", "u_e", "V_cmd")
"""What the stack computes itself, on every backend: the estimate ḡ_w,i, the observer input, the command."""
TRUTH_FIELDS = ("g_wi", "g_w0")
"""The simulated world's poses (on real hardware they are motion capture's measurements)."""
POSE_FIELDS = frozenset({"g_bar_w", "g_wi", "g_w0"})
COMPONENTS = ("x", "y", "z", "θ")


class DivergedError(RuntimeError):
    """The recorded state left every bound; the message says when, which drone and which quantity."""


def check_rows(rec: Recording, k0: int, k1: int, simulated: bool = True) -> None:
    """Raise DivergedError at the first row in k0..k1−1 of `rec` with a state value that is not finite or
    exceeds its bound in size (ESTIMATE_FIELDS, and TRUTH_FIELDS when `simulated`)."""
    if k1 <= k0:
        return
    first: tuple[int, str, tuple[int, ...]] | None = None
    for name in ESTIMATE_FIELDS + (TRUTH_FIELDS if simulated else ()):
        rows = np.abs(getattr(rec, name)[k0:k1])
        limit = _limit(name)
        if rows.max() <= limit:  # one reduction per field; False for NaN and inf too
            continue
        where = np.argwhere(~(rows <= limit))[0]
        if first is None or where[0] < first[0]:
            first = (int(where[0]), name, tuple(int(i) for i in where[1:]))
    if first is None:
        return
    row, name, index = first
    k = k0 + row
    value = float(getattr(rec, name)[(k, *index)])
    drone = f"drone {rec.drone_ids[index[0]]}, " if len(index) == 2 else ""
    raise DivergedError(
        f"diverged at t = {float(rec.t[k]):.6g} s ({drone}{name} {COMPONENTS[index[-1]]} = {value:.3g}; "
        f"|value| must stay within {_limit(name):g})"
    )


def _limit(name: str) -> float:
    return DIVERGED_POSITION_M if name in POSE_FIELDS else DIVERGED_ABOVE


__all__ = ["DIVERGED_ABOVE", "DIVERGED_POSITION_M", "DivergedError", "check_rows"]
