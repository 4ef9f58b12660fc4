"""Scamper ground-robot driver over MAVLink (ArduPilot Rover conventions), implementing `hal.GroundRobot`.

Scamper's own interface is not public, so the robot is driven like an ArduPilot Rover. **Its HEARTBEAT
decides, not a reply**: ``custom_mode`` is the Rover mode (GUIDED = 15), ``base_mode & 128`` says armed. A
COMMAND_ACK can be lost, duplicated, late, or ACCEPTED for a change that never happens
(github.com/ArduPilot/ardupilot/issues/1385), so ACKs only steer re-sends and fast failure; a change
succeeds when a heartbeat received after the send shows it (`_ensure`: nothing sent if a fresh heartbeat
already shows it; an explicit rejection fails at once; no ACK and no change: re-sent every
``ack_timeout_s``, ``command_sends`` in all; ACCEPTED but no change ``ack_timeout_s`` + 2 heartbeat
periods later: not trusted). Only vehicle heartbeats count (as pymavlink's
``probably_vehicle_heartbeat``); a companion computer's are ignored. The reaction to each condition and
the robot's own failsafe settings: docs/drivers.md ("Ground robot").

Threads (drivers/scamper/link.py): ``scamper-rx`` receives everything; ``scamper-tx`` sends a GCS
HEARTBEAT at 1 Hz and re-sends the set-point at ``stream_hz`` (Rover stops ~3 s after the last one) as
``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_BODY_NED``, ``type_mask`` 1511 (vx, vy, yaw_rate).
Neither ends on an error. The driver never fights a mode change or disarm by the robot (a pilot's switch
must win). While muted (guardian takeover, ``set_muted(fn)``) nothing is written and ``close()`` skips
its disarm.

What ArduPilot needs to move indoors (drivers/scamper/nav.py has the frames, clock and sources): from
the first heartbeat on, ``scamper-tx`` sets the EKF origin (SET_GPS_GLOBAL_ORIGIN, msg 48, the configured
lab origin) every ``ORIGIN_RETRY_S`` until the vehicle reports it (GPS_GLOBAL_ORIGIN, msg 49, which
ArduPilot sends when it takes a new origin), from the second try on asking for it too
(MAV_CMD_REQUEST_MESSAGE: a vehicle that had an origin already ignores ours and only answers that);
and it streams the robot's own motion-capture pose
(``pose_source``) as VISION_POSITION_ESTIMATE (msg 102) at ``vision_hz``, never a pose older than
``vision_max_age_s``. ``connect()`` goes on to GUIDED only once the origin is confirmed and
``VISION_LEAD_SAMPLES`` poses were sent (each wait bounded by ``origin_timeout_s``). A vehicle seen
to reboot (SYSTEM_TIME's ``time_boot_ms`` going back) or coming back after a heartbeat gap longer than
``link_timeout_s`` has forgotten its origin: it is set and confirmed again (event
``origin_forgotten``; ``RobotState.ready`` is False meanwhile).

Raw log: given ``tlog_path``, every message received from and written to the robot goes to a pymavlink
.tlog there (drivers/scamper/tlog.py), from connect to close.

Frames and units: ``V = [v_x, v_y, v_z, ω]`` in the flightstack body frame FLU (m/s, rad/s
counter-clockwise seen from above); MAVLink's body frame is FRD with yaw rate clockwise, so the driver
sends ``vx = v_x, vy = -v_y, yaw_rate = -ω``; ``v_z`` is ignored. A non-omni rover cannot move sideways
(ArduPilot behaviour, not verified on hardware).
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from flightstack.drivers.device_threads import MutedCheck
from flightstack.drivers.scamper.link import (
    GCS_HEARTBEAT_PERIOD_S,
    ROVER_GUIDED_MODE,
    TYPE_MASK_VEL_YAWRATE,
    HeartbeatProbe,
    ScamperCommandError,
    ScamperConfig,
    ScamperError,
    ScamperLink,
    ScamperLinkError,
    is_vehicle_heartbeat,
    probe_heartbeat,
)
from flightstack.drivers.scamper.nav import LabOrigin, OriginState, VisionStream
from flightstack.drivers.scamper.tlog import TlogWriter
from flightstack.events import Event, ScamperKind
from flightstack.hal import StampedPose

__all__ = [
    "GCS_HEARTBEAT_PERIOD_S",
    "ROVER_GUIDED_MODE",
    "TYPE_MASK_VEL_YAWRATE",
    "HeartbeatProbe",
    "RobotState",
    "ScamperCommandError",
    "ScamperConfig",
    "ScamperDriver",
    "ScamperError",
    "ScamperLinkError",
    "mode_name",
    "probe_heartbeat",
]

mavlink = mavutil.mavlink

DEFAULT_HEARTBEAT_PERIOD_S = 1.0  # ArduPilot's HEARTBEAT rate, assumed until measured
ORIGIN_TICK_S = 0.1  # how often scamper-tx checks whether the origin is due again (s)
BOOT_BACKSTEP_MS = 200  # SYSTEM_TIME.time_boot_ms going back more than this: the vehicle rebooted
VISION_LEAD_SAMPLES = 10  # poses sent before GUIDED is asked for (0.5 s at 20 Hz): the EKF needs them first
PoseSource = Callable[[], StampedPose | None]  # the robot's own motion-capture pose, time.monotonic() stamp
_PENDING_RESULTS = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)


@dataclass(frozen=True)
class RobotState:
    """What the robot's last HEARTBEAT said; ``custom_mode``/``armed`` are None before the first one."""

    custom_mode: int | None
    armed: bool | None
    age_s: float  # since that heartbeat (s); inf before the first one
    link_alive: bool
    origin_confirmed: bool = False  # the vehicle reported its EKF origin since it (re)booted

    @property
    def mode_name(self) -> str:
        return mode_name(self.custom_mode)

    @property
    def ready(self) -> bool:
        """Heartbeat is live, shows GUIDED and armed, and the EKF has its origin: set-points are obeyed."""
        return (
            self.link_alive
            and self.custom_mode == ROVER_GUIDED_MODE
            and bool(self.armed)
            and self.origin_confirmed
        )


def mode_name(custom_mode: int | None) -> str:
    if custom_mode is None:
        return "unknown"
    return mavutil.mode_mapping_rover.get(custom_mode, f"mode {custom_mode}")


def _result_name(result: int) -> str:
    enum = mavlink.enums["MAV_RESULT"]
    return enum[result].name.removeprefix("MAV_RESULT_") if result in enum else str(result)


class ScamperDriver:
    """MAVLink driver of the Scamper ground robot; implements `flightstack.hal.GroundRobot`.

    ``events`` is a list of ``(t, kind, detail)`` with ``t`` from ``time.monotonic()`` (s) and ``kind`` one
    of ``connected``, ``link_lost``, ``link_restored``, ``no_command_needed``, ``command_resent``,
    ``ack_lost_confirmed_by_heartbeat``, ``ack_contradicted_by_heartbeat``, ``mode_changed``,
    ``disarmed_by_robot``, ``armed_by_robot``, ``disarm_failed``, ``disarm_skipped_muted``,
    ``origin_confirmed``, ``origin_forgotten``.  ``resends`` counts COMMAND_LONG re-sends; ``counts`` the
    link's sends and errors (drivers/scamper/link.py: "sent", "muted", "send_error", "recv_error",
    "rx_error", "tx_error", "thread_error", "muted_check_error"), the messages sent by kind
    ("setpoint_sent", "vision_sent", "origin_sent") and the poses not sent by reason ("vision_stale",
    "vision_no pose", "vision_not new", "vision_not finite").
    """

    def __init__(
        self,
        config: ScamperConfig | None = None,
        muted: MutedCheck | None = None,
        pose_source: PoseSource | None = None,
        tlog_path: str | Path | None = None,
    ) -> None:
        """muted: the guardian's takeover check (module docstring); also settable by `set_muted`.
        pose_source: the robot's motion-capture pose (None: no VISION_POSITION_ESTIMATE is sent; a real
        Rover then refuses GUIDED). tlog_path: the raw .tlog of the link (None: none)."""
        self.config = config or ScamperConfig()
        self.pose_source = pose_source
        self.tlog_path = None if tlog_path is None else Path(tlog_path)
        self.tlog: TlogWriter | None = None
        cfg = self.config
        self.origin = LabOrigin(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.origin_alt_m)
        self._origin_state = OriginState()
        self._vision = VisionStream(self.config.vision_max_age_s)
        self._boot_ms: int | None = None  # the vehicle's last SYSTEM_TIME.time_boot_ms
        self.events: list[Event] = []  # source scamper, time.monotonic() s
        self.resends = 0  # COMMAND_LONG re-sends (no ACK and no heartbeat change in time)
        self.counts: Counter[str] = Counter()
        self._muted = muted
        self._link: ScamperLink | None = None
        self._lock = threading.Lock()  # guards set-point, acks, heartbeat state, events
        self._cv = threading.Condition(self._lock)
        self._ack_log: list[tuple[int, int]] = []  # every COMMAND_ACK received: (command, result)
        self._setpoint = np.zeros(3)  # NED body: vx (m/s), vy right (m/s), yaw_rate clockwise (rad/s)
        self._streaming = False
        self._last_hb: float | None = None
        self._hb_seq = 0  # robot heartbeats received so far
        self._hb_mode: int | None = None
        self._hb_armed: bool | None = None
        self._hb_period: float | None = None  # measured robot HEARTBEAT period (s)
        self._link_alive = False
        self._target = (1, 1)
        self._arm_sent = False

    # ------------------------------------------------------------------ public API
    def connect(self) -> None:
        """Connect, wait for HEARTBEAT, set GUIDED and arm; raises ScamperLinkError / ScamperCommandError.

        Blocks at most ``heartbeat_timeout_s + 2 (command_sends · ack_timeout_s + 2 heartbeat periods)``;
        on failure the robot is disarmed if an arm was sent (best effort) and everything is closed again.
        """
        cfg = self.config
        if self._link is not None:
            raise ScamperError("ScamperDriver.connect() called twice")
        with self._lock:  # a reconnect learns the robot's state afresh
            self._last_hb = self._hb_mode = self._hb_armed = self._hb_period = None
            self._arm_sent = False
            self._origin_state = OriginState()
            self._vision = VisionStream(cfg.vision_max_age_s)
            self._boot_ms = None
        if self.tlog_path is not None and self.tlog is None:
            self.tlog = TlogWriter(self.tlog_path)
        try:
            self._link = ScamperLink(cfg, self.counts, self._muted, self.tlog)
        except BaseException:
            self._close_tlog()
            raise
        self._link.start(
            self._on_message,
            self._stream_tick,
            (1.0 / cfg.vision_hz, self._vision_tick),
            (ORIGIN_TICK_S, self._origin_tick),
        )
        try:
            deadline = time.monotonic() + cfg.heartbeat_timeout_s
            with self._lock:
                while self._last_hb is None:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0.0:
                        raise ScamperLinkError(
                            f"no HEARTBEAT from Scamper at {cfg.url!r} within {cfg.heartbeat_timeout_s:g} s"
                        )
                    self._cv.wait(timeout=min(remaining, 0.05))
            self._wake_origin()
            self._wait_origin()
            self._wait_vision()
            self._ensure(
                "set GUIDED",
                mavlink.MAV_CMD_DO_SET_MODE,
                mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                ROVER_GUIDED_MODE,
                lambda mode, armed: mode == ROVER_GUIDED_MODE,
            )
            self._ensure(
                "arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0, lambda m, armed: armed is True
            )
        except BaseException:
            self._disarm_best_effort()
            self._shutdown()
            raise
        with self._lock:
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

    def set_muted(self, muted: MutedCheck | None) -> None:
        """Install (or with None remove) the guardian's takeover check, effective for the very next send."""
        self._muted = muted
        link = self._link
        if link is not None:
            link.muted = muted

    def is_muted(self) -> bool:
        """What the takeover check says now (False without one; a check that raises does not mute)."""
        link = self._link
        if link is not None:
            return link.is_muted()
        check = self._muted
        try:
            return check is not None and bool(check())
        except Exception:
            return False

    def threads_alive(self) -> dict[str, bool]:
        """Name → alive of the link's background threads (empty before connect and after close)."""
        link = self._link
        return {} if link is None else link.threads_alive()

    def stop(self) -> None:
        """Zero the set-point; the zero is sent immediately (if connected) and then streamed."""
        with self._lock:
            self._setpoint = np.zeros(3)
        self._wake()

    def link_alive(self) -> bool:
        """True while the robot's HEARTBEAT has been seen within ``link_timeout_s``."""
        with self._lock:
            return self._link_alive

    def robot_state(self) -> RobotState:
        """The robot's mode, armed flag and heartbeat age, as its last HEARTBEAT reported them."""
        with self._lock:
            age = math.inf if self._last_hb is None else time.monotonic() - self._last_hb
            return RobotState(
                self._hb_mode, self._hb_armed, age, self._link_alive, self._origin_state.confirmed
            )

    def state_line(self) -> str:
        """What the robot's own telemetry said last (flightstack.hal.ReportsState): its heartbeat, and the
        newest change of mode or arming it made on its own (a failsafe's HOLD, an RC switch)."""
        with self._lock:
            text = self._state_text(time.monotonic())
            own = [
                e for e in self.events if e.kind in ("mode_changed", "disarmed_by_robot", "armed_by_robot")
            ]
        return text if not own else f"{text}; last change by the robot: {own[-1].detail}"

    @property
    def vision_reset_counter(self) -> int:
        """VISION_POSITION_ESTIMATE's reset_counter now (drivers/scamper/nav.py `VisionStream`)."""
        return self._vision.reset_counter

    @property
    def setpoint_ned(self) -> np.ndarray:
        """The set-point being streamed: [vx fwd m/s, vy right m/s, yaw rate clockwise rad/s] (body NED)."""
        with self._lock:
            return self._setpoint.copy()

    def close(self) -> None:
        """Zero the set-point, disarm (best effort, bounded, never raises), stop the I/O; idempotent."""
        if self._link is None:
            return
        self.stop()
        with self._lock:
            self._streaming = False
        self._send_setpoint(np.zeros(3))
        self._disarm_best_effort()
        self._shutdown()

    def __enter__(self) -> ScamperDriver:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _event(self, kind: ScamperKind, detail: str) -> None:
        """Append an event; caller holds the lock."""
        self.events.append(Event(time.monotonic(), None, kind, detail, source="scamper", clock="monotonic"))

    def _state_text(self, now: float) -> str:
        """What the last heartbeat said, for messages; caller holds the lock."""
        if self._last_hb is None:
            return "no heartbeat yet"
        arm, age = "armed" if self._hb_armed else "disarmed", now - self._last_hb
        return f"heartbeat shows {mode_name(self._hb_mode)} ({self._hb_mode}), {arm} ({age:.2f} s old)"

    def _fresh(self, now: float) -> bool:
        return self._last_hb is not None and now - self._last_hb <= self.config.link_timeout_s

    def _wake(self) -> None:
        """Send the current set-point now (from the caller's thread, non-blocking UDP write)."""
        with self._lock:
            streaming, sp = self._streaming, self._setpoint.copy()
        if streaming:
            self._send_setpoint(sp)

    def _shutdown(self) -> None:
        link, self._link = self._link, None
        with self._lock:
            self._streaming = False
        if link is not None:
            link.close()  # joins scamper-rx: a HEARTBEAT it was handling cannot revive the link after this
        with self._lock:
            self._link_alive = False
        self._close_tlog()

    def _close_tlog(self) -> None:
        tlog, self.tlog = self.tlog, None
        if tlog is not None:
            tlog.close()

    # ------------------------------------------------------------------ origin and external navigation
    def _wait_origin(self) -> None:
        """Block until the vehicle reported its EKF origin; ScamperCommandError after origin_timeout_s."""
        cfg = self.config
        deadline = time.monotonic() + cfg.origin_timeout_s
        with self._lock:
            while not self._origin_state.confirmed:
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    raise ScamperCommandError(
                        f"EKF origin not confirmed by Scamper at {cfg.url!r} "
                        f"within {cfg.origin_timeout_s:g} s "
                        f"({self._origin_state.sends} SET_GPS_GLOBAL_ORIGIN sent, no GPS_GLOBAL_ORIGIN "
                        "back): ArduPilot drops every set-point without an origin"
                    )
                self._cv.wait(timeout=min(remaining, 0.05))

    def _wait_vision(self) -> None:
        """Block until VISION_LEAD_SAMPLES poses were sent (no pose source: return at once; a real Rover
        then refuses GUIDED); ScamperCommandError after origin_timeout_s more."""
        cfg = self.config
        if self.pose_source is None:
            return
        deadline = time.monotonic() + cfg.origin_timeout_s
        while self.counts["vision_sent"] < VISION_LEAD_SAMPLES:
            if time.monotonic() >= deadline:
                why = {
                    k.removeprefix("vision_"): n for k, n in self.counts.items() if k.startswith("vision_")
                }
                raise ScamperCommandError(
                    f"no fresh motion-capture pose of the robot to send to Scamper at {cfg.url!r} within "
                    f"{cfg.origin_timeout_s:g} s ({why}): ArduPilot refuses GUIDED without a position "
                    "estimate"
                )
            time.sleep(0.02)

    def _wake_origin(self) -> None:
        """Send the origin now rather than at the next tick (connect, after the first heartbeat)."""
        self._origin_tick()

    def _origin_tick(self) -> None:
        """scamper-tx, every ORIGIN_TICK_S (and connect): while unconfirmed, ORIGIN_RETRY_S after the last
        try, set the origin; from the second try on also ask for it back (MAV_CMD_REQUEST_MESSAGE 49)."""
        link = self._link
        with self._lock:  # decided and claimed at once: connect's wake and the ticker never both send
            if link is None or self._last_hb is None or not self._origin_state.try_due(time.monotonic()):
                return
            state, target, retry = self._origin_state, self._target, self._origin_state.sends > 0
        if link.send_origin(target, self.origin) == "sent":
            with self._lock:
                state.sends += 1
        if retry:  # ArduPilot answers a new origin by itself (set_ekf_origin); one it had already, only asked
            link.request_message(target, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def _vision_tick(self) -> None:
        """scamper-tx, at vision_hz: the robot's newest fresh pose as VISION_POSITION_ESTIMATE."""
        link, source = self._link, self.pose_source
        if link is None or source is None:
            return
        with self._lock:
            if self._last_hb is None:
                return
        sample, why = self._vision.next(source(), time.monotonic())
        if sample is None:
            self.counts[f"vision_{why}"] += 1
            return
        link.send_vision(sample)

    def _forget_origin(self, why: str) -> None:
        """The vehicle lost its origin (reboot, gap): set it again; caller holds the lock."""
        if self._origin_state.confirmed or self._origin_state.sends:
            self._event("origin_forgotten", why)
        self._origin_state.forget()

    def _send_setpoint(self, sp: np.ndarray) -> None:
        """Send the set-point sp (body NED) now, from the caller's thread (never raises)."""
        link = self._link
        if link is not None:
            with self._lock:
                target = self._target
            link.send_setpoint(target, sp)

    def _stream_tick(self) -> None:
        """scamper-tx, at stream_hz: re-send the current set-point while streaming."""
        with self._lock:
            streaming, sp = self._streaming, self._setpoint.copy()
        if streaming:
            self._send_setpoint(sp)

    def _disarm_best_effort(self) -> None:
        """Disarm unless a fresh heartbeat shows disarmed (or we never armed and it never showed armed),
        or the driver is muted (the process that took over is in charge of the robot)."""
        if self._link is None:
            return
        with self._lock:
            now = time.monotonic()
            if self._fresh(now) and self._hb_armed is False:
                return
            if not (self._arm_sent or self._hb_armed):
                return
        if self.is_muted():
            with self._lock:
                self._event("disarm_skipped_muted", "muted: another process has taken over the robot")
            return
        try:
            self._ensure("disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0, 0.0, lambda m, a: a is False)
        except ScamperError as exc:
            with self._lock:
                self._event("disarm_failed", str(exc))

    def _ensure(
        self, what: str, command: int, p1: float, p2: float, want: Callable[[int | None, bool | None], bool]
    ) -> None:
        """Make the robot's HEARTBEAT show want(mode, armed) by COMMAND_LONG (module docstring's rules).

        Raises ScamperCommandError naming the command, the reason and what the heartbeat shows.
        """
        cfg = self.config
        label = f"{what} ({mavlink.enums['MAV_CMD'][command].name})"
        with self._lock:
            now = time.monotonic()
            if self._fresh(now) and want(self._hb_mode, self._hb_armed):
                self._event("no_command_needed", f"{label}: {self._state_text(now)}")
                return
            hb_seq0, ack_i0 = self._hb_seq, len(self._ack_log)  # both re-taken at the first send
        sends, t_send = 0, now
        while True:
            with self._lock:
                now = time.monotonic()
                acks = [r for c, r in self._ack_log[ack_i0:] if c == command]  # since the first send
                state = self._state_text(now)
                if sends > 0 and self._hb_seq > hb_seq0 and want(self._hb_mode, self._hb_armed):
                    if not acks:
                        self._event(
                            "ack_lost_confirmed_by_heartbeat", f"{label}: no ACK to {sends} send(s), {state}"
                        )
                    elif any(r not in _PENDING_RESULTS for r in acks):
                        self._event(
                            "ack_contradicted_by_heartbeat",
                            f"{label}: ACK {_result_name(acks[0])} yet {state}",
                        )
                    return
                final = bool(acks) or sends >= cfg.command_sends
                hb_period = max(0.02, self._hb_period or DEFAULT_HEARTBEAT_PERIOD_S)
                decide_at = t_send + cfg.ack_timeout_s + (2.0 * hb_period if final else 0.0)
                rejected = [r for r in acks if r not in _PENDING_RESULTS]
                if rejected:
                    error = f"rejected by Scamper: {_result_name(rejected[0])}"
                elif sends > 0 and now < decide_at:
                    self._cv.wait(timeout=min(0.05, decide_at - now))
                    continue
                elif acks:
                    error = (
                        f"answered {_result_name(acks[0])} but its heartbeats still show no change "
                        f"{now - t_send:.1f} s later: the ACK is not trusted"
                    )
                elif sends >= cfg.command_sends:
                    error = f"got no COMMAND_ACK and no heartbeat change after {sends} send(s)"
                else:
                    error = ""
                    sends += 1
                    if sends == 1:
                        hb_seq0, ack_i0 = self._hb_seq, len(self._ack_log)
                    else:
                        self.resends += 1
                        self._event(
                            "command_resent",
                            f"{label}: no COMMAND_ACK and no heartbeat change within {cfg.ack_timeout_s:g} s,"
                            f" send {sends}/{cfg.command_sends}",
                        )
                    sysid, compid = self._target
                if error:
                    raise ScamperCommandError(f"{label} to Scamper at {cfg.url!r} {error}; {state}")
            if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and p1 > 0.5:
                self._arm_sent = True
            t_send = time.monotonic()
            link = self._link
            result = (
                "closed" if link is None else link.send_command((sysid, compid), command, sends - 1, p1, p2)
            )
            if result == "muted":
                raise ScamperCommandError(
                    f"{label} to Scamper at {cfg.url!r} not sent: muted (another process has taken over)"
                )

    def _on_message(self, msg: Any, now: float) -> None:
        """scamper-rx: one received message (or None after a quiet wait), then link supervision."""
        cfg = self.config
        with self._lock:
            if msg is not None:
                self._handle(msg, now)
            if self._link_alive and self._last_hb is not None and now - self._last_hb > cfg.link_timeout_s:
                self._link_alive = False
                self._event("link_lost", f"no HEARTBEAT from {cfg.url} for {now - self._last_hb:.1f} s")

    def _handle(self, msg: Any, now: float) -> None:
        """Process one received message; caller holds the lock."""
        mtype = msg.get_type()
        if mtype == "HEARTBEAT":
            if not is_vehicle_heartbeat(msg):
                return
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if self._last_hb is None:
                self._target = src
            elif src != self._target:
                return
            else:
                dt = now - self._last_hb
                if 0.0 < dt <= self.config.link_timeout_s:
                    self._hb_period = dt if self._hb_period is None else 0.7 * self._hb_period + 0.3 * dt
            self._observe(int(msg.custom_mode), bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED))
            self._hb_seq += 1
            gap = None if self._last_hb is None else now - self._last_hb
            self._last_hb = now
            if gap is not None and gap > self.config.link_timeout_s:
                self._forget_origin(f"no HEARTBEAT for {gap:.1f} s: the robot may have rebooted")
            if not self._link_alive:
                self._link_alive = True
                if self._streaming:
                    self._event("link_restored", f"HEARTBEAT from {self.config.url} again")
            self._cv.notify_all()
        elif mtype == "COMMAND_ACK":
            self._ack_log.append((int(msg.command), int(msg.result)))
            self._cv.notify_all()
        elif (msg.get_srcSystem(), msg.get_srcComponent()) != self._target or self._last_hb is None:
            return  # only the robot's own messages, once its heartbeat chose it
        elif mtype == "GPS_GLOBAL_ORIGIN":
            self._on_origin(msg)
        elif mtype == "SYSTEM_TIME":
            boot = int(msg.time_boot_ms)
            if self._boot_ms is not None and boot + BOOT_BACKSTEP_MS < self._boot_ms:
                self._forget_origin(f"time_boot_ms went back from {self._boot_ms} to {boot}: rebooted")
            self._boot_ms = boot

    def _on_origin(self, msg: Any) -> None:
        """GPS_GLOBAL_ORIGIN from the robot: its EKF has an origin (ours, or one it had already, which
        ArduPilot keeps until reboot: set_ekf_origin); caller holds the lock."""
        try:
            reported = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
        except (AttributeError, TypeError, ValueError):
            self.counts["origin_malformed"] += 1
            return
        if abs(reported[0]) > 900_000_000 or abs(reported[1]) > 1_800_000_000:
            self.counts["origin_malformed"] += 1
            return
        first = not self._origin_state.confirmed
        self._origin_state.confirmed, self._origin_state.reported = True, reported
        if first:
            same = self.origin.matches(*reported)
            lat, lon, alt = reported[0] / 1e7, reported[1] / 1e7, reported[2] / 1000.0
            detail = f"lat {lat:.7f}, lon {lon:.7f}, alt {alt:.3f} m"
            if not same:
                detail += " (not the configured lab origin: the vehicle had one already; kept until reboot)"
            self._event("origin_confirmed", detail)
        self._cv.notify_all()

    def _observe(self, mode: int, armed: bool) -> None:
        """Record the robot's reported state; while streaming, a change not made by us is an event."""
        if self._streaming and self._hb_mode is not None:
            if mode != self._hb_mode:
                self._event(
                    "mode_changed",
                    f"robot reports {mode_name(self._hb_mode)} -> {mode_name(mode)} ({mode}), not commanded "
                    "by this driver (RC mode switch, failsafe or another GCS); set-points need GUIDED",
                )
            if self._hb_armed and not armed:
                self._event("disarmed_by_robot", f"robot reports disarmed while in {mode_name(mode)}")
            elif self._hb_armed is False and armed:
                self._event("armed_by_robot", f"robot reports armed again in {mode_name(mode)}")
        self._hb_mode, self._hb_armed = mode, armed
