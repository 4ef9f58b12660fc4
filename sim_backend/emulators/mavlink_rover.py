"""Loopback MAVLink emulator of an ArduPilot-Rover-like ground robot (stand-in for Scamper) for tests.

A pymavlink ``udpin`` endpoint on ``127.0.0.1`` (port from the OS unless given); it learns the ground
station's address from the first datagram, so a client on ``udpout:127.0.0.1:<emu.port>`` must send
something (e.g. its HEARTBEAT) before it hears anything. A small subset of ArduPilot Rover:

* **HEARTBEAT** at ``heartbeat_hz`` (1 Hz): ``MAV_TYPE_GROUND_ROVER``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``,
  ``custom_mode`` the Rover mode (0 MANUAL, 4 HOLD, 15 GUIDED), the armed flag in ``base_mode``.
* **Mode** by ``SET_MODE`` (acked with command id 11, as ArduPilot) or ``MAV_CMD_DO_SET_MODE``; **arming**
  by ``MAV_CMD_COMPONENT_ARM_DISARM``; only ``ROVER_MODES`` are accepted.
* **Motion**: ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_BODY_NED`` with velocity + yaw rate sets the
  body velocity ``[vx, vy, yaw_rate]`` (m/s, m/s, rad/s; x forward, y right, yaw rate clockwise), only while
  GUIDED and armed; other frames or masks are recorded in ``setpoints`` only. No set-point for
  ``setpoint_timeout_s`` (3 s, Rover/mode_guided.cpp) stops the rover (``stopped_by_timeout``); disarming
  or leaving GUIDED stops it at once.
* **Pose**: integrated exactly into ``(x, y, yaw)`` in the local NED frame (x north, y east, yaw clockwise
  from north, rad) from the origin; ``pose_flu()`` is ``(x, -y, -yaw)`` as a ``Pose``.
* **Faults** (`RoverFaults`), **parameters and the GCS failsafe** (`RoverParams`), each with the reports or
  ArduPilot sources it follows, are described on those classes; ``pilot_override(mode=..., armed=...)``
  changes mode or arming as an RC switch, a failsafe or another GCS would.

Why a client must read the HEARTBEAT: ArduPilot ACKs ``SET_MODE`` with command id 11
(github.com/ArduPilot/pymavlink/pull/411), its maintainers say a mode change is to be checked on the
HEARTBEAT (github.com/ArduPilot/ardupilot/pull/14452), and the armed flag shows only in the next one, up
to 1 s later (github.com/mavlink/qgroundcontrol/pull/10810).

All traffic is on 127.0.0.1. One daemon thread with bounded waits (<= 20 ms); ``close()`` joins it
within 1 s and closes the socket.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

from flightstack.paper.geometry import Pose, wrap_angle

from .device_links import DeviceLinks
from .radio import DeviceRadio

mavlink = mavutil.mavlink

ROVER_MODES = {0: "MANUAL", 4: "HOLD", 5: "LOITER", 10: "AUTO", 11: "RTL", 12: "SMART_RTL", 15: "GUIDED"}
GUIDED = 15
HOLD = 4
LOITER = 5
AUTO = 10
RTL = 11
SMART_RTL = 12
FS_CHECK_PERIOD_S = 0.1  # Rover runs gcs_failsafe_check at 10 Hz
OLD_FIRMWARE_GCS_TIMEOUT_S = 2.0  # the fixed GCS timeout of firmware without FS_GCS_TIMEOUT
FS_OPTION_ACTIVE_IN_HOLD = 1  # FS_OPTIONS bit 0
# Type-mask bits that must be clear for a velocity + yaw-rate set-point: vx (8), vy (16), yaw_rate (2048).
_VEL_YAWRATE_BITS = 8 | 16 | 2048


COMPANION_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER


@dataclass
class RoverFaults:
    """Fault switches a test may flip at any time, each what ArduPilot / MAVLink users reported.

    - ``no_heartbeat``: the autopilot's HEARTBEATs stop (everything else keeps working).
    - ``reject_arm`` / ``reject_disarm``: ``MAV_RESULT_DENIED`` (pre-arm checks failing).
    - ``lost_acks`` (command ids): the command takes effect, its ACK is never sent
      (github.com/PX4/PX4-Autopilot/issues/8924, github.com/mavlink/mavros/issues/1590).
    - ``duplicate_acks``: every ACK twice (github.com/mavlink/qgroundcontrol/issues/2975,
      github.com/mavlink/mavlink/pull/768, github.com/PX4/PX4-Autopilot/pull/27343).
    - ``ack_delay_s``: every ACK this late, the command applied at once; a late ACK is read as the answer
      to a later command with the same id (github.com/PX4/PX4-Autopilot/issues/12685).
    - ``ack_accepted_but_ignored`` (command ids): ACCEPTED but not applied
      (github.com/ArduPilot/ardupilot/issues/1385; github.com/PX4/PX4-Autopilot/issues/26034).
    - ``drop_commands``: the next N COMMAND_LONG / SET_MODE are lost on the way in (counted in
      ``dropped_commands``), so the sender must re-send (github.com/mavlink/mavlink/issues/2198).
    - ``companion_heartbeat``: a companion computer (component 191, ``MAV_TYPE_ONBOARD_CONTROLLER``,
      ``MAV_AUTOPILOT_INVALID``, mode 0, disarmed) also beats, just before the autopilot, even with
      ``no_heartbeat`` (github.com/mavlink/MAVSDK/pull/516, github.com/ArduPilot/pymavlink/pull/87).
    - ``drop_param_replies`` / ``duplicate_param_replies``: PARAM_VALUE lost / sent twice.
    """

    no_heartbeat: bool = False
    reject_arm: bool = False
    reject_disarm: bool = False
    lost_acks: set[int] = field(default_factory=set)  # COMMAND_ACK.command ids never answered
    duplicate_acks: bool = False
    ack_delay_s: float = 0.0
    ack_accepted_but_ignored: set[int] = field(default_factory=set)  # ACCEPTED, but nothing happens
    drop_commands: int = 0  # the next N COMMAND_LONG / SET_MODE never arrive
    companion_heartbeat: bool = False
    drop_param_replies: int = 0  # the next N PARAM_VALUE are lost on the way out
    duplicate_param_replies: bool = False  # every PARAM_VALUE is sent twice


@dataclass(frozen=True)
class RoverParams:
    """The emulated firmware's parameters; the defaults are what the lab's Scamper must be set to: the
    failsafe on, Hold, 3 s + 1 s, our GCS system id 255 (docs/drivers.md, "The robot's own failsafe").

    Read with ``PARAM_REQUEST_READ`` (by name or index) or ``PARAM_REQUEST_LIST``, answered with
    ``PARAM_VALUE`` typed as ArduPilot's (INT8 enums, INT16 system ids, REAL32 times); an unknown one or a
    request to another system gets no answer. The GCS failsafe follows ArduPilot Rover (Rover/Rover.cpp
    ``gcs_failsafe_check``, Rover/failsafe.cpp ``failsafe_trigger``, libraries/GCS_MAVLink): the GCS is
    lost after ``FS_GCS_TIMEOUT`` without a HEARTBEAT from system ``SYSID_MYGCS`` (newer firmware:
    ``MAV_GCS_SYSID`` .. ``MAV_GCS_SYSID_HI``; absent: a fixed 2 s), checked at 10 Hz, never for a GCS never
    heard; ``FS_ACTION`` is taken once per loss ``FS_TIMEOUT`` later (armed or not; not in RTL, nor in
    HOLD unless ``FS_OPTIONS`` bit 0; an AUTO mission continues with ``FS_GCS_ENABLE`` 2). RTL and SmartRTL
    drive straight home (the pose at arming) at ``rtl_speed_mps`` until within ``wp_radius_m``, HOLD
    without a home; LOITER stays still. ``failsafe_events`` records each action.
    """

    fs_gcs_enable: int = 1
    fs_action: int = 2  # Hold
    fs_timeout_s: float = 1.0
    fs_gcs_timeout_s: float = 3.0
    gcs_sysid: int = 255
    gcs_sysid_name: str = "SYSID_MYGCS"  # or "MAV_GCS_SYSID" (newer firmware, which also has _HI)
    gcs_sysid_hi: int = 0  # MAV_GCS_SYSID_HI (only with gcs_sysid_name "MAV_GCS_SYSID")
    fs_options: int = 0
    absent: frozenset[str] = frozenset()  # parameters this firmware does not have (never answered)
    rtl_speed_mps: float = 0.5  # emulator's RTL / SmartRTL speed toward home
    wp_radius_m: float = 2.0  # WP_RADIUS: RTL stops this close to home

    def __post_init__(self) -> None:
        if self.gcs_sysid_name not in ("SYSID_MYGCS", "MAV_GCS_SYSID"):
            raise ValueError(
                f"gcs_sysid_name must be SYSID_MYGCS or MAV_GCS_SYSID, got {self.gcs_sysid_name!r}"
            )

    def table(self, system_id: int) -> list[tuple[str, float, int]]:
        """(name, value, MAV_PARAM_TYPE) in index order, without the absent ones."""
        i8, i16, i32, f32 = (
            mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_INT16, mavlink.MAV_PARAM_TYPE_INT32,
            mavlink.MAV_PARAM_TYPE_REAL32,
        )  # fmt: skip
        rows = [
            ("SYSID_THISMAV", float(system_id), i16),
            (self.gcs_sysid_name, float(self.gcs_sysid), i16),
            ("FS_ACTION", float(self.fs_action), i8),
            ("FS_TIMEOUT", float(self.fs_timeout_s), f32),
            ("FS_GCS_ENABLE", float(self.fs_gcs_enable), i8),
            ("FS_OPTIONS", float(self.fs_options), i32),
            ("FS_GCS_TIMEOUT", float(self.fs_gcs_timeout_s), f32),
        ]
        if self.gcs_sysid_name == "MAV_GCS_SYSID":
            rows.insert(2, ("MAV_GCS_SYSID_HI", float(self.gcs_sysid_hi), i16))
        return [r for r in rows if r[0] not in self.absent]

    def is_gcs(self, sysid: int) -> bool:
        """Does a HEARTBEAT from this source system count as our GCS's (GCS::sysid_is_gcs)?"""
        if self.gcs_sysid_name == "MAV_GCS_SYSID" and self.gcs_sysid_hi >= self.gcs_sysid:
            return self.gcs_sysid <= sysid <= self.gcs_sysid_hi
        return sysid == self.gcs_sysid

    @property
    def gcs_lost_after_s(self) -> float:
        """FS_GCS_TIMEOUT, or the fixed 2 s of firmware without it."""
        return OLD_FIRMWARE_GCS_TIMEOUT_S if "FS_GCS_TIMEOUT" in self.absent else self.fs_gcs_timeout_s


@dataclass(frozen=True)
class FailsafeEvent:
    """One GCS failsafe action: t (emulator monotonic s), FS_ACTION value, mode (and armed) after it."""

    t: float
    action: int
    mode: int
    armed: bool


@dataclass(frozen=True)
class SetpointRecord:
    """One received SET_POSITION_TARGET_LOCAL_NED (t: emulator monotonic time, s)."""

    t: float
    frame: int
    type_mask: int
    vx: float
    vy: float
    yaw_rate: float
    applied: bool


@dataclass
class _State:
    mode: int = HOLD
    armed: bool = False
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    vel: tuple[float, float, float] = (0.0, 0.0, 0.0)  # body NED/FRD: vx fwd, vy right (m/s), r cw (rad/s)
    last_setpoint_t: float | None = None
    commands: list[tuple[int, float, int]] = field(default_factory=list)  # (command, param, result)
    acks_sent: list[tuple[int, int]] = field(default_factory=list)  # (command, result), every copy
    dropped: list[int] = field(default_factory=list)  # command ids lost on the way in
    home: tuple[float, float] | None = None  # NED x, y (m) at arming: where RTL drives to
    gcs_last_seen: float | None = None  # last HEARTBEAT from the GCS system id (monotonic s)
    fs_on: bool = False  # GCS lost (FS_GCS_TIMEOUT passed)
    fs_start: float = 0.0
    fs_triggered: bool = False  # the action for this loss was taken
    param_replies: int = 0  # PARAM_VALUE messages sent (duplicates included)


class MavlinkRoverEmulator:
    """A GUIDED-mode velocity-controlled rover speaking MAVLink on ``udpin:127.0.0.1:<port>``."""

    def __init__(
        self,
        port: int = 0,
        system_id: int = 1,
        component_id: int = 1,
        heartbeat_hz: float = 1.0,
        setpoint_timeout_s: float = 3.0,
        params: RoverParams | None = None,
        radio: DeviceRadio | None = None,
        links: DeviceLinks | None = None,
    ) -> None:
        """radio: the robot's network (`radio.DeviceRadio` with links "uplink" (from the ground station)
        and "downlink"); None: a perfect link. links: the rig's links of the robot
        (`device_links.DeviceLinks`: every MAVLink message from the ground station is acted on late by
        the "robot" link, or lost, after the radio); None: none."""
        self.faults = RoverFaults()
        self.radio = radio
        self.params = params or RoverParams()
        self.system_id = system_id
        self.failsafe_events: list[FailsafeEvent] = []
        self.setpoint_timeout_s = setpoint_timeout_s
        self.heartbeat_period_s = 1.0 / heartbeat_hz
        self.setpoints: list[SetpointRecord] = []
        self.gcs_heartbeats: list[float] = []  # emulator monotonic times (s) of the client's HEARTBEATs
        self.stopped_by_timeout = False
        self._s = _State()
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
        """Current body velocity (vx fwd m/s, vy right m/s, yaw rate clockwise rad/s)."""
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

    def pilot_override(self, mode: int | None = None, armed: bool | None = None) -> None:
        """Change mode and/or arming as an RC switch or failsafe would (no ACK, shows in the heartbeat)."""
        with self._lock:
            if mode is not None:
                self._s.mode = mode
            if armed is not None:
                self._s.armed = armed
            if self._s.mode != GUIDED or not self._s.armed:
                self._s.vel = (0.0, 0.0, 0.0)

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

    # ------------------------------------------------------------------ internals
    def _run(self) -> None:
        last = time.monotonic()
        next_hb = next_fs = last
        while not self._stop.is_set():
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.02)
            except OSError:
                if self._stop.is_set():
                    break
                msg = None
            now = time.monotonic()
            with self._lock:
                self._integrate(now - last)
                last = now
                if msg is not None:
                    self._handle(msg, now)
                self._flush_acks(now)
                if (
                    self._s.last_setpoint_t is not None
                    and now - self._s.last_setpoint_t > self.setpoint_timeout_s
                    and self._s.vel != (0.0, 0.0, 0.0)
                ):
                    self._s.vel = (0.0, 0.0, 0.0)
                    self.stopped_by_timeout = True
                if now >= next_fs:
                    next_fs = now + FS_CHECK_PERIOD_S
                    self._gcs_failsafe_check(now)
                self._drive_home()
            if now >= next_hb:
                next_hb = now + self.heartbeat_period_s
                self._send_heartbeat()

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
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if self._s.armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            mode = self._s.mode
            status = mavlink.MAV_STATE_ACTIVE if self._s.armed else mavlink.MAV_STATE_STANDBY
        self._send(
            lambda: self._conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode, status
            )
        )

    def _send(self, fn: Callable[[], None]) -> None:
        with contextlib.suppress(OSError):
            fn()

    def _integrate(self, dt: float) -> None:
        """Exact integration of the constant body twist over dt (s); caller holds the lock."""
        vx, vy, r = self._s.vel
        if dt <= 0.0 or (vx == 0.0 and vy == 0.0 and r == 0.0):
            return
        yaw0 = self._s.yaw
        dpsi = r * dt
        if abs(dpsi) < 1e-9:
            bx, by = vx * dt, vy * dt
        else:
            s, c = math.sin(dpsi), math.cos(dpsi)
            bx = (vx * s + vy * (c - 1.0)) / r
            by = (vx * (1.0 - c) + vy * s) / r
        c0, s0 = math.cos(yaw0), math.sin(yaw0)
        self._s.x += c0 * bx - s0 * by
        self._s.y += s0 * bx + c0 * by
        self._s.yaw = wrap_angle(yaw0 + dpsi)

    def _ack(self, command: int, result: int, param: float, now: float) -> None:
        """Log the command and queue its ACK(s) per the faults; caller holds the lock."""
        self._s.commands.append((command, param, result))
        if command in self.faults.lost_acks:
            return
        due = now + max(0.0, self.faults.ack_delay_s)
        for _ in range(2 if self.faults.duplicate_acks else 1):
            self._pending_acks.append((due, command, result))

    def _flush_acks(self, now: float) -> None:
        """Send the ACKs that are due; caller holds the lock."""
        due = [a for a in self._pending_acks if a[0] <= now]
        self._pending_acks = [a for a in self._pending_acks if a[0] > now]
        for _, command, result in due:
            self._s.acks_sent.append((command, result))
            self._send(functools.partial(self._conn.mav.command_ack_send, command, result))

    def _ignored(self, command: int) -> bool:
        return command in self.faults.ack_accepted_but_ignored

    # ---- parameters and the GCS failsafe (caller holds the lock) ---------------------------------------
    def _answer_params(self, msg: Any) -> None:
        table = self.params.table(self.system_id)
        if msg.get_type() == "PARAM_REQUEST_LIST":
            wanted = list(range(len(table)))
        elif int(msg.param_index) >= 0:
            wanted = [int(msg.param_index)] if int(msg.param_index) < len(table) else []
        else:
            wanted = [i for i, row in enumerate(table) if row[0] == str(msg.param_id)]
        for i in wanted:  # an unknown name or index: no answer, as ArduPilot
            name, value, ptype = table[i]
            for _ in range(2 if self.faults.duplicate_param_replies else 1):
                if self.faults.drop_param_replies > 0:
                    self.faults.drop_param_replies -= 1
                    continue
                self._s.param_replies += 1
                self._send(
                    functools.partial(
                        self._conn.mav.param_value_send, name.encode(), value, ptype, len(table), i
                    )
                )

    def _gcs_failsafe_check(self, now: float) -> None:
        """Rover::gcs_failsafe_check then failsafe_trigger (module docstring), at 10 Hz."""
        p, st = self.params, self._s
        if p.fs_gcs_enable == 0 or st.gcs_last_seen is None:
            return
        on = now - st.gcs_last_seen >= p.gcs_lost_after_s
        if on and not st.fs_on:
            st.fs_start = now
        st.fs_on = on
        if not on:
            st.fs_triggered = False
            return
        in_hold = st.mode == HOLD and not (p.fs_options & FS_OPTION_ACTIVE_IN_HOLD)
        if st.fs_triggered or now - st.fs_start <= p.fs_timeout_s or st.mode == RTL or in_hold:
            return
        st.fs_triggered = True
        if not (st.mode == AUTO and p.fs_gcs_enable == 2):  # 2: an AUTO mission continues
            self._failsafe_action(p.fs_action)
        self.failsafe_events.append(FailsafeEvent(now, p.fs_action, st.mode, st.armed))

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
            self._s.vel = (0.0, 0.0, 0.0)
        elif action == 6:
            self._enter(LOITER)

    def _enter(self, mode: int) -> None:
        self._s.mode = mode
        self._s.vel = (0.0, 0.0, 0.0)

    def _drive_home(self) -> None:
        """RTL / SmartRTL: face home and drive to it at rtl_speed_mps; stop within wp_radius_m."""
        st = self._s
        if st.mode not in (RTL, SMART_RTL) or not st.armed or st.home is None:
            return
        dx, dy = st.home[0] - st.x, st.home[1] - st.y
        if math.hypot(dx, dy) <= self.params.wp_radius_m:
            st.vel = (0.0, 0.0, 0.0)
            return
        st.yaw = math.atan2(dy, dx)  # NED: yaw clockwise from north = atan2(east, north)
        st.vel = (self.params.rtl_speed_mps, 0.0, 0.0)

    def _set_mode(self, mode: int, ack_id: int) -> int:
        if mode not in ROVER_MODES:
            return mavlink.MAV_RESULT_DENIED
        if self._ignored(ack_id):
            return mavlink.MAV_RESULT_ACCEPTED
        self._s.mode = mode
        if mode != GUIDED:
            self._s.vel = (0.0, 0.0, 0.0)
        return mavlink.MAV_RESULT_ACCEPTED

    def _handle(self, msg: Any, now: float) -> None:
        """Dispatch one received message; caller holds the lock."""
        mtype = msg.get_type()
        if mtype in ("SET_MODE", "COMMAND_LONG") and self.faults.drop_commands > 0:
            self.faults.drop_commands -= 1
            self._s.dropped.append(
                mavlink.MAVLINK_MSG_ID_SET_MODE if mtype == "SET_MODE" else int(msg.command)
            )
            return
        if mtype == "HEARTBEAT":
            self.gcs_heartbeats.append(now)
            if self.params.is_gcs(int(msg.get_srcSystem())):
                self._s.gcs_last_seen = now
        elif mtype in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"):
            if int(msg.target_system) in (0, self.system_id):
                self._answer_params(msg)
        elif mtype == "SET_MODE":
            sm = mavlink.MAVLINK_MSG_ID_SET_MODE
            self._ack(sm, self._set_mode(int(msg.custom_mode), sm), msg.custom_mode, now)
        elif mtype == "COMMAND_LONG":
            cmd = int(msg.command)
            if cmd == mavlink.MAV_CMD_DO_SET_MODE:
                self._ack(cmd, self._set_mode(int(msg.param2), cmd), msg.param2, now)
            elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                arm = msg.param1 > 0.5
                reject = self.faults.reject_arm if arm else self.faults.reject_disarm
                if reject:
                    result = mavlink.MAV_RESULT_DENIED
                else:
                    if not self._ignored(cmd):
                        if arm and not self._s.armed:
                            self._s.home = (self._s.x, self._s.y)
                        self._s.armed = arm
                        if not arm:
                            self._s.vel = (0.0, 0.0, 0.0)
                    result = mavlink.MAV_RESULT_ACCEPTED
                self._ack(cmd, result, msg.param1, now)
            else:
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg.param1, now)
        elif mtype == "SET_POSITION_TARGET_LOCAL_NED":
            frame, mask = int(msg.coordinate_frame), int(msg.type_mask)
            ok = (
                frame == mavlink.MAV_FRAME_BODY_NED
                and (mask & _VEL_YAWRATE_BITS) == 0
                and self._s.mode == GUIDED
                and self._s.armed
            )
            vx, vy, r = float(msg.vx), float(msg.vy), float(msg.yaw_rate)
            if ok and all(math.isfinite(v) for v in (vx, vy, r)):
                self._s.vel = (vx, vy, r)
                self._s.last_setpoint_t = now
                self.stopped_by_timeout = False
            else:
                ok = False
            self.setpoints.append(SetpointRecord(now, frame, mask, vx, vy, r, ok))
