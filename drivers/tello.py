"""DJI/Ryze Tello driver over djitellopy: implements flightstack.hal.Drone and hal.Camera.

What it does, and its reaction to each failure (also in README.md, "Tello driver"):
- connect(): enters SDK mode and waits for the first state packet, both within `connect_timeout_s`;
  raises TelloLinkError naming the drone's IP when the drone does not answer.
- preflight(): battery ≥ min_battery_pct, highest temperature ≤ max_temperature_c, state stream alive,
  on the ground (height ≤ 0.3 m); returns every check with its value; never raises for a failed check.
- takeoff() / land(): run on the driver's own worker thread with a bounded wait (takeoff_timeout_s,
  land_timeout_s); a failure raises TelloCommandError (land is retried once before that).
- send_body_velocity(V): maps m/s and rad/s to `rc a b c d` integers with the calibrated gains
  (flightstack.tello_rc), clipped to ±100, sent fire-and-forget: the control loop never waits for the
  drone. Non-finite values become 0.
- keep-alive: while flying, if the loop sent nothing for `keepalive_s` (< the Tello's 15 s auto-land),
  the driver sends `rc 0 0 0 0` (hover) and logs `keepalive`.
- link loss: no state packet for `link_timeout_s` → state().link_alive is False and `link_lost` is
  logged (the safety supervisor sees it through state()); `link_restored` when packets return.
- emergency_stop(): `emergency` without waiting for a reply.
Several drones in one process (swarm in station mode): one driver per IP; djitellopy shares its UDP
sockets and tells drones apart by source IP. Each drone streams video to its own `video_port`.

Frames: body velocity V = [v_x, v_y, v_z, ω] in the drone's FLU frame (m/s, rad/s). Time: monotonic
seconds (time.monotonic), the hardware clock of flightstack.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flightstack.hal import DroneState, Frame
from flightstack.tello_rc import RcGains, velocity_to_rc

LOG = logging.getLogger("flightstack.tello")

# One djitellopy.Tello per host for the whole process: a second instance for the same IP would, when the
# first is garbage-collected, delete the shared per-host queues the new one reads (djitellopy __del__).
_TELLOS: dict[str, Any] = {}
_TELLOS_LOCK = threading.Lock()


class TelloLinkError(ConnectionError):
    """The drone does not answer (connect) or its state stream stopped."""


class TelloCommandError(RuntimeError):
    """A blocking command (takeoff, land, streamon, …) failed or timed out."""


@dataclass(frozen=True)
class TelloConfig:
    """One Tello. `host` is its IP (station mode); `control_port` 8889 on a real drone."""

    host: str
    control_port: int = 8889
    video_port: int = 11111
    rc_gains: RcGains = field(default_factory=RcGains)
    connect_timeout_s: float = 5.0
    command_timeout_s: float = 3.0
    takeoff_timeout_s: float = 10.0
    land_timeout_s: float = 8.0
    link_timeout_s: float = 1.0
    keepalive_s: float = 5.0
    min_battery_pct: float = 30.0
    max_temperature_c: float = 85.0
    downward_camera: bool = False

    def __post_init__(self) -> None:
        if not self.keepalive_s < 15.0:
            raise ValueError("keepalive_s must be below the Tello's 15 s auto-land")


@dataclass(frozen=True)
class PreflightCheck:
    name: str
    ok: bool
    detail: str


def _tello_for(host: str) -> Any:
    from djitellopy import Tello  # lazy: the simulator and CI's math tests do not need it

    with _TELLOS_LOCK:
        t = _TELLOS.get(host)
        if t is None:
            t = Tello(host, retry_count=1)
            _TELLOS[host] = t
        return t


class TelloDriver:
    """hal.Drone for one Tello (see the module docstring for behaviour on failure)."""

    def __init__(self, cfg: TelloConfig, tello_factory: Callable[[str], Any] = _tello_for) -> None:
        self.cfg = cfg
        self._factory = tello_factory
        self.tello: Any = None
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"tello-{cfg.host}")
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._monitor: threading.Thread | None = None
        self._last_state_obj: object = None
        self._last_state_t = -math.inf
        self._link_alive = False
        self._last_rc_t = -math.inf
        self._flying = False
        self.last_rc: tuple[int, int, int, int] = (0, 0, 0, 0)
        self.events: list[tuple[float, str, str]] = []
        self.rc_sent = 0

    # ---- helpers ---------------------------------------------------------------------------------
    def _event(self, kind: str, detail: str = "") -> None:
        self.events.append((time.monotonic(), kind, detail))
        LOG.warning("tello %s %s %s", self.cfg.host, kind, detail)

    def _run(self, fn: Callable[[], Any], timeout: float, what: str) -> Any:
        """Run a blocking djitellopy call on the worker thread; TelloCommandError after `timeout` s."""
        fut: Future = self._worker.submit(fn)
        try:
            return fut.result(timeout=timeout)
        except FutureTimeout:
            self._event("command_timeout", what)
            msg = f"Tello {self.cfg.host}: '{what}' got no answer within {timeout:.1f} s"
            raise TelloCommandError(msg) from None
        except Exception as exc:
            self._event("command_failed", f"{what}: {exc}")
            raise TelloCommandError(f"Tello {self.cfg.host}: '{what}' failed: {exc}") from exc

    def _ask(self, command: str, timeout: float) -> str:
        """Send `command` and wait up to `timeout` s (float) for its reply; runs on the worker thread.

        Uses djitellopy's sockets and receiver thread but not its send_command_with_return, whose
        timeout must be an int and which polls at 10 Hz. Stale replies are dropped first: djitellopy
        matches replies by order only, so a late reply would be taken as the answer to this command.
        """
        t = self.tello
        responses = t.get_own_udp_object()["responses"]
        responses.clear()
        t.send_command_without_return(command)
        deadline = time.monotonic() + timeout
        while not responses:
            if time.monotonic() > deadline:
                raise TelloCommandError(f"no reply within {timeout:.1f} s")
            time.sleep(0.005)
        return responses.pop(0).decode("utf-8", errors="replace").strip()

    def _control(self, command: str, timeout: float) -> None:
        """A command that must answer 'ok' (TelloCommandError otherwise)."""

        def call() -> None:
            reply = self._ask(command, timeout)
            if reply.lower() != "ok":
                raise TelloCommandError(f"reply {reply!r}")

        self._run(call, timeout + 0.5, command)

    def _read(self, command: str) -> str:
        """A read command (`battery?`, …): its reply text."""
        return self._run(
            lambda: self._ask(command, self.cfg.command_timeout_s), self.cfg.command_timeout_s + 0.5, command
        )

    # ---- hal.Drone --------------------------------------------------------------------------------
    def connect(self) -> None:
        """SDK mode and the first state packet within connect_timeout_s; TelloLinkError otherwise.

        Idempotent: a driver that is already connected (its monitor running) returns at once, so the
        hardware backend can connect at build time and the runner's connect() costs nothing."""
        if self._monitor is not None and self._monitor.is_alive():
            return
        self.tello = self._factory(self.cfg.host)
        self.tello.address = (self.cfg.host, self.cfg.control_port)
        self.tello.vs_udp_port = self.cfg.video_port
        try:
            self._control("command", self.cfg.connect_timeout_s)
        except TelloCommandError as exc:
            raise TelloLinkError(
                f"Tello at {self.cfg.host}:{self.cfg.control_port} did not answer 'command' within "
                f"{self.cfg.connect_timeout_s:.1f} s (is it on, in station mode, on this network?)"
            ) from exc
        deadline = time.monotonic() + self.cfg.connect_timeout_s
        while not self.tello.get_current_state():
            if time.monotonic() > deadline:
                raise TelloLinkError(
                    f"Tello at {self.cfg.host} answered but sent no state packet within "
                    f"{self.cfg.connect_timeout_s:.1f} s (UDP port 8890 blocked?)"
                )
            time.sleep(0.02)
        self._last_state_obj = self.tello.get_current_state()
        self._last_state_t = time.monotonic()
        self._link_alive = True
        self._stop.clear()
        self._monitor = threading.Thread(
            target=self._monitor_loop, name=f"tello-mon-{self.cfg.host}", daemon=True
        )
        self._monitor.start()

    def preflight(self) -> list[PreflightCheck]:
        """Battery, temperature, state stream and height checks (values from the state stream)."""
        st = self.tello.get_current_state() if self.tello else {}
        checks = []
        bat = st.get("bat")
        checks.append(
            PreflightCheck(
                "battery",
                bat is not None and bat >= self.cfg.min_battery_pct,
                f"{bat} % (min {self.cfg.min_battery_pct:.0f} %)",
            )
        )
        temp = st.get("temph")
        checks.append(
            PreflightCheck(
                "temperature",
                temp is not None and temp <= self.cfg.max_temperature_c,
                f"{temp} °C (max {self.cfg.max_temperature_c:.0f} °C)",
            )
        )
        alive = self.link_alive()
        checks.append(PreflightCheck("state stream", alive, "alive" if alive else "silent"))
        h = st.get("h")
        checks.append(PreflightCheck("on the ground", h is not None and h <= 30, f"height {h} cm"))
        return checks

    def takeoff(self) -> None:
        self._control("takeoff", self.cfg.takeoff_timeout_s)
        self._flying = True
        self._last_rc_t = time.monotonic()

    def land(self) -> None:
        """Land, retried once; TelloCommandError if both attempts fail (the caller may retry)."""
        try:
            self._control("land", self.cfg.land_timeout_s)
        except TelloCommandError:
            self._control("land", self.cfg.land_timeout_s)
        self._flying = False

    def emergency_stop(self) -> None:
        """Motors off at once (`emergency`, no reply awaited)."""
        if self.tello is not None:
            self.tello.send_command_without_return("emergency")
        self._flying = False
        self._event("emergency", "motors off")

    def send_body_velocity(self, V: np.ndarray) -> None:
        rc = velocity_to_rc(V, self.cfg.rc_gains)  # Python ints, clipped, NaN → 0
        self._send_rc(rc)

    def _send_rc(self, rc: tuple[int, int, int, int]) -> None:
        if self.tello is None:
            return
        # djitellopy drops an rc sent within 1 ms of the previous one; send directly instead
        self.tello.send_command_without_return("rc {} {} {} {}".format(*rc))
        with self._lock:
            self.last_rc, self._last_rc_t = rc, time.monotonic()
            self.rc_sent += 1

    def state(self) -> DroneState:
        st = self.tello.get_current_state() if self.tello else {}
        return DroneState(
            battery_pct=float(st.get("bat", 0.0)),
            height_m=float(st.get("h", 0.0)) / 100.0,
            link_alive=self.link_alive(),
            flying=self._flying,
        )

    def link_alive(self) -> bool:
        return self._link_alive and time.monotonic() - self._last_state_t <= self.cfg.link_timeout_s

    def close(self) -> None:
        """Stop the monitor and worker; does NOT land (the supervisor lands before closing)."""
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(timeout=1.0)
        self._worker.shutdown(wait=False, cancel_futures=True)
        if self.tello is not None:
            self.tello.is_flying = False  # djitellopy's end()/__del__ would otherwise send a blocking land
            self.tello.stream_on = False

    # ---- background: state freshness and keep-alive ----------------------------------------------
    def _monitor_loop(self) -> None:
        while not self._stop.wait(0.02):
            now = time.monotonic()
            st = self.tello.get_current_state()
            if st is not self._last_state_obj:  # djitellopy stores a new dict per packet
                self._last_state_obj = st
                self._last_state_t = now
                if not self._link_alive:
                    self._link_alive = True
                    self._event("link_restored")
            elif self._link_alive and now - self._last_state_t > self.cfg.link_timeout_s:
                self._link_alive = False
                self._event("link_lost", f"no state packet for {now - self._last_state_t:.2f} s")
            if self._flying and now - self._last_rc_t > self.cfg.keepalive_s:
                self._send_rc((0, 0, 0, 0))
                self._event("keepalive", "hover rc sent: the control loop was silent")


class TelloCamera:
    """hal.Camera over the Tello's video stream (forward, or downward on the EDU with `downvision 1`).

    Frames are RGB uint8 (djitellopy decodes with PyAV); each distinct decoded frame is stamped with the
    monotonic time at which this driver first saw it.
    """

    def __init__(self, driver: TelloDriver, frame_timeout_s: float = 10.0) -> None:
        self.driver = driver
        self.frame_timeout_s = frame_timeout_s
        self._reader: Any = None
        self._last: object = None
        self._placeholder: object = None
        self._stamp = -math.inf
        self.frames_seen = 0

    def start(self) -> None:
        d = self.driver
        if d.cfg.video_port != 11111:  # swarm: each drone streams to its own port
            d._control(f"port 8890 {d.cfg.video_port}", d.cfg.command_timeout_s)
        if d.cfg.downward_camera:
            d._control("downvision 1", d.cfg.command_timeout_s)
        d._control("streamon", d.cfg.command_timeout_s)
        self._reader = d._run(d.tello.get_frame_read, self.frame_timeout_s, "open video stream")
        # djitellopy starts with a black 400x300 placeholder until the first frame is decoded: not a frame
        self._placeholder = self._reader.frame

    def latest(self) -> Frame | None:
        if self._reader is None:
            return None
        img = self._reader.frame
        if img is None or img is self._placeholder:
            return None
        if img is not self._last:
            self._last = img
            self._stamp = time.monotonic()
            self.frames_seen += 1
        return Frame(self._stamp, img, None)

    def stop(self, streamoff_timeout_s: float = 1.0) -> None:
        """Stop decoding and ask the drone to stop streaming (`streamoff`, bounded, failure ignored: the
        stream is only a load on the link, and a drone that cannot answer is handled elsewhere)."""
        if self._reader is not None:
            self._reader.stop()
            self._reader = None
            # djitellopy caches its reader per Tello object (one per host, for the whole process):
            # forget it, or the next start() gets this stopped reader bound to the old video port
            if self.driver.tello is not None:
                self.driver.tello.background_frame_read = None
            with contextlib.suppress(TelloCommandError):
                self.driver._control("streamoff", streamoff_timeout_s)
