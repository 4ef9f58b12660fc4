"""Loopback MAVLink emulator of an ArduPilot-Rover-like ground robot (stand-in for Scamper) for tests.

The emulator is a pymavlink ``udpin`` endpoint bound to ``127.0.0.1`` (port picked by the OS unless given);
it learns the ground station's address from the first datagram it receives (pymavlink ``udpin``
behaviour), so a client on ``udpout:127.0.0.1:<emu.port>`` must send something (e.g. its own HEARTBEAT)
before it hears anything back.

Behaviour (a small subset of ArduPilot Rover, these are the emulator's rules):

* **HEARTBEAT** at 1 Hz: type ``MAV_TYPE_GROUND_ROVER``, autopilot ``MAV_AUTOPILOT_ARDUPILOTMEGA``,
  ``custom_mode`` = current mode number (Rover: 0 MANUAL, 4 HOLD, 15 GUIDED), ``base_mode`` with
  ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` and ``MAV_MODE_FLAG_SAFETY_ARMED`` when armed.
* **Mode**: ``SET_MODE`` (acked with ``COMMAND_ACK.command`` = 11, the SET_MODE message id, as ArduPilot
  does) and ``COMMAND_LONG MAV_CMD_DO_SET_MODE`` (param2 = custom mode).  Only modes in ``ROVER_MODES`` are
  accepted.
* **Arming**: ``COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM`` (param1 = 1 arm, 0 disarm) answered with
  ``COMMAND_ACK``; ``faults.reject_arm`` / ``faults.reject_disarm`` answer ``MAV_RESULT_DENIED``.
* **Motion**: ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_BODY_NED`` (8) with velocity + yaw-rate
  (type mask bits 4, 5 and 12 clear) sets the body velocity ``[vx, vy, yaw_rate]`` (m/s, m/s, rad/s; x
  forward, y right, yaw rate clockwise seen from above), but only while GUIDED and armed.  Other frames or
  masks are recorded in ``setpoints`` but have no effect.  If no set-point arrives for
  ``setpoint_timeout_s`` (3 s, like Rover's guided-mode timeout) the rover stops and ``stopped_by_timeout``
  is set.  Disarming or leaving GUIDED stops it at once.
* **Pose**: the body velocity is integrated exactly (constant twist over each step) into a planar pose
  ``(x, y, yaw)`` in the emulator's local NED frame (x north, y east, yaw clockwise from north, rad), which
  starts at the origin.  ``pose_flu()`` gives the same pose in FLU/ENU-like terms (x forward-at-start,
  y left, yaw counter-clockwise), i.e. ``(x, -y, -yaw)``, as a ``flightstack.geometry.Pose``.
* **Faults**: ``faults.no_heartbeat`` suppresses HEARTBEATs (everything else keeps working).

All traffic is on 127.0.0.1.  One daemon thread with a stop flag and bounded waits (<= 20 ms);
``close()`` joins it within 1 s and closes the socket.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

from flightstack.geometry import Pose, wrap_angle

mavlink = mavutil.mavlink

ROVER_MODES = {0: "MANUAL", 4: "HOLD", 10: "AUTO", 11: "RTL", 15: "GUIDED"}
GUIDED = 15
HOLD = 4
# Type-mask bits that must be clear for a velocity + yaw-rate set-point: vx (8), vy (16), yaw_rate (2048).
_VEL_YAWRATE_BITS = 8 | 16 | 2048


@dataclass
class RoverFaults:
    """Fault switches a test may flip at any time."""

    no_heartbeat: bool = False
    reject_arm: bool = False
    reject_disarm: bool = False


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


class MavlinkRoverEmulator:
    """A GUIDED-mode velocity-controlled rover speaking MAVLink on ``udpin:127.0.0.1:<port>``."""

    def __init__(
        self,
        port: int = 0,
        system_id: int = 1,
        component_id: int = 1,
        heartbeat_hz: float = 1.0,
        setpoint_timeout_s: float = 3.0,
    ) -> None:
        self.faults = RoverFaults()
        self.setpoint_timeout_s = setpoint_timeout_s
        self.heartbeat_period_s = 1.0 / heartbeat_hz
        self.setpoints: list[SetpointRecord] = []
        self.stopped_by_timeout = False
        self._s = _State()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=system_id, source_component=component_id
        )
        self.port: int = self._conn.port.getsockname()[1]
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
        """Received COMMAND_LONG / SET_MODE as (command id, param, MAV_RESULT sent back)."""
        with self._lock:
            return list(self._s.commands)

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

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop the thread (joined within 1 s) and close the socket. Idempotent."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)
        with contextlib.suppress(OSError):
            self._conn.close()

    def __enter__(self) -> MavlinkRoverEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _run(self) -> None:
        last = time.monotonic()
        next_hb = last
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
                if (
                    self._s.last_setpoint_t is not None
                    and now - self._s.last_setpoint_t > self.setpoint_timeout_s
                    and self._s.vel != (0.0, 0.0, 0.0)
                ):
                    self._s.vel = (0.0, 0.0, 0.0)
                    self.stopped_by_timeout = True
            if now >= next_hb:
                next_hb = now + self.heartbeat_period_s
                if not self.faults.no_heartbeat:
                    self._send_heartbeat()

    def _send_heartbeat(self) -> None:
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

    def _ack(self, command: int, result: int, param: float) -> None:
        self._s.commands.append((command, param, result))
        self._send(lambda: self._conn.mav.command_ack_send(command, result))

    def _set_mode(self, mode: int) -> int:
        if mode not in ROVER_MODES:
            return mavlink.MAV_RESULT_DENIED
        self._s.mode = mode
        if mode != GUIDED:
            self._s.vel = (0.0, 0.0, 0.0)
        return mavlink.MAV_RESULT_ACCEPTED

    def _handle(self, msg: Any, now: float) -> None:
        """Dispatch one received message; caller holds the lock."""
        mtype = msg.get_type()
        if mtype == "SET_MODE":
            self._ack(mavlink.MAVLINK_MSG_ID_SET_MODE, self._set_mode(int(msg.custom_mode)), msg.custom_mode)
        elif mtype == "COMMAND_LONG":
            cmd = int(msg.command)
            if cmd == mavlink.MAV_CMD_DO_SET_MODE:
                self._ack(cmd, self._set_mode(int(msg.param2)), msg.param2)
            elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                arm = msg.param1 > 0.5
                reject = self.faults.reject_arm if arm else self.faults.reject_disarm
                if reject:
                    result = mavlink.MAV_RESULT_DENIED
                else:
                    self._s.armed = arm
                    if not arm:
                        self._s.vel = (0.0, 0.0, 0.0)
                    result = mavlink.MAV_RESULT_ACCEPTED
                self._ack(cmd, result, msg.param1)
            else:
                self._ack(cmd, mavlink.MAV_RESULT_UNSUPPORTED, msg.param1)
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
