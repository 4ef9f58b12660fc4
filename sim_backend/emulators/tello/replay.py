"""`TelloReplayer`: a recorded Tello session (drivers/tello/traffic.py) served over loopback UDP as the drone.

A driver configured with the replayer's `address` (`host`, `control_port`) and `state_port` talks to it
as to a Tello: commands in on one socket, replies out of that socket to the command's sender, state lines
from the replayer's ip to `(client ip, state_port)`. Only IPv4 loopback (127.0.0.0/8): the constructor
refuses any other address, and datagrams from any other sender are dropped (`counts["rejected_sender"]`).

The rules (times: the recording's s, `time.monotonic()` s on the wire):

- **Segments.** The recording is cut at every recorded command ("sent" record) but `rc` (a flight's own
  recording holds one per control tick: `is_stick_command`). A datagram whose text
  (stripped, case-insensitive) equals the next recorded command not yet served, or a later one up to and
  including the next recorded *phase command* (`takeoff`, `land`, `emergency`), is that command: the
  replay clock is shifted so that the command's recorded time maps to now, the state lines from that time
  on are sent at their recorded offsets, and the recorded replies (the "reply" records between it and the
  next recorded command) at their recorded delays (+ `reply_delay_extra_s`), unmodified, to its sender.
  So `land` while the recording is still at `forward 50` jumps to the recorded landing; `land` before the
  recorded takeoff matches nothing (it may not skip a phase command). Commands skipped by such a jump get
  no reply. A jump (a match past the next unserved command) also cancels the replies not yet sent
  (`counts["replies_cancelled"]`): `land` 1 s into the climb gets the landing's `ok`, never the takeoff's,
  recorded 8.7 s after it; otherwise a reply once due is sent even when the next command comes first.
- **Unrecorded commands.** A datagram that matches no such command (`rc`, `battery?`, `sdk?`, `sn?`,
  `streamon`, a command already served and sent again, ...) gets no reply and changes nothing
  (`counts["unmatched"]`; listed in `received`).
- **Between commands.** The recorded state lines play on through the segments of commands the driver did
  not send (a drone does not pause: a flight goes on as recorded) up to the recorded time of the next
  phase command not yet served. There the replayer *holds*: it repeats the last line it passed, at the
  recording's median state interval, until that command (or another matching one) arrives: the drone on
  the ground before `takeoff`, hovering before `land` (the recording's own manoeuvres play first). While
  hovering, the repeats' `time` field (motor-on s) counts on in whole seconds, as a flying Tello's does,
  every other byte as recorded; on the ground it stays (the SDK guide calls `time` motor time; the xg590
  flight has one ground line, so it cannot show whether `time` counts on the ground, and its README reads
  the 49 s there as time since power-on). From the start, lines play from the first record (a recording's
  lines before its `command`: the drone was already streaming) and hold at the first phase command. The
  recorded landing is never played without a `land` (a real Tello would land by itself after 15 s without
  a command; a replay does not invent that).
- **After the last recorded line** (past the last phase command): `after_end="repeat"` (default: a landed
  Tello goes on streaming its state; silence would read as a lost link) repeats the last line at the
  median interval; `"silence"` sends nothing more.
- **Recorded vs synthesised.** Every state datagram is logged in `sent` with its origin, "recorded" (a
  recorded line at its recorded offset) or "synthesised" (a repeat while holding or after the end), and
  counted apart: `counts["state_recorded"]`, `counts["state_synthesised"]`.
- **Test options.** `reply_delay_extra_s` delays every reply further (s, ≥ 0); `drop_state` drops that
  fraction of state datagrams, recorded and synthesised alike, drawn from `random.Random(seed)`
  (`counts["state_dropped_recorded"]`, `counts["state_dropped_synthesised"]`; not in `sent`; `drops`
  lists every draw in order).

The state destination ip is `client_ip` until a `command` is served, then that command's sender ip (a
Tello streams to whoever sent `command`). Video records ("video", lengths only) are not served. Threads
(receive, send) are daemons with bounded waits (≤ 0.05 s), joined by `close()`; a context manager.
`access_units` and `video_datagrams` cut a recorded H.264 dump into the datagrams a Tello sends.
"""

from __future__ import annotations

import bisect
import logging
import math
import random
import re
import socket
import statistics
import threading
import time
from collections import Counter
from dataclasses import dataclass
from types import TracebackType
from typing import Literal

from flightstack.drivers.tello.traffic import TelloSession
from flightstack.drivers.tello.video_check import TELLO_DATAGRAM_BYTES

from ..net import bind_drone_sockets, is_loopback, require_loopback

LOG = logging.getLogger(__name__)
PHASE_COMMANDS = frozenset({"takeoff", "land", "emergency"})
"""Commands a replay never plays past without receiving them (a flight's phase changes at each)."""
MAX_DATAGRAM_BYTES = 2048
WAIT_S = 0.05  # the longest a thread waits before it looks at the stop flag again (s)
AfterEnd = Literal["repeat", "silence"]
_MOTOR_TIME = re.compile(rb"(^|;)time:(\d{1,6});")


@dataclass(frozen=True)
class Sent:
    """One datagram the replayer sent: monotonic time `t` (s), "state" or "reply", its bytes, its origin
    ("recorded" | "synthesised"), `rec_t`, the recorded time of the record it comes from (s), and `served`,
    how many recorded commands had been served when it was decided (a datagram decided before a command
    can leave just after it: compare `served`, not times)."""

    t: float
    kind: Literal["state", "reply"]
    data: bytes
    origin: Literal["recorded", "synthesised"]
    rec_t: float
    served: int = 0


@dataclass(frozen=True)
class Received:
    """One datagram received: monotonic time `t` (s), its text, the index of the recorded command it
    matched (None: unmatched) and its sender."""

    t: float
    text: str
    matched: int | None
    sender: tuple[str, int]


class TelloReplayer:
    """A recorded `TelloSession` served over loopback UDP (the rules: module docstring).

    Public, append-only logs (take `list(...)` for a snapshot): `sent`, `received`, `drops`, `errors`;
    `counts`.
    `commands` are the recorded commands `(t, text)`; `served` is how many of them are behind the replay."""

    def __init__(
        self,
        session: TelloSession,
        ip: str = "127.0.0.2",
        port: int = 0,
        state_port: int = 8890,
        client_ip: str = "127.0.0.1",
        *,
        after_end: AfterEnd = "repeat",
        reply_delay_extra_s: float = 0.0,
        drop_state: float = 0.0,
        seed: int = 0,
    ) -> None:
        require_loopback(ip, "ip")
        require_loopback(client_ip, "client_ip")
        if after_end not in ("repeat", "silence"):
            raise ValueError(f"after_end must be 'repeat' or 'silence', got {after_end!r}")
        if not (math.isfinite(reply_delay_extra_s) and reply_delay_extra_s >= 0.0):
            raise ValueError(f"reply_delay_extra_s must be finite and >= 0 s, got {reply_delay_extra_s}")
        if not 0.0 <= drop_state < 1.0:
            raise ValueError(f"drop_state must be in [0, 1), got {drop_state}")
        if not 1 <= state_port <= 65535:
            raise ValueError(f"state_port must be a UDP port, got {state_port}")
        self.ip, self._port, self.state_port, self.client_ip = ip, port, state_port, client_ip
        self.after_end: AfterEnd = after_end
        self.reply_delay_extra_s = float(reply_delay_extra_s)
        self.drop_state = float(drop_state)
        self._rng = random.Random(seed)

        states = session.of("state")
        if not states:
            raise ValueError(f"{session.source}: no state lines to replay")
        self.lines: list[tuple[float, bytes]] = [(r.t, r.text.encode("utf-8")) for r in states]
        self._line_t = [t for t, _ in self.lines]
        sent = session.of("sent")
        sent_t = [r.t for r in sent]
        replies_of: list[list[tuple[float, str]]] = [[] for _ in sent]
        for r in session.of("reply"):
            k = bisect.bisect_right(sent_t, r.t) - 1
            if k >= 0:
                replies_of[k].append((r.t - sent_t[k], r.text))
        keep = [k for k, r in enumerate(sent) if not is_stick_command(r.text)]
        self.commands: list[tuple[float, str]] = [(sent[k].t, sent[k].text) for k in keep]
        """The recorded commands that cut segments: every "sent" record but `rc` (see is_stick_command)."""
        self._norm = [text.strip().lower() for _, text in self.commands]
        self.replies: list[list[tuple[float, str]]] = [replies_of[k] for k in keep]
        """Per recorded command: its recorded replies as (delay after the command s, text)."""
        gaps = [b - a for a, b in zip(self._line_t, self._line_t[1:], strict=False) if b > a]
        self.hold_interval_s = statistics.median(gaps) if gaps else 0.1
        """The interval of synthesised lines: the recording's median state interval (s)."""
        self._t_first = min(r.t for r in session.records)

        self.sent: list[Sent] = []
        self.received: list[Received] = []
        self.errors: list[str] = []
        self.counts: Counter[str] = Counter()
        self.drops: list[bool] = []
        """With drop_state: one entry per state datagram due, in order, True when it was dropped."""
        self._cond = threading.Condition()
        self.served = 0
        self._offset = 0.0  # monotonic = recorded t + offset
        self._cursor = 0  # the next recorded line
        self._limit_t = self._phase_limit(0)  # lines play up to (not including) this recorded time
        self._last: tuple[float, bytes] | None = None  # the last line passed (sent or dropped)
        self._airborne = False  # the last phase command served was `takeoff`
        self._hold_next = 0.0  # monotonic time of the next synthesised line (while holding)
        self._replies_due: list[tuple[float, str, tuple[str, int], float]] = []  # (due, text, addr, rec_t)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cmd_sock: socket.socket | None = None
        self._tx_sock: socket.socket | None = None
        self._bound: tuple[str, int] | None = None
        self._started = self._closed = False

    # ------------------------------------------------------------------------------------------- lifecycle
    @property
    def address(self) -> tuple[str, int]:
        """(ip, port) the driver sends commands to (after `start()` when port=0)."""
        if self._bound is None:
            if self._port == 0:
                raise RuntimeError("address is only known after start() when port=0")
            return (self.ip, self._port)
        return self._bound

    def start(self) -> TelloReplayer:
        """Bind the command and state sockets on `ip` and start the replay (the first record is now)."""
        if self._started:
            raise RuntimeError("replayer already started")
        cmd, tx = bind_drone_sockets(self.ip, self._port, WAIT_S)
        host, port = cmd.getsockname()[:2]
        self._cmd_sock, self._tx_sock, self._bound = cmd, tx, (str(host), int(port))
        self._started = True
        with self._cond:
            self._offset = time.monotonic() - self._t_first
        for name, target in (("rx", self._receive_loop), ("tx", self._send_loop)):
            thread = threading.Thread(target=target, name=f"tello-replay-{self.ip}-{name}", daemon=True)
            self._threads.append(thread)
            thread.start()
        return self

    def close(self) -> None:
        """Stop both threads (joined within ~1 s) and close the sockets; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        deadline = time.monotonic() + 1.0
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
            if thread.is_alive():  # pragma: no cover - would indicate a bug
                LOG.error("thread %s did not stop", thread.name)
        for sock in (self._cmd_sock, self._tx_sock):
            if sock is not None:
                sock.close()

    @property
    def threads_alive(self) -> list[str]:
        return [t.name for t in self._threads if t.is_alive()]

    def __enter__(self) -> TelloReplayer:
        if not self._started:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ---------------------------------------------------------------------------------------------- rules
    def _phase_limit(self, served: int) -> float:
        """Recorded time of the first phase command at or after index `served` (inf: none)."""
        k = self._next_phase(served)
        return math.inf if k is None else self.commands[k][0]

    def _next_phase(self, served: int) -> int | None:
        return next((k for k in range(served, len(self.commands)) if self._norm[k] in PHASE_COMMANDS), None)

    def match(self, text: str) -> int | None:
        """The index of the recorded command `text` is now (module docstring, "Segments"), or None."""
        want = text.strip().lower()
        with self._cond:
            last = self._next_phase(self.served)
            end = len(self.commands) - 1 if last is None else last
            return next((k for k in range(self.served, end + 1) if self._norm[k] == want), None)

    def _serve(self, k: int, now: float, sender: tuple[str, int]) -> None:
        """Command `k` arrived at `now` (held lock): shift the clock, move the cursor, queue its replies."""
        t_cmd = self.commands[k][0]
        if k > self.served:  # a jump: the skipped segments' replies go with them
            self.counts["replies_cancelled"] += len(self._replies_due)
            self._replies_due.clear()
        self.served = k + 1
        self._offset = now - t_cmd
        self._cursor = bisect.bisect_left(self._line_t, t_cmd)
        self._limit_t = self._phase_limit(self.served)
        self._hold_next = now + self.hold_interval_s
        if self._norm[k] == "command":
            self.client_ip = sender[0]
        if self._norm[k] in PHASE_COMMANDS:
            self._airborne = self._norm[k] == "takeoff"
        for delay, reply in self.replies[k]:
            due = now + delay + self.reply_delay_extra_s
            self._replies_due.append((due, reply, sender, t_cmd + delay))
        self._replies_due.sort(key=lambda r: r[0])
        self.counts["matched"] += 1

    # -------------------------------------------------------------------------------------------- threads
    def _receive_loop(self) -> None:
        assert self._cmd_sock is not None
        while not self._stop.is_set():
            try:
                data, sender = self._cmd_sock.recvfrom(MAX_DATAGRAM_BYTES)
            except TimeoutError:
                continue
            except OSError as exc:
                if not self._stop.is_set():
                    self.errors.append(f"recv: {exc}")
                    self._stop.wait(WAIT_S)
                continue
            now = time.monotonic()
            if not is_loopback(sender[0]):
                self.counts["rejected_sender"] += 1
                continue
            text = data.decode("utf-8", errors="replace")
            with self._cond:
                k = self.match(text)
                if k is None:
                    self.counts["unmatched"] += 1
                else:
                    self._serve(k, now, (str(sender[0]), int(sender[1])))
                self.received.append(Received(now, text, k, (str(sender[0]), int(sender[1]))))
                self._cond.notify_all()

    def _send_loop(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                now = time.monotonic()
                out = self._due(now)
                if not out:
                    wait = min(WAIT_S, max(0.0, self._next_due() - now))
                    self._cond.wait(wait)
                    continue
            for sent, dest in out:
                self._send(sent, dest)

    def _next_due(self) -> float:
        """Monotonic time of the next datagram (held lock; inf: none)."""
        due = [self._replies_due[0][0]] if self._replies_due else []
        if self._cursor < len(self.lines) and self.lines[self._cursor][0] < self._limit_t:
            due.append(self.lines[self._cursor][0] + self._offset)
        elif self._holding():
            due.append(self._hold_next)
        return min(due, default=math.inf)

    def _due(self, now: float) -> list[tuple[Sent, tuple[str, int] | None]]:
        """Everything due at `now`, in time order (held lock); None as the destination: dropped."""
        out: list[tuple[Sent, tuple[str, int] | None]] = []
        while self._replies_due and self._replies_due[0][0] <= now:
            _, text, addr, rec_t = self._replies_due.pop(0)
            out.append((Sent(now, "reply", text.encode("utf-8"), "recorded", rec_t, self.served), addr))
        dest = (self.client_ip, self.state_port)
        while self._cursor < len(self.lines):
            t_rec, line = self.lines[self._cursor]
            if t_rec >= self._limit_t or t_rec + self._offset > now:
                break
            self._cursor += 1
            self._last = (t_rec, line)
            self._hold_next = t_rec + self._offset + self.hold_interval_s
            out.append(self._state(Sent(now, "state", line, "recorded", t_rec, self.served), dest))
        if self._holding():
            if self._hold_next < now - self.hold_interval_s:  # a hold that starts now, not a catch-up
                self._hold_next = now
            while self._hold_next <= now:
                t_rec, line = self._last  # type: ignore[misc]  # _holding() checked it
                if self._airborne:  # motors run on: their `time` counts on, as a hovering Tello's
                    line = motor_time_on(line, self._hold_next - (t_rec + self._offset))
                out.append(self._state(Sent(now, "state", line, "synthesised", t_rec, self.served), dest))
                self._hold_next += self.hold_interval_s
        return out

    def _holding(self) -> bool:
        """True while the replayer repeats its last line (held lock): no recorded line is to come before
        the next served command, and not past the end with after_end="silence"."""
        if self._last is None:
            return False
        if self._cursor < len(self.lines) and self.lines[self._cursor][0] < self._limit_t:
            return False
        past_end = self._cursor >= len(self.lines) and self._limit_t == math.inf
        return not (past_end and self.after_end == "silence")

    def _state(self, s: Sent, dest: tuple[str, int]) -> tuple[Sent, tuple[str, int] | None]:
        """A state datagram, or its drop (`drop_state`), counted by origin (held lock)."""
        if not self.drop_state:
            return s, dest
        drop = self._rng.random() < self.drop_state
        self.drops.append(drop)
        if drop:
            self.counts[f"state_dropped_{s.origin}"] += 1
            return s, None
        return s, dest

    def _send(self, s: Sent, dest: tuple[str, int] | None) -> None:
        if dest is None:
            return
        sock = self._cmd_sock if s.kind == "reply" else self._tx_sock
        assert sock is not None
        try:
            sock.sendto(s.data, dest)
        except OSError as exc:  # nobody listening yet is fine: counted, not raised
            self.counts["send_error"] += 1
            if len(self.errors) < 100:
                self.errors.append(f"send {s.kind} to {dest}: {exc}")
            return
        with self._cond:
            self.sent.append(Sent(time.monotonic(), s.kind, s.data, s.origin, s.rec_t, s.served))
            self.counts["replies" if s.kind == "reply" else f"state_{s.origin}"] += 1


def is_stick_command(text: str) -> bool:
    """`rc a b c d`: a flight's own recording holds one every control tick. It neither cuts a segment nor is
    matched (a driver's `rc 0 0 0 0` would jump the replay to a recorded hover); a firmware's answers to
    rc (`error Not joystick`, which some send) are not served."""
    return text.strip().lower().startswith("rc ")


def motor_time_on(line: bytes, elapsed_s: float) -> bytes:
    """`line` with its `time` field (motor-on s) advanced by the whole seconds of `elapsed_s`; unchanged
    without a readable field."""
    m = _MOTOR_TIME.search(line)
    if m is None or elapsed_s < 1.0:
        return line
    return line[: m.start(2)] + str(int(m.group(2)) + int(elapsed_s)).encode() + line[m.end(2) :]


def access_units(annexb: bytes) -> list[bytes]:
    """An Annex-B H.264 byte stream cut into access units (each with its start codes), as a Tello sends
    them: a unit starts at an SPS, PPS, SEI or access unit delimiter, or at a picture's first slice
    (first_mb_in_slice 0: the first bit after the NAL header is 1), once the unit has a slice. Bytes
    before the first start code are dropped."""
    starts, i = [], annexb.find(b"\x00\x00\x01")
    while i >= 0:
        starts.append(i - 1 if i > 0 and annexb[i - 1] == 0 else i)  # a 4-byte start code's leading zero
        i = annexb.find(b"\x00\x00\x01", i + 3)
    units: list[bytes] = []
    begin, has_slice = None, False
    for k, s in enumerate(starts):
        head = annexb.find(b"\x00\x00\x01", s) + 3
        kind = annexb[head] & 0x1F if head < len(annexb) else 0
        first_slice = kind in (1, 5) and head + 1 < len(annexb) and annexb[head + 1] & 0x80
        if begin is not None and has_slice and (kind in (6, 7, 8, 9) or first_slice):
            units.append(annexb[begin:s])
            begin, has_slice = None, False
        if begin is None:
            begin = s
        has_slice = has_slice or kind in (1, 5)
        if k == len(starts) - 1:
            units.append(annexb[begin:])
    return units


def video_datagrams(unit: bytes, size: int = TELLO_DATAGRAM_BYTES) -> list[bytes]:
    """One access unit in the Tello's datagrams: `size` bytes each but the last (video_check's framing)."""
    return [unit[k : k + size] for k in range(0, len(unit), size)]


__all__ = [
    "PHASE_COMMANDS",
    "Received",
    "Sent",
    "TelloReplayer",
    "access_units",
    "is_stick_command",
    "motor_time_on",
    "video_datagrams",
]
