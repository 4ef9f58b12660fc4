"""The Tello driver's takeoff and land, confirmed by telemetry (replies are advisory).

`takeoff()` returns once the drone answered `ok` while its telemetry made that plausible (climbed, motors
running, off the ground), or by telemetry alone at `takeoff_timeout_s` (s) once the climb is over; `land()`
sends `land` at once, whatever the phase, and returns once telemetry shows the drone down with the motors off,
re-sending `rc 0 0 0 0` + `land` when telemetry returns after a lost link, every `land_resend_s` (s) while it
is silent, and when it proves the drone holding its height `land_confirm_s` after the last land. Heights in cm
as sent by the drone. Each holds the command exchange (drivers/tello/exchange.py) for its whole length; the
rules on every failure: drivers/tello/driver.py.
"""

from __future__ import annotations

import time
from typing import Literal

from flightstack.drivers.tello.config import TelloCommandError, TelloConfig, TelloLinkError
from flightstack.drivers.tello.exchange import CommandExchange
from flightstack.drivers.tello.link import TelloLink
from flightstack.drivers.tello.replies import is_command_answer
from flightstack.drivers.tello.status import DriverEvents, DriverStatus
from flightstack.drivers.tello.sticks import Sticks
from flightstack.events import TelloKind
from flightstack.hal import FlightPhase

OK_GRACE_S = 3.0
"""How long (s) an `ok` to takeoff waits for telemetry to make it plausible: telemetry lags a reply on a
lossy stream, and an `ok` can come before the climb shows (an emulator's fast takeoff answers at 0.3 s;
the recorded climb reached 50 cm 1.5 s after the command). 3 s is `no_effect_s`: a takeoff that shows no
climb by then did nothing."""


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

        Done = the drone answered `ok` while its telemetry made that answer plausible (the takeoff has
        climbed to `airborne_h_cm` by h or tof, the motors run, it is not near the ground: an `ok` at the
        ground is someone else's, not trusted). A real Tello climbs in ~3 s, then holds for seconds more
        before its `ok` (8.7 s after the command in a recorded flight) and ignores rc until then; its h
        drifts meanwhile (70 → 40 cm at 1 m up), so no single height decides. If the `ok` is lost,
        telemetry alone decides at takeoff_timeout_s (20 s) once the climb is over, while `battery?` probes
        (answered in every phase) keep the drone from its 15 s auto-land.

        TelloCommandError when the drone refuses (an error answer and no motor start), when two sends
        show no effect, when it is not airborne within takeoff_timeout_s (land() then lands it whatever
        it is doing), or when land() is called meanwhile (the takeoff is abandoned for the land)."""
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
                sends, replies, answered, t_probe = 1, [], False, t0
                ok_t: float | None = None  # an `ok` telemetry has not yet made plausible (s)
                while True:
                    now = time.monotonic()
                    if (r := self._exchange.next_answer("takeoff", is_command_answer)) is not None:
                        replies.append(r)  # not a keep-alive's, nor a late one to an earlier request
                        if r.lower() == "ok":
                            ok_t = now
                    if ok_t is not None and not answered:
                        answered, ok_t = self._takeoff_answer(ok_t, now)
                    with st.lock:
                        ph = tracker.phase
                        alive = st.link_alive()
                        over = alive and tracker.climb_over(now)
                        if (
                            ph is FlightPhase.TAKING_OFF
                            and alive
                            and (answered or (over and now >= deadline))
                        ):
                            tracker.confirm_airborne(now)
                            ph = FlightPhase.AIRBORNE
                        abandoned = st.land_requested
                    if ph is FlightPhase.AIRBORNE:
                        self._report_outcome("takeoff", replies, now - t0)
                        st.last_rc_t = st.last_loop_t = now  # the loop watchdog counts from here
                        return
                    if abandoned:
                        raise TelloCommandError(f"Tello {cfg.host}: takeoff abandoned: land requested")
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
                    if over and now - t_probe > cfg.keepalive_s:  # waiting for the ok: no auto-land
                        assert self._link.chan is not None
                        self._link.chan.send("battery?")
                        t_probe = now
                    time.sleep(0.01)
            finally:
                tracker.hold_takeoff = False

    def _takeoff_answer(self, ok_t: float, now: float) -> tuple[bool, float | None]:
        """Is the `ok` received at `ok_t` the takeoff's answer? (answered, the ok still pending or None).

        Yes once telemetry makes it plausible (PhaseTracker.takeoff_answer_plausible); telemetry may lag
        the reply on a lossy stream, so the ok waits up to `ok_grace_s` for it, then is not trusted."""
        with self._status.lock:
            tracker = self._status.tracker
            if tracker.takeoff_answer_plausible(now):
                return True, None
            if now - ok_t < OK_GRACE_S:
                return False, ok_t
            s = tracker.latest
            seen = "no telemetry" if s is None else f"h {s.h_cm:.0f} cm, tof {s.tof_cm:.0f} cm"
            climbed = "climbed" if tracker.climbed() else "not climbed"
            motors = "motors running" if tracker.motors_running(now) else "motors off"
        self._events.counts["reply_not_trusted"] += 1
        why = f"'ok' during takeoff, {OK_GRACE_S:g} s later still at {seen} ({climbed}, {motors})"
        self._events.add("reply_not_trusted", why)
        return False, None

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
        """Land; return once telemetry shows the drone down with the motors off (no-op on the ground with
        the motors off).

        `land` goes out at once, whatever phase the driver believes (a takeoff under way is abandoned for it),
        after `rc 0 0 0 0` (a Tello keeps its last rc) unless the drone is still taking off; not while the
        drone lands by itself (PhaseTracker.self_landing: it refuses rc and land, and near touchdown the land
        would reach a drone whose motors have stopped), unless that landing stops or holds its height. A drone
        busy in its takeoff refuses it and gets the land again the moment an `ok` comes (its takeoff's). It is
        sent again, with `rc 0 0 0 0` first: at once when telemetry returns after a lost link; every
        `land_resend_s` while telemetry is silent; and, from `land_confirm_s` after the last land, whenever
        telemetry proves the drone holding its height (phase.PhaseTracker.holding_after_land): a lossy stream,
        a slow start of the descent or a drift of h is no reason to send it again (a Tello busy landing
        answers `error`). TelloCommandError after land_timeout_s."""
        cfg, st = self.cfg, self._status
        tracker = st.tracker
        with st.lock:
            if st.phase is FlightPhase.GROUND and not tracker.motors_running(time.monotonic()):
                return
            if st.phase is FlightPhase.UNKNOWN:
                raise TelloLinkError(f"Tello {cfg.host}: no telemetry yet; land not sent")
            st.land_requested = True  # a takeoff() under way gives the exchange up for this land
            in_takeoff = st.phase is FlightPhase.TAKING_OFF  # the drone may refuse the land until its `ok`
            # landing by itself, it ignores rc and refuses land, and near touchdown a land reaches a drone
            # whose motors have stopped: none is sent unless telemetry shows it holding its height
            own = st.phase is FlightPhase.LANDING and tracker.self_landing
        if not own:
            self._sticks.hover_now()  # a Tello keeps its last rc: stop it before the quiet window, the land
        with self._exchange.session():
            st.land_requested = True
            t1 = time.monotonic()
            deadline, replies = t1 + cfg.land_timeout_s, []
            silent = not st.link_alive()
            if own:
                self._events.add("resend", "land: not sent: the drone is landing by itself")
            else:  # with telemetry, hover_now went out above when it was flying
                self._send_land(hover_first=silent)
            t_sent = t1
            while True:
                now = time.monotonic()
                why = ""
                if (r := self._exchange.next_reply()) is not None:
                    replies.append(r)
                    # a drone busy in its takeoff refuses the land (its `error Not joystick` reads as an
                    # answer to rc); its takeoff's `ok` says it takes one now. An `ok` that was the land's
                    # own costs one more land, which a landing Tello refuses.
                    if in_takeoff and r.lower() == "ok":
                        in_takeoff = False
                        why = "an ok while it was taking off: its takeoff ended"
                with st.lock:
                    ph, alive = tracker.phase, st.link_alive()
                    low = tracker.near_ground()
                    holding = tracker.holding_after_land(now)
                    flies_on = own and ph is FlightPhase.AIRBORNE  # its descent was no landing after all
                if ph is FlightPhase.GROUND and own:  # no land went out: it landed by itself
                    self._events.add(
                        "land_confirmed", f"by telemetry after {now - t1:.2f} s: it landed by itself"
                    )
                    return
                if ph is FlightPhase.GROUND:
                    self._report_outcome("land", replies, now - t1)
                    return
                if flies_on:
                    own, why = False, "the drone's own landing stopped: it flies on"
                why = why or self._land_lost(now - t_sent, alive, silent, low, holding)
                silent = not alive
                if why:  # no rc to a drone still in its takeoff: it ignores rc, and its sticks are centred
                    hover = "" if in_takeoff else "rc 0 0 0 0 and "
                    self._events.add("resend", f"land: {why}: {hover}land again (replies {replies})")
                    self._send_land(hover_first=not in_takeoff)
                    own = False
                    t_sent = now
                if now > deadline:
                    raise TelloCommandError(
                        f"Tello {cfg.host}: not down within {cfg.land_timeout_s:.0f} s "
                        f"(phase {ph.value}, replies {replies})"
                    )
                time.sleep(0.01)

    def _land_lost(self, since_s: float, alive: bool, silent: bool, low: bool, holding: bool) -> str:
        """Why the last land (sent `since_s` s ago) may be lost ("" if no reason): telemetry silent for
        `land_resend_s`, back after a lost link (the drone not near the ground), or proving the drone
        holding its height `land_confirm_s` after it."""
        cfg = self.cfg
        if not alive:
            if since_s <= cfg.land_resend_s:
                return ""
            with self._status.lock:
                return f"telemetry silent{self._status.health.rejected_note()}"
        if silent:
            return "" if low else "telemetry back after a lost link"
        if holding and since_s >= cfg.land_confirm_s:
            return f"telemetry shows the drone holding its height {since_s:.2f} s after the land"
        return ""

    def _send_land(self, hover_first: bool = False) -> None:
        """`land` (after `rc 0 0 0 0` when asked: with telemetry silent, the hover may not have arrived)."""
        assert self._link.chan is not None
        with self._status.lock:
            self._status.tracker.land_sent(time.monotonic())
        if hover_first:
            self._sticks.hover_unchecked()
        self._link.chan.send("land")
