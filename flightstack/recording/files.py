"""The files of a run directory: their names and limits, atomic writes, JSON-safe values, event lines,
and the check that `--out` can take a run. No threads here (those are in run_dir)."""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import logging
import lzma
import math
import os
import shutil
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

_log = logging.getLogger(__name__)

MIN_FREE_BYTES = 200_000_000
"""Free space (bytes, 200 MB) `--out` must have before takeoff: the row streams and the final npz files,
which are stored, not deflated (the 40 s `paper_sim` run directory holds ~50 MB of each), and the plots."""
BLOCK_PERIOD_S = 0.5
"""Wall time (s) after which the rows gathered are handed to the writer thread."""
BLOCK_MAX_ROWS = 2000
"""Ticks after which the rows gathered are handed over anyway (simulated clocks run faster than real)."""
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
IMAGES_SUFFIX = ".jpgs"
"""Suffix of a mode's camera frames `images_<mode>.jpgs` (flightstack.recording.camera_frames): rigs with
image cameras only."""
PLOTS = {
    "trajectory": "trajectory.png",
    "e_c": "error_ec.png",
    "e_e": "error_ee.png",
    "loop_health": "loop_health.png",  # only when ticks were timed (flightstack.analysis.loop_health)
}
"""The plots of a run (flightstack.analysis.report.write_plots), by what they show."""
AGENT_SUMMARY_FILE = "summary.json"
GUARDIAN_LOG = "guardian.log"
"""An agent process's files besides the recording (`flightstack agent`, flightstack/cli/network.py)."""
EMULATED_LAB_DIR = "emulated_lab"
"""The emulated-lab rig's working directory inside the run directory (mission, calibration; on an impaired
network also network_log.json, what each emulated link did: docs/links.md)."""
REPLAY_FILE = "run.rrd"
"""`flightstack view` without --spawn/--connect/--save on a machine without a display writes it here."""
LIVE_FILE = "live.rrd"
"""`--viewer` on a machine without a display writes the live Rerun recording here."""
LIVE_MCAP_FILE = "recording.mcap"
"""The run as MCAP, written as it goes (flightstack.recording.mcap_live)."""
TORN_MCAP_FILE = f"{LIVE_MCAP_FILE}.torn"
"""The live MCAP as its writer left it when it was killed, kept by `flightstack report` beside the
finalised file (flightstack.recording.mcap_finalise)."""
DEVICES_DIR = "devices"
"""The raw traffic of a flight's real (or emulated) devices: one file per device and connection
(`DeviceFiles`); simulated rigs have no devices and write none."""
PROBE_PREFIX = ".flightstack-write-probe-"

RUN_FILES: tuple[str, ...] = (
    f"timeseries_*{ROWS_SUFFIX}",
    "timeseries_*.npz",
    "timeseries_*.csv",
    f"images_*{IMAGES_SUFFIX}",
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
    DEVICES_DIR,
    REPLAY_FILE,
    LIVE_FILE,
    LIVE_MCAP_FILE,
    TORN_MCAP_FILE,
)
"""Every name (fnmatch pattern) a run of `run`/`sim`/`fly`/`agent` writes in its run directory: the one
list `--out` is checked against and `--force` removes (`run_files`). A writer of a new file adds it here
(tests/test_cli_run_options.py checks that a run writes nothing else)."""

RECORDING_FILES = ("timeseries_<mode>.npz", f"timeseries_<mode>{ROWS_SUFFIX}")
"""A mode's recording: its final npz, else (a run cut short) its row stream."""
REQUIRED_FILES: dict[str, str] = {
    " or ".join(RECORDING_FILES): "every mode found is required (a metrics.json without one of the modes "
    "flown would compare what was not flown); a row stream damaged after N good rows gives those N rows",
    MISSION_FILE: "`report` and `train` need it (unless --mission); `view` and `export` do without",
}
"""What the readers of a run directory (`report`, `export`, `view`) need: a damaged one is a RunDirError
(the CLI: exit 2, one line `error: <file>: <what>`). At least one mode's recording must be there."""
OPTIONAL_FILES: dict[str, str] = {
    STATE_FILE: "without it the recording's state is unknown: reported incomplete",
    EVENTS_FILE: "a line that is not a JSON object is skipped (the last one, cut short by a kill, too)",
    METRICS_FILE: "an earlier report's GP facts and wall time; rebuilt without them",
    DATASETS_FILE: "the GP training data of the plots; plotted without it",
    EXPERTS_FILE: "the GP experts of the gain condition; rebuilt as not evaluated",
}
"""What the readers of a run directory can do without: a damaged one is skipped, and the reader says so
in one line `<file>: <what>` (the CLI prints `skipped: <file>: <what>`)."""
MAX_JSON_BYTES = 64_000_000
"""Bound on a JSON file of a run directory (B); recording.json and metrics.json are a few kB."""
NPZ_KINDS = frozenset("biufcUS")
"""numpy dtype kinds an npz of a run directory may hold (no Python objects: nothing is unpickled)."""


@dataclass(frozen=True)
class DeviceFiles:
    """Where a backend of real devices records their raw traffic: `<out>/devices/`, one file per device
    for each connection, named by `session`: the mode flown on it (a flight connects its devices anew for
    every mode), or for an agent process, which connects once, its modes joined by "+"."""

    out: Path
    session: str

    def tello(self, drone_id: int) -> Path:
        """Drone `drone_id`'s traffic (format: flightstack.drivers.tello.traffic)."""
        return Path(self.out) / DEVICES_DIR / f"tello-{drone_id}_{self.session}.jsonl"

    def scamper(self) -> Path:
        """The ground robot's MAVLink link, both directions (pymavlink .tlog: drivers/scamper/tlog.py)."""
        return Path(self.out) / DEVICES_DIR / f"scamper_{self.session}.tlog"


class RunDirError(ValueError):
    """A file of a run directory is missing or damaged: `path` names it, `what` says what is wrong (one
    line). Raised by the readers at the point where they decode what they read."""

    def __init__(self, path: Path | str, what: str) -> None:
        self.path = Path(path)
        self.what = " ".join(str(what).split())
        super().__init__(f"{self.path}: {self.what}")


def read_json_object(path: Path) -> dict[str, Any]:
    """The JSON object in the file `path` (strict UTF-8 JSON, at most MAX_JSON_BYTES). RunDirError when
    it cannot be read, is not JSON or is JSON of another shape than an object."""
    path = Path(path)
    try:
        size = path.stat().st_size
        data = path.read_bytes() if size <= MAX_JSON_BYTES else b""
    except OSError as exc:
        raise RunDirError(path, errno_text(exc)) from None
    if size > MAX_JSON_BYTES:
        raise RunDirError(path, f"larger than {MAX_JSON_BYTES / 1e6:.0f} MB")
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError
        raise RunDirError(path, f"not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise RunDirError(path, f"JSON {type(doc).__name__}, not an object")
    return doc


def read_npz(path: Path, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """Every array of the npz file `path` by name (without `.npy`). Each member's header is checked
    against the member's size before anything is allocated, and no Python object is unpickled;
    max_bytes: bound on the members' sizes together (uncompressed, from the zip's directory, checked
    before any is read). RunDirError when the file cannot be read, is not a zip of .npy arrays, a member
    is damaged or the members exceed max_bytes."""
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            total = sum(info.file_size for info in infos)
            if max_bytes is not None and total > max_bytes:
                raise RunDirError(path, f"its arrays hold {total:,} B, more than {max_bytes:,} B")
            for info in infos:
                name = info.filename.removesuffix(".npy")
                if name == info.filename:
                    raise RunDirError(path, f"member {info.filename!r} is not a .npy array")
                out[name] = _read_npy(path, zf, info)
    except OSError as exc:
        raise RunDirError(path, f"not a readable npz ({errno_text(exc)})") from None
    except EOFError:
        raise RunDirError(path, "not a readable npz (cut short)") from None
    except zipfile.BadZipFile as exc:
        raise RunDirError(path, f"not a readable npz (not a zip archive: {exc})") from None
    except (zlib.error, lzma.LZMAError) as exc:
        raise RunDirError(path, f"not a readable npz (a damaged member: {exc})") from None
    except (NotImplementedError, RuntimeError) as exc:  # a compression zipfile lacks; an encrypted member
        raise RunDirError(path, f"not a readable npz ({exc})") from None
    return out


def _read_npy(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> np.ndarray:
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
            else:
                raise ValueError(f"npy format version {version}")
        except ValueError as exc:
            raise RunDirError(path, f"{info.filename}: not a .npy array ({exc})") from None
        if dtype.hasobject or dtype.kind not in NPZ_KINDS or any(d < 0 for d in shape):
            raise RunDirError(path, f"{info.filename}: dtype {dtype} shape {shape} not allowed")
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes != info.file_size - fh.tell():
            raise RunDirError(
                path, f"{info.filename}: its header says {nbytes} B, it holds {info.file_size - fh.tell()} B"
            )
        data = fh.read(nbytes)
    a = np.frombuffer(data, dtype=dtype).copy()
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)


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
