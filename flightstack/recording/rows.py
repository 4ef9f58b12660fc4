"""The row stream `timeseries_<mode>.rows`: fixed-size rows readable after a kill (layout: run_dir's
module docstring)."""

from __future__ import annotations

import json
import logging
import math
import os
import struct
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from flightstack.recording.files import ROWS_SUFFIX as ROWS_SUFFIX  # defined with RUN_FILES
from flightstack.recording.files import RunDirError, errno_text, json_safe
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording

_log = logging.getLogger(__name__)

MAGIC = b"FSROWS1\n"
MAX_HEADER_BYTES = 1 << 20
"""Bound on a row stream's header (B): the writer's is about 2 kB (header length read from a file is
checked against it, and against the file's size, before it is read)."""
HEAD_BYTES = len(MAGIC) + 4
"""MAGIC and the uint32 (little-endian) length of the header JSON that follows it."""
MAX_ROW_BYTES = 1 << 20
"""Bound on one row (B): about 1 kB for 3 drones."""
STREAM_FIELDS = tuple(f for f in ARRAY_FIELDS if f not in ("e_c", "e_e"))
"""The Recording arrays a ModeWriter streams (e_c and e_e are derived at the end from the poses)."""


class RowLayout:
    """The fixed-size rows of a row stream: named columns (dtype, per-row shape) plus `_seq`."""

    def __init__(self, columns: Mapping[str, tuple[Any, tuple[int, ...]]], meta: Mapping[str, Any]):
        """columns: name → (numpy dtype, shape of one row's value); meta: JSON-able facts for readers."""
        self.columns = {
            k: (np.dtype(dt).newbyteorder("<"), tuple(shape)) for k, (dt, shape) in columns.items()
        }
        self.meta = dict(meta)
        self.dtype = np.dtype(
            [("_seq", "<i8")] + [(name, dt, shape) for name, (dt, shape) in self.columns.items()]
        )

    @staticmethod
    def of_recording(rec: Recording, fields: Iterable[str] = STREAM_FIELDS) -> RowLayout:
        """The layout of a Recording's arrays (one row per tick), meta {mode, drone_ids}."""
        cols = {f: (getattr(rec, f).dtype, getattr(rec, f).shape[1:]) for f in fields}
        return RowLayout(cols, {"mode": rec.mode, "drone_ids": [int(i) for i in rec.drone_ids]})

    def header(self) -> bytes:
        """MAGIC, uint32 length, JSON padded to a multiple of 64 bytes."""
        doc = {
            "format": "flightstack rows",
            "version": 1,
            "columns": [
                {"name": n, "dtype": dt.str, "shape": list(shape)} for n, (dt, shape) in self.columns.items()
            ],
            "meta": json_safe(self.meta),
        }
        body = json.dumps(doc).encode()
        total = len(MAGIC) + 4 + len(body) + 1
        body += b" " * (-total % 64) + b"\n"
        return MAGIC + struct.pack("<I", len(body)) + body

    def pack(self, arrays: Mapping[str, np.ndarray], first_row: int) -> bytes:
        """Rows first_row, first_row+1, ... of every column (each array has the same number of rows)."""
        m = len(next(iter(arrays.values())))
        block = np.zeros(m, dtype=self.dtype)
        block["_seq"] = np.arange(first_row + 1, first_row + m + 1)
        for name in self.columns:
            block[name] = arrays[name]
        return block.tobytes()


def read_rows(path: Path) -> tuple[dict[str, Any], np.ndarray]:
    """(meta, rows) of a row stream, also one cut short by a kill: only the leading rows whose `_seq`
    is their row number + 1 are returned (a torn or zero-filled tail is dropped). `rows` is a numpy
    structured array; rows[name] is one column, shape (N, *shape). RunDirError if not a row stream."""
    meta, rows, _ = read_row_stream(path)
    return meta, rows


def read_row_stream(path: Path) -> tuple[dict[str, Any], np.ndarray, str | None]:
    """(meta, rows, dropped) of a row stream as `read_rows`; dropped says what was left out after the good
    rows (None when nothing was). RunDirError naming the file when its header is damaged: it is checked
    (length at most MAX_HEADER_BYTES, JSON of the documented shape, numeric columns, a row at most
    MAX_ROW_BYTES) before anything is allocated from it."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            parsed = parse_header(path, fh.read(HEAD_BYTES + MAX_HEADER_BYTES), size)
            if parsed is None:  # shorter than its size a moment ago
                raise RunDirError(path, "the file was cut while it was read")
            layout, start = parsed
            fh.seek(start)
            count = (size - start) // layout.dtype.itemsize
            rows = np.fromfile(fh, dtype=layout.dtype, count=count)
    except OSError as exc:
        raise RunDirError(path, errno_text(exc)) from None
    ok = rows["_seq"] == np.arange(1, len(rows) + 1)
    good = len(rows) if ok.all() else int(np.argmin(ok))
    partial = (size - start) % layout.dtype.itemsize
    dropped = None
    if good < count or partial:
        dropped = f"kept the first {good} rows; dropped " + " and ".join(
            [f"{count - good} rows whose _seq is not their row number"] * (good < count)
            + [f"a partial row of {partial} B"] * bool(partial)
        )
    return layout.meta, rows[:good], dropped


def parse_header(path: Path, data: bytes, file_size: int | None = None) -> tuple[RowLayout, int] | None:
    """(layout, bytes before the first row) from `data`, the start of a row stream. file_size: the whole
    file's size when `data` holds all of its start there is; None for a stream still being written, whose
    header not yet all there gives None. RunDirError naming the file for a damaged header: the magic, a
    length at most MAX_HEADER_BYTES (and the file), JSON of the documented shape, numeric columns and a row
    at most MAX_ROW_BYTES are checked before anything is allocated from it."""
    whole = file_size is not None
    if data[: len(MAGIC)] != MAGIC[: len(data)] or (whole and len(data) < HEAD_BYTES):
        raise RunDirError(path, "not a flightstack row stream (no FSROWS1 magic)")
    if len(data) < HEAD_BYTES:
        return None
    (n,) = struct.unpack_from("<I", data, len(MAGIC))
    if file_size is not None and n > min(MAX_HEADER_BYTES, file_size - HEAD_BYTES):
        raise RunDirError(
            path, f"header length {n} B: more than the file ({file_size} B) or {MAX_HEADER_BYTES} B"
        )
    if n > MAX_HEADER_BYTES:
        raise RunDirError(path, f"header length {n} B: more than {MAX_HEADER_BYTES} B")
    if len(data) < HEAD_BYTES + n:
        return None
    return _layout(path, data[HEAD_BYTES : HEAD_BYTES + n]), HEAD_BYTES + n


def _layout(path: Path, body: bytes) -> RowLayout:
    """The RowLayout of a row stream's header JSON; RunDirError for one of another shape."""
    try:
        doc = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise RunDirError(path, f"header is not JSON ({exc})") from None
    cols = doc.get("columns") if isinstance(doc, dict) else None
    meta = doc.get("meta", {}) if isinstance(doc, dict) else None
    if not isinstance(cols, list) or not isinstance(meta, dict):
        raise RunDirError(path, "header: not an object with a list of columns and a meta object")
    columns: dict[str, tuple[Any, tuple[int, ...]]] = {}
    for c in cols:
        name = c.get("name") if isinstance(c, dict) else None
        dt, shape = (c.get("dtype"), c.get("shape")) if isinstance(c, dict) else (None, None)
        if (
            not isinstance(name, str)
            or name in columns
            or name == "_seq"
            or not isinstance(dt, str)
            or not isinstance(shape, list)
            or not all(
                isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= MAX_ROW_BYTES for d in shape
            )
        ):
            raise RunDirError(path, f"header: column {str(c)[:80]} is not {{name, dtype, shape}}")
        try:
            dtype = np.dtype(dt)
        except (TypeError, ValueError):
            raise RunDirError(path, f"header: column {name}: {dt[:40]!r} is not a dtype") from None
        if dtype.kind not in "biuf" or dtype.subdtype is not None:
            raise RunDirError(path, f"header: column {name}: dtype {dt[:40]!r} is not a number")
        columns[name] = (dtype, tuple(shape))
    itemsize = 8 + sum(dt.itemsize * math.prod(shape) for dt, shape in columns.values())
    if itemsize > MAX_ROW_BYTES:
        raise RunDirError(path, f"header: a row of {itemsize} B, more than {MAX_ROW_BYTES} B")
    return RowLayout(columns, meta)
