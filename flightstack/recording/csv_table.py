"""The main time series of a run as CSV, for the simplest tools (pandas, a spreadsheet).

One file per mode, `timeseries_<mode>.csv`, written by the recorder's writer thread once the mode's final
`timeseries_<mode>.npz` is on disk (flightstack/recording/run_dir.py), never in the control loop; `flightstack
export RUN --csv FILE` writes the same columns for every mode of an older run directory into one file.
Long format: one row per recorded tick and drone (ticks in order, drones in recording order), the columns
of `COLUMNS` (docs/logs.md is generated from it), a header line of their names, `,` between fields,
`\\n` after each row, no quoting (no field holds a comma).

Rows: every `stride` -th tick from tick 0, stride = max(1, floor(CSV_PERIOD_S / dt)) (dt: the recording's
tick period), raised until the rows fit MAX_ROWS. Numbers: integers as such; reals rounded to DECIMALS
decimals (round half to even of value · 10^DECIMALS), trailing zeros dropped; a value that is not finite
is an empty field (pandas reads NaN). Formatting is vectorised (numpy, no per-value Python call); what it
costs a run is measured in docs/logs.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from flightstack.recording.files import RunDirError, atomic_write_bytes
from flightstack.recording.run_reader import read_run
from flightstack.recording.timeseries import Recording

if TYPE_CHECKING:
    from flightstack.config.mission import Mission

CSV_PERIOD_S = 0.02
"""Mission time between two rows of one drone (s), at least: 50 Hz, or every tick when dt is longer."""
MAX_ROWS = 1_048_575
"""Data rows of one file at most: a spreadsheet's 1,048,576 rows with the header."""
DECIMALS = 9
"""Decimals of a real value (1 nm, 1 nrad, 1 ns)."""
_MAX_FIXED = 1e9
"""|value| from which a real is written by Python's repr (fixed point would overflow int64)."""
SUFFIX = ".csv"


@dataclass(frozen=True)
class Column:
    """One CSV column: its name, unit ("-": none), what it holds and its values for ticks `k` (K,):
    `values(rec, k)` is (K, n) (per drone) or (K,) (the same for every drone)."""

    name: str
    unit: str
    meaning: str
    values: Callable[[Recording, np.ndarray], np.ndarray]
    integer: bool = False


def _pose(field: str, c: int) -> Callable[[Recording, np.ndarray], np.ndarray]:
    return lambda rec, k: getattr(rec, field)[k, ..., c]


def _norm(field: str) -> Callable[[Recording, np.ndarray], np.ndarray]:
    return lambda rec, k: np.sqrt((getattr(rec, field)[k] ** 2).sum(axis=-1))


_XYZT = (("x", "m"), ("y", "m"), ("z", "m"), ("theta", "rad"))
_VEL = (("vx", "m/s"), ("vy", "m/s"), ("vz", "m/s"), ("omega", "rad/s"))

COLUMNS: tuple[Column, ...] = (
    Column("mode", "-", "the mode flown (none, local, dgp, oracle)", lambda rec, k: np.zeros(len(k))),
    Column("tick", "-", "tick index from 0 (mission time t = tick · dt)", lambda rec, k: k, integer=True),
    Column("t", "s", "mission time", lambda rec, k: rec.t[k]),
    Column(
        "drone",
        "-",
        "drone id",
        lambda rec, k: np.broadcast_to(rec.drone_ids, (len(k), len(rec.drone_ids))),
        integer=True,
    ),
    *(
        Column(n, u, f"the drone's true pose g_wi in the world frame Σw: {n}", _pose("g_wi", c))
        for c, (n, u) in enumerate(_XYZT)
    ),
    *(
        Column(f"target_{n}", u, f"the target's true pose g_w0 in Σw: {n}", _pose("g_w0", c))
        for c, (n, u) in enumerate(_XYZT)
    ),
    *(
        Column(
            f"est_{n}", u, f"the drone's estimate ḡ_w,i of the target's pose in Σw: {n}", _pose("g_bar_w", c)
        )
        for c, (n, u) in enumerate(_XYZT)
    ),
    Column(
        "e_c_norm",
        "m, rad",
        "‖e_c,i‖: the drone's control error vec(g_d⁻¹ ḡ_i0) as a 4-vector "
        "[x, y, z, θ] (paper Fig. 4 plots the network's √Σ_i ‖e_c,i‖²)",
        _norm("e_c"),
    ),
    Column(
        "e_e_norm",
        "m, rad",
        "‖e_e,i‖: the drone's true estimation error vec(ḡ_i0⁻¹ g_i0) (Fig. 5)",
        _norm("e_e"),
    ),
    *(
        Column(
            f"mu_{n}",
            u,
            f"the GP mean of the target's body velocity the drone used (fused): {n}",
            _pose("mu_used", c),
        )
        for c, (n, u) in enumerate(_VEL)
    ),
    *(
        Column(f"cmd_{n}", u, f"the body-velocity command sent to the drone: {n}", _pose("V_cmd", c))
        for c, (n, u) in enumerate(_VEL)
    ),
    Column(
        "visible",
        "-",
        "1 when the drone's camera saw the target this tick, else 0",
        lambda rec, k: rec.visible[k],
        integer=True,
    ),
    Column(
        "n_fused",
        "-",
        "predictions the drone fused this tick (its own and fresh neighbours')",
        lambda rec, k: rec.n_fused[k],
        integer=True,
    ),
)
"""The CSV's columns, in order (docs/logs.md's table is generated from them)."""
NAMES = tuple(c.name for c in COLUMNS)


def csv_name(mode: str) -> str:
    """The file a run directory holds for `mode`."""
    return f"timeseries_{mode}{SUFFIX}"


def stride(rec: Recording) -> int:
    """Every how many ticks a row is written (module docstring)."""
    n_ticks, n = rec.ticks_done, max(1, len(rec.drone_ids))
    dt = float(rec.t[n_ticks - 1] - rec.t[0]) / (n_ticks - 1) if n_ticks > 1 else 0.0
    s = max(1, math.floor(CSV_PERIOD_S / dt + 1e-9)) if dt > 0 and math.isfinite(dt) else 1
    return max(s, math.ceil(n_ticks * n / MAX_ROWS))


def ticks_written(rec: Recording) -> np.ndarray:
    """The tick indices whose rows the CSV holds."""
    return np.arange(0, rec.ticks_done, stride(rec))


def csv_bytes(recs: Iterable[Recording], header: bool = True) -> bytes:
    """The CSV text of the recordings (each its mode's rows), with the header line unless not `header`."""
    parts = [(",".join(NAMES) + "\n").encode()] if header else []
    for rec in recs:
        k = ticks_written(rec)
        n = len(rec.drone_ids)
        if not len(k) or not n:
            continue
        rows = len(k) * n
        cells: list[np.ndarray] = []
        for j, col in enumerate(COLUMNS):
            if col.name == "mode":
                text = np.frombuffer(_field(rec.mode).encode(), np.uint8)
                cells.append(np.broadcast_to(text, (rows, len(text))))
            else:
                v = np.asarray(col.values(rec, k))
                digits = 0 if col.integer else DECIMALS
                if v.ndim == 1:  # the same for every drone: formatted once per tick
                    cells.append(np.repeat(_text(v, digits), n, axis=0))
                else:
                    cells.append(_text(v.reshape(rows), digits))
            sep = b"\n" if j == len(COLUMNS) - 1 else b","
            cells.append(np.full((rows, 1), sep[0], np.uint8))
        table = np.concatenate(cells, axis=1).ravel()
        parts.append(table[table != 0].tobytes())
    return b"".join(parts)


def write_csv(path: Path, recs: Iterable[Recording]) -> int:
    """Write the CSV of `recs` to `path` atomically; returns its size (bytes). Raises OSError."""
    data = csv_bytes(recs)
    atomic_write_bytes(Path(path), data)
    return len(data)


def export_csv(
    run_dir: Path | str, out: Path | str, modes: list[str] | None = None, mission: Mission | None = None
) -> tuple[list[Recording], list[str]]:
    """Write the CSV of a run directory's recording (every mode in the order flown, or `modes` in that
    order) to `out`; returns the recordings written and what `read_run` skipped. mission: lets a
    recording cut short (a row stream) get its e_c and e_e recomputed. RunDirError for a directory without
    a recording, an unknown mode or a damaged recording; OSError when `out` cannot be written."""
    contents = read_run(run_dir, mission)
    recs = contents.recordings
    if not recs:
        raise RunDirError(run_dir, "no recording (timeseries_<mode>.npz or .rows) in it")
    chosen = list(recs) if modes is None else list(modes)
    unknown = [m for m in chosen if m not in recs]
    if unknown:
        raise RunDirError(run_dir, f"no mode {', '.join(unknown)} recorded (it has {', '.join(recs)})")
    written = [recs[m] for m in chosen]
    write_csv(Path(out), written)
    return written, contents.skipped


def _field(text: str) -> str:
    """A text field as CSV writes it: quoted (RFC 4180) when it holds a comma, a quote or a line break."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _text(x: np.ndarray, decimals: int) -> np.ndarray:
    """(R, W) uint8: value i of x (R,) as decimal text in row i, right-aligned, 0 bytes as padding (dropped
    when the table is joined); a non-finite value is empty (module docstring)."""
    x = np.asarray(x, dtype=np.float64)
    finite = np.isfinite(x)
    if np.any(np.abs(x[finite]) >= _MAX_FIXED):
        return _text_slow(x, decimals)
    scale = 10**decimals
    v = np.rint(np.where(finite, x, 0.0) * scale).astype(np.int64)
    neg = v < 0
    ip, fp = np.divmod(np.abs(v), scale)
    nd = np.ones(len(v), dtype=np.int64)  # digits of the integer part
    top, p = int(ip.max(initial=0)), 10
    while p <= top:
        nd += ip >= p
        p *= 10
    maxnd = int(nd.max(initial=1))
    width = 1 + maxnd + (1 + decimals if decimals else 0)
    out = np.zeros((len(v), width), dtype=np.uint8)
    q = ip.copy()
    for k in range(maxnd):  # integer digits, units first (columns 1..maxnd)
        out[:, maxnd - k] = np.where(k < nd, 48 + q % 10, 0)
        q //= 10
    rows = np.nonzero(neg)[0]
    out[rows, maxnd - nd[rows]] = ord("-")
    if decimals:
        trailing = np.ones(len(v), dtype=bool)
        for k in range(decimals - 1, -1, -1):  # last decimal first: drop trailing zeros
            d = (fp // 10 ** (decimals - 1 - k)) % 10
            trailing &= d == 0
            out[:, maxnd + 2 + k] = np.where(trailing, 0, 48 + d)
        out[:, maxnd + 1] = np.where(fp == 0, 0, ord("."))
    out[~finite] = 0
    return out


def _text_slow(x: np.ndarray, decimals: int) -> np.ndarray:
    """`_text` for a column holding a value too large for fixed point (a diverged flight): Python's
    formatting, per value."""
    texts = [
        (repr(round(float(a), decimals)) if decimals else str(int(a))).encode() if math.isfinite(a) else b""
        for a in x
    ]
    out = np.zeros((len(texts), max([1, *map(len, texts)])), dtype=np.uint8)
    for i, t in enumerate(texts):
        if t:
            out[i, out.shape[1] - len(t) :] = np.frombuffer(t, np.uint8)
    return out


__all__ = [
    "COLUMNS",
    "CSV_PERIOD_S",
    "DECIMALS",
    "MAX_ROWS",
    "NAMES",
    "Column",
    "csv_bytes",
    "csv_name",
    "export_csv",
    "stride",
    "ticks_written",
    "write_csv",
]
