"""Loopback MAVLink emulator of ArduPilot Rover (stand-in for the lab's Scamper), behaviour by behaviour
from ArduPilot's source (the table "What ArduPilot Rover does, and the emulator" in docs/drivers.md names
the source function of each, and what is not modelled).

A pymavlink ``udpin`` endpoint on ``127.0.0.1`` (port from the OS unless given); it learns the ground
station's address from the first datagram, so a client on ``udpout:127.0.0.1:<emu.port>`` must send
something (e.g. its HEARTBEAT) before it hears anything. One daemon thread with bounded waits (<= 20 ms);
``close()`` joins it within 1 s and closes the socket. The pose is integrated in the local NED frame
(x north, y east, yaw clockwise from north; m, rad) from the origin; ``pose_flu()`` is ``(x, -y, -yaw)``.

Why a client must read the HEARTBEAT: ArduPilot ACKs ``SET_MODE`` with command id 11
(github.com/ArduPilot/pymavlink/pull/411), its maintainers say a mode change is to be checked on the
HEARTBEAT (github.com/ArduPilot/ardupilot/pull/14452), and the armed flag shows only in the next one, up
to 1 s later (github.com/mavlink/qgroundcontrol/pull/10810).
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
import time
from typing import Any

from pymavlink import mavutil

from flightstack.paper.geometry import Pose

from ..device_links import DeviceLinks
from ..radio import DeviceRadio
from .faults import RoverFaults
from .guided import Steering, arc, decode_setpoint, twist
from .modes import (
    AUTO,
    GUIDED,
    HOLD,
    LOITER,
    ROVER_MODES,
    RTL,
    SMART_RTL,
    needs_position,
    needs_velocity,
)
from .params import ParamStore, RoverParams
from .state import FailsafeEvent, RoverState, SetpointRecord
from .telemetry import ORIGIN_ID, VERSION_ID, Telemetry

mavlink = mavutil.mavlink
FS_CHECK_PERIOD_S = 0.1  # Rover runs gcs_failsafe_check at 10 Hz
FS_OPTION_ACTIVE_IN_HOLD = 1  # FS_OPTIONS bit 0
# EKF3 flags the filter dead reckoning 1 s after its last position fusion (deadReckonDeclare_ms,
# AP_NavEKF3.h); the emulator drops the position estimate then (ArduPilot's EKF keeps a degrading one and
# times out position aiding only after posRetryTimeNoVel_ms, 7 s, so the emulator is the stricter).
POSITION_TIMEOUT_S = 1.0
VISION_TYPES = ("VISION_POSITION_ESTIMATE", "ODOMETRY", "ATT_POS_MOCAP")
MAX_DRAIN = 200  # messages handled per pass of the loop (a bound on one pass's work)


class MavlinkRoverEmulator(Telemetry):
    """ArduPilot Rover in GUIDED, speaking MAVLink on ``udpin:127.0.0.1:<port>``."""

    def __init__(
        self,
        port: int = 0,
        system_id: int = 1,
        component_id: int = 1,
        heartbeat_hz: float = 1.0,
        params: RoverParams | None = None,
        radio: DeviceRadio | None = None,
        links: DeviceLinks | None = None,
        requires_position_estimate: bool = True,
        position_timeout_s: float = POSITION_TIMEOUT_S,
    ) -> None:
        """radio: the robot's network (`radio.DeviceRadio` with links "uplink" (from the ground station)
        and "downlink"); None: a perfect link. links: the rig's links of the robot
        (`device_links.DeviceLinks`: every MAVLink message from the ground station is acted on late by
        the "robot" link, or lost, after the radio); None: none. requires_position_estimate: as ArduPilot,
        no arming or mode needing a position without external navigation arriving (within
        position_timeout_s, s) and every set-point dropped without an EKF origin; False: a rover that
        always knows where it is (no origin, no vision needed)."""
        self.faults = RoverFaults()
        self.radio = radio
        self.params = params or RoverParams()
        self.store = ParamStore.of(self.params, system_id)
        self.system_id = system_id
        self.requires_position_estimate = requires_position_estimate
        self.position_timeout_s = position_timeout_s
        self.failsafe_events: list[FailsafeEvent] = []
        self.heartbeat_period_s = 1.0 / heartbeat_hz
        self.setpoints: list[SetpointRecord] = []
        self.gcs_heartbeats: list[float] = []  # emulator monotonic times (s) of the client's HEARTBEATs
        self.stopped_by_timeout = False
        self._s = RoverState()
        self._t0 = time.monotonic()
        self._pending_acks: list[tuple[float, int, int]] = []  # (due time, command, result)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=system_id, source_component=component_id
        )
        self.port: int = self._conn.port.getsockname()[1]
        if radio is not None:  # pymavlink reads and writes through `port` (non-blocking, select on fd)
            self._conn.port = radio.socket(self._conn.port, lambda _a: "downlink", "uplink")
        self.links = links
        if links is not None:
            self._conn.port = links.socket(self._conn.port, recv="robot")
        self.url = f"udpout:127.0.0.1:{self.port}"  # what a client should connect to
        self._thread = threading.Thread(target=self._run, name="mavlink-rover-emu", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ queries (thread-safe)
    @property
    def mode(self) -> int:
        with self._lock:
            return self._s.mode

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._s.armed

    @property
    def velocity(self) -> tuple[float, float, float]:
        """Current body velocity (vx fwd m/s, vy right m/s (always 0: a rover), yaw rate clockwise rad/s)."""
        with self._lock:
            return self._s.vel

    @property
    def commands(self) -> list[tuple[int, float, int]]:
        """Received COMMAND_LONG / SET_MODE as (command id, param, MAV_RESULT decided); see ``acks_sent``."""
        with self._lock:
            return list(self._s.commands)

    @property
    def acks_sent(self) -> list[tuple[int, int]]:
        """COMMAND_ACKs actually transmitted as (command id, MAV_RESULT), duplicates included."""
        with self._lock:
            return list(self._s.acks_sent)

    @property
    def dropped_commands(self) -> list[int]:
        """Command ids of the COMMAND_LONG / SET_MODE lost by ``faults.drop_commands``."""
        with self._lock:
            return list(self._s.dropped)

    @property
    def statustexts(self) -> list[tuple[float, int, str]]:
        """STATUSTEXTs sent as (emulator monotonic s, MAV_SEVERITY, text)."""
        with self._lock:
            return list(self._s.texts)

    @property
    def origin(self) -> tuple[int, int, int] | None:
        """The EKF origin (lat, lon degE7, alt mm), None until SET_GPS_GLOBAL_ORIGIN set it."""
        with self._lock:
            return self._s.origin

    @property
    def vision_count(self) -> int:
        """Valid external-navigation messages received (VISION_POSITION_ESTIMATE, ODOMETRY, ATT_POS_MOCAP)."""
        with self._lock:
            return self._s.vision_count

    def position_ok(self) -> bool:
        """Rover::ekf_position_ok as modelled: external navigation fresh and no EKF failsafe."""
        with self._lock:
            return self._position_ok(time.monotonic())

    def system_status(self) -> int:
        """The HEARTBEAT's system_status (GCS_MAVLINK_Rover::vehicle_system_status)."""
        with self._lock:
            return self._system_status()

    def param(self, name: str) -> float:
        """A parameter's current value (NaN if the firmware has none of that name)."""
        with self._lock:
            return self.store.get(name)

    def pilot_override(self, mode: int | None = None, armed: bool | None = None) -> None:
        """Change mode and/or arming as an RC switch or failsafe would (no ACK, shows in the heartbeat)."""
        with self._lock:
            if mode is not None:
                self._enter(mode)
            if armed is not None:
                self._s.armed = armed
            self._update_twist()

    def pose_ned(self) -> tuple[float, float, float]:
        """(x north m, y east m, yaw clockwise rad) in the emulator's local NED frame."""
        with self._lock:
            return self._s.x, self._s.y, self._s.yaw

    def pose_flu(self) -> Pose:
        """The same pose with y to the left and yaw counter-clockwise (the flightstack convention), z = 0."""
        x, y, yaw = self.pose_ned()
        return Pose.make([x, -y, 0.0], -yaw)

    def setpoint_records(self) -> list[SetpointRecord]:
        with self._lock:
            return list(self.setpoints)

    def gcs_heartbeat_count(self) -> int:
        """How many HEARTBEATs the client (ground station) has sent so far."""
        with self._lock:
            return len(self.gcs_heartbeats)

    @property
    def failsafe_t(self) -> float | None:
        """When the GCS failsafe first acted (emulator monotonic s), None if never."""
        with self._lock:
            return self.failsafe_events[0].t if self.failsafe_events else None

    @property
    def failsafe_action(self) -> int | None:
        """The FS_ACTION the GCS failsafe first took, None if never."""
        with self._lock:
            return self.failsafe_events[0].action if self.failsafe_events else None

    @property
    def gcs_last_seen(self) -> float | None:
        """Last HEARTBEAT from the GCS system id (emulator monotonic s), None before the first."""
        with self._lock:
            return self._s.gcs_last_seen

    @property
    def param_replies(self) -> int:
        """PARAM_VALUE messages sent so far (duplicates included, dropped ones not)."""
        with self._lock:
            return self._s.param_replies

    def network_counts(self) -> dict[str, dict[str, float]]:
        """What the radio did per link (`radio.DeviceRadio.counts`); empty on a perfect link."""
        return {} if self.radio is None else self.radio.counts()

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop the thread (joined within 1 s) and close the socket. Idempotent."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        if self.links is not None:
            self.links.close()
        if self.radio is not None:
            self.radio.close()
        with contextlib.suppress(OSError):
            self._conn.close()

    def __enter__(self) -> MavlinkRoverEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the loop
    def _run(self) -> None:
        last = time.monotonic()
        next_hb = next_fs = last
        while not self._stop.is_set():
            try:
                msgs = self._received()
            except OSError:
                if self._stop.is_set():
                    break
                msgs = []
            now = time.monotonic()
            with self._lock:
                self._integrate(now - last)
                last = now
                for msg in msgs:
                    self._handle(msg, now)
                self._flush_acks(now)
                self._guided_timeout(now)
                self._ekf_check(now)
                if now >= next_fs:
                    next_fs = now + FS_CHECK_PERIOD_S
                    self._gcs_failsafe_check(now)
                self._drive_home()
                self._update_twist()
                self._send_streams(now)
            if now >= next_hb:
                next_hb = now + self.heartbeat_period_s
                self._send_heartbeat()

    def _received(self) -> list[Any]:
        """Every message waiting (at most MAX_DRAIN), the first waited for up to 20 ms. All of them are
        handled before the timeouts are checked: a vehicle's autopilot reads its link as messages come,
        so messages that queued while this thread was not scheduled (a busy test machine) count as
        received in time; checking a timeout after only the oldest of them tripped a false EKF failsafe
        (the newest pose estimate still queued) that a real Rover would not have had."""
        msg = self._conn.recv_match(blocking=True, timeout=0.02)
        msgs: list[Any] = []
        while msg is not None and len(msgs) < MAX_DRAIN:
            msgs.append(msg)
            msg = self._conn.recv_match(blocking=False)
        if msg is not None:
            msgs.append(msg)
        return msgs

    # ------------------------------------------------------------------ motion (caller holds the lock)
    def _steering(self) -> Steering:
        s = self.store
        radius = None if s.skid_steering else s.get("TURN_RADIUS", 0.0)
        return Steering(math.radians(s.get("ATC_STR_RAT_MAX", 0.0)), s.get("ATC_STR_ANG_P", 0.0), radius)

    def _twist(self) -> tuple[float, float]:
        st = self._s
        if not st.armed:
            return 0.0, 0.0
        if st.mode == GUIDED and st.target is not None:
            return twist(st.target, st.yaw, self._steering())
        if st.mode in (RTL, SMART_RTL):
            return st.rtl_speed, 0.0
        return 0.0, 0.0

    def _update_twist(self) -> None:
        v, r = self._twist()
        self._s.vel = (v, 0.0, r)

    def _integrate(self, dt: float) -> None:
        """Drive (speed, turn rate) over dt (s), re-deciding the turn rate every <= 10 ms."""
        st = self._s
        while dt > 0.0:
            h = min(dt, 0.01)
            v, r = self._twist()
            st.vel = (v, 0.0, r)
            if v != 0.0 or r != 0.0:
                st.x, st.y, st.yaw = arc(st.x, st.y, st.yaw, v, r, h)
            dt -= h

    def _guided_timeout(self, now: float) -> None:
        """ModeGuided::update: no set-point for GUID_TIMEOUT s drops the target, with ArduPilot's text."""
        st = self._s
        timeout = max(self.store.get("GUID_TIMEOUT", 3.0), 0.1)
        if st.mode == GUIDED and st.target is not None and now - st.target_t > timeout:
            st.target = None
            self.stopped_by_timeout = True
            self._text("WARNING", f"target not received last {timeout:.1f} secs, stopping")

    def _drive_home(self) -> None:
        """RTL / SmartRTL: face home and drive to it at rtl_speed_mps; stop within WP_RADIUS."""
        st = self._s
        st.rtl_speed = 0.0
        if st.mode not in (RTL, SMART_RTL) or not st.armed or st.home is None:
            return
        dx, dy = st.home[0] - st.x, st.home[1] - st.y
        if math.hypot(dx, dy) <= self.store.get("WP_RADIUS", 2.0):
            return
        st.yaw = math.atan2(dy, dx)  # NED: yaw clockwise from north = atan2(east, north)
        st.rtl_speed = self.store.get("RTL_SPEED", 0.5)

    # ------------------------------------------------------------------ position estimate and EKF failsafe
    def _position_ok(self, now: float) -> bool:
        """Rover::ekf_position_ok as modelled; caller holds the lock."""
        if not self.requires_position_estimate:
            return True
        st = self._s
        fresh = st.vision_t is not None and now - st.vision_t <= self.position_timeout_s
        return fresh and self.store.external_nav and not st.ekf_failsafe

    def _ekf_check(self, now: float) -> None:
        """Rover::failsafe_ekf_event / failsafe_ekf_off_event when the estimate goes / comes back (armed)."""
        st = self._s
        if not self.requires_position_estimate:
            return
        fresh = st.vision_t is not None and now - st.vision_t <= self.position_timeout_s
        good = fresh and self.store.external_nav
        if not st.armed or good:
            if st.ekf_failsafe:
                st.ekf_failsafe = False
                self._text("INFO", "EKF failsafe cleared")
            return
        if st.ekf_failsafe or st.vision_t is None:  # never had an estimate: nothing to lose
            return
        st.ekf_failsafe = True
        action = int(self.store.get("FS_EKF_ACTION", 1.0))
        if not needs_position(st.mode) or action == 0:
            return
        if action != 2:  # 2: report only
            self._enter(HOLD)
        self._text("CRITICAL", "EKF failsafe")

    # ------------------------------------------------------------------ commands (caller holds the lock)
    def _ack(self, command: int, result: int, param: float, now: float) -> None:
        """Log the command and queue its ACK(s) per the faults."""
        self._s.commands.append((command, param, result))
        if command in self.faults.lost_acks:
            return
        due = now + max(0.0, self.faults.ack_delay_s)
        for _ in range(2 if self.faults.duplicate_acks else 1):
            self._pending_acks.append((due, command, result))

    def _flush_acks(self, now: float) -> None:
        due = [a for a in self._pending_acks if a[0] <= now]
        self._pending_acks = [a for a in self._pending_acks if a[0] > now]
        for _, command, result in due:
            self._s.acks_sent.append((command, result))
            self._send(functools.partial(self._conn.mav.command_ack_send, command, result))

    def _ignored(self, command: int) -> bool:
        return command in self.faults.ack_accepted_but_ignored

    def _enter(self, mode: int) -> None:
        """Switch mode; a new mode starts without a GUIDED target (ModeGuided::_enter: start_stop)."""
        if mode != self._s.mode:
            self._s.target = None
        self._s.mode = mode

    def _set_mode(self, mode: int, base_mode: int, ack_id: int) -> int:
        """GCS_MAVLINK::_set_mode_common -> Rover::set_mode -> Mode::enter."""
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return int(mavlink.MAV_RESULT_UNSUPPORTED)
        if mode not in ROVER_MODES:
            self._text("WARNING", f"No such mode {mode}")
            return int(mavlink.MAV_RESULT_FAILED)
        if self._ignored(ack_id) or mode == self._s.mode:
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if self._s.armed:  # Mode::enter checks only while armed
            ok = self._position_ok(time.monotonic())
            if (needs_position(mode) or needs_velocity(mode, self.store.skid_steering)) and not ok:
                self._text("WARNING", "Flight mode change failed")
                return int(mavlink.MAV_RESULT_FAILED)
        self._enter(mode)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _arm(self, msg: Any) -> int:
        """GCS_MAVLINK::handle_command_component_arm_disarm with AP_Arming_Rover's checks."""
        st = self._s
        arm, force = msg.param1 > 0.5, abs(msg.param2 - 21196.0) < 0.5
        if self.faults.reject_arm if arm else self.faults.reject_disarm:
            return int(mavlink.MAV_RESULT_FAILED)
        if self._ignored(int(msg.command)) or arm == st.armed:
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if arm and not force:
            traits = ROVER_MODES[st.mode]
            wants = needs_position(st.mode) or needs_velocity(st.mode, self.store.skid_steering)
            if not traits.allows_arming:
                self._text("CRITICAL", "PreArm: Mode not armable")
                return int(mavlink.MAV_RESULT_FAILED)
            # AP_Arming_Rover::gps_checks, only for a mode that needs a position: the AHRS (EKF3's source
            # check first, NavEKF3::pre_arm_check), then the position estimate
            refusal = self.store.ekf_sources_refusal() if wants else None
            if refusal is not None:
                self._text("CRITICAL", f"PreArm: AHRS: {refusal}")
                return int(mavlink.MAV_RESULT_FAILED)
            if wants and not self._position_ok(time.monotonic()):
                self._text("CRITICAL", "PreArm: Need Position Estimate")
                return int(mavlink.MAV_RESULT_FAILED)
        if arm:
            st.home = (st.x, st.y)
        st.armed = arm
        self._update_twist()
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _command(self, msg: Any, now: float) -> None:
        cmd = int(msg.command)
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            self._ack(cmd, self._set_mode(int(msg.param2), int(msg.param1), cmd), msg.param2, now)
        elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            self._ack(cmd, self._arm(msg), msg.param1, now)
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            self._ack(cmd, self._request_message(int(msg.param1)), msg.param1, now)
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            self._ack(cmd, self._set_interval(int(msg.param1), float(msg.param2), now), msg.param1, now)
        elif cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(cmd, self._request_message(VERSION_ID), msg.param1, now)
        else:
            self._ack(cmd, int(mavlink.MAV_RESULT_UNSUPPORTED), msg.param1, now)

    # ------------------------------------------------------------------ messages out (caller holds the lock)
    # ---- parameters ------------------------------------------------------------------------------------
    # ---- the GCS failsafe --------------------------------------------------------------------------------
    def _gcs_failsafe_check(self, now: float) -> None:
        """Rover::gcs_failsafe_check then Rover::failsafe_trigger, at 10 Hz."""
        s, st = self.store, self._s
        enable = int(s.get("FS_GCS_ENABLE", 0.0))
        if enable == 0 or st.gcs_last_seen is None:
            return
        on = now - st.gcs_last_seen >= s.gcs_lost_after_s
        if on and not st.fs_on:
            st.fs_start = now
        st.fs_on = on
        if not on:
            if st.fs_triggered:
                self._text("INFO", "GCS Failsafe Cleared")
            st.fs_triggered = False
            return
        in_hold = st.mode == HOLD and not (int(s.get("FS_OPTIONS", 0.0)) & FS_OPTION_ACTIVE_IN_HOLD)
        if st.fs_triggered or now - st.fs_start <= s.get("FS_TIMEOUT", 1.0) or st.mode == RTL or in_hold:
            return
        st.fs_triggered = True
        action = int(s.get("FS_ACTION", 0.0))
        self._text("WARNING", "GCS Failsafe")
        if not (st.mode == AUTO and enable == 2):  # 2: an AUTO mission continues
            self._failsafe_action(action)
        self.failsafe_events.append(FailsafeEvent(now, action, st.mode, st.armed))

    def _failsafe_action(self, action: int) -> None:
        """FS_ACTION as Rover/failsafe.cpp takes it (fallbacks when a mode cannot be entered)."""
        returns = self._s.home is not None  # RTL and SmartRTL need a home
        if action == 1:
            self._enter(RTL if returns else HOLD)
        elif action == 2:
            self._enter(HOLD)
        elif action in (3, 4):
            self._enter(SMART_RTL if returns else HOLD)
        elif action == 5:
            self._s.armed = False
        elif action == 6:
            self._enter(LOITER)
        self._update_twist()

    # ------------------------------------------------------------------ dispatch
    def _for_us(self, msg: Any) -> bool:
        return int(getattr(msg, "target_system", 0)) in (0, self.system_id)

    def _handle(self, msg: Any, now: float) -> None:
        """Dispatch one received message; caller holds the lock."""
        mtype = msg.get_type()
        if mtype in ("SET_MODE", "COMMAND_LONG") and self.faults.drop_commands > 0:
            cid = mavlink.MAVLINK_MSG_ID_SET_MODE if mtype == "SET_MODE" else int(msg.command)
            if not self.faults.drop_command_ids or cid in self.faults.drop_command_ids:
                self.faults.drop_commands -= 1
                self._s.dropped.append(cid)
                return
        if mtype == "HEARTBEAT":
            self.gcs_heartbeats.append(now)
            if self.store.is_gcs(int(msg.get_srcSystem())):
                self._s.gcs_last_seen = now
        elif not self._for_us(msg):
            return
        elif mtype in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"):
            self._answer_params(msg)
        elif mtype == "PARAM_SET":
            self._param_set(msg)
        elif mtype == "SET_MODE":
            sm = mavlink.MAVLINK_MSG_ID_SET_MODE
            result = self._set_mode(int(msg.custom_mode), int(msg.base_mode), sm)
            self._ack(sm, result, msg.custom_mode, now)
        elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
            self._command(msg, now)
        elif mtype == "SET_GPS_GLOBAL_ORIGIN":
            self._set_origin(msg)
        elif mtype in VISION_TYPES:
            self._vision(msg, now)
        elif mtype == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(msg, now)

    def _set_origin(self, msg: Any) -> None:
        """GCS_MAVLINK::handle_set_gps_global_origin / set_ekf_origin: once per boot; GPS_GLOBAL_ORIGIN."""
        lat, lon, alt = int(msg.latitude), int(msg.longitude), int(msg.altitude)
        if abs(lat) > 900_000_000 or abs(lon) > 1_800_000_000 or self._s.origin is not None:
            return
        self._s.origin = (lat, lon, alt)
        self._emit(ORIGIN_ID)

    def _vision(self, msg: Any, now: float) -> None:
        """AP_VisualOdom (VISO_TYPE > 0) hands a finite pose to EKF3; the pose itself is not fused here."""
        if msg.get_type() == "ATT_POS_MOCAP":
            fields = [*msg.q, msg.x, msg.y]
        else:
            yaw = [msg.yaw] if msg.get_type() == "VISION_POSITION_ESTIMATE" else [*msg.q]
            fields = [msg.x, msg.y, *yaw]
        if self.store.get("VISO_TYPE", 0.0) > 0 and all(math.isfinite(float(f)) for f in fields):
            self._s.vision_t = now
            self._s.vision_count += 1

    def _setpoint(self, msg: Any, now: float) -> None:
        """GCS_MAVLINK_Rover::handle_set_position_target_local_ned."""
        st = self._s
        frame, mask = int(msg.coordinate_frame), int(msg.type_mask)
        vx, vy, r = float(msg.vx), float(msg.vy), float(msg.yaw_rate)
        reason = ""
        if st.mode != GUIDED:
            reason = "not in GUIDED"
        elif self.requires_position_estimate and st.origin is None:
            reason = "no EKF origin"
        else:
            d = decode_setpoint(frame, mask, (vx, vy), float(msg.yaw), r, st.yaw, self.store.speed_max)
            if d.text:
                self._text("INFO", d.text)
            if d.target is None:
                reason = d.reason
            else:
                st.target, st.target_t = d.target, now
                self.stopped_by_timeout = False
                self._update_twist()
        self.setpoints.append(SetpointRecord(now, frame, mask, vx, vy, r, not reason, reason))
