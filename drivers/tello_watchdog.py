"""The Tello driver's monitor thread: link freshness and the control-loop watchdog.

Every 0.02 s: no state packet for `link_timeout_s` (s) → link lost (`link_lost` / `link_restored`
events); while airborne with no blocking command and no land pending, a control loop silent for
`loop_hover_s` (s) gets `rc 0 0 0 0` once, and after `loop_land_s` (s) the driver lands by itself on its
own thread. The thread survives any error (counted, logged). `TelloWatchdog` is one layer of
drivers/tello.py's `TelloDriver`.
"""

from __future__ import annotations

import logging
import threading
import time

from flightstack.drivers.tello_flight import TelloFlight
from flightstack.hal import FlightPhase

LOG = logging.getLogger("flightstack.tello")


class TelloWatchdog(TelloFlight):
    """The background monitor of `TelloDriver` (started by `connect`)."""

    def _monitor_loop(self) -> None:
        while not self._stop.wait(0.02):
            try:
                self._monitor_step(time.monotonic())
            except Exception as exc:  # the monitor must outlive any error (counted, logged sparsely)
                self._errors.record("monitor_error", exc)

    def _monitor_step(self, now: float) -> None:
        age = now - self._last_state_t
        if self._link_alive and age > self.cfg.link_timeout_s:
            self._link_alive = False
            self._event("link_lost", f"no state packet for {age:.2f} s")
        elif not self._link_alive and age <= self.cfg.link_timeout_s:
            self._link_alive = True
            self._event("link_restored")
        with self._lock:
            watched = (
                self._tracker.phase is FlightPhase.AIRBORNE and not self._busy and not self._land_requested
            )
            silent = now - self._last_loop_t
        if not watched:
            return
        if silent > self.cfg.loop_land_s:
            if self._self_landing is None or not self._self_landing.is_alive():
                self._event("loop_lost_land", f"no velocity from the control loop for {silent:.2f} s: land")
                self._self_landing = threading.Thread(
                    target=self._land_by_itself, name=f"tello-autoland-{self.cfg.host}", daemon=True
                )
                self._self_landing.start()
        elif silent > self.cfg.loop_hover_s and self.last_rc != (0, 0, 0, 0):
            self._send_rc((0, 0, 0, 0), why="loop_silent_hover")

    def _land_by_itself(self) -> None:
        """The loop watchdog's land (own thread); errors counted and logged, never raised."""
        try:
            self.land()
        except Exception as exc:
            self.counts["loop_land_error"] += 1
            LOG.error("tello %s: land after the loop stopped failed: %s", self.cfg.host, exc)
