"""`command` again while a Tello's state stream is silent, at a bounded rate.

A Tello that lost power in flight (battery knocked loose) falls and reboots out of SDK mode: it streams no
state until it gets `command` again (DJITelloPy #169: after a battery swap, `connect()` again "tells the
restarted drone your PC controls it"; SMerrony/tellodesk#3: status no longer updated after a reconnect
following a battery change). Without `command` its landing can never be confirmed. So while the driver's
link is lost, `SdkRejoin.step` sends `command` at most every `rejoin_s` (s; 1 s by default): a drone still
in SDK mode answers `ok` (discarded: no exchange waits for it) and nothing else changes. Called by the
monitor thread (drivers/tello/watchdog.py); never while a blocking exchange other than a land runs (its
`ok` could pass for another command's answer). Times: time.monotonic() s.
"""

from __future__ import annotations

import math
import threading

from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.status import DriverEvents


class SdkRejoin:
    """`command` at most every `rejoin_s` (s) while the link is lost; `sent` counts them."""

    def __init__(self, rejoin_s: float, link: TelloLink, events: DriverEvents) -> None:
        self.rejoin_s = rejoin_s
        self._link, self._events = link, events
        self._lock = threading.Lock()
        self._last_t = -math.inf
        self._outage_sends = 0
        self.sent = 0

    def step(self, now: float, link_up: bool) -> bool:
        """Send `command` if the link is down and the last one went out `rejoin_s` ago; True if sent."""
        with self._lock:
            if link_up:
                self._outage_sends = 0
                return False
            chan = self._link.chan
            if chan is None or now - self._last_t < self.rejoin_s:
                return False
            self._last_t = now
            if not chan.send("command"):
                return False
            self.sent += 1
            self._outage_sends += 1
            first = self._outage_sends == 1
        self._events.counts["rejoin_sent"] += 1
        if first:  # once per outage; the count tells how many followed
            what = f"state stream silent: 'command' every {self.rejoin_s:g} s until it streams"
            self._events.add("rejoin", what)
        return True
