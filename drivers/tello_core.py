"""The Tello driver's shared state: settings, locks, the phase tracker, events and the telemetry view.

`TelloDriverCore` is the bottom layer of drivers/tello.py's `TelloDriver`: its constructor (every flag the
other layers share), the event log (`events`: (time.monotonic() s, kind, detail), also logged), the state
receiver's callback (one validated packet → phase tracker), the hal.Drone state view (battery in %,
height in m, from the packet's `bat` and `h` in cm) and the mute hook (drivers/guardian.py). Layers on top:
drivers/tello_exchange.py (blocking command exchange), drivers/tello_sticks.py (`rc` and `emergency`),
drivers/tello_flight.py (takeoff and land), drivers/tello_watchdog.py (link and loop watchdog).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable

from flightstack.drivers.tello_config import TelloConfig
from flightstack.drivers.tello_link import CommandChannel, ErrorLog, StateReceiver
from flightstack.drivers.tello_phase import PhaseTracker
from flightstack.drivers.tello_state import TelloTelemetry
from flightstack.events import Event, TelloKind
from flightstack.hal import DroneState, FlightPhase

LOG = logging.getLogger("flightstack.tello")


class TelloDriverCore:
    """State shared by the layers of `TelloDriver` (drivers/tello.py)."""

    def __init__(self, cfg: TelloConfig) -> None:
        self.cfg = cfg
        self._lock = threading.RLock()  # tracker, flags, last rc
        self._cmd_lock = threading.Lock()  # one blocking exchange at a time
        self._tracker = PhaseTracker(cfg.phase)
        self._chan: CommandChannel | None = None
        self._rx: StateReceiver | None = None
        self._state_fields: dict[str, float] = {}
        self._last_state_t = -math.inf
        self._link_alive = False
        self._busy = False  # a blocking exchange is running: no rc
        self._land_requested = False  # land sent (until the next takeoff): no rc, no keep-alive
        self._last_rc_t = -math.inf
        self._last_loop_t = -math.inf  # the loop's last send_body_velocity (monotonic s)
        self._self_landing: threading.Thread | None = None
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None
        self._once: set[str] = set()
        self.last_rc: tuple[int, int, int, int] = (0, 0, 0, 0)
        self.events: list[Event] = []  # source tello, time.monotonic() s
        self.counts: Counter[str] = Counter()
        self.rc_sent = 0
        self._muted: Callable[[], bool] | None = None
        self._errors = ErrorLog(self.counts, f"tello {cfg.host} monitor", LOG)
        self.sdk_version: str | None = None
        self.serial: str | None = None

    # ---- events, state ---------------------------------------------------------------------------
    def _event(self, kind: TelloKind, detail: str = "") -> None:
        self.events.append(Event(time.monotonic(), None, kind, detail, source="tello", clock="monotonic"))
        del self.events[:-1000]
        LOG.warning("tello %s %s %s", self.cfg.host, kind, detail)

    def _on_state(self, s: TelloTelemetry) -> None:
        """State receiver thread: one validated packet."""
        with self._lock:
            self._state_fields = dict(s.fields)  # a new dict per packet (drivers/identify.py relies on it)
            self._last_state_t = s.t
            for change in self._tracker.observe(s):
                self._event("phase", change)
            if self._tracker.phase is FlightPhase.GROUND:
                self._land_requested = False

    @property
    def phase(self) -> FlightPhase:
        with self._lock:
            return self._tracker.phase

    def current_state(self) -> dict[str, float]:
        """The fields of the latest valid state packet (a new dict per packet)."""
        return self._state_fields

    def link_alive(self) -> bool:
        return self._link_alive and time.monotonic() - self._last_state_t <= self.cfg.link_timeout_s

    def state(self) -> DroneState:
        st, ph = self._state_fields, self.phase
        return DroneState(
            battery_pct=float(st.get("bat", 0.0)),
            height_m=float(st.get("h", 0.0)) / 100.0,
            link_alive=self.link_alive(),
            flying=ph is FlightPhase.AIRBORNE,
            phase=ph.value,
        )

    def set_muted(self, muted: Callable[[], bool] | None) -> None:
        """After `muted()` returns True nothing more is sent to the drone (a guardian process took it over:
        drivers/guardian.py); checked right before every datagram, from every thread."""
        self._muted = muted

    def is_muted(self) -> bool:
        m = self._muted
        return m is not None and m()
