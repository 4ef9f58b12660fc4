"""The Scamper's MAVLink link: one pymavlink connection, its one send path and its two background threads.

drivers/scamper/driver.py (the robot's semantics: heartbeat state, mode/arm confirmation) runs on top of
`ScamperLink`:

* ``scamper-rx`` receives everything (``recv_match``, ≤ 20 ms waits) and hands each message, or None
  when nothing came, to the driver's handler (which also supervises the link);
* ``scamper-tx`` sends the GCS HEARTBEAT at 1 Hz and calls the driver's stream tick at ``stream_hz``
  (the set-point re-send ArduPilot Rover needs: it stops after ~3 s without one).

Neither thread ends on an error: an exception from receiving (``recv_error``: a socket error such as
ENETUNREACH, a pymavlink parse failure), from the handler (``rx_error``) or from a tick (``tx_error``) is
counted in the driver's ``counts`` (plus ``thread_error``), logged at the first and every 100th
occurrence, and the thread goes on after a pause of ``ERROR_PAUSE_S``. Every send, from any thread, goes
through `ScamperLink.send`: an exception from the pymavlink write is counted (``send_error``), never
raised; note that pymavlink's UDP transport swallows socket errors of ``sendto`` itself (serial and TCP
ones reach this code).

Mute (guardian takeover): `ScamperLink.muted`, a callable checked synchronously under the send lock right
before each write, from whichever thread sends; while it returns True nothing is written (``counts["muted"]``,
`send` returns "muted"). A check that raises is counted (``muted_check_error``) and does not mute.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pymavlink import mavutil

from flightstack.drivers.device_threads import ERROR_PAUSE_S, ErrorLog, MutedCheck, evaluate_mute
from flightstack.drivers.scamper.nav import POSE_UNKNOWN_COVARIANCE, LabOrigin, VisionSample
from flightstack.drivers.scamper.tlog import TlogWriter

mavlink = mavutil.mavlink
LOG = logging.getLogger("flightstack.scamper")

ROVER_GUIDED_MODE = 15
# Ignore x, y, z (1, 2, 4), vz (32), afx/afy/afz (64, 128, 256), yaw (1024); use vx, vy, yaw_rate.
TYPE_MASK_VEL_YAWRATE = 1511
GCS_HEARTBEAT_PERIOD_S = 1.0
RX_WAIT_S = 0.02  # longest wait of the receiver thread in recv_match (s)
_NOT_VEHICLE_TYPES = (
    mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_TYPE_ADSB, mavlink.MAV_TYPE_ONBOARD_CONTROLLER
)  # fmt: skip
_GCS_HEARTBEAT = (mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)

SendResult = Literal["sent", "muted", "failed", "closed"]
MessageHandler = Callable[[Any, float], None]  # (message or None, time.monotonic() s)
Tick = tuple[float, Callable[[], object]]  # (period s, what scamper-tx calls every period)


class ScamperError(RuntimeError):
    """Base class of Scamper driver errors."""


class ScamperLinkError(ScamperError):
    """No (or no more) HEARTBEAT from the robot."""


class ScamperCommandError(ScamperError):
    """A mode change or (dis)arm was rejected, not sent (muted), or the robot's HEARTBEAT never showed it."""


@dataclass(frozen=True)
class ScamperConfig:
    """Connection and timing parameters (all times in seconds, rates in Hz)."""

    url: str = "udpout:127.0.0.1:14550"  # pymavlink connection string of the robot
    heartbeat_timeout_s: float = 5.0  # connect(): max wait for the robot's first HEARTBEAT
    ack_timeout_s: float = 2.0  # wait for a COMMAND_ACK (or heartbeat change) before re-sending
    stream_hz: float = 10.0  # set-point re-send rate (>= 1 Hz needed; Rover stops after 3 s)
    link_timeout_s: float = 3.0  # no HEARTBEAT for this long -> link lost
    source_system: int = 255  # our MAVLink system id (GCS convention)
    source_component: int = 190  # MAV_COMP_ID_MISSIONPLANNER
    command_sends: int = 3  # max sends of one COMMAND_LONG that gets neither ACK nor heartbeat change
    # the EKF origin (drivers/scamper/nav.py; docs/drivers.md "Ground robot"): WGS84 degrees, m above MSL
    origin_lat_deg: float = 52.0
    origin_lon_deg: float = 4.0
    origin_alt_m: float = 0.0
    origin_timeout_s: float = 5.0  # connect(): max wait for the vehicle to report the origin
    vision_hz: float = 20.0  # VISION_POSITION_ESTIMATE rate (ArduPilot asks >= 4 Hz)
    vision_max_age_s: float = 0.2  # a motion-capture pose older than this is not sent

    def __post_init__(self) -> None:
        names = ("heartbeat_timeout_s", "ack_timeout_s", "stream_hz", "link_timeout_s", "origin_timeout_s")
        for name in (*names, "vision_hz", "vision_max_age_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"ScamperConfig.{name} must be finite and > 0, got {value}")
        if self.stream_hz < 1.0:
            raise ValueError(f"ScamperConfig.stream_hz must be >= 1 Hz, got {self.stream_hz}")
        if self.vision_hz < 4.0:
            raise ValueError(f"ScamperConfig.vision_hz must be >= 4 Hz (ArduPilot), got {self.vision_hz}")
        LabOrigin(self.origin_lat_deg, self.origin_lon_deg, self.origin_alt_m)  # ValueError if not WGS84
        if self.command_sends < 1:
            raise ValueError(f"ScamperConfig.command_sends must be >= 1, got {self.command_sends}")


def is_vehicle_heartbeat(msg: Any) -> bool:
    """As pymavlink's ``mavfile.probably_vehicle_heartbeat``: not a GCS, gimbal, ADS-B or companion."""
    return (
        msg.get_srcComponent() != mavlink.MAV_COMP_ID_GIMBAL
        and msg.type not in _NOT_VEHICLE_TYPES
        and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
    )


class ScamperLink:
    """The pymavlink connection of one driver, its send path (mute, error accounting) and its threads."""

    def __init__(
        self,
        config: ScamperConfig,
        counts: Counter[str],
        muted: MutedCheck | None = None,
        tlog: TlogWriter | None = None,
    ) -> None:
        """Open ``config.url`` (pymavlink); counts: the driver's counters; muted: see the module docstring;
        tlog: where every message received and written is logged (drivers/scamper/tlog.py), or None."""
        self.config = config
        self.muted = muted
        self.counts = counts
        self.errors = ErrorLog(counts, f"scamper {config.url}", LOG)
        self.conn: Any = mavutil.mavlink_connection(
            config.url, source_system=config.source_system, source_component=config.source_component
        )
        self._send_lock = threading.Lock()  # serialises writes on the pymavlink connection
        self._closed = False
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.tlog = tlog
        if tlog is not None:  # called by pymavlink after each successful write, under our send lock
            self.conn.mav.set_send_callback(self._log_sent)

    # ------------------------------------------------------------------ threads
    def start(self, on_message: MessageHandler, on_stream_tick: Callable[[], None], *ticks: Tick) -> None:
        """Start ``scamper-rx`` (every message, or None after ≤ 20 ms of silence, to on_message) and
        ``scamper-tx`` (GCS HEARTBEAT at 1 Hz, on_stream_tick at ``stream_hz``, each further tick at its
        own period)."""
        every: list[Tick] = [
            (
                GCS_HEARTBEAT_PERIOD_S,
                lambda: self.send_heartbeat(),
            ),  # late-bound: a replaced one takes effect
            (1.0 / self.config.stream_hz, on_stream_tick),
            *ticks,
        ]
        self._threads = [
            threading.Thread(target=self._rx_loop, args=(on_message,), name="scamper-rx", daemon=True),
            threading.Thread(target=self._tx_loop, args=(every,), name="scamper-tx", daemon=True),
        ]
        for th in self._threads:
            th.start()

    def threads_alive(self) -> dict[str, bool]:
        """Name → alive, of this link's threads."""
        return {th.name: th.is_alive() for th in self._threads}

    def close(self) -> None:
        """Stop and join the threads (≤ 1 s each), then close the connection; idempotent."""
        self._stop.set()
        for th in self._threads:
            if th is not threading.current_thread():
                th.join(timeout=1.0)
        with self._send_lock:
            self._closed = True
            with contextlib.suppress(OSError):
                self.conn.close()

    def _rx_loop(self, on_message: MessageHandler) -> None:
        """Receiver thread: survives every error (counted, logged without flooding)."""
        while not self._stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=RX_WAIT_S)
            except Exception as exc:  # ENETUNREACH from recvfrom, a closed socket, a pymavlink parse bug
                msg = None
                if self._stop.is_set():
                    break
                self.errors.record("recv_error", exc)
                self._stop.wait(ERROR_PAUSE_S)
            if msg is not None and self.tlog is not None and msg.get_type() != "BAD_DATA":
                self.tlog.record(msg.get_msgbuf())
            try:
                on_message(msg, time.monotonic())
            except Exception as exc:
                self.errors.record("rx_error", exc)
                self._stop.wait(ERROR_PAUSE_S)

    def _tx_loop(self, every: list[Tick]) -> None:
        """Sender thread: calls each tick at its period (GCS heartbeat, set-point, ...); survives errors."""
        due = [time.monotonic()] * len(every)
        while True:
            if self._stop.wait(max(0.0, min(due) - time.monotonic())):
                break
            for i, (period, fn) in enumerate(every):
                now = time.monotonic()
                if now < due[i]:
                    continue
                due[i] = now + period
                try:
                    fn()
                except Exception as exc:
                    self.errors.record("tx_error", exc)
                    self._stop.wait(ERROR_PAUSE_S)

    # ------------------------------------------------------------------ sending (any thread)
    def is_muted(self) -> bool:
        """The mute check, evaluated now (flightstack.drivers.device_threads.evaluate_mute)."""
        return evaluate_mute(self.muted, self.errors)

    def send(self, fn: str, *args: Any) -> SendResult:
        """Call ``conn.mav.<fn>(*args)`` unless muted or closed; never raises, never waits on the network."""
        with self._send_lock:
            if self._closed:
                return "closed"
            if self.is_muted():  # right before the write, under the lock: no send slips past a takeover
                what = fn.removesuffix("_send")
                self.errors.record("muted", f"{what} not sent: another process took over", thread=False)
                return "muted"
            try:
                getattr(self.conn.mav, fn)(*args)
            except Exception as exc:  # OSError of a serial/TCP write, a packing error: counted, not raised
                self.errors.record("send_error", f"{fn}: {type(exc).__name__}: {exc}", thread=False)
                return "failed"
        self.counts["sent"] += 1
        return "sent"

    def _log_sent(self, mavmsg: Any) -> None:
        """pymavlink's send callback: the bytes just written go to the tlog."""
        if self.tlog is not None:
            self.tlog.record(mavmsg.get_msgbuf())

    def send_heartbeat(self) -> SendResult:
        """The GCS HEARTBEAT (ArduPilot's GCS failsafe watches it)."""
        return self.send("heartbeat_send", *_GCS_HEARTBEAT)

    def send_setpoint(self, target: tuple[int, int], sp: np.ndarray) -> SendResult:
        """SET_POSITION_TARGET_LOCAL_NED, body NED velocity sp = [vx m/s, vy right m/s, yaw rate cw rad/s]."""
        t_ms = int((time.monotonic() - self._t0) * 1000.0) & 0xFFFFFFFF
        vx, vy, r = (float(x) for x in sp)
        result = self.send(
            "set_position_target_local_ned_send",
            t_ms, target[0], target[1], mavlink.MAV_FRAME_BODY_NED, TYPE_MASK_VEL_YAWRATE,
            0.0, 0.0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, 0.0, r,
        )  # fmt: skip
        if result == "sent":
            self.counts["setpoint_sent"] += 1
        return result

    def send_vision(self, v: VisionSample) -> SendResult:
        """VISION_POSITION_ESTIMATE (msg 102): NED m, rad, usec on time.monotonic() (scamper.nav).

        covariance and reset_counter are MAVLink 2 extensions: pymavlink's MAVLink 1 dialects (the
        default until the vehicle speaks MAVLink 2) lack reset_counter, and a MAVLink 1 frame carries
        neither (ArduPilot then reads zeros: its VISO_*_M_NSE noise, no reset)."""
        args: list[Any] = [v.usec, v.x, v.y, v.z, v.roll, v.pitch, v.yaw, list(POSE_UNKNOWN_COVARIANCE)]
        if "reset_counter" in inspect.signature(self.conn.mav.vision_position_estimate_send).parameters:
            args.append(v.reset_counter)
        result = self.send("vision_position_estimate_send", *args)
        if result == "sent":
            self.counts["vision_sent"] += 1
        return result

    def send_origin(self, target: tuple[int, int], origin: LabOrigin) -> SendResult:
        """SET_GPS_GLOBAL_ORIGIN (msg 48) with the lab origin, time_usec 0 (unknown)."""
        lat, lon, alt = origin.as_mavlink()
        result = self.send("set_gps_global_origin_send", target[0], lat, lon, alt, 0)
        if result == "sent":
            self.counts["origin_sent"] += 1
        return result

    def request_message(self, target: tuple[int, int], msg_id: int) -> SendResult:
        """MAV_CMD_REQUEST_MESSAGE (512) for message `msg_id` (MAVLink common.xml; GCS_MAVLINK handles it)."""
        return self.send(
            "command_long_send", target[0], target[1], mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
            float(msg_id), 0, 0, 0, 0, 0, 0,
        )  # fmt: skip

    def send_command(
        self, target: tuple[int, int], command: int, confirmation: int, p1: float, p2: float
    ) -> SendResult:
        """COMMAND_LONG `command` with param1, param2 (the others 0)."""
        return self.send(
            "command_long_send", target[0], target[1], command, confirmation, p1, p2, 0, 0, 0, 0, 0
        )


@dataclass(frozen=True)
class HeartbeatProbe:
    """What one HEARTBEAT of the robot said (for `flightstack preflight`); mode is Rover's custom mode."""

    mav_type: int
    custom_mode: int
    armed: bool


def probe_heartbeat(config: ScamperConfig) -> HeartbeatProbe:
    """Wait up to heartbeat_timeout_s for the robot's HEARTBEAT without changing its mode or arming it.

    Sends GCS heartbeats meanwhile (a `udpin` vehicle only learns our address from what we send); only a
    vehicle's heartbeat counts (not a companion computer's, gimbal's, GCS's).  Raises ScamperLinkError
    when nothing arrives in time.
    """
    conn = open_connection(config)
    try:
        return wait_vehicle_heartbeat(conn, config)[0]
    finally:
        with contextlib.suppress(OSError):
            conn.close()


def open_connection(config: ScamperConfig) -> Any:
    """A pymavlink connection to ``config.url`` with our source system and component."""
    return mavutil.mavlink_connection(
        config.url, source_system=config.source_system, source_component=config.source_component
    )


def send_gcs_heartbeat(conn: Any) -> None:
    """Our GCS HEARTBEAT on a bare pymavlink connection (probes; a socket error is ignored)."""
    with contextlib.suppress(OSError):
        conn.mav.heartbeat_send(*_GCS_HEARTBEAT)


def wait_vehicle_heartbeat(conn: Any, config: ScamperConfig) -> tuple[HeartbeatProbe, tuple[int, int]]:
    """`probe_heartbeat` on an open connection; also returns the vehicle's (system, component)."""
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
            send_gcs_heartbeat(conn)
        try:
            msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(0.05, deadline - now))
        except (OSError, ValueError):
            msg = None
        if msg is not None and is_vehicle_heartbeat(msg):
            armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            probe = HeartbeatProbe(int(msg.type), int(msg.custom_mode), armed)
            return probe, (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
