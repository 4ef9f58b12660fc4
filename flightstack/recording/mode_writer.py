"""ModeWriter: one flown mode's Recording written as it is filled (see flightstack.recording.run_dir)."""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import math
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any

from flightstack.events import Event
from flightstack.recording.files import CLOSE_TIMEOUT_S, ROWS_SUFFIX, errno_text, event_line, fsync_dir
from flightstack.recording.rows import RowLayout
from flightstack.recording.timeseries import Recording

if TYPE_CHECKING:
    from flightstack.recording.run_dir import RunWriter


_log = logging.getLogger(__name__)


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
