"""DJI/Ryze Tello driver: implements flightstack.hal.Drone; the drone's own telemetry decides its phase.

Written against the Tello SDK 2.0 and 3.0 user guides (Tello EDU firmware 02.05.01.x with SDK 3.0;
SDK 2.0 firmware lacks `port`, `downvision` and the other SDK-3.0-only commands). Video: drivers/
tello_camera.py (own UDP receiver and PyAV decoder).

`TelloDriver` owns its parts, each given only what it uses: `link` (drivers/tello/link.py: own command
socket, place on the shared state port), `status` and its events (drivers/tello/status.py: telemetry,
phase from drivers/tello/phase.py, the flags that decide what may be sent), `exchange` (drivers/
tello_exchange.py: blocking command and reply), `sticks` (drivers/tello/sticks.py: `rc`, hover,
`emergency`), `flight` (drivers/tello/flight.py: takeoff and land), `rejoin` (drivers/tello/rejoin.py:
`command` again while the state stream is silent) and `watchdog` (drivers/tello/watchdog.py: link
freshness, loop watchdog). This module wires them, adds `connect` (with the lab file's SDK 3.0 video
settings: drivers/tello/video_settings.py), `close` and `preflight`, and is the import path (settings,
errors and reply parsers: drivers/tello/config.py).

Principles (telemetry decides, replies are advisory, nothing the drone would reject in its phase, never
blocking the control loop, the loop watchdog, lands re-sent until telemetry shows the descent, link loss
and a rebooted drone, a drone landing by itself; an implausible state value used as sent and flagged, a run
of rejected state lines an event: drivers/tello/stream_health.py), the phase
rules and the reaction to each failure: docs/drivers.md, "Tello driver" (why: docs/architecture.md
decision 26).

Frames: body velocity V = [v_x, v_y, v_z, ω] in the drone's FLU frame (m/s, rad/s). Time: monotonic
seconds (time.monotonic), the hardware clock of flightstack.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable

import numpy as np

from flightstack.drivers.tello.config import (
    DEFAULT_VIDEO_PORT,
    TELLO_OWN_TIMEOUT_S,
    PreflightCheck,
    TelloCommandError,
    TelloConfig,
    TelloLinkError,
    parse_int_reply,
    parse_sdk,
    parse_serial,
)
from flightstack.drivers.tello.exchange import CommandExchange
from flightstack.drivers.tello.flight import FlightPhases
from flightstack.drivers.tello.link import TelloLink, is_notice
from flightstack.drivers.tello.preflight import tello_preflight
from flightstack.drivers.tello.rejoin import SdkRejoin
from flightstack.drivers.tello.status import DriverEvents, DriverStatus
from flightstack.drivers.tello.sticks import Sticks
from flightstack.drivers.tello.traffic import TrafficWriter
from flightstack.drivers.tello.video_settings import SettingOutcome, send_video_settings
from flightstack.drivers.tello.watchdog import Watchdog
from flightstack.events import Event
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


class TelloDriver:
    """hal.Drone for one Tello (see the module docstring for the behaviour on every failure).

    `events` (source tello, time.monotonic() s) and `counts` are the driver's log; `sdk_version`,
    `serial` and `video_outcomes` (the SDK 3.0 video settings' answers) are read by `connect`. `traffic`
    (optional): where the link and the camera record the drone's raw traffic (drivers/tello/traffic.py;
    the caller closes it after `close()`)."""

    def __init__(self, cfg: TelloConfig, traffic: TrafficWriter | None = None) -> None:
        self.cfg = cfg
        self.traffic = traffic
        self._log = DriverEvents(cfg.host)
        self.events: list[Event] = self._log.events
        self.counts: Counter[str] = self._log.counts
        self.link = TelloLink(cfg.host, cfg.control_port, cfg.state_port, cfg.bind_ip, traffic, cfg.interface)
        self.status = DriverStatus(cfg.phase, cfg.link_timeout_s, self._log)
        self.exchange = CommandExchange(cfg, self.link, self.status, self._log)
        self.sticks = Sticks(cfg.rc_gains, self.link, self.status, self._log)
        self.flight = FlightPhases(cfg, self.link, self.status, self._log, self.exchange, self.sticks)
        self.rejoin = SdkRejoin(cfg.rejoin_s, self.link, self._log)
        self.watchdog = Watchdog(cfg, self.status, self._log, self.sticks, self.rejoin, land=self.land)
        self.sdk_version: str | None = None
        self.serial: str | None = None
        self.video_outcomes: tuple[SettingOutcome, ...] = ()

    # ---- hal.Drone ----------------------------------------------------------------------------------
    def connect(self) -> None:
        """SDK mode, confirmed by the state stream, within connect_timeout_s; then `sdk?`, `sn?` and the
        SDK 3.0 video settings (drivers/tello/video_settings.py: their answers in `video_outcomes`).

        Idempotent (a connected driver returns at once). TelloLinkError names the drone's address."""
        if self.watchdog.running():
            return
        cfg, st = self.cfg, self.status
        try:
            self.link.open(st.observe, st.reject, self._on_drone_error)
        except OSError as exc:
            self.close()
            raise TelloLinkError(f"Tello at {cfg.host}: {exc}") from exc
        deadline = time.monotonic() + cfg.connect_timeout_s
        answered = False
        while time.monotonic() < deadline and st.last_state_t == -math.inf:
            wait = max(0.05, min(1.0, deadline - time.monotonic()))
            answered |= self.exchange.request("command", wait, lambda r: r.lower() == "ok") is not None
            t_state = time.monotonic() + (0.5 if answered else 0.0)
            while st.last_state_t == -math.inf and time.monotonic() < min(t_state, deadline):
                time.sleep(0.01)
        if st.last_state_t == -math.inf:
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
            self._log.add("reply_lost_confirmed", "'command': SDK mode confirmed by the state stream")
        st.link_up = True
        self.sdk_version = self.query("sdk?", parse_sdk)
        self.serial = self.query("sn?", parse_serial)
        self.video_outcomes = send_video_settings(cfg, self.sdk_version, self.exchange, self._log)
        self._await_phase()
        self.watchdog.start()

    def _on_drone_error(self, t: float, text: str) -> None:
        """An `error …` that answers no command (link.CommandChannel.on_error, on its reader thread): an event
        naming it. `error Auto land` means the drone lands by itself: phase `landing` first (no rc goes out
        from then on: sticks.Sticks), then the event."""
        if not is_notice(text):
            self._log.add("error_unanswered", f"{text!r} answers no command")
            return
        with self.status.lock:
            before = self.status.tracker.phase
            self.status.tracker.landing_by_itself(t)
            after = self.status.tracker.phase
        moved = f" ({before.value} -> {after.value})" if after is not before else ""
        self._log.add("error_unanswered", f"{text!r}: the drone lands by itself{moved}")

    def _await_phase(self) -> None:
        """Wait (at most motor_quiet_s and a little) for telemetry to tell ground from air: a drone at rest
        where `tof` reads above the ground threshold is on the ground once its motor time has held still
        that long (drivers/tello/phase.py). Returns with the phase still UNKNOWN when it did not (a
        takeoff() then refuses, a land() goes out)."""
        st = self.status
        deadline = time.monotonic() + st.tracker.th.motor_quiet_s + 0.5
        while st.phase is FlightPhase.UNKNOWN and time.monotonic() < deadline:
            time.sleep(0.02)

    def close(self) -> None:
        """Stop the monitor and the sockets; does NOT land (the supervisor lands before closing)."""
        self.watchdog.stop()
        self.link.close()

    def takeoff(self) -> None:
        """Take off and return once airborne and done (drivers/tello/flight.py)."""
        self.flight.takeoff()

    def land(self) -> None:
        """Land and return once down with the motors off (drivers/tello/flight.py)."""
        self.flight.land()

    def send_body_velocity(self, V: np.ndarray) -> None:
        """V = [v_x, v_y, v_z, ω] (m/s, rad/s, FLU body) as `rc`; never blocks (drivers/tello/sticks.py)."""
        self.sticks.send_body_velocity(V)

    def send_rc(self, rc: tuple[int, int, int, int]) -> None:
        """Raw stick values (-100..100) as the control loop; for system identification."""
        self.sticks.send_rc(rc)

    def emergency_stop(self) -> None:
        """Motors off at once (`emergency`)."""
        self.sticks.emergency_stop()

    @property
    def phase(self) -> FlightPhase:
        return self.status.phase

    def current_state(self) -> dict[str, float]:
        """The fields of the latest valid state packet (a new dict per packet)."""
        return self.status.fields

    def link_alive(self) -> bool:
        return self.status.link_alive()

    @property
    def own_timeout_s(self) -> float:
        """How long the Tello flies its last `rc` on by itself (s; hal.HoldsLastCommand)."""
        return TELLO_OWN_TIMEOUT_S

    def state(self) -> DroneState:
        st, ph = self.status.fields, self.phase
        return DroneState(
            battery_pct=float(st.get("bat", 0.0)),
            height_m=float(st.get("h", 0.0)) / 100.0,
            link_alive=self.link_alive(),
            flying=ph is FlightPhase.AIRBORNE,
            phase=ph.value,
        )

    @property
    def last_rc(self) -> tuple[int, int, int, int]:
        """The last stick values sent."""
        return self.sticks.last_rc

    @property
    def rc_sent(self) -> int:
        return self.sticks.sent

    # ---- commands, mute -----------------------------------------------------------------------------
    def query(self, command: str, parse: Callable[[str], str | None], attempts: int = 2) -> str | None:
        """A read command (`sdk?`, `sn?`, `wifi?`): the first reply `parse` accepts, or None."""
        return self.exchange.query(command, parse, attempts)

    def control(self, command: str, timeout: float, attempts: int = 2) -> None:
        """A command answered `ok` (`streamon`, `port`, …) within `timeout` s; TelloCommandError if not."""
        self.exchange.control(command, timeout, attempts)

    def set_muted(self, muted: Callable[[], bool] | None) -> None:
        """After `muted()` returns True nothing more is sent to the drone (a guardian process took it over:
        drivers/guardian/launcher.py); checked right before every datagram, from every thread."""
        self.link.set_muted(muted)

    def is_muted(self) -> bool:
        return self.link.is_muted()

    # ---- preflight --------------------------------------------------------------------------------
    def preflight(self) -> list[PreflightCheck]:
        """Battery, temperature, state stream, on the ground, SDK version and serial, Wi-Fi signal."""
        return tello_preflight(self)
