"""The Tello driver's blocking command exchange: quiet window, one command, the reply that answers it.

Replies carry no identifier, so before every blocking command the driver stops sending `rc`, waits for a
quiet window (`quiet_s`, s, since the last rc sent and the last datagram received), discards what is
pending, sends, and takes the first reply that answers it within the timeout (s): one its `accept` test
passes while no other request still owed a reply could have drawn it (drivers/tello/replies.py). Every
other reply is skipped: the answer to a request of this exchange (a keep-alive's value) silently, any other
as a stray (`counts["stray_reply_<kind>"]`, kind `ok`, `error` or `value`; event `stray_reply` at the first
of each kind). `error Not joystick` (a firmware's answer to rc) is never taken as the answer. One exchange
at a time per drone; `session()` holds one open for takeoff and land.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from flightstack.drivers.tello.config import TelloCommandError, TelloConfig
from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.replies import RC_REPLIES, Request, expected, is_command_answer, reply_kind
from flightstack.drivers.tello.status import DriverEvents, DriverStatus


class CommandExchange:
    """Blocking commands to one Tello: `request`, `control` (expects `ok`), `query`; `session` for a
    caller that reads the replies itself (`next_answer`, `next_reply`)."""

    def __init__(self, cfg: TelloConfig, link: TelloLink, status: DriverStatus, events: DriverEvents) -> None:
        self._cfg, self._link, self._status, self._events = cfg, link, status, events
        self._lock = threading.Lock()  # one blocking exchange at a time
        self._opened_t = -math.inf  # when the open exchange began (time.monotonic() s)

    @contextmanager
    def session(self) -> Iterator[None]:
        """Hold the exchange: rc stopped, quiet window waited, pending replies discarded; reopened to rc
        on exit. Blocks while another exchange runs."""
        with self._lock:
            self._begin()
            try:
                yield
            finally:
                self._end()

    def _begin(self) -> None:
        chan = self._link.chan
        assert chan is not None
        with self._status.lock:
            self._status.busy = True
        deadline = time.monotonic() + 4 * self._cfg.quiet_s
        while time.monotonic() < deadline:
            last = max(self._status.last_rc_t, chan.last_rx_t)
            if time.monotonic() - last >= self._cfg.quiet_s:
                break
            time.sleep(0.01)
        n = chan.open_exchange()
        self._opened_t = time.monotonic()
        if n:
            self._events.add("replies_discarded", f"{n} pending before a command")

    def _end(self) -> None:
        if self._link.chan is not None:
            self._link.chan.close_exchange()
        with self._status.lock:
            self._status.busy = False

    def next_reply(self) -> str | None:
        """The next reply of the open exchange that is not a firmware's answer to rc, whatever it answers
        (given to the request it answers: drivers/tello/replies.py)."""
        chan = self._link.chan
        assert chan is not None
        while (item := chan.pop_reply()) is not None:
            if item[1].lower() in RC_REPLIES:
                self._events.counts["rc_reply_ignored"] += 1
                continue
            chan.ledger.place(*item)
            return item[1]
        return None

    def next_answer(self, command: str, accept: Callable[[str], bool]) -> str | None:
        """The next reply of the open exchange that answers `command` (`accept` passes it and no other owed
        request could have drawn it), or None; the replies before it are skipped (module docstring)."""
        chan = self._link.chan
        assert chan is not None
        while (item := chan.pop_reply()) is not None:
            t, r = item
            if r.lower() in RC_REPLIES:
                self._events.counts["rc_reply_ignored"] += 1
                continue
            owner = chan.ledger.place(t, r, command, accept(r))
            if owner is not None and owner.command == command:
                return r
            if owner is None or owner.t < self._opened_t or not expected(r, owner.command):
                self._stray(command, r, t, owner)
        return None

    def _stray(self, command: str, reply: str, t: float, owner: Request | None) -> None:
        """Count a reply that answers neither `command` nor a request of this exchange as expected; log
        the first of each kind."""
        key = f"stray_reply_{reply_kind(reply)}"
        self._events.counts[key] += 1
        if self._events.counts[key] > 1:
            return
        if owner is None:
            whose = "it answers no request owed a reply"
        else:
            whose = f"taken for {owner.command!r}, sent {t - owner.t:.2f} s before it and still unanswered"
        self._events.add("stray_reply", f"{command!r} got {reply!r}: {whose} (the next only counted: {key})")

    def request(self, command: str, timeout: float, accept: Callable[[str], bool]) -> str | None:
        """Send `command`; the first reply that answers it (`next_answer`) within `timeout` s, or None."""
        with self.session():
            chan = self._link.chan
            assert chan is not None
            chan.send(command)
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                if (r := self.next_answer(command, accept)) is not None:
                    return r
                time.sleep(0.005)
            return None

    def answer(self, command: str, timeout: float, attempts: int = 2) -> str | None:
        """The first `ok` or refusal (`error …`) answering `command` within `timeout` s (a value is a
        stray, skipped), sent again (up to `attempts` tries in all) while none comes; None when every try
        went unanswered."""
        for _ in range(attempts):
            reply = self.request(command, timeout, accept=is_command_answer)
            if reply is not None:
                return reply
        return None

    def control(self, command: str, timeout: float, attempts: int = 2) -> None:
        """A command with no telemetry effect (`streamon`, `port`, …): an `ok` within `timeout` s (`answer`),
        retried once when no answer came; TelloCommandError on a refusal or silence."""
        reply = self.answer(command, timeout, attempts)
        if reply is None:
            raise TelloCommandError(f"Tello {self._cfg.host}: {command!r} got no answer ({attempts} tries)")
        if reply.lower() != "ok":
            raise TelloCommandError(f"Tello {self._cfg.host}: {command!r} answered {reply!r}")

    def query(self, command: str, parse: Callable[[str], str | None], attempts: int = 2) -> str | None:
        """A read command (`sdk?`, `sn?`, `wifi?`): the first reply `parse` accepts, or None."""
        for _ in range(attempts):
            r = self.request(command, self._cfg.command_timeout_s, lambda x: parse(x) is not None)
            if r is not None:
                return parse(r)
        return None
