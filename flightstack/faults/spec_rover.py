"""A minimal ArduPilot Rover on loopback for the preflight fault rows and the driver's tests: heartbeat and
SYSTEM_TIME at 10 Hz, parameters by name, the EKF origin, GUIDED only with a position estimate, arming.

Written from the MAVLink specification and ArduPilot's source, not from the driver:
``GCS_MAVLINK::set_ekf_origin`` (libraries/GCS_MAVLink/GCS_Common.cpp) takes an origin only while none is
set and then sends GPS_GLOBAL_ORIGIN; MAV_CMD_REQUEST_MESSAGE (512) for message 49 is answered with it
when there is one; Rover refuses GUIDED without a position estimate (``Mode::requires_position``,
Rover/mode.h) with MAV_RESULT_FAILED; PARAM_REQUEST_READ by name is answered with PARAM_VALUE and an
unknown name is not answered. It is not the project's rover emulator (sim_backend/emulators/
mavlink_rover.py), which models driving; this one models only what the driver's and preflight's
handshakes need, so that they can be tested against something they were not written with.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from pymavlink import mavutil

mavlink = mavutil.mavlink

GUIDED, HOLD = 15, 4
ARDUPILOT_DEFAULTS: dict[str, float] = {
    "AHRS_EKF_TYPE": 3, "EK3_SRC1_POSXY": 3, "EK3_SRC1_YAW": 1, "VISO_TYPE": 0, "GUID_TIMEOUT": 3.0,
    "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELXY": 3, "EK3_SRC1_VELZ": 3,
    "FRAME_CLASS": 1, "FRAME_TYPE": 0, "SERVO1_FUNCTION": 26, "SERVO3_FUNCTION": 70,
    "FS_GCS_ENABLE": 0, "FS_ACTION": 2, "FS_TIMEOUT": 1.5, "FS_GCS_TIMEOUT": 5, "SYSID_MYGCS": 255,
}  # fmt: skip
"""ArduPilot Rover's defaults of what preflight reads (Rover/Parameters.cpp and the libraries')."""
LAB_SETTINGS: dict[str, float] = {
    **ARDUPILOT_DEFAULTS,
    "EK3_SRC1_POSXY": 6, "EK3_SRC1_YAW": 6, "VISO_TYPE": 1, "EK3_SRC1_VELXY": 0, "EK3_SRC1_VELZ": 0,
    "SERVO1_FUNCTION": 73, "SERVO3_FUNCTION": 74,
    "FS_GCS_ENABLE": 1, "FS_ACTION": 2, "FS_TIMEOUT": 1, "FS_GCS_TIMEOUT": 3,
}  # fmt: skip
"""What docs/drivers.md tells the lab to set (a skid-steered Scamper)."""


class SpecRover:
    """The module docstring's vehicle; `close()` stops it."""

    def __init__(self, answer_origin: bool = True, params: Mapping[str, float] | None = None) -> None:
        """answer_origin False: a vehicle that never reports its origin. params: name -> value (default
        LAB_SETTINGS); `port` is where a ``udpout:127.0.0.1:<port>`` client reaches it."""
        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.port = self.conn.port.getsockname()[1]
        self.answer_origin = answer_origin
        self.params = dict(LAB_SETTINGS if params is None else params)
        self.lock = threading.Lock()
        self.origin: tuple[int, int, int] | None = None
        self.origin_sets = 0
        self.vision: list[tuple[float, Any]] = []  # (receive time.monotonic(), message)
        self.mode, self.armed = HOLD, False
        self.boot_t0 = time.monotonic()
        self.refused: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="spec-rover")
        self._thread.start()

    def reboot(self) -> None:
        with self.lock:
            self.origin, self.mode, self.armed, self.boot_t0 = None, HOLD, False, time.monotonic()

    def _send(self, fn: str, *args: Any) -> None:
        if self.conn.clients:  # udpin: the ground station is known once it sent something
            getattr(self.conn.mav, fn)(*args)

    def _run(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 0.1
                with self.lock:
                    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (128 if self.armed else 0)
                    mode, boot_ms = self.mode, int((now - self.boot_t0) * 1000)
                self._send(
                    "heartbeat_send", mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                    base, mode, mavlink.MAV_STATE_ACTIVE,
                )  # fmt: skip
                self._send("system_time_send", 0, boot_ms)
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is not None:
                with self.lock:
                    self._handle(msg, time.monotonic())

    def _send_origin(self) -> None:
        if self.origin is not None and self.answer_origin:
            self._send("gps_global_origin_send", *self.origin, 0)

    def _handle(self, msg: Any, now: float) -> None:
        t = msg.get_type()
        if t == "PARAM_REQUEST_READ":
            name = str(msg.param_id)
            if name in self.params:
                names = list(self.params)
                self._send(
                    "param_value_send", name.encode("ascii"), float(self.params[name]),
                    mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name),
                )  # fmt: skip
        elif t == "SET_GPS_GLOBAL_ORIGIN":
            self.origin_sets += 1
            if self.origin is None:  # set_ekf_origin: only while none is set, then MSG_ORIGIN
                self.origin = (msg.latitude, msg.longitude, msg.altitude)
                self._send_origin()
        elif t == "VISION_POSITION_ESTIMATE":
            self.vision.append((now, msg))
        elif t == "COMMAND_LONG":
            cmd = msg.command
            result = mavlink.MAV_RESULT_ACCEPTED
            if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == 49:
                self._send_origin()
            elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
                want = int(msg.param2)
                fresh = bool(self.vision) and now - self.vision[-1][0] < 0.3
                if want == GUIDED and not (fresh and self.origin is not None):
                    result = mavlink.MAV_RESULT_FAILED
                    self.refused.append(want)
                else:
                    self.mode = want
            elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                self.armed = msg.param1 > 0.5
            self._send("command_ack_send", cmd, result)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()
