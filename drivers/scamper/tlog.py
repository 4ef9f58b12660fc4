"""A raw MAVLink telemetry log (.tlog) of the robot link, both directions, as pymavlink writes one.

The format (pymavlink ``mavutil.mavfile.setup_logfile``, read by ``mavlogdump.py``, MAVExplorer, MAVProxy):
each record is an 8-byte big-endian UNIX time in µs, its two low bits cleared (pymavlink keeps a link
number there), followed by the MAVLink message's bytes exactly as they went over the link. Received
messages are stamped when pymavlink decoded them, sent ones when they were written to the socket.

`record` only appends to a bounded in-memory queue (a lock, no I/O), so neither the link's threads nor
the control loop ever wait on the disk; a writer thread writes and flushes the queue every
``FLUSH_PERIOD_S``. A full queue (a disk that does not keep up) drops records, counted in ``dropped``; a
write error stops the log (counted, logged once), never the link. docs/logs.md describes the file.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
import time
from collections import deque
from pathlib import Path

LOG = logging.getLogger("flightstack.scamper")

FLUSH_PERIOD_S = 0.25
MAX_PENDING = 100_000  # records (~100 s of the link at its busiest)


class TlogWriter:
    """Appends MAVLink messages to a .tlog file from any thread (module docstring)."""

    def __init__(self, path: str | Path) -> None:
        """Open `path` for appending (a reconnect of the same driver adds to it; records are
        self-delimiting), creating it and its directory; OSError when it cannot be opened."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "ab")  # noqa: SIM115 (closed by close(), written by the thread)
        self._lock = threading.Lock()
        self._pending: deque[bytes] = deque()
        self._stop = threading.Event()
        self.records = 0  # written
        self.dropped = 0  # queue full
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="scamper-tlog", daemon=True)
        self._thread.start()

    def record(self, msgbuf: bytes, t_unix: float | None = None) -> None:
        """Queue one message's bytes, stamped `t_unix` (s, default now); never blocks on I/O."""
        usec = int((time.time() if t_unix is None else t_unix) * 1e6) & ~3
        with self._lock:
            if self.error is not None or self._stop.is_set():
                return
            if len(self._pending) >= MAX_PENDING:
                self.dropped += 1
                return
            self._pending.append(struct.pack(">Q", usec) + bytes(msgbuf))

    def _drain(self) -> None:
        with self._lock:
            batch, self._pending = self._pending, deque()
        if not batch or self.error is not None:
            return
        try:
            self._f.write(b"".join(batch))
            self._f.flush()
            self.records += len(batch)
        except (OSError, ValueError) as exc:
            with self._lock:
                self.error = f"{type(exc).__name__}: {exc}"
            LOG.warning("scamper tlog %s: stopped: %s", self.path, self.error)

    def _run(self) -> None:
        while not self._stop.wait(FLUSH_PERIOD_S):
            self._drain()
        self._drain()

    def close(self) -> None:
        """Write what is queued, stop the thread (≤ 2 s) and close the file; idempotent."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        with contextlib.suppress(OSError):
            self._f.close()
