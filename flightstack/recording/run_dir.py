"""Writes a run directory as the run goes, so that a kill, a crash or a full disk loses at most ~1 s.

One `RunWriter` per run directory, one `ModeWriter` per flown mode:

    run = RunWriter(out)                         # before takeoff: opens events.jsonl, recording.json
    w = run.mode("dgp", ids, n_ticks)            # handed to runner.run_mode(..., writer=w)
    w.append(rec, k + 1)                         # every tick; cheap, writes a block about every 0.5 s
    w.event({...})                               # an event that must reach the disk now
    w.close(rec)                                 # after landing: final timeseries_dgp.npz
    run.write_metrics(metrics); run.close()      # metrics.json (with "recording": complete, reason)

A background thread writes every file, so a slow or hung disk never blocks the control loop (which only
copies the new rows, about every BLOCK_PERIOD_S):

- `timeseries_<mode>.rows` (while the mode flies; removed once the npz is on disk): append-only, readable
  after a kill (`read_rows`): the 8 bytes MAGIC, a little-endian uint32 length L, L bytes of UTF-8 JSON
  {"format", "version", "columns": [{"name", "dtype", "shape"}...], "meta"} space-padded to a multiple of
  64 bytes, then rows of the structured dtype the columns describe (C order, no padding). Column `_seq`
  (row number + 1) lets a torn or zero-filled tail be dropped. e_c and e_e are not written (`load_run`
  recomputes them). About 1 kB per tick for 3 drones.
- `timeseries_<mode>.npz` at the end of the mode; `recording.json` (state, completeness, reason, per-mode
  progress) when a mode starts or ends; `metrics.json` through `write_metrics`: each tmp + fsync +
  os.replace, so a full disk never leaves a half-written file.
- `timeseries_<mode>.csv` after the npz: the main time series for pandas or a spreadsheet
  (flightstack/recording/csv_table.py); a failure to write it is logged, the recording stays complete.
- `events.jsonl`: one JSON object per line, one write(2) each (it survives a kill once written), fsync'ed
  at most every FSYNC_PERIOD_S and at close. Non-finite floats are written as null.

A SIGKILL loses the rows not yet handed over (≤ BLOCK_PERIOD_S of wall time, or BLOCK_MAX_ROWS ticks) plus
the write in flight: ≤ 1 s. On any write error (ENOSPC, EIO, ...) the recording stops without raising into
the control loop (the flight goes on), with a `recording_stopped` event and "recording": {"complete":
false, "reason": ...} in metrics.json; tests inject the error at `_write_bytes`. A run directory needs
MIN_FREE_BYTES free before anything takes off (`check_out_dir`).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import math
import os
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from flightstack.durability import FSYNC_PERIOD_S
from flightstack.events import Event
from flightstack.recording.csv_table import csv_name, write_csv
from flightstack.recording.files import (
    BLOCK_MAX_ROWS,
    BLOCK_PERIOD_S,
    CLOSE_TIMEOUT_S,
    EVENTS_FILE,
    IMAGES_SUFFIX,
    MAX_PENDING_BYTES,
    METRICS_FILE,
    MIN_FREE_BYTES,
    ROWS_SUFFIX,
    STATE_FILE,
    atomic_write_bytes,
    atomic_write_json,
    check_out_dir,
    errno_text,
    event_line,
    fsync_dir,
)
from flightstack.recording.mcap_live import LiveMcap
from flightstack.recording.rows import MAGIC, STREAM_FIELDS, RowLayout, read_rows
from flightstack.recording.run_reader import load_run, read_events, read_state, recording_status
from flightstack.recording.timeseries import Recording

__all__ = [  # the public face: RunWriter here, the rest re-exported from the modules that hold it
    "BLOCK_MAX_ROWS",
    "BLOCK_PERIOD_S",
    "CLOSE_TIMEOUT_S",
    "FSYNC_PERIOD_S",
    "MAGIC",
    "MAX_PENDING_BYTES",
    "MIN_FREE_BYTES",
    "ROWS_SUFFIX",
    "STREAM_FIELDS",
    "ModeWriter",
    "RowLayout",
    "RunWriter",
    "atomic_write_bytes",
    "atomic_write_json",
    "check_out_dir",
    "event_line",
    "load_run",
    "read_events",
    "read_rows",
    "read_state",
    "recording_status",
]

_log = logging.getLogger(__name__)


def _write_bytes(fd: int, data: bytes) -> None:
    """Write all of `data` to the file descriptor (loops over partial writes). Every write of the row
    stream and of events.jsonl goes through here (tests inject OSError(ENOSPC) at this point)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


class RunWriter:
    """The run directory `out_dir`, written as the run goes by one background thread (see the module).

    Created before takeoff (raises OSError if the directory cannot be written: nothing flew yet); from
    then on no method raises for a write error of the recording: it stops the recording instead
    (`status()`). Thread-safe. Starting a run truncates events.jsonl, rewrites recording.json and
    removes metrics.json, the row streams and the camera frames of an earlier run in this directory; a
    mode's npz is removed when that mode starts (and written again when it ends). live_mcap: a follower
    process writes recording.mcap as the run goes (mcap_live.py); `close` waits for it to finish the
    file (`live_mcap_error` says when it did not)."""

    def __init__(
        self,
        out_dir: Path | str,
        *,
        block_period_s: float = BLOCK_PERIOD_S,
        block_max_rows: int = BLOCK_MAX_ROWS,
        live_mcap: bool = False,
    ) -> None:
        self.out = Path(out_dir)
        self.block_period_s = block_period_s
        self.block_max_rows = block_max_rows
        self.out.mkdir(parents=True, exist_ok=True)
        stale_files = [
            *self.out.glob(f"timeseries_*{ROWS_SUFFIX}"),
            *self.out.glob(f"images_*{IMAGES_SUFFIX}"),
        ]
        for stale in [*stale_files, self.out / METRICS_FILE]:
            stale.unlink(missing_ok=True)
        self._lock = threading.RLock()
        self._failure: str | None = None
        self._failure_reported = False
        self._modes: dict[str, ModeWriter] = {}
        self._state: dict[str, Any] = {"state": "running", "complete": False, "reason": "in progress"}
        self._state_modes: dict[str, dict[str, Any]] = {}
        self._unsynced: set[int] = set()  # fds written to since the last fsync (writer thread only)
        self._last_fsync = time.monotonic()
        self._events_fd = os.open(
            self.out / EVENTS_FILE, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644
        )
        self._write_state()
        self._queue: queue.Queue[tuple[int, bool, Callable[[], None]] | None] = queue.Queue()
        self._pending_bytes = 0  # handed to the thread, not yet written (approximate: for back-pressure)
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="flightstack-recorder", daemon=True)
        self._thread.start()
        self.live_mcap: LiveMcap | None = None
        if live_mcap:  # after the stale files are gone: the follower reads only this run's
            try:
                self.live_mcap = LiveMcap(self.out)
            except OSError as exc:
                _log.error("the live MCAP was not started: %s (the flight goes on)", exc)

    # ---- the API ---------------------------------------------------------------------------------
    def mode(self, mode: str, ids: list[int], n_ticks: int) -> ModeWriter:
        """A writer for one mode's recording (drone ids in recording order, n_ticks planned); an earlier
        timeseries_<mode>.npz of this directory is removed now. Never raises."""
        with self._lock:
            old = self._modes.get(mode)
        if old is not None and not old.closed:
            old.close()
        w = ModeWriter(self, mode, list(ids), int(n_ticks))
        with self._lock:
            self._modes[mode] = w
            self._state_modes[mode] = {
                "state": "recording",
                "drone_ids": [int(i) for i in ids],
                "n_ticks": int(n_ticks),
                "rows_written": 0,
            }
        self._submit(0, w._start)
        return w

    def record(self, rec: Recording) -> None:
        """Write a whole recording at once (final npz and its events) unless this writer already wrote
        its mode (a ModeWriter handed to run_mode and closed with it). Never raises."""
        with self._lock:
            done = rec.mode in self._modes and self._modes[rec.mode].closed
        if not done:
            self.mode(rec.mode, rec.drone_ids, rec.ticks_done).close(rec, stream=False)

    def write_file(self, name: str, data: bytes | str) -> None:
        """Write a file of the run directory atomically now (raises OSError; the recording is not
        stopped by it: the caller decides)."""
        atomic_write_bytes(self.out / name, data.encode() if isinstance(data, str) else data)

    def write_metrics(
        self, metrics: Mapping[str, Any], name: str = METRICS_FILE, strict: bool = True
    ) -> dict[str, Any]:
        """metrics + {"recording": status()} written atomically as strict JSON after everything handed
        to the writer thread is written (bounded by CLOSE_TIMEOUT_S); returns what was written. Raises
        OSError if it cannot be written; strict: ValueError if a metric is not finite (nothing written),
        else a non-finite metric is written as null (a run that ended in an error, e.g. diverged)."""
        self.drain()
        out = {**metrics, "recording": self.status()}
        atomic_write_json(self.out / name, out, strict=strict)
        return out

    def status(self) -> dict[str, Any]:
        """{"complete": bool, "reason": str | None}: complete when nothing failed and every mode started
        was closed with its final npz on disk (the recording has every tick that was flown)."""
        with self._lock:
            if self._failure is not None:
                return {"complete": False, "reason": self._failure}
            open_modes = [m for m, w in self._modes.items() if not w.closed]
            if open_modes:
                return {"complete": False, "reason": f"in progress (modes {open_modes} not closed)"}
            partial = [m for m, s in self._state_modes.items() if not s.get("final")]
            if partial:
                return {"complete": False, "reason": f"no final recording of modes {partial}"}
            return {"complete": True, "reason": None}

    @property
    def failure(self) -> str | None:
        """Why the recording stopped (None while it works)."""
        return self._failure

    def fail(self, reason: str) -> None:
        """Stop the recording (first reason kept); logged once. Never raises."""
        with self._lock:
            if self._failure is not None:
                return
            self._failure = reason
        _log.error("recording stopped: %s (the flight goes on)", reason)
        self._submit(0, self._write_state_quietly, always=True)

    def drain(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Wait until the writer thread has done everything handed to it; False on timeout (s)."""
        if threading.current_thread() is self._thread or self._closed:
            return True
        if not self._thread.is_alive():
            return False
        done = threading.Event()
        self._queue.put((0, True, done.set))  # one thread, FIFO: every earlier job is done when it runs
        return done.wait(timeout_s)

    def close(self) -> None:
        """Close every mode still open (without a final npz: its row stream stays), write everything,
        fsync, rewrite recording.json as closed and stop the thread. Idempotent; never raises."""
        with self._lock:
            if self._closed:
                return
            modes = list(self._modes.values())
        for w in modes:
            if not w.closed:
                w.close()
        self._submit(0, self._close_files, always=True)
        if not self.drain():
            self.fail(f"the writer thread did not finish within {CLOSE_TIMEOUT_S:g} s (disk hung?)")
        with self._lock:
            self._closed = True
        self._queue.put(None)
        self._thread.join(timeout=1.0)
        if self.live_mcap is not None:  # every file is final: the follower reads the rest and closes
            self.live_mcap.finish()

    @property
    def live_mcap_error(self) -> str | None:
        """Why the live MCAP is not a finished file (None: finished, or none asked for); known once
        `close` returned. The caller reports it (the run's exit code)."""
        report = None if self.live_mcap is None else self.live_mcap.report
        return None if report is None else report.get("error")

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- inside ----------------------------------------------------------------------------------
    def _submit(self, nbytes: int, job: Callable[[], None], always: bool = False) -> None:
        """Hand a job to the writer thread (never blocks). always: run it even after a failure (then its
        own errors are ignored)."""
        with self._lock:
            if self._closed or (self._failure is not None and not always):
                return
            over = self._pending_bytes + nbytes > MAX_PENDING_BYTES
            if not over:
                self._pending_bytes += nbytes
        if over:
            self.fail(f"the disk does not keep up: {MAX_PENDING_BYTES / 1e6:.0f} MB waiting to be written")
            return
        self._queue.put((nbytes, always, job))

    def _work(self) -> None:
        last_poll = time.monotonic()
        while True:
            try:
                item = self._queue.get(timeout=min(FSYNC_PERIOD_S, self.block_period_s))
            except queue.Empty:
                item = (0, False, self._maybe_fsync)
            if item is None:
                return
            if time.monotonic() - last_poll >= self.block_period_s:  # event sources, also during
                last_poll = time.monotonic()  # takeoff and landing (no append then)
                with self._lock:
                    open_modes = [w for w in self._modes.values() if not w.closed]
                for w in open_modes:
                    w._poll_sources()
            nbytes, always, job = item
            try:
                if always or self._failure is None:
                    job()
                    self._maybe_fsync()
            except OSError as exc:
                if not always:
                    self.fail(f"{errno_text(exc)} writing {getattr(exc, 'filename', None) or self.out}")
            except Exception as exc:  # a bug must not kill the thread (drain would wait for ever)
                _log.exception("recorder job failed")
                if not always:
                    self.fail(f"recorder error: {type(exc).__name__}: {exc}")
            finally:
                with self._lock:
                    self._pending_bytes -= nbytes

    def _maybe_fsync(self, force: bool = False) -> None:
        """fsync every file written since the last fsync, if FSYNC_PERIOD_S has passed (or force)."""
        now = time.monotonic()
        if not force and now - self._last_fsync < FSYNC_PERIOD_S:
            return
        self._last_fsync = now
        while self._unsynced:
            os.fsync(self._unsynced.pop())

    def _write_stream(self, fd: int, data: bytes, what: str) -> None:
        try:
            _write_bytes(fd, data)
        except OSError as exc:
            exc.filename = exc.filename or what
            raise
        self._unsynced.add(fd)

    def _write_event_line(self, line: bytes) -> None:
        self._write_stream(self._events_fd, line, EVENTS_FILE)

    def _write_state(self) -> None:
        with self._lock:
            doc = {
                **self._state,
                **({"complete": False, "reason": self._failure} if self._failure else {}),
                "modes": {m: dict(s) for m, s in self._state_modes.items()},
            }
        atomic_write_json(self.out / STATE_FILE, doc, strict=False)

    def _write_state_quietly(self) -> None:
        try:
            self._write_state()
        except OSError as exc:
            _log.error("recording.json not updated: %s", errno_text(exc))

    def _close_files(self) -> None:
        with contextlib.suppress(OSError):
            self._maybe_fsync(force=True)
        self._unsynced.clear()
        with contextlib.suppress(OSError):
            os.close(self._events_fd)
        with self._lock:
            self._state.update(state="closed", **{k: v for k, v in self.status().items()})
        self._write_state_quietly()

    def _mode_state(self, mode: str, **changes: Any) -> None:
        with self._lock:
            self._state_modes.setdefault(mode, {}).update(changes)


class ModeWriter:
    """Writes one mode's Recording as it is filled (see the module): `append` every tick, `event` for an
    event that must reach the disk now, `close` at the end. No method raises into the control loop."""

    def __init__(self, run: RunWriter, mode: str, ids: list[int], n_ticks: int) -> None:
        self.run = run
        self.mode = mode
        self.ids = ids
        self.n_ticks = n_ticks
        self.closed = False
        self.rows_written = 0  # rows on disk (updated by the writer thread)
        self._layout: RowLayout | None = None
        self._fd: int | None = None
        self._sent = 0  # rows handed to the writer thread
        self._last_send = time.monotonic()
        self._event_cursor = 0  # rec.events[:cursor] were handled
        self._direct: Counter[bytes] = Counter()  # lines written by event() not yet seen in rec.events
        self._sources: list[tuple[Callable[[], Iterable[Mapping[str, Any]]], list[int]]] = []
        self._lock = threading.Lock()
        self._source_lock = threading.Lock()
        self.rows_path = run.out / f"timeseries_{mode}{ROWS_SUFFIX}"
        self.npz_path = run.out / f"timeseries_{mode}.npz"

    # ---- the API ---------------------------------------------------------------------------------
    def append(self, rec: Recording, upto_tick: int) -> None:
        """Rows [0, upto_tick) of `rec` are final: hand the new ones to the writer when BLOCK_PERIOD_S of
        wall time or BLOCK_MAX_ROWS ticks have gathered, and flush the events added to rec.events since
        the last call (each at once). Call it every tick; it costs ~1 µs when it writes nothing."""
        try:
            if len(rec.events) > self._event_cursor:
                self._sync_events(rec)
            if self.run._failure is not None:
                self._report_failure(rec)
                return
            few = upto_tick - self._sent < self.run.block_max_rows
            if few and time.monotonic() - self._last_send < self.run.block_period_s:
                return
            self._send_rows(rec, upto_tick)
        except Exception as exc:  # never into the control loop
            self.run.fail(f"recorder error: {type(exc).__name__}: {exc}")

    def event(self, ev: Mapping[str, Any]) -> None:
        """Write one event now (events.jsonl). If the same event is (or later is) in the recording's
        events, it is written once. Thread-safe; never raises."""
        try:
            line = event_line(ev)
            with self._lock:
                self._direct[line] += 1
            self.run._submit(len(line), lambda: self.run._write_event_line(line))
        except Exception as exc:
            self.run.fail(f"recorder error: {type(exc).__name__}: {exc}")

    def add_event_source(self, source: Callable[[], Iterable[Mapping[str, Any]]]) -> None:
        """A thread-safe function returning every event of some log so far (oldest first, append-only,
        e.g. the safety EventLog as dicts): the writer thread polls it every BLOCK_PERIOD_S (also during
        takeoff and landing) and at close, and writes each new event once, even if it is added to
        rec.events later."""
        self._sources.append((source, [0]))

    def flush(self, rec: Recording | None = None, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Hand everything of `rec` gathered so far (rows up to rec.ticks_done, events) to the writer
        and wait until it is written; False on timeout (s). For tests and checkpoints."""
        self._poll_sources()
        if rec is not None:
            self.append(rec, rec.ticks_done)
            if self.run._failure is None:
                self._send_rows(rec, rec.ticks_done)
        return self.run.drain(timeout_s)

    def close(self, rec: Recording | None = None, *, stream: bool = True) -> None:
        """End the mode. With `rec` (after landing): its remaining rows and events, then the final
        timeseries_<mode>.npz (atomic) and its meta in recording.json, then the row stream is removed.
        Without: the row stream stays as the mode's data (`load_run` reads it). Waits for the writer
        thread (≤ CLOSE_TIMEOUT_S). stream=False: write no row stream (a whole recording at once).
        Idempotent; never raises."""
        if self.closed:
            return
        try:
            self._poll_sources()  # first: an event of a source that is also in rec.events is written once
            if rec is not None:
                self._sync_events(rec)
                if stream and self.run._failure is None:
                    self._send_rows(rec, rec.ticks_done)
                self.run.drain()  # a write error of the above is reported in the recording too
                self._report_failure(rec)
            final = rec.truncated() if rec is not None else None
            self.run._submit(0, lambda: self._finish(final), always=True)
        except Exception as exc:
            self.run.fail(f"recorder error: {type(exc).__name__}: {exc}")
        finally:
            self.closed = True
        self.run.drain()

    # ---- inside ----------------------------------------------------------------------------------
    def _send_rows(self, rec: Recording, upto: int) -> None:
        start = self._sent
        self._last_send = time.monotonic()
        if upto <= start:
            return
        if self._layout is None:
            self._layout = RowLayout.of_recording(rec)
            self._layout.meta["n_ticks"] = self.n_ticks
            self.run._submit(0, self._open_stream)
        data = self._layout.pack({f: getattr(rec, f)[start:upto] for f in self._layout.columns}, start)
        self._sent = upto
        self.run._submit(len(data), lambda: self._write_rows(data, upto))

    def _start(self) -> None:
        """In the writer thread: a stale final file or row stream of an earlier run in this directory
        must not pass for this run's; recording.json names the mode."""
        self.npz_path.unlink(missing_ok=True)
        self.rows_path.unlink(missing_ok=True)
        (self.run.out / csv_name(self.mode)).unlink(missing_ok=True)
        self.run._write_state()

    def _open_stream(self) -> None:
        assert self._layout is not None
        self._fd = os.open(self.rows_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        self.run._write_stream(self._fd, self._layout.header(), self.rows_path.name)

    def _write_rows(self, data: bytes, upto: int) -> None:
        if self._fd is None:
            raise OSError(errno.EBADF, "row stream not open", self.rows_path.name)
        self.run._write_stream(self._fd, data, self.rows_path.name)
        self.rows_written = upto
        self.run._mode_state(self.mode, rows_written=upto)

    def _sync_events(self, rec: Recording) -> None:
        new = rec.events[self._event_cursor :]
        self._event_cursor += len(new)
        for ev in new:
            line = event_line(ev)
            with self._lock:
                if self._direct[line] > 0:
                    self._direct[line] -= 1
                    continue
            self.run._submit(len(line), functools.partial(self.run._write_event_line, line))

    def _poll_sources(self) -> None:
        with self._source_lock:
            self._poll_sources_locked()

    def _poll_sources_locked(self) -> None:
        for source, cursor in self._sources:
            try:
                evs = list(source())
            except Exception as exc:
                _log.error("event source failed: %s", exc)
                continue
            for ev in evs[cursor[0] :]:
                self.event(ev)
            cursor[0] = max(cursor[0], len(evs))

    def _report_failure(self, rec: Recording | None) -> None:
        """Once per run: a `recording_stopped` event in the recording (and, if the disk still takes it,
        in events.jsonl)."""
        run = self.run
        with run._lock:
            if run._failure_reported or run._failure is None:
                return
            run._failure_reported = True
        t = float(rec.t[rec.ticks_done - 1]) if rec is not None and rec.ticks_done else math.nan
        facts = {"reason": run._failure, "ticks_written": int(self.rows_written), "wall_t": time.time()}
        ev = Event(t, None, "recording_stopped", facts=facts).record(self.mode)
        if rec is not None:
            rec.events.append(ev)
            self._event_cursor = len(rec.events)
        line = event_line(ev)

        def best_effort() -> None:
            with contextlib.suppress(OSError):
                run._write_event_line(line)

        run._submit(len(line), best_effort, always=True)

    def _finish(self, final: Recording | None) -> None:
        """In the writer thread: the final npz (also after a failure of the stream: the data in memory
        is complete, so it is tried), then recording.json."""
        run = self.run
        state: dict[str, Any] = {"state": "closed", "rows_written": self.rows_written}
        if final is not None:
            state.update(final.meta())
            try:
                tmp = self.npz_path.with_name(f".{self.npz_path.name}.tmp{os.getpid()}")
                try:
                    with open(tmp, "wb") as fh:
                        final.save(fh)
                        fh.flush()
                        os.fsync(fh.fileno())
                    os.replace(tmp, self.npz_path)
                finally:
                    tmp.unlink(missing_ok=True)
                fsync_dir(run.out)
                state["final"] = self.npz_path.name
            except OSError as exc:
                run.fail(f"{errno_text(exc)} writing {self.npz_path.name}")
        if self._fd is not None:
            if self._fd in run._unsynced:
                run._unsynced.discard(self._fd)
                if not state.get("final"):  # the row stream stays the mode's data
                    with contextlib.suppress(OSError):
                        os.fsync(self._fd)
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None
            if state.get("final"):
                self.rows_path.unlink(missing_ok=True)
        run._mode_state(self.mode, **state)
        run._write_state_quietly()
        if final is not None and state.get("final"):
            self._write_csv(final)

    def _write_csv(self, final: Recording) -> None:
        """In the writer thread, after the final npz: timeseries_<mode>.csv (csv_table.py). A failure is
        logged, not a failure of the recording (the npz holds every value; `export --csv` remakes it)."""
        path = self.run.out / csv_name(self.mode)
        try:
            write_csv(path, [final])
        except Exception as exc:
            _log.error("%s not written: %s", path.name, errno_text(exc) if isinstance(exc, OSError) else exc)
