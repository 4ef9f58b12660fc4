"""The time series of one run (every tick, every drone) and its on-disk form (npz).

While a run flies, flightstack.recording.run_dir appends the same arrays to the run directory block by block
and
writes this npz at the end; `flightstack.recording.run_dir.load_run` reads either back as Recordings.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from flightstack.paper.geometry import compose_arrays, inverse_arrays, vec_arrays
from flightstack.recording.files import RunDirError, read_npz

ARRAY_LAYOUT: dict[str, tuple[tuple[int | str, ...], type, float]] = {
    # field: (shape of one tick, "n" standing for the drones; dtype; value before it is recorded)
    "t": ((), np.float64, 0.0),
    "g_w0": ((4,), np.float64, 0.0),
    "g_wi": (("n", 4), np.float64, 0.0),
    "g_bar_w": (("n", 4), np.float64, 0.0),
    "e_c": (("n", 4), np.float64, 0.0),
    "e_e": (("n", 4), np.float64, 0.0),
    "e_e_meas": (("n", 4), np.float64, 0.0),
    "u_e": (("n", 4), np.float64, 0.0),
    "mu_used": (("n", 4), np.float64, 0.0),
    "var_own": (("n", 4), np.float64, 0.0),
    "V_cmd": (("n", 4), np.float64, 0.0),
    "visible": (("n",), np.bool_, 0.0),
    "n_fused": (("n",), np.int_, 0.0),
    "wall_t": ((), np.float64, 0.0),
    "loop_period": ((), np.float64, np.nan),
    "loop_compute": ((), np.float64, np.nan),
    "frame_age": (("n",), np.float64, np.nan),
    "pose_age": (("n",), np.float64, np.nan),
}
"""The in-memory arrays of a Recording, in ARRAY_FIELDS order: `Recording.empty` allocates exactly these
and `recording_nbytes` sizes them."""
ARRAY_FIELDS = tuple(ARRAY_LAYOUT)


def _array_shape(field: str, n_ticks: int, n_drones: int) -> tuple[int, ...]:
    return (n_ticks, *(n_drones if d == "n" else int(d) for d in ARRAY_LAYOUT[field][0]))


def recording_nbytes(n_drones: int, n_ticks: int) -> int:
    """Bytes that `Recording.empty(mode, ids, n_ticks)` allocates for n_drones drones (its arrays)."""
    total = 0
    for f, (_, dtype, _) in ARRAY_LAYOUT.items():
        total += math.prod(_array_shape(f, n_ticks, n_drones)) * np.dtype(dtype).itemsize
    return total


LOOP_HEALTH_FIELDS = ("loop_period", "loop_compute", "frame_age", "pose_age")
"""Arrays that are NaN where nothing was measured (the first tick's period, a compiled chunk, a tick
without a frame or during a pose dropout): never required finite."""
MACHINE_FIELDS = ("wall_t", "loop_period", "loop_compute")
"""Arrays that measure the computer that flew, not the flight: two runs of the same mission differ in
them (the compiled loop's guard test compares every other array)."""

REQUIRED_FIELDS = ("t", "g_w0", "g_wi", "g_bar_w")
"""Arrays every stored recording has (the others default as `Recording.from_columns` says)."""
MAX_DRONES = 1000
"""Bound on the drones of a stored recording (a drone count read from a file is checked against it)."""
VALUE_BOUND = 1e6
"""Bound on the magnitude of a recorded value (m, rad, m/s, s of mission time, ...; wall_t: WALL_T_BOUND)
beyond which a value read back from a row stream is damage, not a flight (`plausible_ticks`)."""
WALL_T_BOUND = 1e11
"""Bound on wall_t (s since the epoch: the year 5138)."""
_KINDS = {"b": "b", "i": "iu", "f": "fiu"}
"""dtype kinds a stored array may have, by the kind of its in-memory array."""

META_FIELDS = (
    "ticks_done", "bus_dropped", "wall_seconds", "interrupted", "error", "vision_rejections", "video_counts",
    "vision_gate",
)  # fmt: skip
"""The scalar facts of a Recording besides its arrays and events (JSON-able; see `Recording.meta`)."""


@dataclass
class Recording:
    """Arrays indexed [tick, drone, component]; poses are [x, y, z, θ] in Σw (m, rad); t in s."""

    mode: str
    drone_ids: list[int]
    t: np.ndarray
    g_w0: np.ndarray  # (N, 4) true target pose
    g_wi: np.ndarray  # (N, n, 4) true drone poses
    g_bar_w: np.ndarray  # (N, n, 4) estimates ḡ_w,i
    e_c: np.ndarray  # (N, n, 4) vec(g_d⁻¹ ḡ_i0)
    e_e: np.ndarray  # (N, n, 4) true vec(ḡ_i0⁻¹ g_i0)
    e_e_meas: np.ndarray  # (N, n, 4) J⁺(f − f̄)
    u_e: np.ndarray  # (N, n, 4)
    mu_used: np.ndarray  # (N, n, 4)
    var_own: np.ndarray  # (N, n, 4)
    V_cmd: np.ndarray  # (N, n, 4) body-velocity command sent (m/s, rad/s)
    visible: np.ndarray  # (N, n) bool
    n_fused: np.ndarray  # (N, n) int: predictions fused (own + fresh neighbours) by each agent
    wall_t: np.ndarray  # (N,) wall-clock time.time() of each tick (s since the epoch; across processes)
    # loop health (flightstack.analysis.loop_health); NaN where not measured (compiled ticks, old files)
    loop_period: np.ndarray  # (N,) wall time (s) from the previous tick's start to this one's
    loop_compute: np.ndarray  # (N,) wall time (s) of this tick's sensing, fusion, command and record
    frame_age: np.ndarray  # (N, n) age (s, mission clock) of the camera frame the tick looked at
    pose_age: np.ndarray  # (N, n) age (s, mission clock) of the drone's own pose the tick used
    ticks_done: int = 0
    bus_dropped: dict[str, int] = field(default_factory=dict)
    wall_seconds: float = 0.0
    interrupted: bool = False
    error: str | None = None
    events: list[dict[str, Any]] = field(default_factory=list)
    vision_rejections: dict[str, dict[str, int]] = field(default_factory=dict)
    video_counts: dict[str, dict[str, int]] = field(default_factory=dict)
    """Per drone, what its camera's stream did in this mode (hal.StreamCounting); empty when no camera
    counts a stream (every simulated rig), and then not written: `meta()` omits it."""
    vision_gate: dict[str, dict[str, int]] = field(default_factory=dict)
    """Per drone whose camera gives images, the detection gate's counts (runtime.tick_record.count_gate);
    empty on the ideal camera, and then not written."""

    @staticmethod
    def empty(mode: str, ids: list[int], n_ticks: int) -> Recording:
        """n_ticks ticks of every array of ARRAY_LAYOUT (zeros; NaN where nothing is measured yet)."""
        n = len(ids)

        def alloc(f: str) -> np.ndarray:
            _, dtype, fill = ARRAY_LAYOUT[f]
            shape = _array_shape(f, n_ticks, n)
            return np.zeros(shape, dtype) if fill == 0 else np.full(shape, fill, dtype)

        arrays: dict[str, Any] = {f: alloc(f) for f in ARRAY_FIELDS}
        return Recording(mode, list(ids), **arrays)

    def truncated(self) -> Recording:
        """Only the ticks actually flown (after an interrupt or an error)."""
        k = self.ticks_done
        out = Recording(self.mode, self.drone_ids, *(getattr(self, f)[:k] for f in ARRAY_FIELDS))
        for name in (*META_FIELDS, "events"):
            setattr(out, name, getattr(self, name))
        return out

    @staticmethod
    def from_columns(mode: str, ids: list[int], columns: Mapping[str, np.ndarray]) -> Recording:
        """A recording of the N rows in `columns` (ARRAY_FIELDS, each with N rows); a missing field keeps
        `empty`'s value of its usual shape: zeros (e_c and e_e before `fill_true_errors`, or files written
        before a field existed), NaN for the loop-health arrays (not measured). ValueError (saying
        which) when a REQUIRED_FIELDS array is missing, or an array's shape or dtype does not fit ids."""
        problem = columns_problem(ids, columns)
        if problem is not None:
            raise ValueError(problem)
        N = int(np.asarray(columns["t"]).shape[0])
        rec = Recording.empty(mode, ids, N)
        for f in ARRAY_FIELDS:
            if f in columns:
                setattr(rec, f, np.asarray(columns[f]))
        rec.ticks_done = N
        return rec

    def plausible_ticks(self) -> tuple[int, str | None]:
        """(k, why): the leading k of the ticks done whose every float value is finite and within
        VALUE_BOUND (wall_t within WALL_T_BOUND; the loop-health arrays may be NaN: not measured), and
        what is wrong with tick k (None when every tick is plausible). For data without a checksum (a
        row stream), where a damaged byte gives a value no flight records."""
        k, why = self.ticks_done, None
        for f in ARRAY_FIELDS:
            a = getattr(self, f)[: self.ticks_done]
            if a.dtype.kind != "f" or len(a) == 0:
                continue
            with np.errstate(invalid="ignore"):
                bad = np.abs(a) > (WALL_T_BOUND if f == "wall_t" else VALUE_BOUND)
            bad |= np.isinf(a) if f in LOOP_HEALTH_FIELDS else ~np.isfinite(a)
            first = np.flatnonzero(bad.reshape(len(a), -1).any(axis=1))
            if first.size and first[0] < k:
                k, why = int(first[0]), f"{f} not finite or beyond {VALUE_BOUND:g} at tick {first[0]}"
        return k, why

    def meta(self) -> dict[str, Any]:
        """META_FIELDS as a JSON-able dict (the run directory's recording.json keeps it per mode)."""
        out: dict[str, Any] = {
            "ticks_done": int(self.ticks_done),
            "bus_dropped": {str(k): int(v) for k, v in self.bus_dropped.items()},
            "wall_seconds": float(self.wall_seconds),
            "interrupted": bool(self.interrupted),
            "error": self.error,
            "vision_rejections": {
                str(i): {str(k): int(v) for k, v in c.items()} for i, c in self.vision_rejections.items()
            },
        }
        if self.video_counts:
            out["video_counts"] = {
                str(i): {str(k): int(v) for k, v in c.items()} for i, c in self.video_counts.items()
            }
        if self.vision_gate:
            out["vision_gate"] = {
                str(i): {str(k): int(v) for k, v in c.items()} for i, c in self.vision_gate.items()
            }
        return out

    @staticmethod
    def meta_problem(meta: Mapping[str, Any]) -> str | None:
        """What is wrong with stored META_FIELDS (JSON read back), or None when each present one has the
        type `meta` writes."""
        kinds: dict[str, tuple[type | tuple[type, ...], str]] = {
            "ticks_done": (int, "an integer"),
            "wall_seconds": ((int, float), "a number"),
            "interrupted": (bool, "a boolean"),
            "error": ((str, type(None)), "a text or null"),
        }
        for name, (ok, what) in kinds.items():
            v = meta.get(name)
            if name in meta and (not isinstance(v, ok) or (isinstance(v, bool) and ok is not bool)):
                return f"{name}: {str(v)[:40]!r} is not {what}"

        def counts(c: object) -> bool:
            return isinstance(c, dict) and all(
                isinstance(v, int) and not isinstance(v, bool) for v in c.values()
            )

        rejections = meta.get("vision_rejections", {})
        if not counts(meta.get("bus_dropped", {})):
            return "bus_dropped: not a map of counts"
        if not isinstance(rejections, dict) or not all(counts(c) for c in rejections.values()):
            return "vision_rejections: not a map of counts per drone"
        for name in ("video_counts", "vision_gate"):
            per_drone = meta.get(name, {})
            if not isinstance(per_drone, dict) or not all(counts(c) for c in per_drone.values()):
                return f"{name}: not a map of counts per drone"
        return None

    def apply_meta(self, meta: Mapping[str, Any]) -> None:
        """Restore the META_FIELDS present in `meta` (as written by `meta`), except ticks_done, which
        stays the number of rows actually read."""
        for name in META_FIELDS:
            if name in meta and name != "ticks_done":
                setattr(self, name, meta[name])

    def save(self, path: str | os.PathLike[str] | IO[bytes]) -> None:
        """The arrays of the ticks done as an npz (a path, or a binary file opened for writing; numpy
        appends `.npz` to a path without it). Stored, not deflated: the float64 rows compress to only 80 %
        and deflating them cost about 1 s of CPU per 20 MB, which the run waits for at each mode's end."""
        np.savez(
            path,
            mode=self.mode,
            drone_ids=np.array(self.drone_ids),
            **{f: getattr(self, f)[: self.ticks_done] for f in ARRAY_FIELDS},
        )

    @staticmethod
    def load(path: str | os.PathLike[str]) -> Recording:
        """Read a recording written by `save` (arrays only; events and counters live in the run dir).
        RunDirError naming the file when it is not one (files.read_npz; shapes as `from_columns`)."""
        z = read_npz(Path(path))
        mode, ids = z.get("mode"), z.get("drone_ids")
        if mode is None or mode.shape != () or mode.dtype.kind != "U":
            raise RunDirError(Path(path), "no mode name in it")
        if ids is None or ids.ndim != 1 or ids.dtype.kind not in "iu" or len(ids) > MAX_DRONES:
            raise RunDirError(Path(path), f"drone_ids: not a list of at most {MAX_DRONES} integers")
        try:  # fields missing in older files: n_fused and wall_t zeros, loop health NaN
            return Recording.from_columns(str(mode), [int(i) for i in ids], z)
        except ValueError as exc:
            raise RunDirError(Path(path), str(exc)) from None

    def fill_true_errors(self, g_d: np.ndarray) -> None:
        """e_c = vec(g_d⁻¹ ḡ_i0) and the true e_e = vec(ḡ_i0⁻¹ g_i0) from the recorded poses (vectorised).

        g_d: (n, 4) desired poses [x, y, z, θ] of the drones in recording order.
        """
        k = self.ticks_done
        inv_wi = inverse_arrays(self.g_wi[:k])
        g_bar_i0 = compose_arrays(inv_wi, self.g_bar_w[:k])
        g_i0 = compose_arrays(inv_wi, self.g_w0[:k, None, :])
        self.e_c[:k] = vec_arrays(compose_arrays(inverse_arrays(g_d)[None], g_bar_i0))
        self.e_e[:k] = vec_arrays(compose_arrays(inverse_arrays(g_bar_i0), g_i0))

    def true_relative_error(self, g_d: np.ndarray) -> np.ndarray:
        """vec(g_d⁻¹ g_i0) per tick and drone from the true poses: how far each drone is from its
        desired pose relative to the target, (N, n, 4)."""
        k = self.ticks_done
        g_i0 = compose_arrays(inverse_arrays(self.g_wi[:k]), self.g_w0[:k, None, :])
        return vec_arrays(compose_arrays(inverse_arrays(g_d)[None], g_i0))


def columns_problem(ids: list[int], columns: Mapping[str, np.ndarray]) -> str | None:
    """What keeps `columns` (stored arrays by name) from being the recording of the drones `ids`, or None:
    a REQUIRED_FIELDS array missing, more than MAX_DRONES drones, or an ARRAY_FIELDS array whose shape is
    not (N, *one tick's shape for len(ids) drones) or whose dtype kind does not fit. Checked before
    anything is allocated for the recording."""
    missing = [f for f in REQUIRED_FIELDS if f not in columns]
    if missing:
        return f"no {', '.join(missing)} array"
    if len(ids) > MAX_DRONES or len(set(ids)) != len(ids):
        return f"drone ids {ids[:10]}...: more than {MAX_DRONES} or repeated"
    ref = Recording.empty("", list(ids), 0)
    N = int(np.asarray(columns["t"]).shape[0]) if np.ndim(columns["t"]) == 1 else -1
    for f in ARRAY_FIELDS:
        if f not in columns:
            continue
        a, want = np.asarray(columns[f]), getattr(ref, f)
        if a.shape != (N, *want.shape[1:]) or a.dtype.kind not in _KINDS[want.dtype.kind]:
            return (
                f"{f}: shape {a.shape} {a.dtype}, expected {('N', *want.shape[1:])} {want.dtype} for "
                f"{len(ids)} drones (N = {N} ticks of t)"
            )
    return None
