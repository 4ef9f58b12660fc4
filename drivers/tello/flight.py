"""The Tello driver's takeoff and land, confirmed by telemetry (replies are advisory).

`takeoff()` returns once the state stream shows the drone airborne at a stable height and it answered `ok`
at that height (or telemetry alone at `takeoff_timeout_s`, s); `land()` once it shows the drone down with
the motors off, re-sending `rc 0 0 0 0` + `land` at once when telemetry returns after a lost link, and
every `land_resend_s` (s) while telemetry is silent or shows neither a descent nor the ground. Heights in
cm as sent by the drone. Each holds the command exchange (drivers/tello/exchange.py) for its whole length;
the rules on every failure: drivers/tello/driver.py.
"""

from __future__ import annotations

import time
from typing import Literal

from flightstack.drivers.tello.config import TelloCommandError, TelloConfig, TelloLinkError
from flightstack.drivers.tello.exchange import CommandExchange
from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.status import DriverEvents, DriverStatus
from flightstack.drivers.tello.sticks import Sticks
from flightstack.events import TelloKind
from flightstack.hal import FlightPhase


class FlightPhases:
    """Takeoff and land of one Tello (blocking their caller only)."""

    def __init__(
        self,
        cfg: TelloConfig,
        link: TelloLink,
        status: DriverStatus,
        events: DriverEvents,
        exchange: CommandExchange,
        sticks: Sticks,
    ) -> None:
        self.cfg, self._link, self._status, self._events = cfg, link, status, events
        self._exchange, self._sticks = exchange, sticks

    def takeoff(self) -> None:
        """Take off; return once the drone is airborne and done with its takeoff.

        Done = telemetry shows it airborne at a stable height AND it answered `ok` while at that height
        (an `ok` at the ground is someone else's: not trusted). A Tello stabilises at height for seconds
        before its `ok` and ignores rc until then, and telemetry cannot tell that from a finished takeoff;
        so if the `ok` is lost, telemetry alone decides at takeoff_timeout_s (20 s), while `battery?`
        probes (answered in every phase) keep the drone from its 15 s auto-land.

        TelloCommandError when the drone refuses (an error answer and no motor start), when two sends
        show no effect, or when it is not airborne and stable within takeoff_timeout_s (it may still be
        climbing: land() then waits for the climb to end)."""
        cfg = self.cfg
        st, tracker = self._status, self._status.tracker
        if st.phase is FlightPhase.AIRBORNE:
            return
        if st.phase is not FlightPhase.GROUND:
            raise TelloCommandError(f"Tello {cfg.host}: takeoff while {st.phase.value}")
        t0 = time.monotonic()
        deadline = t0 + cfg.takeoff_timeout_s
        with self._exchange.session():
            tracker.hold_takeoff = True
            try:
                st.land_requested = False
                self._send_takeoff()
                sends, replies, ok_at_height, t_probe = 1, [], False, t0
                while True:
                    now = time.monotonic()
                    if (r := self._exchange.next_reply()) is not None:
                        replies.append(r)
                        ok_at_height |= self._ok_at_height(r)
                    with st.lock:
                        ph = tracker.phase
                        stable = st.link_alive() and tracker.airborne_stable(now)
                        if ph is FlightPhase.TAKING_OFF and stable and (ok_at_height or now >= deadline):
                            tracker.confirm_airborne(now)
                            ph = FlightPhase.AIRBORNE
                    if ph is FlightPhase.AIRBORNE:
                        self._report_outcome("takeoff", [r for r in replies if not r.isdigit()], now - t0)
                        st.last_rc_t = st.last_loop_t = now  # the loop watchdog counts from here
                        return
                    if ph is FlightPhase.GROUND:  # no motor start within no_effect_s
                        refused = [r for r in replies if r.lower().startswith(("error", "unknown", "out"))]
                        if refused or sends >= 2:
                            why = f"answered {refused[-1]!r}" if refused else "no effect after 2 sends"
                            raise TelloCommandError(f"Tello {cfg.host}: takeoff refused ({why})")
                        self._events.add("resend", "takeoff: no reply and no motor start")
                        self._send_takeoff()
                        sends += 1
                    if now > deadline:
                        raise TelloCommandError(
                            f"Tello {cfg.host}: not airborne within {cfg.takeoff_timeout_s:.0f} s "
                            f"(phase {ph.value}, replies {replies})"
                        )
                    if stable and now - t_probe > cfg.keepalive_s:  # waiting for the ok: no auto-land
                        assert self._link.chan is not None
                        self._link.chan.send("battery?")
                        t_probe = now
                    time.sleep(0.01)
            finally:
                tracker.hold_takeoff = False

    def _ok_at_height(self, reply: str) -> bool:
        """An `ok` counts as the takeoff's answer only when the drone is at height when it arrives."""
        if reply.lower() != "ok":
            return False
        s = self._status.tracker.latest
        if s is not None and s.h_cm >= self.cfg.phase.airborne_h_cm:
            return True
        self._events.counts["reply_not_trusted"] += 1
        self._events.add("reply_not_trusted", f"'ok' during takeoff at h {s.h_cm if s else '?'} cm")
        return False

    def _send_takeoff(self) -> None:
        assert self._link.chan is not None
        with self._status.lock:
            self._status.tracker.takeoff_sent(time.monotonic())
        self._link.chan.send("takeoff")

    def _report_outcome(self, what: Literal["takeoff", "land"], replies: list[str], elapsed: float) -> None:
        confirmed: TelloKind = "takeoff_confirmed" if what == "takeoff" else "land_confirmed"
        self._events.add(confirmed, f"by telemetry after {elapsed:.2f} s; replies {replies}")
        if not replies:
            self._events.add("reply_lost_confirmed", f"{what!r}: no reply; telemetry shows it done")
        elif all(r.lower() != "ok" for r in replies):
            self._events.add(
                "error_reply_but_effect", f"{what!r} answered {replies}; telemetry shows it done"
            )

    def land(self) -> None:
        """Land; return once telemetry shows the drone down with the motors off (no-op on the ground).

        A drone still taking off is landed as soon as it is airborne. Whatever the replies say, `rc 0 0 0 0`
        + `land` go out again (a lost land leaves a Tello on its last rc): at once when telemetry returns
        after a lost link; every `land_resend_s` while it is silent; and every `land_resend_s` while it
        shows neither a descent nor the ground, from `land_confirm_s` after the first land. A drone that
        lands by itself (phase landing) gets a land only if its descent stops. TelloCommandError after
        land_timeout_s (takeoff_timeout_s more if climbing)."""
        cfg, st = self.cfg, self._status
        tracker = st.tracker
        if st.phase is FlightPhase.GROUND:
            return
        if st.phase is FlightPhase.UNKNOWN:
            raise TelloLinkError(f"Tello {cfg.host}: no telemetry yet; land not sent")
        self._sticks.hover_now()  # a Tello keeps its last rc: stop it before the quiet window and the land
        t0 = time.monotonic()
        with self._exchange.session():
            st.land_requested = True
            climb_end = t0 + cfg.takeoff_timeout_s
            while st.phase is FlightPhase.TAKING_OFF:
                if time.monotonic() > climb_end:
                    raise TelloCommandError(f"Tello {cfg.host}: still taking off; land not sent")
                time.sleep(0.01)
            if st.phase is FlightPhase.GROUND:
                return
            t1 = time.monotonic()
            deadline, replies = t1 + cfg.land_timeout_s, []
            t_sent, wait = t1, cfg.land_confirm_s
            silent = not st.link_alive()
            if st.phase is FlightPhase.AIRBORNE:
                self._send_land(hover_first=silent)
            while True:
                now = time.monotonic()
                if (r := self._exchange.next_reply()) is not None:
                    replies.append(r)
                with st.lock:
                    ph, alive = tracker.phase, st.link_alive()
                    low = tracker.near_ground()
                    settling = low or tracker.descending(now, tracker.th.descent_cm / 2)
                if ph is FlightPhase.GROUND:
                    self._report_outcome("land", replies, now - t1)
                    return
                why = ""
                if not alive:
                    silent = True
                    if now - t_sent > cfg.land_resend_s:
                        why = "telemetry silent"
                elif silent:
                    silent = False
                    if not low:
                        why = "telemetry back after a lost link"
                elif not settling and now - t_sent >= wait:
                    why = f"telemetry shows no descent {now - t_sent:.2f} s after the last land"
                if why:
                    self._events.add("resend", f"land: {why}: rc 0 0 0 0 and land again (replies {replies})")
                    self._send_land(hover_first=True)
                    t_sent, wait = now, cfg.land_resend_s
                if now > deadline:
                    raise TelloCommandError(
                        f"Tello {cfg.host}: not down within {cfg.land_timeout_s:.0f} s "
                        f"(phase {ph.value}, replies {replies})"
                    )
                time.sleep(0.01)

    def _send_land(self, hover_first: bool = False) -> None:
        """`land` (after `rc 0 0 0 0` when asked: with telemetry silent, the hover may not have arrived)."""
        assert self._link.chan is not None
        with self._status.lock:
            self._status.tracker.land_sent(time.monotonic())
        if hover_first:
            self._sticks.hover_unchecked()
        self._link.chan.send("land")
