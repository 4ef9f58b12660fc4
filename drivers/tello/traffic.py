"""A Tello's raw device traffic: what was sent to it and what it sent, with the times they were seen.

One format for two uses: every flight writes it (a `TrafficWriter` per drone, in the run directory), and
the replayer (sim_backend/emulators/tello/replay.py) serves it back to a driver, as it serves the real
recordings in `../shared/data/peers/tello/` (`read_xg590_db`: the SQLite flight log of xg590/Tello-Python).

File: JSON Lines, UTF-8. The first line is the header
    {"format": "flightstack-tello-traffic", "version": 1, "drone": "<ip>", "clock": "monotonic"}
and every further line one record
    {"t": <s>, "kind": "sent" | "reply" | "state", "text": "<the datagram as text>"}
    {"t": <s>, "kind": "video", "bytes": <datagram length>}
`t` is time.monotonic() of the recording computer (s) when the datagram was sent ("sent") or received
(the others); "state" text is the state line as received (with its trailing "\\r\\n"); video datagrams are
recorded by length and time only (the pictures are in the recording's frames, not here).

Reading trusts nothing: a line that is not a JSON object of the shape above, a non-finite or decreasing
`t` beyond `MAX_BACKSTEP_S`, a text longer than `MAX_TEXT_CHARS` is skipped and counted by reason
(`TelloSession.dropped`); a file without the header or larger than `MAX_FILE_BYTES` raises
TrafficFormatError naming the file.
"""

from __future__ import annotations

import contextlib
import json
import math
import sqlite3
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

FORMAT = "flightstack-tello-traffic"
VERSION = 1
MAX_TEXT_CHARS = 512  # a state line is ~150-250 characters, a reply or command less
MAX_FILE_BYTES = 512 * 1024 * 1024
MAX_BACKSTEP_S = 0.05  # records of different threads reach the writer slightly out of order

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
        last_t = -math.inf
        for raw in f:
            rec, why = _record(raw)
            if rec is None:
                session.dropped[why] += 1
                continue
            if rec.t < last_t - MAX_BACKSTEP_S:
                session.dropped["time_backwards"] += 1
                continue
            last_t = max(last_t, rec.t)
            session.records.append(rec)
    session.records.sort(key=lambda r: r.t)  # stable: equal times keep the file's order
    return session


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
    """Appends one drone's traffic to a JSON Lines file (thread-safe; callable from the link's threads).

    Writing never raises into a caller: an OSError (disk full, file gone) is counted in `errors` and the
    writer stops writing (`failed`); `max_bytes` (default 64 MiB, ~4 h of a Tello's state and commands) ends
    the file likewise, counted as `truncated`. Lines are flushed every `flush_every` records and on
    close, so a killed flight leaves every line up to the last flush."""

    def __init__(
        self, path: str | Path, drone: str, max_bytes: int = 64 * 1024 * 1024, flush_every: int = 20
    ):
        self.path = Path(path)
        self.max_bytes, self.flush_every = max_bytes, max(1, flush_every)
        self.errors: Counter[str] = Counter()
        self.written = 0
        self.failed = False
        self._lock = threading.Lock()
        self._bytes = 0
        self._f: IO[str] | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = self.path.open("w", encoding="utf-8")
            self._write({"format": FORMAT, "version": VERSION, "drone": drone, "clock": "monotonic"})
            self._f.flush()
        except OSError as exc:
            self._fail(exc)

    def sent(self, t: float, text: str) -> None:
        self._add({"t": t, "kind": "sent", "text": text[:MAX_TEXT_CHARS]})

    def reply(self, t: float, text: str) -> None:
        self._add({"t": t, "kind": "reply", "text": text[:MAX_TEXT_CHARS]})

    def state(self, t: float, data: bytes) -> None:
        self._add({"t": t, "kind": "state", "text": data[:MAX_TEXT_CHARS].decode("ascii", "replace")})

    def video(self, t: float, nbytes: int) -> None:
        self._add({"t": t, "kind": "video", "bytes": int(nbytes)})

    def close(self) -> None:
        with self._lock:
            if self._f is not None:
                try:
                    self._f.close()
                except OSError as exc:
                    self.errors[type(exc).__name__] += 1
                self._f = None

    def _add(self, obj: dict[str, object]) -> None:
        with self._lock:
            if self._f is None:
                return
            if self._bytes >= self.max_bytes:
                self.errors["truncated"] += 1
                return
            try:
                self._write(obj)
                self.written += 1
                if self.written % self.flush_every == 0:
                    self._f.flush()
            except OSError as exc:
                self._fail(exc)

    def _write(self, obj: dict[str, object]) -> None:
        assert self._f is not None
        line = json.dumps(obj, separators=(",", ":")) + "\n"
        self._f.write(line)
        self._bytes += len(line)

    def _fail(self, exc: OSError) -> None:
        self.errors[type(exc).__name__] += 1
        self.failed = True
        if self._f is not None:
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None
