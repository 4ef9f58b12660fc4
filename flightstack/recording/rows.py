"""The row stream `timeseries_<mode>.rows`: fixed-size rows readable after a kill (layout: run_dir's
module docstring)."""

from __future__ import annotations

import json
import logging
import os
import struct
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from flightstack.recording.files import ROWS_SUFFIX as ROWS_SUFFIX  # defined with RUN_FILES
from flightstack.recording.files import json_safe
from flightstack.recording.timeseries import ARRAY_FIELDS, Recording

if TYPE_CHECKING:
    pass

_log = logging.getLogger(__name__)

MAGIC = b"FSROWS1\n"
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
    structured array; rows[name] is one column, shape (N, *shape). ValueError if not a row stream."""
    with open(path, "rb") as fh:
        head = fh.read(len(MAGIC) + 4)
        if len(head) < len(MAGIC) + 4 or head[: len(MAGIC)] != MAGIC:
            raise ValueError(f"{path}: not a flightstack row stream")
        (n,) = struct.unpack("<I", head[len(MAGIC) :])
        body = fh.read(n)
        if len(body) < n:
            raise ValueError(f"{path}: header cut short")
        doc = json.loads(body)
        cols = {c["name"]: (c["dtype"], tuple(c["shape"])) for c in doc["columns"]}
        layout = RowLayout(cols, doc.get("meta", {}))
        size = os.fstat(fh.fileno()).st_size - len(MAGIC) - 4 - n
        count = max(size, 0) // layout.dtype.itemsize
        rows = np.fromfile(fh, dtype=layout.dtype, count=count)
    ok = rows["_seq"] == np.arange(1, len(rows) + 1)
    good = len(rows) if ok.all() else int(np.argmin(ok))
    return layout.meta, rows[:good]
