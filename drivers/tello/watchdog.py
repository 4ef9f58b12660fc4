"""The Tello driver's monitor thread: link freshness and the control-loop watchdog.

Every 0.02 s: no valid state packet for `link_timeout_s` (s) → link lost (`link_lost` / `link_restored`
events; `link_lost` names the drone's rejected datagrams when it sent any: drivers/tello/stream_health.py),
and while it is lost `command` at most every `rejoin_s` (drivers/tello/rejoin.py: a drone that rebooted
streams again only after it); while airborne with no blocking command and no land pending, a control loop
silent for `loop_hover_s` (s) gets `rc 0 0 0 0` once, and after `loop_land_s` (s) the driver lands by
itself on its own thread. The thread survives any error (counted, logged).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from flightstack.drivers.device_threads import ErrorLog
from flightstack.drivers.tello.config import TelloConfig
from flightstack.drivers.tello.rejoin import SdkRejoin
from flightstack.drivers.tello.status import LOG, DriverEvents, DriverStatus
from flightstack.drivers.tello.sticks import HOVER, Sticks
from flightstack.hal import FlightPhase


class Watchdog:
    """The background monitor of one Tello driver; `land` is the driver's own (blocking) land."""

    def __init__(
        self,
        cfg: TelloConfig,
        status: DriverStatus,
        events: DriverEvents,
        sticks: Sticks,
        rejoin: SdkRejoin,
        land: Callable[[], None],
    ) -> None:
        self._cfg, self._status, self._events, self._sticks, self._land = cfg, status, events, sticks, land
        self._rejoin = rejoin
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._self_landing: threading.Thread | None = None
        self._errors = ErrorLog(events.counts, f"tello {cfg.host} monitor", LOG)

    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name=f"tello-mon-{self._cfg.host}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread (joined ≤ 1 s); a land it started goes on."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def _loop(self) -> None:
        while not self._stop.wait(0.02):
            try:
                self.step(time.monotonic())
            except Exception as exc:  # the monitor must outlive any error (counted, logged sparsely)
                self._errors.record("monitor_error", exc)

    def step(self, now: float) -> None:
        """One check at `now` (time.monotonic() s)."""
        st, cfg = self._status, self._cfg
        age = now - st.last_state_t
        if st.link_up and age > cfg.link_timeout_s:
            st.link_up = False
            with st.lock:
                why = st.health.rejected_note()
            self._events.add("link_lost", f"no valid state packet for {age:.2f} s{why}")
        elif not st.link_up and age <= cfg.link_timeout_s:
            st.link_up = True
            self._events.add("link_restored")
        with st.lock:
            if not st.busy or st.land_requested:  # no other exchange: command's ok is no answer
                self._rejoin.step(now, st.link_up)
            watched = st.tracker.phase is FlightPhase.AIRBORNE and not st.busy and not st.land_requested
            silent = now - st.last_loop_t
        if not watched:
            return
        if silent > cfg.loop_land_s:
            if self._self_landing is None or not self._self_landing.is_alive():
                self._events.add(
                    "loop_lost_land", f"no velocity from the control loop for {silent:.2f} s: land"
                )
                self._self_landing = threading.Thread(
                    target=self._land_by_itself, name=f"tello-autoland-{cfg.host}", daemon=True
                )
                self._self_landing.start()
        elif silent > cfg.loop_hover_s and self._sticks.last_rc != HOVER:
            self._sticks.send(HOVER, why="loop_silent_hover")

    def _land_by_itself(self) -> None:
        """The loop watchdog's land (own thread); errors counted and logged, never raised."""
        try:
            self._land()
        except Exception as exc:
            self._events.counts["loop_land_error"] += 1
            LOG.error("tello %s: land after the loop stopped failed: %s", self._cfg.host, exc)
