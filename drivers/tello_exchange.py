"""The Tello driver's blocking command exchange: quiet window, one command, the reply it accepts.

Replies carry no identifier, so before every blocking command the driver stops sending `rc`, waits for a
quiet window (`quiet_s`, s, since the last rc sent and the last datagram received), discards what is
pending, sends, and takes the first reply its `accept` test passes within the timeout (s); others are
counted (`reply_rejected`), and `error Not joystick` (a firmware's answer to rc) is never taken as the
answer. `TelloExchange` is one layer of drivers/tello.py's `TelloDriver` (see drivers/tello_core.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from flightstack.drivers.tello_config import TelloCommandError
from flightstack.drivers.tello_core import TelloDriverCore

RC_REPLIES = ("error not joystick",)  # firmware answers to rc, never another command's answer


class TelloExchange(TelloDriverCore):
    """The command exchange of `TelloDriver`: `_request`, `_control` (expects `ok`) and `query`."""

    # ---- the command exchange ----------------------------------------------------------------------
    def _begin_exchange(self) -> None:
        """Stop rc, wait for the quiet window, discard what is pending. Caller holds _cmd_lock."""
        assert self._chan is not None
        with self._lock:
            self._busy = True
        deadline = time.monotonic() + 4 * self.cfg.quiet_s
        while time.monotonic() < deadline:
            last = max(self._last_rc_t, self._chan.last_rx_t)
            if time.monotonic() - last >= self.cfg.quiet_s:
                break
            time.sleep(0.01)
        n = self._chan.open_exchange()
        if n:
            self._event("replies_discarded", f"{n} pending before a command")

    def _end_exchange(self) -> None:
        if self._chan is not None:
            self._chan.close_exchange()
        with self._lock:
            self._busy = False

    def _next_reply(self) -> str | None:
        """The next reply of the open exchange that is not a firmware's answer to rc."""
        assert self._chan is not None
        while (item := self._chan.pop_reply()) is not None:
            if item[1].lower() in RC_REPLIES:
                self.counts["rc_reply_ignored"] += 1
                continue
            return item[1]
        return None

    def _request(self, command: str, timeout: float, accept: Callable[[str], bool]) -> str | None:
        """Send `command`; the first reply `accept`s within `timeout` s (others are counted), or None."""
        with self._cmd_lock:
            self._begin_exchange()
            try:
                assert self._chan is not None
                self._chan.send(command)
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    r = self._next_reply()
                    if r is None:
                        time.sleep(0.005)
                    elif accept(r):
                        return r
                    else:
                        self.counts["reply_rejected"] += 1
                        self._event("reply_rejected", f"{command!r} got {r!r}")
                return None
            finally:
                self._end_exchange()

    def _control(self, command: str, timeout: float, attempts: int = 2) -> None:
        """A command with no telemetry effect (`streamon`, `port`, …): an `ok` within `timeout` s, retried
        once when no answer came; TelloCommandError on an error answer or silence."""
        for _ in range(attempts):
            reply = self._request(command, timeout, accept=lambda r: True)
            if reply is None:
                continue
            if reply.lower() == "ok":
                return
            raise TelloCommandError(f"Tello {self.cfg.host}: {command!r} answered {reply!r}")
        raise TelloCommandError(f"Tello {self.cfg.host}: {command!r} got no answer ({attempts} tries)")

    def query(self, command: str, parse: Callable[[str], str | None], attempts: int = 2) -> str | None:
        """A read command (`sdk?`, `sn?`, `wifi?`): the first reply `parse` accepts, or None."""
        for _ in range(attempts):
            r = self._request(command, self.cfg.command_timeout_s, lambda x: parse(x) is not None)
            if r is not None:
                return parse(r)
        return None
