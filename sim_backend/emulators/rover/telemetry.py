"""What the emulated Rover sends: HEARTBEAT, STATUSTEXT, PARAM_VALUE and the messages a ground station
asks for (MAV_CMD_REQUEST_MESSAGE, MAV_CMD_SET_MESSAGE_INTERVAL), as ArduPilot's GCS_MAVLINK sends them. A
mix-in of `emulator.MavlinkRoverEmulator`; every method but `_send_heartbeat` runs with its lock held."""

from __future__ import annotations

import contextlib
import functools
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil

from .faults import RoverFaults
from .modes import HOLD, INITIALISING, ROVER_MODES
from .params import ParamStore
from .state import RoverState

mavlink = mavutil.mavlink
COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
FIRMWARE_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # 4.5.7 official (AUTOPILOT_VERSION)
CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
)  # not MAVLINK2: the emulator's pymavlink parses MAVLink 1 unless MAVLINK20 is set
SEVERITY = {
    "CRITICAL": mavlink.MAV_SEVERITY_CRITICAL,
    "WARNING": mavlink.MAV_SEVERITY_WARNING,
    "INFO": mavlink.MAV_SEVERITY_INFO,
}
# messages the emulator can send on MAV_CMD_REQUEST_MESSAGE / at a SET_MESSAGE_INTERVAL
HEARTBEAT_ID, ATTITUDE_ID, LOCAL_POSITION_ID, ORIGIN_ID, VERSION_ID = 0, 30, 32, 49, 148
SENDABLE = (HEARTBEAT_ID, ATTITUDE_ID, LOCAL_POSITION_ID, ORIGIN_ID, VERSION_ID)


class Telemetry:
    """The sending half of the emulator (attributes set by `MavlinkRoverEmulator.__init__`)."""

    _s: RoverState
    _conn: Any
    _lock: threading.Lock
    _t0: float
    store: ParamStore
    faults: RoverFaults
    requires_position_estimate: bool
    heartbeat_period_s: float

    def _send(self, fn: Callable[[], None]) -> None:
        with contextlib.suppress(OSError):
            fn()

    def _text(self, severity: str, text: str) -> None:
        """STATUSTEXT (GCS_SEND_TEXT); caller holds the lock."""
        self._s.texts.append((time.monotonic(), SEVERITY[severity], text))
        self._send(functools.partial(self._conn.mav.statustext_send, SEVERITY[severity], text.encode()[:50]))

    def _system_status(self) -> int:
        st = self._s
        if st.fs_triggered or st.ekf_failsafe:
            return int(mavlink.MAV_STATE_CRITICAL)
        if st.mode == INITIALISING:
            return int(mavlink.MAV_STATE_CALIBRATING)
        if st.mode == HOLD:
            return int(mavlink.MAV_STATE_STANDBY)
        return int(mavlink.MAV_STATE_ACTIVE)

    def _send_heartbeat(self) -> None:
        if self.faults.companion_heartbeat:
            mav = self._conn.mav
            own = mav.srcComponent  # only this thread sends, so borrowing the component id is safe
            mav.srcComponent = COMPANION_COMPONENT
            try:
                self._send(
                    lambda: mav.heartbeat_send(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                    )
                )
            finally:
                mav.srcComponent = own
        if self.faults.no_heartbeat:
            return
        with self._lock:
            base, mode, status = self._base_mode(), self._s.mode, self._system_status()
        self._send(
            lambda: self._conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode, status
            )
        )

    def _base_mode(self) -> int:
        """GCS_MAVLINK_Rover::base_mode (STICK_MIXING 0); caller holds the lock."""
        traits = ROVER_MODES[self._s.mode]
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if traits.manual_input:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if traits.autopilot:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if self._s.armed and self._s.mode != INITIALISING:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return int(base)

    def _request_message(self, msg_id: int) -> int:
        """GCS_MAVLINK::handle_command_request_message: FAILED for a message it cannot send."""
        if msg_id not in SENDABLE:
            return int(mavlink.MAV_RESULT_FAILED)
        self._emit(msg_id)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _set_interval(self, msg_id: int, interval_us: float, now: float) -> int:
        """GCS_MAVLINK::handle_command_set_message_interval: -1 stops, 0 the default (none here), > 0 us."""
        if msg_id not in SENDABLE or not math.isfinite(interval_us):
            return int(mavlink.MAV_RESULT_FAILED)
        if msg_id == HEARTBEAT_ID and interval_us > 0:
            self.heartbeat_period_s = interval_us * 1e-6
        elif interval_us > 0:
            self._s.intervals[msg_id] = [interval_us * 1e-6, now]
        else:
            self._s.intervals.pop(msg_id, None)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _send_streams(self, now: float) -> None:
        for msg_id, slot in self._s.intervals.items():
            if now >= slot[1]:
                slot[1] = max(slot[1] + slot[0], now)
                self._emit(msg_id)

    def _emit(self, msg_id: int) -> None:
        st, mav = self._s, self._conn.mav
        boot_ms = int(1e3 * (time.monotonic() - self._t0)) & 0xFFFFFFFF
        if msg_id == ORIGIN_ID:
            if st.origin is not None:  # GCS_MAVLINK::send_ekf_origin: nothing without an origin
                self._send(functools.partial(mav.gps_global_origin_send, *st.origin))
        elif msg_id == VERSION_ID:
            zeros = [0] * 8
            version = (CAPABILITIES, FIRMWARE_VERSION, 0, 0, 0, zeros, zeros, zeros, 0, 0, 0)
            self._send(functools.partial(mav.autopilot_version_send, *version))
        elif msg_id == ATTITUDE_ID:
            self._send(functools.partial(mav.attitude_send, boot_ms, 0.0, 0.0, st.yaw, 0.0, 0.0, st.vel[2]))
        elif msg_id == LOCAL_POSITION_ID:
            if st.origin is not None or not self.requires_position_estimate:
                v = st.vel[0]
                vn, ve = v * math.cos(st.yaw), v * math.sin(st.yaw)
                position = (boot_ms, st.x, st.y, 0.0, vn, ve, 0.0)
                self._send(functools.partial(mav.local_position_ned_send, *position))
        elif msg_id == HEARTBEAT_ID:
            base, status = self._base_mode(), self._system_status()
            kind = (mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
            self._send(functools.partial(mav.heartbeat_send, *kind, base, st.mode, status))

    def _send_param(self, i: int) -> None:
        name, value, ptype = self.store.rows[i]
        for _ in range(2 if self.faults.duplicate_param_replies else 1):
            if self.faults.drop_param_replies > 0:
                self.faults.drop_param_replies -= 1
                continue
            self._s.param_replies += 1
            self._send(
                functools.partial(
                    self._conn.mav.param_value_send, name.encode(), value, ptype, len(self.store.rows), i
                )
            )

    def _answer_params(self, msg: Any) -> None:
        rows = self.store.rows
        if msg.get_type() == "PARAM_REQUEST_LIST":
            wanted = list(range(len(rows)))
        elif int(msg.param_index) >= 0:
            wanted = [int(msg.param_index)] if int(msg.param_index) < len(rows) else []
        else:
            wanted = [i for i, row in enumerate(rows) if row[0] == str(msg.param_id)]
        for i in wanted:  # an unknown name or index: no answer, as ArduPilot
            self._send_param(i)

    def _param_set(self, msg: Any) -> None:
        """GCS_MAVLINK::handle_param_set: set, then PARAM_VALUE with the new value; unknown: ignored."""
        i = self.store.set(str(msg.param_id), float(msg.param_value))
        if i is not None:
            self._send_param(i)
