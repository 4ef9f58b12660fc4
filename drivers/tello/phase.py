"""What a Tello is doing, decided from its own state stream (pure: no sockets, threads or clocks).

Tello replies carry no identifier and get lost, duplicated and delayed, so a reply never decides the flight
phase; telemetry does. The driver tells the tracker what it sent (`takeoff_sent`, `land_sent`,
`emergency_sent`) and feeds it every state packet (`observe`); the tracker moves between the phases of
`flightstack.hal.FlightPhase` only when the telemetry shows it.

Signals (units as the drone sends them, see drivers/tello/state.py; every threshold's source: docs/drivers.md,
"What a real Tello sends"):
- **motors running**: the motor-on time `time` (whole seconds) changed less than `motor_quiet_s` ago. It
  rises by one every second while the motors turn, so 1.5 s without a change means the motors are off.
  **Motors off** needs that much telemetry: `motor_quiet_s` of samples (since the first, or since a
  takeoff was sent) without a change. A Tello cannot fly with its motors off, so *on the ground* is decided
  by the motors alone: whatever is under the drone. A height cannot decide it: a real Tello resting on a
  raised surface (a box, a carpet, a landing pad) reads `tof` 31 cm, not its floor value 10, and `h` is
  relative to the takeoff point and drifts.
- **height evidence**: `h` (relative to the takeoff point, in 10 cm steps, and drifting: a real Tello's
  read 40 cm while it hovered ~1 m up) and the floor height from `tof` (the downward sensor: `tof` minus
  its ground reading `tof_floor_cm`; it measures the surface below, so a table or an edge changes it;
  6553 = out of range, not used). A sample is **near the ground** when the floor height (h when tof is out
  of range) is at most `ground_h_cm`; the takeoff **has climbed** once h or the floor height reached
  `airborne_h_cm` since the takeoff began.
- **descending**: the latest h is more than `descent_cm` (10 cm) below the highest of the last
  `descent_window_s` (0.5 s). **Its own landing**: over the last `self_land_s` (1 s, at least
  `descent_samples` samples) every sample moving down at `descent_vgz_dm_s` (3 dm/s) or more by `vgz`
  (positive DOWN on a real Tello) and h fallen by more than `descent_cm` — not one step of the readout, a
  hover's drift (|vgz| ≤ 2 dm/s in the recording), an object passed over, or an ordinary descent: over
  real flights the descents the driver did not command lasted 0.1–0.8 s and then flew on (users' flight
  logs), while a Tello's own landing goes on to the ground (the recorded land: 2.1 s from the descent's
  start to touchdown). With the battery at or below `low_battery_pct` (15 %), where a Tello lands by
  itself, the descent has a reason and the quick rule holds: h fallen by more than `descent_cm` within
  `descent_window_s` and the last `descent_samples` samples moving down that fast. A landing shorter than
  that (from below ~0.5 m) is seen when the motors stop.
- **descent commanded**: the last `rc` the driver sent had a negative throttle, or one with a negative
  throttle went out within `uncommanded_after_s` (1 s: the drone's velocity lags the stick).
- **climb over**: over the last `stable_window_s` (1 s, ≥ 3 samples) the takeoff has climbed, no sample is
  near the ground or climbing (vgz < −`stable_vgz_dm_s`, i.e. up faster than 1 dm/s), and the
  least-squares slope of h is at most `stable_slope_cm_s` (3 cm/s) upwards (a drone still climbing, even
  slowly at 7 cm/s, is in its takeoff; h drifting down is not a climb).
- **holding after a land**: over the last `stuck_window_s` (1 s) at least `stuck_samples` (5) samples, the
  motors running, none near the ground, none moving up or down at `descent_vgz_dm_s` or more by vgz, neither
  h nor the floor height fallen or risen by more than `descent_cm`: the only evidence on which a land is
  sent again while the state stream is alive (a lossy stream proves nothing either way).

Transitions (every one is returned as an event text by `observe`):
- UNKNOWN → GROUND at the first sample near the ground, or once the motors are off; → AIRBORNE once the
  motors run (the motor time changed) away from the ground. A drone at rest where `tof` reads above the
  ground threshold stays UNKNOWN for `motor_quiet_s` (the driver's connect waits for it).
- GROUND → TAKING_OFF when takeoff was sent, or when the motors run and h rises (not commanded by us).
- TAKING_OFF → AIRBORNE when the climb is over (while the driver holds a takeoff, only when it confirms:
  see `hold_takeoff`); → GROUND when, `no_effect_s` after the takeoff was sent, the motors are off (the
  takeoff was refused or never arrived).
- AIRBORNE or TAKING_OFF → LANDING when land was sent; AIRBORNE → LANDING on its own landing with no
  descent commanded (`self_landing`: the drone's low-battery landing or 15 s auto-land, during which a
  Tello ignores rc), or at once when the drone says so (`error Auto land`: `landing_by_itself`);
  → GROUND when the motors are off (someone else's land).
- LANDING → GROUND when the motors are off; → AIRBORNE when, `no_effect_s` after the land
  was sent, the motors run and h has not dropped by `descent_cm` (the land was lost or refused); a
  landing of its own → AIRBORNE when h holds still above the ground for `descent_window_s` with the
  motors running (it was no landing).
- any → GROUND at once after `emergency` (motors stop; the drone drops).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from flightstack.drivers.tello.state import TelloTelemetry
from flightstack.hal import FlightPhase


@dataclass(frozen=True)
class PhaseThresholds:
    """Thresholds of the phase decisions (cm, dm/s, s); docs/drivers.md explains the choices."""

    ground_h_cm: float = 20.0
    airborne_h_cm: float = 50.0
    tof_floor_cm: float = 10.0
    tof_out_of_range_cm: float = 6553.0
    stable_window_s: float = 1.0
    stable_range_cm: float = 10.0
    stable_slope_cm_s: float = 3.0
    stable_vgz_dm_s: float = 1.0
    motor_quiet_s: float = 1.5
    no_effect_s: float = 3.0
    descent_cm: float = 10.0
    descent_window_s: float = 0.5
    descent_samples: int = 3
    descent_vgz_dm_s: float = 3.0
    self_land_s: float = 1.0
    low_battery_pct: float = 15.0
    stuck_window_s: float = 1.0
    stuck_samples: int = 5
    uncommanded_after_s: float = 1.0


class PhaseTracker:
    """The flight phase of one Tello from its telemetry; not thread-safe (the driver holds a lock)."""

    def __init__(self, thresholds: PhaseThresholds | None = None) -> None:
        self.th = thresholds or PhaseThresholds()
        self.phase = FlightPhase.UNKNOWN
        self.latest: TelloTelemetry | None = None
        self._window: deque[TelloTelemetry] = deque()
        self._motor_value: float | None = None
        self._motor_changed_t = -float("inf")
        self._first_t: float | None = None  # the first sample's time: motors off needs telemetry
        self._takeoff_sent_t: float | None = None
        self._climb_peak_cm = -float("inf")  # highest height evidence since the takeoff began
        self._land_sent_t: float | None = None
        self._land_h0 = 0.0
        self._min_h_since_land = float("inf")
        self.phase_since = -float("inf")
        self._last_throttle = 0
        self._down_cmd_t = -float("inf")
        self.self_landing = False
        """True from a descent the driver did not command until the drone is down or flies on."""
        self.hold_takeoff = False
        """Set by the driver while takeoff() waits for the drone's own `ok`: telemetry cannot tell a Tello
        still stabilising in its takeoff (it ignores rc) from one done, so TAKING_OFF → AIRBORNE then
        waits for `confirm_airborne`."""

    # ---- what the driver sent ------------------------------------------------------------------------
    def takeoff_sent(self, t: float) -> None:
        self._takeoff_sent_t = t
        self._last_throttle = 0  # a Tello takes off with its sticks centred
        # its motors may run from now on, before `time` first rises (+1.05 s in the recorded flight):
        # "motors off" needs motor_quiet_s without a change from here
        self._motor_changed_t = max(self._motor_changed_t, t)
        if self.phase is FlightPhase.GROUND:
            self._set(FlightPhase.TAKING_OFF, t)
            self._climb_peak_cm = -float("inf")

    def land_sent(self, t: float) -> None:
        self._land_sent_t = t
        self._land_h0 = self.latest.h_cm if self.latest is not None else 0.0
        self._min_h_since_land = self._land_h0
        if self.phase in (FlightPhase.AIRBORNE, FlightPhase.TAKING_OFF):
            self._set(FlightPhase.LANDING, t)

    def rc_sent(self, t: float, throttle: int) -> None:
        """An `rc` went out at `t` with this throttle (-100..100; negative: down)."""
        if throttle < 0 or self._last_throttle < 0:  # a descent was commanded until now
            self._down_cmd_t = t
        self._last_throttle = throttle

    def emergency_sent(self, t: float) -> None:
        self._set(FlightPhase.GROUND, t)

    def landing_by_itself(self, t: float) -> None:
        """The drone lands of its own accord (its descent, its `error Auto land`): LANDING, self_landing."""
        if self.phase in (FlightPhase.AIRBORNE, FlightPhase.TAKING_OFF):
            self.self_landing = True
            self._land_sent_t = None
            self._set(FlightPhase.LANDING, t)

    def confirm_airborne(self, t: float) -> None:
        """The driver's decision that a held takeoff is over (see `hold_takeoff`)."""
        if self.phase is FlightPhase.TAKING_OFF:
            self._set(FlightPhase.AIRBORNE, t)

    # ---- signals -------------------------------------------------------------------------------------
    def motors_running(self, t: float) -> bool:
        return t - self._motor_changed_t < self.th.motor_quiet_s

    def motors_off(self, t: float) -> bool:
        """The motor time has not changed over `motor_quiet_s` of telemetry (since the first sample, the
        last change or a takeoff sent): the motors are off, so the drone is on the ground."""
        return (
            self._first_t is not None
            and t - max(self._motor_changed_t, self._first_t) >= self.th.motor_quiet_s
        )

    def floor_cm(self, s: TelloTelemetry) -> float | None:
        """Height above the surface below from `tof` (cm), None when out of range."""
        if s.tof_cm >= self.th.tof_out_of_range_cm:
            return None
        return s.tof_cm - self.th.tof_floor_cm

    def height_evidence_cm(self, s: TelloTelemetry) -> float:
        """The higher of h and the floor height (cm): h drifts, tof under-reads over objects."""
        floor = self.floor_cm(s)
        return s.h_cm if floor is None else max(s.h_cm, floor)

    def low(self, s: TelloTelemetry) -> bool:
        """This sample is near the ground: the floor height (h when tof is out of range) at most
        `ground_h_cm`. tof first: h drifts by a metre in a flight, tof reads its ground value at rest."""
        floor = self.floor_cm(s)
        return (s.h_cm if floor is None else floor) <= self.th.ground_h_cm

    def down(self, t: float) -> bool:
        """On the ground: the motors off (`motors_off`), whatever the height reads."""
        return self.latest is not None and self.motors_off(t)

    def near_ground(self) -> bool:
        """The latest sample is near the ground (motors on or off)."""
        s = self.latest
        return s is not None and self.low(s)

    def climbed(self) -> bool:
        """The takeoff under way has reached `airborne_h_cm` by h or by the floor height."""
        return self._climb_peak_cm >= self.th.airborne_h_cm

    def descending(self, t: float, drop_cm: float | None = None) -> bool:
        """h fell by more than `drop_cm` (default `descent_cm`) within the last `descent_window_s` before
        `t`."""
        w = [s.h_cm for s in self._window if s.t >= t - self.th.descent_window_s]
        drop = self.th.descent_cm if drop_cm is None else drop_cm
        return len(w) >= 2 and max(w) - w[-1] > drop

    def own_landing(self, t: float) -> bool:
        """A descent that has lasted `self_land_s`, every sample of it moving down at `descent_vgz_dm_s` or
        more; with the battery at or below `low_battery_pct`, `descending` with the last `descent_samples`
        samples moving down that fast (module docstring)."""
        th = self.th
        latest = self.latest
        if latest is not None and latest.bat_pct <= th.low_battery_pct:
            tail = [s for s in self._window if s.t >= t - th.descent_window_s][-max(2, th.descent_samples) :]
            return (
                self.descending(t)
                and len(tail) >= max(2, th.descent_samples)
                and all(s.vgz_dm_s >= th.descent_vgz_dm_s for s in tail)
            )
        w = [s for s in self._window if s.t >= t - th.self_land_s]
        if len(w) < max(2, th.descent_samples) or w[-1].t - w[0].t < 0.8 * th.self_land_s:
            return False
        hs = [s.h_cm for s in w]
        return max(hs) - hs[-1] > th.descent_cm and all(s.vgz_dm_s >= th.descent_vgz_dm_s for s in w)

    def descent_commanded(self, t: float) -> bool:
        return self._last_throttle < 0 or t - self._down_cmd_t <= self.th.uncommanded_after_s

    def holding_height(self, t: float, since: float = -float("inf")) -> bool:
        """h still (within `stable_range_cm`, vgz below `descent_vgz_dm_s`) above the ground over
        `descent_window_s` of samples taken at or after `since` (s), motors running."""
        th = self.th
        w = [s for s in self._window if s.t >= max(t - th.descent_window_s, since)]
        if len(w) < 3 or w[-1].t - w[0].t < 0.8 * th.descent_window_s:
            return False
        hs = [s.h_cm for s in w]
        still = all(abs(s.vgz_dm_s) < th.descent_vgz_dm_s for s in w)  # h moves in 10 cm steps: vgz too
        return (
            still
            and min(hs) > th.ground_h_cm
            and max(hs) - min(hs) <= th.stable_range_cm
            and self.motors_running(t)
        )

    def climb_over(self, t: float) -> bool:
        """The takeoff has climbed and, over the last `stable_window_s`, neither climbs nor is near the
        ground (see the module docstring)."""
        th = self.th
        w = [s for s in self._window if s.t >= t - th.stable_window_s]
        if not self.climbed() or len(w) < 3 or w[-1].t - w[0].t < 0.8 * th.stable_window_s:
            return False
        hs = [s.h_cm for s in w]
        ts = [s.t for s in w]
        tm, hm = sum(ts) / len(ts), sum(hs) / len(hs)
        slope = sum((a - tm) * (b - hm) for a, b in zip(ts, hs, strict=True)) / sum((a - tm) ** 2 for a in ts)
        return (
            slope <= th.stable_slope_cm_s
            and not any(self.low(s) for s in w)
            and all(s.vgz_dm_s >= -th.stable_vgz_dm_s for s in w)
        )

    def takeoff_answer_plausible(self, t: float) -> bool:
        """An `ok` now can be the takeoff's: the takeoff has climbed, the motors run, the drone is not near
        the ground (an `ok` at the ground is someone else's)."""
        s = self.latest
        return (
            self.phase is FlightPhase.TAKING_OFF
            and self.climbed()
            and self.motors_running(t)
            and s is not None
            and not self.low(s)
        )

    def holding_after_land(self, t: float) -> bool:
        """Telemetry proves the drone holding its height (see the module docstring): the one reason to send
        a land again while the state stream is alive."""
        th = self.th
        w = [s for s in self._window if s.t >= t - th.stuck_window_s]
        if len(w) < th.stuck_samples or w[-1].t - w[0].t < 0.6 * th.stuck_window_s:
            return False
        if not self.motors_running(t) or any(
            self.low(s) or abs(s.vgz_dm_s) >= th.descent_vgz_dm_s for s in w
        ):
            return False
        for series in ([s.h_cm for s in w], [f for s in w if (f := self.floor_cm(s)) is not None]):
            if len(series) >= 2 and max(series[-1] - min(series), max(series) - series[-1]) > th.descent_cm:
                return False  # falling, or still climbing (a land during the takeoff waits for its end)
        return True

    # ---- telemetry -----------------------------------------------------------------------------------
    def observe(self, s: TelloTelemetry) -> list[str]:
        """Take one state sample; return the transitions it caused, as event texts."""
        t = s.t
        if self._motor_value is not None and s.motor_s != self._motor_value:
            self._motor_changed_t = t
        self._motor_value = s.motor_s
        self._first_t = t if self._first_t is None else self._first_t
        self.latest = s
        self._window.append(s)
        while self._window and self._window[0].t < t - 2.0 * self.th.stable_window_s:
            self._window.popleft()
        self._min_h_since_land = min(self._min_h_since_land, s.h_cm)
        if self.phase is FlightPhase.TAKING_OFF:
            self._climb_peak_cm = max(self._climb_peak_cm, self.height_evidence_cm(s))
        before = self.phase
        self._step(t, s)
        if self.phase is before:
            return []
        why = ", a descent not commanded: its own landing" if self.self_landing else ""
        seen = f"h {s.h_cm:.0f} cm, motor time {s.motor_s:.0f} s{why}"
        return [f"{before.value} -> {self.phase.value} ({seen})"]

    def _step(self, t: float, s: TelloTelemetry) -> None:
        th, P = self.th, FlightPhase
        if self.phase is P.UNKNOWN:
            if self.low(s) or self.motors_off(t):
                self._set(P.GROUND, t)
            elif self.motors_running(t):
                self._set(P.AIRBORNE, t)
        elif self.phase is P.GROUND:
            if not self.low(s) and self.motors_running(t):
                self._set(P.TAKING_OFF, t)
                self._climb_peak_cm = self.height_evidence_cm(s)
        elif self.phase is P.TAKING_OFF:
            if self.climb_over(t) and not self.hold_takeoff:
                self._set(P.AIRBORNE, t)
            elif (
                self._takeoff_sent_t is not None
                and t - self._takeoff_sent_t > th.no_effect_s
                and self.motors_off(t)
            ):
                self._set(P.GROUND, t)
        elif self.phase is P.AIRBORNE:
            if self.down(t):
                self._set(P.GROUND, t)
            elif self.own_landing(t) and not self.descent_commanded(t):
                self.landing_by_itself(t)
        elif self.phase is P.LANDING:
            if self.down(t):
                self._set(P.GROUND, t)
            elif (
                self.self_landing and self._land_sent_t is None and self.holding_height(t, self.phase_since)
            ) or (
                self._land_sent_t is not None
                and t - self._land_sent_t > th.no_effect_s
                and self.motors_running(t)
                and self._min_h_since_land > self._land_h0 - th.descent_cm
            ):
                self._set(P.AIRBORNE, t)

    def _set(self, phase: FlightPhase, t: float) -> None:
        if phase is not self.phase:
            if phase is not FlightPhase.LANDING:
                self.self_landing = False
            self.phase = phase
            self.phase_since = t
