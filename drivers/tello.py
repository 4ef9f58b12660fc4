"""DJI/Ryze Tello driver: implements flightstack.hal.Drone; the drone's own telemetry decides its phase.

Written against the Tello SDK 2.0 and 3.0 user guides (Tello EDU firmware 02.05.01.x with SDK 3.0;
SDK 2.0 firmware lacks `port`, `downvision` and the other SDK-3.0-only commands). Transport:
drivers/tello_link.py (own command socket per drone, shared state-port receiver); phase: drivers/
tello_phase.py; video: drivers/tello_camera.py (own UDP receiver and PyAV decoder).

The driver class is built in layers, one job each: drivers/tello_core.py (settings, locks, events, the
telemetry view), drivers/tello_exchange.py (the blocking command exchange), drivers/tello_sticks.py
(`rc`, hover, `emergency`), drivers/tello_flight.py (takeoff and land), drivers/tello_watchdog.py (link
freshness and the loop watchdog); this module adds `connect`, `close` and `preflight` and is the import
path for all of it (settings, errors and reply parsers: drivers/tello_config.py).

Principles (telemetry decides, replies are advisory, nothing the drone would reject in its phase, never
blocking the control loop, the loop watchdog, re-sent lands on silent telemetry, link loss), the phase
rules and the reaction to each failure: docs/drivers.md, "Tello driver" (why: docs/architecture.md
decision 26).

Frames: body velocity V = [v_x, v_y, v_z, ω] in the drone's FLU frame (m/s, rad/s). Time: monotonic
seconds (time.monotonic), the hardware clock of flightstack.
"""

from __future__ import annotations

import math
import threading
import time

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
from flightstack.drivers.tello_core import LOG as LOG
from flightstack.drivers.tello_exchange import RC_REPLIES as RC_REPLIES
from flightstack.drivers.tello_link import CommandChannel, StateReceiver
from flightstack.drivers.tello_watchdog import TelloWatchdog

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


class TelloDriver(TelloWatchdog):
    """hal.Drone for one Tello (see the module docstring for the behaviour on every failure)."""

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
