"""DJI/Ryze Tello driver: implements flightstack.hal.Drone; the drone's own telemetry decides its phase.

Written against the Tello SDK 2.0 and 3.0 user guides (Tello EDU firmware 02.05.01.x with SDK 3.0;
SDK 2.0 firmware lacks `port`, `downvision` and the other SDK-3.0-only commands). Transport:
drivers/tello_link.py (own command socket per drone, shared state-port receiver); phase: drivers/
tello_phase.py; video: drivers/tello_camera.py (own UDP receiver and PyAV decoder).

Principles (README "Tello driver", docs/architecture.md decision 26):
- **Telemetry decides.** The state stream gives the phase (ground, taking off, airborne, landing).
  `takeoff()` returns only when telemetry shows the drone airborne at a stable height (within
  `takeoff_timeout_s` ≥ 20 s, what djitellopy allows); `land()` returns only when telemetry shows it on
  the ground with the motors off. A lost reply whose effect telemetry confirms is a success (event
  `reply_lost_confirmed`); an `error` reply while telemetry shows the command took effect likewise
  (`error_reply_but_effect`); an `ok` that telemetry does not confirm is not trusted.
- **Replies are advisory.** They carry no identifier. Before every blocking command the driver stops
  sending `rc`, waits for a quiet window (`quiet_s`, 150 ms, since the last rc sent and the last datagram
  received) and discards what is pending; replies arriving while no command waits are discarded and
  counted (`counts["reply_discarded"]`); `error Not joystick` (the answer some firmwares give to `rc`) is
  never taken as another command's answer.
- **Nothing the drone would reject in its phase**: no `rc` unless airborne (and no land pending), no
  keep-alive after `land` was sent or once down, no `land` while taking off (land waits until airborne,
  bounded), `emergency` only when asked for. Suppressed commands are counted (`counts["rc_suppressed"]`).
- **Never blocks the control loop**: send_body_velocity is a non-blocking datagram; takeoff/land block
  only their caller (flightstack.safety runs them on worker threads).
- **Loop watchdog** (the keep-alive is tied to the control loop): while airborne, a loop that sent no
  velocity for `loop_hover_s` (0.5 s) gets `rc 0 0 0 0` once (hover; event `loop_silent_hover`) and after
  `loop_land_s` (2 s) the driver lands by itself on its own thread (event `loop_lost_land`). A loop must
  therefore command every tick (flightstack.safety's command watchdog sends zeros on a silent tick);
  nothing keeps a drone hovering with no loop behind it.
- **Silent telemetry during a land**: `rc 0 0 0 0` and `land` are re-sent every `land_resend_s` (0.5 s)
  until the drone is seen down (the uplink may work while the state stream does not).
- link loss: no state packet for `link_timeout_s` → state().link_alive is False (`link_lost`,
  `link_restored` events). The monitor thread survives any error (counted, logged).

Frames: body velocity V = [v_x, v_y, v_z, ω] in the drone's FLU frame (m/s, rad/s). Time: monotonic
seconds (time.monotonic), the hardware clock of flightstack.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable

import numpy as np

from flightstack.drivers.tello_config import (
    DEFAULT_VIDEO_PORT,
    PreflightCheck,
    TelloCommandError,
    TelloConfig,
    TelloLinkError,
    parse_int_reply,
    parse_sdk,
    parse_serial,
)
from flightstack.drivers.tello_link import CommandChannel, ErrorLog, StateReceiver
from flightstack.drivers.tello_phase import PhaseTracker
from flightstack.drivers.tello_rc import velocity_to_rc
from flightstack.drivers.tello_state import TelloTelemetry
from flightstack.hal import DroneState, FlightPhase

__all__ = [
    "DEFAULT_VIDEO_PORT",
    "PreflightCheck",
    "TelloCommandError",
    "TelloConfig",
    "TelloDriver",
    "TelloLinkError",
    "parse_int_reply",
    "parse_sdk",
    "parse_serial",
]

LOG = logging.getLogger("flightstack.tello")
RC_REPLIES = ("error not joystick",)  # firmware answers to rc, never another command's answer


class TelloDriver:
    """hal.Drone for one Tello (see the module docstring for the behaviour on every failure)."""

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
        self.events: list[tuple[float, str, str]] = []
        self.counts: Counter[str] = Counter()
        self.rc_sent = 0
        self._muted: Callable[[], bool] | None = None
        self._errors = ErrorLog(self.counts, f"tello {cfg.host} monitor", LOG)
        self.sdk_version: str | None = None
        self.serial: str | None = None

    # ---- events, state ---------------------------------------------------------------------------
    def _event(self, kind: str, detail: str = "") -> None:
        self.events.append((time.monotonic(), kind, detail))
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

    # ---- the command exchange ----------------------------------------------------------------------
    def _begin_exchange(self) -> None:
        """Stop rc, wait for the quiet window, discard what is pending. Caller holds _cmd_lock."""
        assert self._chan is not None
        with self._lock:
            self._busy = True
        deadline = time.monotonic() + 4 * self.cfg.quiet_s
        while time.monotonic() < deadline:
            last = max(self._last_rc_t, self._chan.last_rx_t)
            if time.monotonic() - last >= self.cfg.quiet_s:
                break
            time.sleep(0.01)
        n = self._chan.open_exchange()
        if n:
            self._event("replies_discarded", f"{n} pending before a command")

    def _end_exchange(self) -> None:
        if self._chan is not None:
            self._chan.close_exchange()
        with self._lock:
            self._busy = False

    def _next_reply(self) -> str | None:
        """The next reply of the open exchange that is not a firmware's answer to rc."""
        assert self._chan is not None
        while (item := self._chan.pop_reply()) is not None:
            if item[1].lower() in RC_REPLIES:
                self.counts["rc_reply_ignored"] += 1
                continue
            return item[1]
        return None

    def _request(self, command: str, timeout: float, accept: Callable[[str], bool]) -> str | None:
        """Send `command`; the first reply `accept`s within `timeout` s (others are counted), or None."""
        with self._cmd_lock:
            self._begin_exchange()
            try:
                assert self._chan is not None
                self._chan.send(command)
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline:
                    r = self._next_reply()
                    if r is None:
                        time.sleep(0.005)
                    elif accept(r):
                        return r
                    else:
                        self.counts["reply_rejected"] += 1
                        self._event("reply_rejected", f"{command!r} got {r!r}")
                return None
            finally:
                self._end_exchange()

    def _control(self, command: str, timeout: float, attempts: int = 2) -> None:
        """A command with no telemetry effect (`streamon`, `port`, …): an `ok` within `timeout` s, retried
        once when no answer came; TelloCommandError on an error answer or silence."""
        for _ in range(attempts):
            reply = self._request(command, timeout, accept=lambda r: True)
            if reply is None:
                continue
            if reply.lower() == "ok":
                return
            raise TelloCommandError(f"Tello {self.cfg.host}: {command!r} answered {reply!r}")
        raise TelloCommandError(f"Tello {self.cfg.host}: {command!r} got no answer ({attempts} tries)")

    def query(self, command: str, parse: Callable[[str], str | None], attempts: int = 2) -> str | None:
        """A read command (`sdk?`, `sn?`, `wifi?`): the first reply `parse` accepts, or None."""
        for _ in range(attempts):
            r = self._request(command, self.cfg.command_timeout_s, lambda x: parse(x) is not None)
            if r is not None:
                return parse(r)
        return None

    # ---- hal.Drone ----------------------------------------------------------------------------------
    def connect(self) -> None:
        """SDK mode, confirmed by the state stream, within connect_timeout_s; then `sdk?` and `sn?`.

        Idempotent (a connected driver returns at once). TelloLinkError names the drone's address."""
        if self._monitor is not None and self._monitor.is_alive():
            return
        cfg = self.cfg
        try:
            self._rx = StateReceiver.acquire(cfg.host, self._on_state, cfg.state_port, cfg.bind_ip)
            self._chan = CommandChannel(cfg.host, cfg.control_port, cfg.bind_ip, muted=self.is_muted)
        except OSError as exc:
            self.close()
            raise TelloLinkError(f"Tello at {cfg.host}: {exc}") from exc
        deadline = time.monotonic() + cfg.connect_timeout_s
        answered = False
        while time.monotonic() < deadline and self._last_state_t == -math.inf:
            wait = max(0.05, min(1.0, deadline - time.monotonic()))
            answered |= self._request("command", wait, lambda r: r.lower() == "ok") is not None
            t_state = time.monotonic() + (0.5 if answered else 0.0)
            while self._last_state_t == -math.inf and time.monotonic() < min(t_state, deadline):
                time.sleep(0.01)
        if self._last_state_t == -math.inf:
            self.close()
            if answered:
                raise TelloLinkError(
                    f"Tello at {cfg.host} answered but sent no state packet within "
                    f"{cfg.connect_timeout_s:.1f} s (UDP port {cfg.state_port} blocked?)"
                )
            raise TelloLinkError(
                f"Tello at {cfg.host}:{cfg.control_port} did not answer 'command' within "
                f"{cfg.connect_timeout_s:.1f} s (is it on, and is this computer on its network?)"
            )
        if not answered:
            self._event("reply_lost_confirmed", "'command': SDK mode confirmed by the state stream")
        self._link_alive = True
        self.sdk_version = self.query("sdk?", parse_sdk)
        self.serial = self.query("sn?", parse_serial)
        self._stop.clear()
        self._monitor = threading.Thread(target=self._monitor_loop, name=f"tello-mon-{cfg.host}", daemon=True)
        self._monitor.start()

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
        if self.phase is FlightPhase.AIRBORNE:
            return
        if self.phase is not FlightPhase.GROUND:
            raise TelloCommandError(f"Tello {cfg.host}: takeoff while {self.phase.value}")
        t0 = time.monotonic()
        deadline = t0 + cfg.takeoff_timeout_s
        with self._cmd_lock:
            self._begin_exchange()
            self._tracker.hold_takeoff = True
            try:
                self._land_requested = False
                self._send_takeoff()
                sends, replies, ok_at_height, t_probe = 1, [], False, t0
                while True:
                    now = time.monotonic()
                    if (r := self._next_reply()) is not None:
                        replies.append(r)
                        ok_at_height |= self._ok_at_height(r)
                    with self._lock:
                        ph = self._tracker.phase
                        stable = self.link_alive() and self._tracker.airborne_stable(now)
                        if ph is FlightPhase.TAKING_OFF and stable and (ok_at_height or now >= deadline):
                            self._tracker.confirm_airborne(now)
                            ph = FlightPhase.AIRBORNE
                    if ph is FlightPhase.AIRBORNE:
                        self._report_outcome("takeoff", [r for r in replies if not r.isdigit()], now - t0)
                        self._last_rc_t = self._last_loop_t = now  # the loop watchdog counts from here
                        return
                    if ph is FlightPhase.GROUND:  # no motor start within no_effect_s
                        refused = [r for r in replies if r.lower().startswith(("error", "unknown", "out"))]
                        if refused or sends >= 2:
                            why = f"answered {refused[-1]!r}" if refused else "no effect after 2 sends"
                            raise TelloCommandError(f"Tello {cfg.host}: takeoff refused ({why})")
                        self._event("resend", "takeoff: no reply and no motor start")
                        self._send_takeoff()
                        sends += 1
                    if now > deadline:
                        raise TelloCommandError(
                            f"Tello {cfg.host}: not airborne within {cfg.takeoff_timeout_s:.0f} s "
                            f"(phase {ph.value}, replies {replies})"
                        )
                    if stable and now - t_probe > cfg.keepalive_s:  # waiting for the ok: no auto-land
                        assert self._chan is not None
                        self._chan.send("battery?")
                        t_probe = now
                    time.sleep(0.01)
            finally:
                self._tracker.hold_takeoff = False
                self._end_exchange()

    def _ok_at_height(self, reply: str) -> bool:
        """An `ok` counts as the takeoff's answer only when the drone is at height when it arrives."""
        if reply.lower() != "ok":
            return False
        s = self._tracker.latest
        if s is not None and s.h_cm >= self.cfg.phase.airborne_h_cm:
            return True
        self.counts["reply_not_trusted"] += 1
        self._event("reply_not_trusted", f"'ok' during takeoff at h {s.h_cm if s else '?'} cm")
        return False

    def _send_takeoff(self) -> None:
        assert self._chan is not None
        with self._lock:
            self._tracker.takeoff_sent(time.monotonic())
        self._chan.send("takeoff")

    def _report_outcome(self, what: str, replies: list[str], elapsed: float) -> None:
        self._event(f"{what}_confirmed", f"by telemetry after {elapsed:.2f} s; replies {replies}")
        if not replies:
            self._event("reply_lost_confirmed", f"{what!r}: no reply; telemetry shows it done")
        elif all(r.lower() != "ok" for r in replies):
            self._event("error_reply_but_effect", f"{what!r} answered {replies}; telemetry shows it done")

    def land(self) -> None:
        """Land; return once telemetry shows the drone down with the motors off (no-op on the ground).

        A drone still taking off is landed as soon as it is airborne. `land` is re-sent when telemetry
        shows no descent; TelloCommandError after land_timeout_s (takeoff_timeout_s more if climbing)."""
        cfg = self.cfg
        if self.phase is FlightPhase.GROUND:
            return
        if self.phase is FlightPhase.UNKNOWN:
            raise TelloLinkError(f"Tello {cfg.host}: no telemetry yet; land not sent")
        self._hover_now()  # a Tello keeps its last rc: stop it before the quiet window and the land
        t0 = time.monotonic()
        with self._cmd_lock:
            self._begin_exchange()
            try:
                self._land_requested = True
                climb_end = t0 + cfg.takeoff_timeout_s
                while self.phase is FlightPhase.TAKING_OFF:
                    if time.monotonic() > climb_end:
                        raise TelloCommandError(f"Tello {cfg.host}: still taking off; land not sent")
                    time.sleep(0.01)
                if self.phase is FlightPhase.GROUND:
                    return
                t1 = time.monotonic()
                deadline, replies = t1 + cfg.land_timeout_s, []
                t_sent = t1
                if self.phase is FlightPhase.AIRBORNE:
                    self._send_land()
                while True:
                    now = time.monotonic()
                    if (r := self._next_reply()) is not None:
                        replies.append(r)
                    ph = self.phase
                    if ph is FlightPhase.GROUND:
                        self._report_outcome("land", replies, now - t1)
                        return
                    if ph is FlightPhase.AIRBORNE:  # no descent within no_effect_s: lost or refused
                        self._event("resend", f"land: no descent (replies {replies})")
                        self._send_land()
                        t_sent = now
                    elif not self.link_alive() and now - t_sent > cfg.land_resend_s:
                        self._event("resend", "land: telemetry silent; rc 0 0 0 0 and land again")
                        self._send_land(hover_first=True)
                        t_sent = now
                    if now > deadline:
                        raise TelloCommandError(
                            f"Tello {cfg.host}: not down within {cfg.land_timeout_s:.0f} s "
                            f"(phase {ph.value}, replies {replies})"
                        )
                    time.sleep(0.01)
            finally:
                self._end_exchange()

    def _hover_now(self) -> None:
        """`rc 0 0 0 0` if airborne, even with a land pending (a lost land must not leave it moving)."""
        with self._lock:
            if self._chan is None or self._tracker.phase is not FlightPhase.AIRBORNE:
                return
            self._last_rc_t = time.monotonic()
            if self._chan.send("rc 0 0 0 0"):
                self.last_rc = (0, 0, 0, 0)
                self.rc_sent += 1

    def _send_land(self, hover_first: bool = False) -> None:
        """`land` (after `rc 0 0 0 0` when asked: with telemetry silent, the hover may not have arrived)."""
        assert self._chan is not None
        with self._lock:
            self._tracker.land_sent(time.monotonic())
        if hover_first and self._chan.send("rc 0 0 0 0"):
            self.last_rc = (0, 0, 0, 0)
            self.rc_sent += 1
        self._chan.send("land")

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

    def _send_rc(self, rc: tuple[int, int, int, int], why: str = "") -> None:
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

    def close(self) -> None:
        """Stop the monitor and the sockets; does NOT land (the supervisor lands before closing)."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(timeout=1.0)
        if self._rx is not None:
            self._rx.release(self.cfg.host)
            self._rx = None
        if self._chan is not None:
            self._chan.close()

    # ---- preflight --------------------------------------------------------------------------------
    def preflight(self) -> list[PreflightCheck]:
        """Battery, temperature, state stream, on the ground, SDK version and serial, Wi-Fi signal."""
        from flightstack.drivers.tello_preflight import tello_preflight

        return tello_preflight(self)

    # ---- background: state freshness and the loop watchdog ------------------------------------------
    def set_muted(self, muted: Callable[[], bool] | None) -> None:
        """After `muted()` returns True nothing more is sent to the drone (a guardian process took it over:
        drivers/guardian.py); checked right before every datagram, from every thread."""
        self._muted = muted

    def is_muted(self) -> bool:
        m = self._muted
        return m is not None and m()

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
