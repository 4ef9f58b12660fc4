"""The files of a run directory: their names and limits, atomic writes, JSON-safe values, event lines,
and the check that `--out` can take a run. No threads here (those are in run_dir and mode_writer)."""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import logging
import math
import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    pass

_log = logging.getLogger(__name__)

MIN_FREE_BYTES = 50_000_000
"""Free space (bytes, 50 MB) `--out` must have before takeoff: ~1 min of a 3-drone mission at 500 Hz in
the row stream, or hours at a hardware rate of 20 Hz, plus the final npz files and the plots."""
BLOCK_PERIOD_S = 0.5
"""Wall time (s) after which the rows gathered are handed to the writer thread."""
BLOCK_MAX_ROWS = 2000
"""Ticks after which the rows gathered are handed over anyway (simulated clocks run faster than real)."""
FSYNC_PERIOD_S = 1.0
"""The writer thread fsyncs a file written to at most this often (s), and at close."""
MAX_PENDING_BYTES = 64_000_000
"""Bytes handed to the writer thread and not yet written beyond which the recording stops (a disk that
does not keep up) rather than letting memory grow."""
CLOSE_TIMEOUT_S = 60.0
"""How long (s) closing waits for the writer thread (final npz included) before giving up."""
EVENTS_FILE = "events.jsonl"
STATE_FILE = "recording.json"
METRICS_FILE = "metrics.json"
MISSION_FILE = "mission_resolved.yaml"
"""The resolved mission of a run (absolute file paths): `flightstack report` and `train` read it."""
DATASETS_FILE = "datasets.npz"
EXPERTS_FILE = "experts.npz"
ROWS_SUFFIX = ".rows"
"""Suffix of a mode's row stream `timeseries_<mode>.rows` (flightstack.recording.rows)."""
PLOTS = {
    "trajectory": "trajectory.png",
    "e_c": "error_ec.png",
    "e_e": "error_ee.png",
    "loop_health": "loop_health.png",  # only when ticks were timed (flightstack.recording.loop_health)
}
"""The plots of a run (flightstack.recording.report.write_plots), by what they show."""
AGENT_SUMMARY_FILE = "summary.json"
GUARDIAN_LOG = "guardian.log"
"""An agent process's files besides the recording (`flightstack agent`, flightstack/cli/network.py)."""
EMULATED_LAB_DIR = "emulated_lab"
"""The emulated-lab rig's working directory inside the run directory (mission, calibration)."""
REPLAY_FILE = "run.rrd"
"""`flightstack view` without --spawn/--connect/--save on a machine without a display writes it here."""
LIVE_FILE = "live.rrd"
"""`--viewer` on a machine without a display writes the live Rerun recording here."""
PROBE_PREFIX = ".flightstack-write-probe-"

RUN_FILES: tuple[str, ...] = (
    f"timeseries_*{ROWS_SUFFIX}",
    "timeseries_*.npz",
    EVENTS_FILE,
    STATE_FILE,
    METRICS_FILE,
    MISSION_FILE,
    DATASETS_FILE,
    EXPERTS_FILE,
    *PLOTS.values(),
    AGENT_SUMMARY_FILE,
    GUARDIAN_LOG,
    EMULATED_LAB_DIR,
    REPLAY_FILE,
    LIVE_FILE,
)
"""Every name (fnmatch pattern) a run of `run`/`sim`/`fly`/`agent` writes in its run directory: the one
list `--out` is checked against and `--force` removes (`run_files`). A writer of a new file adds it here
(tests/test_cli_run_options.py checks that a run writes nothing else)."""


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `path` atomically: a temporary file in the same directory, fsync, os.replace, then fsync of
    the directory (best effort). Raises OSError; never leaves a partial `path` behind."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(path.parent)


def atomic_write_json(path: Path, obj: Any, strict: bool = True) -> None:
    """`obj` as indented strict JSON, written atomically. strict: a non-finite float raises ValueError
    (a metric that is NaN is a finding); else it is written as null."""
    text = json.dumps(obj if strict else json_safe(obj), indent=2, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())


def fsync_dir(d: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(d, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def json_safe(x: Any) -> Any:
    """`x` with numpy values as Python ones and non-finite floats as None (strict JSON)."""
    if isinstance(x, Mapping):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple | set | frozenset):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, np.generic):
        return json_safe(x.item())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, bool | int | str):
        return x
    return str(x)


def event_line(ev: Mapping[str, Any]) -> bytes:
    """One events.jsonl line (strict JSON, newline-terminated)."""
    try:
        text = json.dumps(ev, allow_nan=False)
    except (TypeError, ValueError):
        text = json.dumps(json_safe(ev), allow_nan=False)
    return (text + "\n").encode()


def is_run_file(name: str) -> bool:
    """True when an entry called `name` of a run directory is written by a run: one of RUN_FILES, or an
    atomic write's temporary file of one of them (`.NAME.tmpPID`, left by a kill), or a write probe."""
    patterns = [*RUN_FILES, *(f".{p}.tmp*" for p in RUN_FILES), f"{PROBE_PREFIX}*"]
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


def run_files(out: Path) -> list[Path]:
    """The entries of the directory `out` that a run writes (is_run_file), sorted; [] if it is missing."""
    try:
        return sorted(p for p in Path(out).iterdir() if is_run_file(p.name))
    except (FileNotFoundError, NotADirectoryError):
        return []


def out_dir_entries(out: Path) -> list[Path]:
    """Every entry of the directory `out`, sorted ([] when it is missing or not a directory)."""
    try:
        return sorted(Path(out).iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []


def clear_run_files(out: Path) -> list[Path]:
    """Remove the entries of `out` a run writes (run_files; a directory among them with its contents)
    and nothing else; returns what was removed. Raises OSError if one cannot be removed."""
    removed = run_files(out)
    for p in removed:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    if removed:
        fsync_dir(Path(out))
    return removed


def check_out_dir(out: Path, min_free_bytes: int = MIN_FREE_BYTES) -> str | None:
    """None when `out` can hold a run: it is (or is created as) a directory in which a file can be
    created, written, fsync'ed and removed, on a file system with at least min_free_bytes (B) free;
    else a sentence saying why not. Call it before anything takes off. Directories it had to create are
    removed again (a check leaves nothing behind: a refused `fly` writes nothing)."""
    out = Path(out)
    created = [p for p in (out, *out.parents) if not p.exists()]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the directory: {exc.strerror or exc}"
    try:
        return _probe_out_dir(out, min_free_bytes)
    finally:
        for p in created:  # deepest first
            with contextlib.suppress(OSError):
                p.rmdir()


def _probe_out_dir(out: Path, min_free_bytes: int) -> str | None:
    probe = out / f"{PROBE_PREFIX}{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, b"\0" * 4096)  # not through _write_bytes: that is the recording stream's
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        return f"not writable: {exc.strerror or exc}"
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    free = shutil.disk_usage(out).free
    if free < min_free_bytes:
        return (
            f"only {free / 1e6:.1f} MB free on its file system; a run needs at least "
            f"{min_free_bytes / 1e6:.0f} MB (flightstack.recording.files.MIN_FREE_BYTES)"
        )
    return None


def errno_text(exc: OSError) -> str:
    name = errno.errorcode.get(exc.errno or 0, "")
    return f"{exc.strerror or exc}{f' ({name})' if name else ''}"
