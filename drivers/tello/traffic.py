"""A Tello's raw device traffic: what was sent to it and what it sent, with the times they were seen.

One format for two uses: every flight on real Tellos (or the emulated lab) writes it, one `TrafficWriter`
per drone and connection, into its run directory (`devices/`), and the replayer (sim_backend/emulators/
tello/replay.py) serves it back to a driver, as it serves the real recordings in `../shared/data/peers/
tello/` (`read_xg590_db`: the SQLite flight log of xg590/Tello-Python).

The format (JSON Lines: a header line, then one record per datagram, `t` in time.monotonic() s), what each
kind of record holds, what a reader skips and refuses, and the writer's crash guarantees are described in
docs/logs.md, "Device traffic" (the one place; FORMAT, VERSION and the limits below are its constants).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sqlite3
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

from flightstack.durability import FSYNC_PERIOD_S

FORMAT = "flightstack-tello-traffic"
VERSION = 1
MAX_TEXT_CHARS = 512  # a state line is ~150-250 characters, a reply or command less
MAX_FILE_BYTES = 512 * 1024 * 1024
MAX_BACKSTEP_S = 1.0
"""A record may come this much (s) before the one above it: the writer sorts each batch, but a thread that
stamped a datagram and then waited for the GIL may hand it over after the next batch was written."""
AHEAD_WINDOW = 3
"""A record is judged ahead of time against the median of this many records after it: a run of up to two
bad stamps is dropped, never the records after them (three or more in a row read as a jump in time)."""
FLUSH_PERIOD_S = 0.25
"""The writer thread writes and flushes the records handed over at least this often (s)."""
MAX_PENDING = 100_000
"""Records handed over and not yet written beyond which further ones are dropped (counted): ~100 s of a
Tello's video datagrams; a writer thread this far behind has a disk that does not keep up."""

Kind = Literal["sent", "reply", "state", "video"]
KINDS: tuple[Kind, ...] = ("sent", "reply", "state", "video")


class TrafficFormatError(ValueError):
    """A traffic file that cannot be read at all (its name and the reason in the message)."""


@dataclass(frozen=True)
class TrafficRecord:
    """One datagram: `t` (s, the recording's clock), its kind, its text (not video) or length (video)."""

    t: float
    kind: Kind
    text: str = ""
    nbytes: int = 0


@dataclass
class TelloSession:
    """One drone's recorded traffic in time order, from `source` (a path)."""

    source: str
    drone: str
    records: list[TrafficRecord]
    dropped: Counter[str] = field(default_factory=Counter)

    def of(self, *kinds: Kind) -> list[TrafficRecord]:
        """The records of these kinds, in time order."""
        return [r for r in self.records if r.kind in kinds]

    def first(self, kind: Kind, text: str) -> TrafficRecord | None:
        """The first record of `kind` whose text, stripped and lower-cased, is `text`."""
        want = text.strip().lower()
        return next((r for r in self.records if r.kind == kind and r.text.strip().lower() == want), None)


def read_traffic(path: str | Path) -> TelloSession:
    """Read a traffic file written by `TrafficWriter` (see the module docstring for what is refused)."""
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise TrafficFormatError(f"{p}: {exc.strerror or exc}") from None
    if size > MAX_FILE_BYTES:
        raise TrafficFormatError(f"{p}: {size} bytes, more than the {MAX_FILE_BYTES} a traffic file may have")
    with p.open("rb") as f:
        first = f.readline(4096)
        header = _json_object(first)
        if header is None or header.get("format") != FORMAT:
            raise TrafficFormatError(f"{p}: no '{FORMAT}' header on the first line")
        if header.get("version") != VERSION:
            raise TrafficFormatError(f"{p}: version {header.get('version')!r}, this reader reads {VERSION}")
        drone = header.get("drone")
        session = TelloSession(str(p), drone if isinstance(drone, str) else "", [])
        read: list[TrafficRecord] = []
        for raw in f:
            rec, why = _record(raw)
            if rec is None:
                session.dropped[why] += 1
            else:
                read.append(rec)
    session.records = _in_time(read, session.dropped)
    session.records.sort(key=lambda r: r.t)  # stable: equal times keep the file's order
    return session


def _in_time(records: list[TrafficRecord], dropped: Counter[str]) -> list[TrafficRecord]:
    """The records (file order) without those out of time, counted in `dropped`: "time_ahead", one more than
    MAX_BACKSTEP_S after the median of the (up to) AHEAD_WINDOW records that follow it (a bad stamp, not
    the records after it); "time_backwards", one more than MAX_BACKSTEP_S before an earlier record kept."""
    kept: list[TrafficRecord] = []
    last_t = -math.inf
    for i, rec in enumerate(records):
        after = sorted(r.t for r in records[i + 1 : i + 1 + AHEAD_WINDOW])
        if after and rec.t > after[len(after) // 2] + MAX_BACKSTEP_S:
            dropped["time_ahead"] += 1
        elif rec.t < last_t - MAX_BACKSTEP_S:
            dropped["time_backwards"] += 1
        else:
            last_t = max(last_t, rec.t)
            kept.append(rec)
    return kept


def _json_object(raw: bytes) -> dict[str, object] | None:
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def _record(raw: bytes) -> tuple[TrafficRecord | None, str]:
    if len(raw) > 4 * MAX_TEXT_CHARS:
        return None, "line_too_long"
    obj = _json_object(raw)
    if obj is None:
        return None, "not_json_object"
    t, kind = obj.get("t"), obj.get("kind")
    if not isinstance(t, int | float) or isinstance(t, bool) or not math.isfinite(t):
        return None, "bad_time"
    if kind not in KINDS:
        return None, "bad_kind"
    if kind == "video":
        n = obj.get("bytes")
        if not isinstance(n, int) or isinstance(n, bool) or not 0 < n <= 65535:
            return None, "bad_video_length"
        return TrafficRecord(float(t), "video", nbytes=n), ""
    text = obj.get("text")
    if not isinstance(text, str) or len(text) > MAX_TEXT_CHARS:
        return None, "bad_text"
    return TrafficRecord(float(t), kind, text=text), ""


def read_xg590_db(path: str | Path) -> TelloSession:
    """The SQLite flight log of xg590/Tello-Python (`states(timestamp, log)`, `commands(timestamp,
    command, who)` with who "Station" = sent, "Tello" = reply; timestamps: wall-clock s) as a session.
    Opened read-only; TrafficFormatError when it is not such a file."""
    p = Path(path)
    if not p.is_file():
        raise TrafficFormatError(f"{p}: no such file")
    try:
        con = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
        try:
            states = con.execute("SELECT timestamp, log FROM states").fetchall()
            commands = con.execute("SELECT timestamp, command, who FROM commands").fetchall()
        finally:
            con.close()
    except sqlite3.Error as exc:
        raise TrafficFormatError(f"{p}: not an xg590 Tello flight log ({exc})") from None
    session = TelloSession(str(p), "", [])
    for t, text in states:
        if isinstance(t, float | int) and isinstance(text, str) and len(text) <= MAX_TEXT_CHARS:
            session.records.append(TrafficRecord(float(t), "state", text=text))
        else:
            session.dropped["bad_state_row"] += 1
    for t, text, who in commands:
        kinds: dict[object, Kind] = {"Station": "sent", "Tello": "reply"}
        kind = kinds.get(who)
        if kind is not None and isinstance(t, float | int) and isinstance(text, str):
            session.records.append(TrafficRecord(float(t), kind, text=text))
        else:
            session.dropped["bad_command_row"] += 1
    session.records.sort(key=lambda r: r.t)
    return session


class TrafficWriter:
    """Records one drone's traffic into a JSON Lines file, from any thread, without ever blocking it.

    The link's threads hand each datagram over with `sent`, `reply`, `state` or `video` (a deque append,
    ~1 µs: no formatting, no lock, no system call in the caller); the writer's own daemon thread formats
    the records, sorts each batch by time, writes it and flushes it to the OS every `flush_period_s`
    (FLUSH_PERIOD_S), and fsyncs at most every FSYNC_PERIOD_S and at `close()`.

    Crash guarantees: a killed process (SIGKILL, a crash) leaves every record handed over more than
    `flush_period_s` (plus one batch's write) before it; an OS crash or power loss every record handed over
    more than FSYNC_PERIOD_S before it. The last line may be cut short: `read_traffic` skips it (counted).

    Never raises into a caller: an OSError (disk full, file gone) is counted in `errors` and ends the
    recording (`failed`); `max_bytes` (default 64 MiB, ~4 h of a Tello's state and commands, ~1 h with its
    video timing) ends the file (`errors["truncated"]` counts the records left out), as does a writer thread
    that falls `MAX_PENDING` records behind (`errors["overflow"]`). `written` counts the records on file."""

    def __init__(
        self,
        path: str | Path,
        drone: str,
        max_bytes: int = 64 * 1024 * 1024,
        flush_period_s: float = FLUSH_PERIOD_S,
    ):
        self.path = Path(path)
        self.max_bytes, self.flush_period_s = max_bytes, max(0.01, float(flush_period_s))
        self.errors: Counter[str] = Counter()
        self.written = 0
        self.failed = False
        self._pending: deque[tuple[float, Kind, str | bytes | int]] = deque()
        self._bytes = 0
        self._f: IO[str] | None = None
        self._stop = threading.Event()
        self._closed = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = self.path.open("w", encoding="utf-8")
            self._write_line({"format": FORMAT, "version": VERSION, "drone": drone, "clock": "monotonic"})
            self._f.flush()
        except OSError as exc:
            self._fail(exc)
        self._thread = threading.Thread(target=self._loop, name=f"tello-traffic-{drone}", daemon=True)
        if self._f is not None:
            self._thread.start()

    # ---- from the link's threads: hand over, nothing else ------------------------------------------------
    def sent(self, t: float, text: str) -> None:
        """A command datagram sent at `t` (time.monotonic() s)."""
        self._put(t, "sent", text)

    def reply(self, t: float, data: bytes | str) -> None:
        """A datagram received on the command socket at `t` (s), as received."""
        self._put(t, "reply", data)

    def state(self, t: float, data: bytes) -> None:
        """A state datagram received at `t` (s), as received (also one the parser rejects)."""
        self._put(t, "state", data)

    def video(self, t: float, nbytes: int) -> None:
        """A video datagram of `nbytes` received at `t` (s)."""
        self._put(t, "video", nbytes)

    def _put(self, t: float, kind: Kind, payload: str | bytes | int) -> None:
        if self._closed:
            return
        if len(self._pending) >= MAX_PENDING:
            self.errors["overflow"] += 1  # rare path; a count off by one under a race is acceptable
            return
        self._pending.append((t, kind, payload))  # deque.append is atomic: no lock

    # ---- the writer thread -------------------------------------------------------------------------------
    def close(self) -> None:
        """Write what is pending, fsync and close (idempotent; joins the writer thread, ≤ 2 s)."""
        self._closed = True
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        if self._thread.is_alive():  # a stuck disk: leave the file to the thread, count it
            self.errors["close_timeout"] += 1
            return
        self._drain()
        if self._f is not None:
            try:
                self._f.flush()
                os.fsync(self._f.fileno())
                self._f.close()
            except OSError as exc:
                self.errors[type(exc).__name__] += 1
            self._f = None

    def __enter__(self) -> TrafficWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _loop(self) -> None:
        """Every flush_period_s: write and flush the pending records; fsync every FSYNC_PERIOD_S."""
        last_fsync = time.monotonic()
        while not self._stop.wait(self.flush_period_s):
            try:
                self._drain()
                f = self._f
                if f is None:
                    return
                f.flush()
                if time.monotonic() - last_fsync >= FSYNC_PERIOD_S:
                    os.fsync(f.fileno())
                    last_fsync = time.monotonic()
            except OSError as exc:
                self._fail(exc)
                return
            except Exception as exc:  # a bug here must not end the thread silently: count and stop
                self.errors[f"writer_{type(exc).__name__}"] += 1
                self._fail(None)
                return

    def _drain(self) -> None:
        """Write every pending record, each batch in time order (threads hand records over slightly out
        of order). OSError ends the recording."""
        batch = []
        while self._pending:
            batch.append(self._pending.popleft())
        if not batch or self._f is None:
            return
        batch.sort(key=lambda r: r[0])
        try:
            lines = []
            for t, kind, payload in batch:
                if self._bytes >= self.max_bytes:
                    self.errors["truncated"] += 1
                    continue
                lines.append(_line(t, kind, payload))
                self._bytes += len(lines[-1])
            self._f.write("".join(lines))
            self.written += len(lines)
        except OSError as exc:
            self._fail(exc)

    def _write_line(self, obj: dict[str, object]) -> None:
        assert self._f is not None
        line = json.dumps(obj, separators=(",", ":")) + "\n"
        self._f.write(line)
        self._bytes += len(line)

    def _fail(self, exc: OSError | None) -> None:
        if exc is not None:
            self.errors[type(exc).__name__] += 1
        self.failed = True
        self._closed = True
        self._pending.clear()
        if self._f is not None:
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None


def _line(t: float, kind: Kind, payload: str | bytes | int) -> str:
    """One record's line (the module docstring's shape)."""
    if kind == "video":
        return f'{{"t":{float(t)!r},"kind":"video","bytes":{int(payload)}}}\n'
    if isinstance(payload, bytes | bytearray):
        payload = bytes(payload[:MAX_TEXT_CHARS]).decode("ascii", "replace")
    text = json.dumps(str(payload)[:MAX_TEXT_CHARS])
    return f'{{"t":{float(t)!r},"kind":"{kind}","text":{text}}}\n'
