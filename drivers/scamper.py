"""Scamper ground-robot driver over MAVLink (ArduPilot Rover conventions), implementing `hal.GroundRobot`.

Scamper's own interface is not public, so the robot is driven like an ArduPilot Rover:

* ``connect()`` opens the pymavlink connection (``ScamperConfig.url``), starts one I/O thread that sends a
  GCS HEARTBEAT at 1 Hz and receives everything, waits for the robot's HEARTBEAT, switches to GUIDED
  (custom mode 15, ``COMMAND_LONG MAV_CMD_DO_SET_MODE``) and arms (``MAV_CMD_COMPONENT_ARM_DISARM``); both
  commands must be answered by ``COMMAND_ACK`` with ``MAV_RESULT_ACCEPTED``.
* ``send_body_velocity(V)`` only stores the set-point; the I/O thread re-sends it at ``stream_hz``
  (ArduPilot Rover stops after ~3 s without one) as ``SET_POSITION_TARGET_LOCAL_NED`` in
  ``MAV_FRAME_BODY_NED`` with ``type_mask`` 1511 (only vx, vy and yaw_rate used).

Frames and units: ``V = [v_x, v_y, v_z, ω]`` is a body velocity in the flightstack body frame FLU
(x forward, y left, z up; m/s, and ω in rad/s counter-clockwise seen from above).  MAVLink's body NED/FRD
frame has y to the RIGHT and yaw rate positive clockwise, so the driver sends
``vx = v_x, vy = -v_y, yaw_rate = -ω``; ``v_z`` is ignored (ground robot).

Caveat (ArduPilot behaviour, not verified on hardware): a non-omni ArduPilot rover cannot move sideways;
it derives speed/heading from (vx, vy), so ``v_y`` is only meaningful for an omni/holonomic Scamper.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink import mavutil

mavlink = mavutil.mavlink

ROVER_GUIDED_MODE = 15
# Ignore x, y, z (1, 2, 4), vz (32), afx/afy/afz (64, 128, 256), yaw (1024); use vx, vy, yaw_rate.
TYPE_MASK_VEL_YAWRATE = 1511
GCS_HEARTBEAT_PERIOD_S = 1.0


class ScamperError(RuntimeError):
    """Base class of Scamper driver errors."""


class ScamperLinkError(ScamperError):
    """No (or no more) HEARTBEAT from the robot."""


class ScamperCommandError(ScamperError):
    """A COMMAND_LONG was not acknowledged with MAV_RESULT_ACCEPTED (or not at all)."""


@dataclass(frozen=True)
class ScamperConfig:
    """Connection and timing parameters (all times in seconds, rates in Hz)."""

    url: str = "udpout:127.0.0.1:14550"  # pymavlink connection string of the robot
    heartbeat_timeout_s: float = 5.0  # connect(): max wait for the robot's first HEARTBEAT
    ack_timeout_s: float = 2.0  # max wait for each COMMAND_ACK
    stream_hz: float = 10.0  # set-point re-send rate (>= 1 Hz needed; Rover stops after 3 s)
    link_timeout_s: float = 3.0  # no HEARTBEAT for this long -> link lost
    source_system: int = 255  # our MAVLink system id (GCS convention)
    source_component: int = 190  # MAV_COMP_ID_MISSIONPLANNER

    def __post_init__(self) -> None:
        for name in ("heartbeat_timeout_s", "ack_timeout_s", "stream_hz", "link_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"ScamperConfig.{name} must be finite and > 0, got {value}")
        if self.stream_hz < 1.0:
            raise ValueError(f"ScamperConfig.stream_hz must be >= 1 Hz, got {self.stream_hz}")


class ScamperDriver:
    """MAVLink driver of the Scamper ground robot; implements `flightstack.hal.GroundRobot`.

    ``events`` is a list of ``(t, kind, detail)`` with ``t`` from ``time.monotonic()`` (s) and ``kind`` one
    of ``connected``, ``link_lost``, ``link_restored``, ``disarm_failed``.
    """

    def __init__(self, config: ScamperConfig | None = None) -> None:
        self.config = config or ScamperConfig()
        self.events: list[tuple[float, str, str]] = []
        self._conn: Any = None
        self._lock = threading.Lock()  # guards set-point, acks, link state, events
        self._send_lock = threading.Lock()  # serialises writes on the pymavlink connection
        self._ack_cv = threading.Condition(self._lock)
        self._acks: dict[int, int] = {}  # command id -> latest MAV_RESULT
        self._setpoint = np.zeros(3)  # NED body: vx (m/s), vy right (m/s), yaw_rate clockwise (rad/s)
        self._streaming = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self._last_hb: float | None = None
        self._link_alive = False
        self._target = (1, 1)
        self._armed = False

    # ------------------------------------------------------------------ public API
    def connect(self) -> None:
        """Connect, wait for HEARTBEAT, set GUIDED and arm; raises ScamperLinkError / ScamperCommandError.

        Blocks at most ``heartbeat_timeout_s + 2 * ack_timeout_s``; on failure everything is closed again.
        """
        cfg = self.config
        if self._thread is not None:
            raise ScamperError("ScamperDriver.connect() called twice")
        self._conn = mavutil.mavlink_connection(
            cfg.url, source_system=cfg.source_system, source_component=cfg.source_component
        )
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="scamper-io", daemon=True)
        self._thread.start()
        try:
            deadline = time.monotonic() + cfg.heartbeat_timeout_s
            with self._lock:
                while self._last_hb is None:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0.0:
                        raise ScamperLinkError(
                            f"no HEARTBEAT from Scamper at {cfg.url!r} within {cfg.heartbeat_timeout_s:g} s"
                        )
                    self._ack_cv.wait(timeout=min(remaining, 0.05))
            self._command(
                mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ROVER_GUIDED_MODE
            )
            self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        except BaseException:
            self._shutdown()
            raise
        with self._lock:
            self._armed = True
            self._setpoint = np.zeros(3)
            self._streaming = True
            self._event("connected", f"{cfg.url} sys={self._target[0]} comp={self._target[1]}")

    def send_body_velocity(self, V: np.ndarray) -> None:
        """Store V = [v_x, v_y, v_z, ω] (body FLU; m/s, rad/s ccw) as set-point; never blocks on I/O.

        v_z is ignored.  Any non-finite component makes the whole set-point zero (stop).
        """
        v = np.asarray(V, dtype=float).reshape(-1)
        if v.size != 4:
            raise ValueError(f"body velocity must have 4 components [v_x, v_y, v_z, ω], got shape {v.shape}")
        ned = np.array([v[0], -v[1], -v[3]]) if np.all(np.isfinite(v)) else np.zeros(3)
        with self._lock:
            self._setpoint = ned
        self._wake()

    def stop(self) -> None:
        """Zero the set-point; the zero is sent immediately (if connected) and then streamed."""
        with self._lock:
            self._setpoint = np.zeros(3)
        self._wake()

    def link_alive(self) -> bool:
        """True while the robot's HEARTBEAT has been seen within ``link_timeout_s``."""
        with self._lock:
            return self._link_alive

    @property
    def setpoint_ned(self) -> np.ndarray:
        """The set-point being streamed: [vx fwd m/s, vy right m/s, yaw rate clockwise rad/s] (body NED)."""
        with self._lock:
            return self._setpoint.copy()

    def close(self) -> None:
        """Zero the set-point, disarm (bounded by ack_timeout_s), stop the I/O thread, close. Idempotent."""
        if self._thread is None:
            return
        self.stop()
        if self._armed:
            with self._lock:
                self._streaming = False
            self._send_setpoint(np.zeros(3))
            try:
                self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
                self._armed = False
            except ScamperError as exc:
                with self._lock:
                    self._event("disarm_failed", str(exc))
        self._shutdown()

    def __enter__(self) -> ScamperDriver:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _event(self, kind: str, detail: str) -> None:
        """Append an event; caller holds the lock."""
        self.events.append((time.monotonic(), kind, detail))

    def _wake(self) -> None:
        """Send the current set-point now (from the caller's thread, non-blocking UDP write)."""
        with self._lock:
            streaming, sp = self._streaming, self._setpoint.copy()
        if streaming:
            self._send_setpoint(sp)

    def _shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
        with self._lock:
            self._streaming = False
            self._link_alive = False
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.close()
            self._conn = None

    def _send(self, fn: str, *args: Any) -> None:
        conn = self._conn
        if conn is None:
            return
        with self._send_lock, contextlib.suppress(OSError):
            getattr(conn.mav, fn)(*args)

    def _send_setpoint(self, sp: np.ndarray) -> None:
        t_ms = int((time.monotonic() - self._t0) * 1000.0) & 0xFFFFFFFF
        sysid, compid = self._target
        vx, vy, r = (float(x) for x in sp)
        self._send(
            "set_position_target_local_ned_send",
            t_ms, sysid, compid, mavlink.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE,
            0.0, 0.0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, 0.0, r,
        )  # fmt: skip

    def _command(self, command: int, p1: float = 0.0, p2: float = 0.0) -> None:
        """COMMAND_LONG and wait up to ack_timeout_s for an ACCEPTED COMMAND_ACK (re-sent once halfway)."""
        timeout = self.config.ack_timeout_s
        with self._lock:
            self._acks.pop(command, None)
        sysid, compid = self._target
        deadline = time.monotonic() + timeout
        resend_at = time.monotonic() + timeout / 2.0
        confirmation = 0
        self._send("command_long_send", sysid, compid, command, confirmation, p1, p2, 0.0, 0.0, 0.0, 0.0, 0.0)
        with self._lock:
            while command not in self._acks:
                now = time.monotonic()
                if now >= deadline:
                    raise ScamperCommandError(
                        f"no COMMAND_ACK for command {command} from {self.config.url!r} within {timeout:g} s"
                    )
                if confirmation == 0 and now >= resend_at:
                    confirmation = 1
                    self._lock.release()
                    try:
                        self._send(
                            "command_long_send", sysid, compid, command, confirmation, p1, p2, 0, 0, 0, 0, 0
                        )
                    finally:
                        self._lock.acquire()
                    continue
                self._ack_cv.wait(timeout=min(deadline, resend_at if confirmation == 0 else deadline) - now)
            result = self._acks.pop(command)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            name = (
                mavlink.enums["MAV_RESULT"][result].name if result in mavlink.enums["MAV_RESULT"] else result
            )
            raise ScamperCommandError(f"command {command} (p1={p1:g}, p2={p2:g}) rejected by Scamper: {name}")

    def _run(self) -> None:
        """I/O thread: GCS heartbeat at 1 Hz, set-point at stream_hz, receive, link supervision."""
        cfg = self.config
        period = 1.0 / cfg.stream_hz
        next_hb = next_sp = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + GCS_HEARTBEAT_PERIOD_S
                self._send(
                    "heartbeat_send",
                    mavlink.MAV_TYPE_GCS,
                    mavlink.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    mavlink.MAV_STATE_ACTIVE,
                )
            if now >= next_sp:
                next_sp = now + period
                with self._lock:
                    streaming, sp = self._streaming, self._setpoint.copy()
                if streaming:
                    self._send_setpoint(sp)
            try:
                msg = self._conn.recv_match(blocking=True, timeout=min(0.02, max(0.0, next_sp - now)))
            except (OSError, ValueError):
                msg = None
                if self._stop.wait(0.02):
                    break
            now = time.monotonic()
            with self._lock:
                if msg is not None:
                    self._handle(msg, now)
                if (
                    self._link_alive
                    and self._last_hb is not None
                    and now - self._last_hb > cfg.link_timeout_s
                ):
                    self._link_alive = False
                    self._event("link_lost", f"no HEARTBEAT from {cfg.url} for {now - self._last_hb:.1f} s")

    def _handle(self, msg: Any, now: float) -> None:
        """Process one received message; caller holds the lock."""
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                return
            if self._last_hb is None:
                self._target = (msg.get_srcSystem(), msg.get_srcComponent())
            self._last_hb = now
            if not self._link_alive:
                self._link_alive = True
                if self._streaming:
                    self._event("link_restored", f"HEARTBEAT from {self.config.url} again")
            self._ack_cv.notify_all()
        elif mtype == "COMMAND_ACK":
            self._acks[int(msg.command)] = int(msg.result)
            self._ack_cv.notify_all()


@dataclass(frozen=True)
class HeartbeatProbe:
    """What one HEARTBEAT of the robot said (for `flightstack preflight`); mode is Rover's custom mode."""

    mav_type: int
    custom_mode: int
    armed: bool


def probe_heartbeat(config: ScamperConfig) -> HeartbeatProbe:
    """Wait up to heartbeat_timeout_s for the robot's HEARTBEAT without changing its mode or arming it.

    Sends GCS heartbeats meanwhile (a `udpin` vehicle only learns our address from what we send).
    Raises ScamperLinkError when nothing arrives in time.
    """
    conn = mavutil.mavlink_connection(
        config.url, source_system=config.source_system, source_component=config.source_component
    )
    try:
        deadline = time.monotonic() + config.heartbeat_timeout_s
        next_hb = 0.0
        while True:
            now = time.monotonic()
            if now >= deadline:
                raise ScamperLinkError(
                    f"no HEARTBEAT from Scamper at {config.url!r} within {config.heartbeat_timeout_s:g} s"
                )
            if now >= next_hb:
                next_hb = now + 0.25
                with contextlib.suppress(OSError):
                    conn.mav.heartbeat_send(
                        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
                    )
            try:
                msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(0.05, deadline - now))
            except (OSError, ValueError):
                msg = None
            if msg is not None and msg.type != mavlink.MAV_TYPE_GCS:
                armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                return HeartbeatProbe(int(msg.type), int(msg.custom_mode), armed)
    finally:
        with contextlib.suppress(OSError):
            conn.close()
