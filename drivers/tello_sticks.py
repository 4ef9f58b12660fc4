"""The Tello driver's stick commands: `rc` (body velocity or raw sticks), hover and `emergency`.

`send_body_velocity` maps V = [v_x, v_y, v_z, ω] in the drone's FLU body frame (m/s, rad/s) to
`rc a b c d` (drivers/tello_rc.py; -100..100 each) and sends it as one non-blocking datagram, only while
the drone is airborne, no blocking command is running and no land is pending (otherwise counted in
`counts["rc_suppressed"]`); every call tells the loop watchdog (drivers/tello_watchdog.py) that the
control loop is alive. `TelloSticks` is one layer of drivers/tello.py's `TelloDriver`.
"""

from __future__ import annotations

import time

import numpy as np

from flightstack.drivers.tello_core import TelloDriverCore
from flightstack.drivers.tello_rc import velocity_to_rc
from flightstack.events import TelloKind
from flightstack.hal import FlightPhase


class TelloSticks(TelloDriverCore):
    """`rc` and `emergency` of `TelloDriver`; never blocks, never raises for the phase."""

    def _hover_now(self) -> None:
        """`rc 0 0 0 0` if airborne, even with a land pending (a lost land must not leave it moving)."""
        with self._lock:
            if self._chan is None or self._tracker.phase is not FlightPhase.AIRBORNE:
                return
            self._last_rc_t = time.monotonic()
            if self._chan.send("rc 0 0 0 0"):
                self.last_rc = (0, 0, 0, 0)
                self.rc_sent += 1

    def emergency_stop(self) -> None:
        """Motors off at once (`emergency`, no reply awaited, no quiet window)."""
        with self._lock:
            self._land_requested = True
            self._tracker.emergency_sent(time.monotonic())
        if self._chan is not None:
            self._chan.send("emergency")
        self._event("emergency", "motors off")

    def send_body_velocity(self, V: np.ndarray) -> None:
        """Map V (m/s, rad/s, FLU body) to `rc a b c d` and send it; never blocks, never raises for phase.

        Every call, sent or suppressed, tells the loop watchdog that the control loop is alive."""
        self._last_loop_t = time.monotonic()
        self._send_rc(velocity_to_rc(V, self.cfg.rc_gains))  # Python ints, clipped, NaN → 0

    def send_rc(self, rc: tuple[int, int, int, int]) -> None:
        """Send raw stick values (-100..100 each: roll, pitch, throttle, yaw) as the control loop (the loop
        watchdog counts it); same phase rules as send_body_velocity. For system identification."""
        self._last_loop_t = time.monotonic()
        self._send_rc(tuple(max(-100, min(100, int(v))) for v in rc))  # type: ignore[arg-type]

    def _send_rc(self, rc: tuple[int, int, int, int], why: TelloKind | None = None) -> None:
        with self._lock:
            reason = ""
            if self._chan is None:
                reason = "not connected"
            elif self._busy:
                reason = "a command is in progress"
            elif self._land_requested:
                reason = "land sent"
            elif self._tracker.phase is not FlightPhase.AIRBORNE:
                reason = f"drone is {self._tracker.phase.value}"
            if reason:
                self.counts["rc_suppressed"] += 1
                if reason not in self._once:
                    self._once.add(reason)
                    self._event("rc_suppressed", reason)
                return
            self._once.clear()
            assert self._chan is not None
            self._last_rc_t = time.monotonic()
            if self._chan.send("rc {} {} {} {}".format(*rc)):
                self.last_rc = rc
                self.rc_sent += 1
        if why:
            self._event(why, f"rc {rc} sent")
