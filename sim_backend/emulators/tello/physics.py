"""The Tello emulator's simulation: flight phases, motion model, battery and the state stream.

Ground truth in the world frame ``x`` forward at takeoff heading, ``y`` right, ``z`` up (cm), yaw in degrees
clockwise wrapped to [-180, 180); ``rc`` targets are body-frame velocities (cm/s: right, forward, up) and a
yaw rate (deg/s, clockwise), followed with a first-order lag ``tau_s``; discrete moves are instantaneous.
Phases ``landed`` -> ``takeoff`` -> ``flying`` -> ``landing`` -> ``landed`` (logged in ``phase_log``; motor-on
time runs in all but ``landed``); a takeoff climbs to ``takeoff_height_cm`` in at most ``TAKEOFF_CLIMB_S``
(*unverified*) and not in its last ``takeoff_hover_s``, and its deferred ``ok`` is queued when it completes.
No datagram for ``auto_land_s`` (15 s, SDK guides "Safety Function"; DJITelloPy #141) while flying: the drone
lands itself (``landed_by_timeout``); so it does below ``faults.self_land_battery_pct``
(``landed_by_battery``). A power loss (``faults.powered_off``) drops it to the floor; it boots out of SDK
mode, motor-on time 0. The battery drains from the set-point ``faults.battery_pct``. The simulation thread
steps every ``TICK_S`` s and sends the state string (``mid:-1;x:..;...;agz:..;\\r\\n``; ``vgx/vgy/vgz`` in
dm/s, ``h``/``tof`` in cm, ``x/y/z`` the integrated position in cm where a real drone reports mission-pad
coordinates, ``time`` = motor-on s, ``bat`` in %) at ``state_hz`` to ``(client_ip, state_port)`` in SDK mode.
What the state reports of height and velocity follows the recordings of real Tellos (``recorded``): ``vgz``
positive down, ``vgx``/``vgy`` in the frame of yaw 0; ``h`` in 10 cm steps, drifting at ``h_drift_cm_s``
from each takeoff up to ``h_drift_max_cm``; ``tof`` the height above ``surface`` plus 10 cm, 6553 beyond
``tof_max_cm``. `TelloPhysics` is one layer of ``TelloEmulator``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .base import TelloEmulatorBase
from .recorded import drifted, reported_h, reported_tof, reported_vg


class TelloPhysics(TelloEmulatorBase):
    """Ground-truth state, its public read-outs, the motion model and the simulation/state thread."""

    # ------------------------------------------------------------------------------------- public helpers
    @property
    def flying(self) -> bool:
        """True while the motors run (takeoff, flight and landing phases)."""
        return self._phase != "landed"

    @property
    def phase(self) -> str:
        """``landed``, ``takeoff``, ``flying`` or ``landing``."""
        return self._phase

    @property
    def position_cm(self) -> tuple[float, float, float]:
        """Ground-truth position ``(x forward, y right, z up)`` in cm."""
        with self._lock:
            return (float(self._pos[0]), float(self._pos[1]), float(self._pos[2]))

    @property
    def yaw_deg(self) -> float:
        """Ground-truth yaw in degrees, clockwise, wrapped to [-180, 180)."""
        return wrap_deg(self._yaw)

    @property
    def velocity_cm_s(self) -> tuple[float, float, float]:
        """Ground-truth world velocity in cm/s."""
        with self._lock:
            return (float(self._vel_world[0]), float(self._vel_world[1]), float(self._vel_world[2]))

    @property
    def battery(self) -> int:
        """Battery percentage currently reported."""
        with self._lock:
            return self._battery_locked()

    def _displace(self, fwd: float, right: float, up: float) -> None:
        c, s = math.cos(math.radians(self._yaw)), math.sin(math.radians(self._yaw))
        self._pos += (fwd * c - right * s, fwd * s + right * c, up)
        self._pos[2] = max(0.0, self._pos[2])

    # ------------------------------------------------------------------------------------------- simulation
    def _set_phase(self, phase: str, now: float) -> None:
        if phase != self._phase:
            self._phase = phase
            self.phase_log.append((now, phase))

    def _start_phase(self, phase: str, now: float, duration_s: float) -> None:
        self._set_phase(phase, now)
        self._phase_t0 = now
        self._phase_z0 = float(self._pos[2])
        self._phase_s = max(0.0, duration_s)

    def _set_landed(self, now: float) -> None:
        self._set_phase("landed", now)
        self._rc[:] = 0.0
        self._vel_body[:] = 0.0
        self._vel_world[:] = 0.0
        self._acc_body[:] = 0.0

    def _battery_locked(self) -> int:
        if self.faults.battery_pct != self._bat_setpoint:
            self._bat_setpoint = self.faults.battery_pct
            self._drain = 0.0
        return max(0, min(100, math.ceil(self._bat_setpoint - self._drain)))

    def _finish_phase(self, now: float) -> None:
        deferred, self._deferred = self._deferred, None
        if deferred is not None:  # a land's ok comes land_ok_s after the command, after the touchdown
            late = self.land_ok_s - self._phase_s if self._phase == "landed" else 0.0
            self._reply("ok", deferred.addr, now, deferred.delay_s + max(0.0, late))

    def _step(self, now: float, dt: float) -> None:
        with self._lock:
            self._battery_locked()
            self._drain += dt * (self.DRAIN_FLYING_PCT_S if self.flying else self.DRAIN_IDLE_PCT_S)
            if self.flying:
                self._motor_s += dt
                self._h_drift = drifted(self._h_drift, self.h_drift_cm_s, dt, self.h_drift_max_cm)
            z_before = float(self._pos[2])
            if self._phase == "takeoff":  # climb at the normal rate, then hover (stabilise) until the ok
                elapsed = now - self._phase_t0
                climb_s = max(min(self._phase_s - self.takeoff_hover_s, self.TAKEOFF_CLIMB_S), 1e-3)
                frac = min(1.0, elapsed / climb_s)
                target = max(self._phase_z0, self.takeoff_height_cm)
                self._pos[2] = self._phase_z0 + frac * (target - self._phase_z0)
                self._vel_world[:2] = 0.0
                self._vel_world[2] = (self._pos[2] - z_before) / dt
                if elapsed >= self._phase_s:
                    self._set_phase("flying", now)
                    self._last_cmd_t = now
                    self._vel_world[:] = 0.0
                    self._finish_phase(now)
            elif self._phase == "landing":
                frac = min(1.0, (now - self._phase_t0) / max(self._phase_s, 1e-3))
                self._pos[2] = self._phase_z0 * (1.0 - frac)
                self._vel_world[:2] = 0.0
                self._vel_world[2] = (self._pos[2] - z_before) / dt
                if frac >= 1.0:
                    self._set_landed(now)
                    self._finish_phase(now)
            elif self._phase == "flying":
                if now - self._last_cmd_t > self.auto_land_s:
                    self.landed_by_timeout = True
                    self._rc[:] = 0.0
                    self._start_phase("landing", now, self.land_s)
                    self._own_landing_notice(now)
                    return
                if self.faults.self_land_now:
                    self.faults.self_land_now = False
                    self.landed_by_itself = True
                    self._rc[:] = 0.0
                    self._start_phase("landing", now, self.land_s)
                    self._own_landing_notice(now)
                    return
                low = self.faults.self_land_battery_pct
                if low is not None and self._battery_locked() < low:
                    self.landed_by_battery = True
                    self._rc[:] = 0.0
                    self._start_phase("landing", now, self.land_s)
                    self._own_landing_notice(now)
                    return
                acting = (int(self._rc[0]), int(self._rc[1]), int(self._rc[2]), int(self._rc[3]))
                if not self.rc_acted or self.rc_acted[-1][1] != acting:
                    self.rc_acted.append((now - dt, acting))
                alpha = 1.0 - math.exp(-dt / max(self.tau_s, 1e-6))
                previous = self._vel_body.copy()
                self._vel_body += alpha * (self._rc - self._vel_body)
                self._acc_body = (self._vel_body[:3] - previous[:3]) / dt
                # the step moves by the mean of the velocity over it (trapezoid), not by its end value: an
                # end value moved the drone half a step early, which a latency calibration reads as 5 ms
                right, fwd, up, yaw_rate = 0.5 * (previous + self._vel_body)
                c, s = math.cos(math.radians(self._yaw)), math.sin(math.radians(self._yaw))
                self._pos += np.array([fwd * c - right * s, fwd * s + right * c, up]) * dt
                right, fwd, up, _ = self._vel_body
                self._vel_world[:] = (fwd * c - right * s, fwd * s + right * c, up)
                if self._pos[2] < 0.0:
                    self._pos[2] = 0.0
                    self._vel_world[2] = 0.0
                self._yaw = wrap_deg(self._yaw + yaw_rate * dt)

    def _own_landing_notice(self, now: float) -> None:
        """``error Auto land`` to the client, unprompted, as the drone starts a landing of its own
        (``faults.auto_land_notice``: assumed)."""
        to = self._first_client if self.reply_port_latch and self._first_client else self._last_client
        if self.faults.auto_land_notice and to is not None:
            self._reply("error Auto land", to, now, float(self.faults.reply_delay_s))

    def _power(self, now: float) -> None:
        """Act on ``faults.powered_off`` once per change: a power loss (it falls), or a boot."""
        off = bool(self.faults.powered_off)
        if off == self._powered_off:
            return
        with self._lock:
            self._powered_off = off
            if off:  # motors off at once, on the floor; all it knew of its client is gone
                self._set_landed(now)
                self._pos[2] = 0.0
                self._deferred = None
                self.sdk_mode = False
                self.streaming = False
                self._first_client = self._last_client = None
            self._motor_s = 0.0  # the motor-on time counts from power-on
            self._h_drift = 0.0  # so does the height estimate (unverified)
            self._last_cmd_t = now
            self.power_log.append((now, "off" if off else "boot"))

    def _reported_h(self) -> int:
        """The ``h`` a real Tello would report now (cm; ``recorded.reported_h``)."""
        return reported_h(float(self._pos[2]), self._h_drift)

    def _reported_tof(self) -> int:
        """The ``tof`` a real Tello would report now (cm; ``recorded.reported_tof``)."""
        below = float(self.surface(float(self._pos[0]), float(self._pos[1])))
        return reported_tof(float(self._pos[2]) - below, self.tof_max_cm)

    def _state_string(self) -> str:
        with self._lock:
            x, y, z = (round(float(v)) for v in self._pos)
            vx, vy, vz = (float(v) for v in self._vel_world)
            vgx, vgy, vgz = reported_vg((vx, vy, vz))
            h, tof = self._reported_h(), self._reported_tof()
            acc = self._acc_body / 981.0 * 1000.0
            return (
                f"mid:-1;x:{x};y:{y};z:{z};mpry:0,0,0;pitch:0;roll:0;yaw:{round(wrap_deg(self._yaw))};"
                f"vgx:{vgx};vgy:{vgy};vgz:{vgz};templ:60;temph:63;tof:{tof};h:{h};"
                f"bat:{self._battery_locked()};baro:{12.3 + z / 100:.2f};time:{int(self._motor_s)};"
                f"agx:{acc[1]:.2f};agy:{acc[0]:.2f};agz:{acc[2] - 1000.0:.2f};\r\n"
            )

    def _sim_loop(self) -> None:
        sock = self._tx_sock
        assert sock is not None
        last = time.monotonic()
        next_state = last
        while not self._stop.wait(self.TICK_S):
            now = time.monotonic()
            self._power(now)
            if not self._powered_off:
                self._step(now, min(max(now - last, 1e-4), self.MAX_STEP_S))
            last = now
            if now < next_state:
                continue
            next_state = max(next_state + 1.0 / self.state_hz, now - 1.0 / self.state_hz)
            if not self.sdk_mode or self.faults.drop_state:
                continue
            if self.downlink_blocked():
                self.state_packets_lost += 1
                continue
            state = self._state_string()
            try:
                sock.sendto(state.encode("ascii"), (self.client_ip, self.state_port))
            except OSError as exc:
                self.errors.append(f"state send failed: {exc!r}")
                continue
            with self._lock:
                self.last_state = state
                self.state_packets_sent += 1


def wrap_deg(angle: float) -> float:
    """``angle`` (degrees) wrapped into [-180, 180)."""
    return (angle + 180.0) % 360.0 - 180.0
