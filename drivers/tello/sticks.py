"""The Tello driver's stick commands: `rc` (body velocity or raw sticks), hover and `emergency`.

`send_body_velocity` maps V = [v_x, v_y, v_z, ω] in the drone's FLU body frame (m/s, rad/s) to `rc a b c d`
(drivers/tello/rc.py; -100..100 each) and sends it as one non-blocking datagram, only while the drone is
airborne, no blocking command is running and no land is pending (otherwise counted in
`counts["rc_suppressed"]`; a drone landing by itself is `landing`, so it gets no rc); every call tells the
loop watchdog (drivers/tello/watchdog.py) that the control loop is alive.
"""

from __future__ import annotations

import time

import numpy as np

from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.rc import RcGains, velocity_to_rc
from flightstack.drivers.tello.status import DriverEvents, DriverStatus
from flightstack.events import TelloKind
from flightstack.hal import FlightPhase

HOVER = (0, 0, 0, 0)


class Sticks:
    """`rc` and `emergency` of one Tello; never blocks, never raises for the phase.

    `last_rc`: the last stick values sent; `sent`: how many rc datagrams went out."""

    def __init__(self, gains: RcGains, link: TelloLink, status: DriverStatus, events: DriverEvents) -> None:
        self._gains, self._link, self._status, self._events = gains, link, status, events
        self._once: set[str] = set()  # suppression reasons already reported since the last rc sent
        self.last_rc: tuple[int, int, int, int] = HOVER
        self.sent = 0

    def hover_now(self) -> None:
        """`rc 0 0 0 0` if airborne, even with a land pending (a lost land must not leave it moving)."""
        with self._status.lock:
            chan = self._link.chan
            if chan is None or self._status.tracker.phase is not FlightPhase.AIRBORNE:
                return
            self._status.last_rc_t = now = time.monotonic()
            if chan.send("rc 0 0 0 0"):
                self.last_rc = HOVER
                self.sent += 1
                self._status.tracker.rc_sent(now, 0)

    def hover_unchecked(self) -> None:
        """`rc 0 0 0 0` whatever the phase and flags (a land re-sent while telemetry is silent)."""
        chan = self._link.chan
        assert chan is not None
        if chan.send("rc 0 0 0 0"):
            self.last_rc = HOVER
            self.sent += 1
            with self._status.lock:
                self._status.tracker.rc_sent(time.monotonic(), 0)

    def emergency_stop(self) -> None:
        """Motors off at once (`emergency`, no reply awaited, no quiet window)."""
        with self._status.lock:
            self._status.land_requested = True
            self._status.tracker.emergency_sent(time.monotonic())
        if self._link.chan is not None:
            self._link.chan.send("emergency")
        self._events.add("emergency", "motors off")

    def send_body_velocity(self, V: np.ndarray) -> None:
        """Map V (m/s, rad/s, FLU body) to `rc a b c d` and send it; never blocks, never raises for phase.

        Every call, sent or suppressed, tells the loop watchdog that the control loop is alive."""
        self._status.last_loop_t = time.monotonic()
        self.send(velocity_to_rc(V, self._gains))  # Python ints, clipped, NaN → 0

    def send_rc(self, rc: tuple[int, int, int, int]) -> None:
        """Send raw stick values (-100..100 each: roll, pitch, throttle, yaw) as the control loop (the loop
        watchdog counts it); same phase rules as send_body_velocity. For system identification."""
        self._status.last_loop_t = time.monotonic()
        self.send(tuple(max(-100, min(100, int(v))) for v in rc))  # type: ignore[arg-type]

    def send(self, rc: tuple[int, int, int, int], why: TelloKind | None = None) -> None:
        """`rc a b c d` when the phase rules allow it (else counted, the reason reported once); `why`: an
        event kind to report the send under (the watchdog's hover). Not the control loop."""
        st = self._status
        with st.lock:
            reason = ""
            if self._link.chan is None:
                reason = "not connected"
            elif st.busy:
                reason = "a command is in progress"
            elif st.land_requested:
                reason = "land sent"
            elif st.tracker.phase is not FlightPhase.AIRBORNE:
                reason = f"drone is {st.tracker.phase.value}"
            if reason:
                self._events.counts["rc_suppressed"] += 1
                if reason not in self._once:
                    self._once.add(reason)
                    self._events.add("rc_suppressed", reason)
                return
            self._once.clear()
            chan = self._link.chan
            assert chan is not None
            st.last_rc_t = now = time.monotonic()
            if chan.send("rc {} {} {} {}".format(*rc)):
                self.last_rc = rc
                self.sent += 1
                st.tracker.rc_sent(now, rc[2])
        if why:
            self._events.add(why, f"rc {rc} sent")
