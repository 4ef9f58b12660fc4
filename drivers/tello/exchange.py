"""The Tello driver's blocking command exchange: quiet window, one command, the reply it accepts.

Replies carry no identifier, so before every blocking command the driver stops sending `rc`, waits for a
quiet window (`quiet_s`, s, since the last rc sent and the last datagram received), discards what is
pending, sends, and takes the first reply its `accept` test passes within the timeout (s); others are
counted (`reply_rejected`), and `error Not joystick` (a firmware's answer to rc) is never taken as the
answer. One exchange at a time per drone; `session()` holds one open for takeoff and land.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from flightstack.drivers.tello.config import TelloCommandError, TelloConfig
from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.status import DriverEvents, DriverStatus

RC_REPLIES = ("error not joystick",)  # firmware answers to rc, never another command's answer


class CommandExchange:
    """Blocking commands to one Tello: `request`, `control` (expects `ok`), `query`; `session` for a
    caller that reads the replies itself (`next_reply`)."""

    def __init__(self, cfg: TelloConfig, link: TelloLink, status: DriverStatus, events: DriverEvents) -> None:
        self._cfg, self._link, self._status, self._events = cfg, link, status, events
        self._lock = threading.Lock()  # one blocking exchange at a time

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
        if n:
            self._events.add("replies_discarded", f"{n} pending before a command")

    def _end(self) -> None:
        if self._link.chan is not None:
            self._link.chan.close_exchange()
        with self._status.lock:
            self._status.busy = False

    def next_reply(self) -> str | None:
        """The next reply of the open exchange that is not a firmware's answer to rc."""
        chan = self._link.chan
        assert chan is not None
        while (item := chan.pop_reply()) is not None:
            if item[1].lower() in RC_REPLIES:
                self._events.counts["rc_reply_ignored"] += 1
                continue
            return item[1]
        return None

    def request(self, command: str, timeout: float, accept: Callable[[str], bool]) -> str | None:
        """Send `command`; the first reply `accept`s within `timeout` s (others are counted), or None."""
        with self.session():
            chan = self._link.chan
            assert chan is not None
            chan.send(command)
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                r = self.next_reply()
                if r is None:
                    time.sleep(0.005)
                elif accept(r):
                    return r
                else:
                    self._events.counts["reply_rejected"] += 1
                    self._events.add("reply_rejected", f"{command!r} got {r!r}")
            return None

    def answer(self, command: str, timeout: float, attempts: int = 2) -> str | None:
        """The first answer to `command` within `timeout` s, sent again (up to `attempts` tries in all)
        while none comes; None when every try went unanswered."""
        for _ in range(attempts):
            reply = self.request(command, timeout, accept=lambda r: True)
            if reply is not None:
                return reply
        return None

    def control(self, command: str, timeout: float, attempts: int = 2) -> None:
        """A command with no telemetry effect (`streamon`, `port`, …): an `ok` within `timeout` s, retried
        once when no answer came; TelloCommandError on an error answer or silence."""
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
