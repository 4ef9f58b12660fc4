"""What the parts of one Tello driver share: its telemetry view, the flags that decide what may be sent,
and its events.

`DriverStatus` is fed by the state receiver's thread (`observe`: one parsed packet → phase tracker and
`health`; `reject`: one rejected datagram → `health`, drivers/tello/stream_health.py) and read and written
by the control loop, the blocking commands and the monitor, every flag under `lock`.
`DriverEvents` is the driver's event log and counters. Times: time.monotonic() s; heights cm.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter

from flightstack.drivers.tello.phase import PhaseThresholds, PhaseTracker
from flightstack.drivers.tello.state import TelloTelemetry
from flightstack.drivers.tello.stream_health import StreamHealth
from flightstack.events import Event, TelloKind, log_level
from flightstack.hal import FlightPhase

LOG = logging.getLogger("flightstack.tello")


class DriverEvents:
    """`events` (source tello, time.monotonic() s; the last 1000, each also logged) and `counts`."""

    def __init__(self, host: str) -> None:
        self.host = host
        self.events: list[Event] = []
        self.counts: Counter[str] = Counter()

    def add(self, kind: TelloKind, detail: str = "") -> None:
        self.events.append(Event(time.monotonic(), None, kind, detail, source="tello", clock="monotonic"))
        del self.events[:-1000]
        LOG.log(log_level(kind), "tello %s %s %s", self.host, kind, detail)


class DriverStatus:
    """The drone as one driver sees it, and what the driver is doing; flags read and written under `lock`.

    `link_timeout_s` (s): a state packet older than this means the link is down; rejected datagrams for
    that long are a run (`health`)."""

    def __init__(self, thresholds: PhaseThresholds, link_timeout_s: float, events: DriverEvents) -> None:
        self.lock = threading.RLock()
        self.tracker = PhaseTracker(thresholds)
        self.link_timeout_s = link_timeout_s
        self.health = StreamHealth(link_timeout_s)
        self.fields: dict[str, float] = {}  # the latest valid state packet (a new dict per packet)
        self.last_state_t = -math.inf
        self.link_up = False  # set by connect, then by the monitor from the packets' age
        self.busy = False  # a blocking exchange is running: no rc
        self.land_requested = False  # land sent (until the next takeoff): no rc, no keep-alive
        self.last_rc_t = -math.inf  # the last rc sent (monotonic s)
        self.last_loop_t = -math.inf  # the loop's last send_body_velocity (monotonic s)
        self._events = events

    def observe(self, s: TelloTelemetry) -> None:
        """State receiver thread: one parsed packet (implausible values as sent: stream_health.py)."""
        with self.lock:
            self.fields = dict(s.fields)  # a new dict per packet (drivers/tello/identify.py relies on it)
            self.last_state_t = s.t
            if s.implausible:
                self._events.counts["state_implausible"] += 1
            for detail in self.health.accepted(s):
                self._events.add("state_implausible", detail)
            for change in self.tracker.observe(s):
                self._events.add("phase", change)
            if self.tracker.phase is FlightPhase.GROUND:
                self.land_requested = False

    def reject(self, t: float, reason: str) -> None:
        """State receiver thread: a datagram from the drone that the parser rejected for `reason` at `t`."""
        with self.lock:
            run = self.health.rejected(t, reason)
            if run is not None:
                self._events.add("state_rejected_run", run)

    @property
    def phase(self) -> FlightPhase:
        with self.lock:
            return self.tracker.phase

    def link_alive(self) -> bool:
        return self.link_up and time.monotonic() - self.last_state_t <= self.link_timeout_s
