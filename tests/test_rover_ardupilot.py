"""The rover emulator seen by ground stations that know nothing of flightstack's driver: one written here
from the MAVLink specification with pymavlink's mavutil, and MAVProxy 1.8.75. What each expects is ArduPilot
Rover's behaviour from its source (docs/drivers.md, "What ArduPilot Rover does, and the emulator")."""

from __future__ import annotations

import math
import queue
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil

from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator
from flightstack.sim_backend.emulators.rover.modes import ACRO, GUIDED, HOLD, MANUAL, STEERING
from flightstack.sim_backend.emulators.rover.params import RoverParams
from tests.conftest import eventually, skip_or_fail_in_ci

pytestmark = pytest.mark.system
mavlink = mavutil.mavlink
MASK_VEL_YAWRATE = 1511  # x y z, vz, ax ay az, yaw ignored: vx, vy and the yaw rate used
MASK_VEL_ONLY = 3559  # ... and the yaw rate ignored too: drive along (vx, vy)
MASK_WITH_ACCEL = 1511 & ~(64 | 128)  # accelerations not ignored
FAILED, ACCEPTED = mavlink.MAV_RESULT_FAILED, mavlink.MAV_RESULT_ACCEPTED
SLACK_S = 1.5  # scheduling allowance on a loaded 2-core machine (s)
LAB_ORIGIN = (515_000_000, -1_000_000, 50_000)  # lat, lon (degE7), alt (mm): any valid place


class Gcs:
    """A ground station from the MAVLink specification. A background thread plays the lab's motion capture
    (VISION_POSITION_ESTIMATE of the emulated robot's pose at 20 Hz, while ``mocap``) and the GCS's 1 Hz
    HEARTBEAT (while ``beating``); the test thread sends commands and reads replies."""

    def __init__(self, emu: MavlinkRoverEmulator, mocap: bool = True) -> None:
        self.emu = emu
        self.conn: Any = mavutil.mavlink_connection(emu.url, source_system=255, source_component=190)
        self.mocap, self.beating = mocap, True
        self.inbox: list[Any] = []
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._background, daemon=True)
        self._thread.start()

    def send(self, name: str, *args: Any) -> None:
        with self._send_lock:
            getattr(self.conn.mav, name + "_send")(*args)

    def _background(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if self.beating and now >= next_hb:
                next_hb = now + 1.0
                self.send("heartbeat", mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if self.mocap:
                x, y, yaw = self.emu.pose_ned()
                self.send("vision_position_estimate", int(now * 1e6), x, y, 0.0, 0.0, 0.0, yaw)
            time.sleep(0.05)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.conn.close()

    def recv(self, mtype: str, pred: Callable[[Any], bool] = lambda _m: True, timeout: float = 2.0) -> Any:
        """The first message of this type (and `pred`) received, kept or to come within `timeout` s; every
        other message is kept for a later call (a STATUSTEXT comes before the COMMAND_ACK it explains)."""
        deadline = time.monotonic() + timeout
        while True:
            for i, m in enumerate(self.inbox):
                if m.get_type() == mtype and pred(m):
                    return self.inbox.pop(i)
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            m = self.conn.recv_match(blocking=True, timeout=left)
            if m is not None and m.get_type() != "BAD_DATA":
                self.inbox.append(m)
                self.inbox = self.inbox[-500:]

    def text(self, words: str, timeout: float = 2.0) -> Any:
        return self.recv("STATUSTEXT", lambda m: words in m.text, timeout)

    def command(self, command: int, *params: float) -> int | None:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self.send("command_long", 1, 1, command, 0, *p)
        ack = self.recv("COMMAND_ACK", lambda m: m.command == command)
        return None if ack is None else int(ack.result)

    def set_mode(self, mode: int) -> int | None:
        self.send("set_mode", 1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
        ack = self.recv("COMMAND_ACK", lambda m: m.command == mavlink.MAVLINK_MSG_ID_SET_MODE)
        return None if ack is None else int(ack.result)

    def arm(self) -> int | None:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)

    def set_origin(self) -> Any:
        self.send("set_gps_global_origin", 1, *LAB_ORIGIN)
        return self.recv("GPS_GLOBAL_ORIGIN")

    def ready(self) -> None:
        """Origin, motion capture, GUIDED, armed: what ArduPilot needs before a set-point moves it."""
        self.heartbeat_once()
        assert self.set_origin() is not None
        assert eventually(self.emu.position_ok, 2.0)
        assert self.set_mode(GUIDED) == ACCEPTED and self.arm() == ACCEPTED

    def heartbeat_once(self) -> None:
        self.send("heartbeat", mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert self.recv("HEARTBEAT") is not None

    def stream(
        self,
        seconds: float,
        vx: float,
        vy: float,
        yaw_rate: float,
        mask: int = MASK_VEL_YAWRATE,
        frame: int = mavlink.MAV_FRAME_BODY_NED,
    ) -> None:
        """SET_POSITION_TARGET_LOCAL_NED at 20 Hz for `seconds` (m/s, rad/s clockwise)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            target = (0, 0, 0, vx, vy, 0, 0, 0, 0, 0, yaw_rate)
            self.send("set_position_target_local_ned", 0, 1, 1, frame, mask, *target)
            time.sleep(0.05)


@pytest.fixture
def emu() -> Iterator[MavlinkRoverEmulator]:
    with MavlinkRoverEmulator(heartbeat_hz=5.0) as e:
        yield e


@pytest.fixture
def gcs(emu: MavlinkRoverEmulator) -> Iterator[Gcs]:
    g = Gcs(emu)
    yield g
    g.close()


def driven_s(emu: MavlinkRoverEmulator, vy: float) -> float:
    """How long the emulator drove on set-points with this vy (first applied one to the first other one)."""
    recs = [r for r in emu.setpoint_records() if r.applied]
    t0 = next(r.t for r in recs if abs(r.vy - vy) < 1e-6)  # float32 on the wire
    t1 = next(r.t for r in recs if r.t > t0 and abs(r.vy - vy) >= 1e-6)
    return t1 - t0


# ---- velocity semantics ---------------------------------------------------------------------------------
def test_sideways_velocity_drives_forward_at_its_length(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    """v_x 0, v_y 0.2, yaw rate 0, mask 1511, 1.5 s: speed = sign(v_x)|(v_x, v_y)| forward, not sideways."""
    gcs.ready()
    gcs.stream(1.5, 0.0, 0.2, 0.0)
    assert emu.velocity == pytest.approx((0.2, 0.0, 0.0)), emu.statustexts
    gcs.stream(0.3, 0.0, 0.0, 0.0)
    x, y, yaw = emu.pose_ned()
    expected = 0.2 * driven_s(emu, 0.2)  # from the first v_y set-point to the first zero one
    print(f"drove x {x:.4f} m (expected {expected:.4f} m from the set-points' times), y {y:.5f} m")
    assert x == pytest.approx(0.3, abs=0.05) and x == pytest.approx(expected, abs=0.01)
    assert abs(y) < 0.01 and yaw == 0.0


def test_negative_vx_reverses_at_the_vectors_length(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.ready()
    gcs.stream(1.0, -0.1, 0.2, 0.0)
    assert emu.velocity[0] == pytest.approx(-math.hypot(0.1, 0.2)) and emu.velocity[1] == 0.0
    assert emu.velocity[0] == pytest.approx(-0.224, abs=1e-3)
    gcs.stream(0.3, 0.0, 0.0, 0.0)
    x, y, _ = emu.pose_ned()
    assert x < -0.15 and abs(y) < 0.01


def test_speed_is_clamped_to_cruise_speed_and_turn_rate_is_the_yaw_rate(
    emu: MavlinkRoverEmulator, gcs: Gcs
) -> None:
    gcs.ready()
    assert emu.param("CRUISE_SPEED") == 0.5 and emu.param("WP_SPEED") == 0.0
    gcs.stream(0.5, 2.0, 0.0, -0.4)  # 2 m/s asked, counter-clockwise 0.4 rad/s
    assert emu.velocity == pytest.approx((0.5, 0.0, -0.4))


def test_without_yaw_rate_it_turns_to_the_vectors_heading(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    """Yaw and yaw rate ignored: steer to atan2(v_y, v_x) (MAV_FRAME_LOCAL_NED: from north) and drive at
    |(v_x, v_y)|; the turn rate is ATC_STR_ANG_P x the heading error, at most ATC_STR_RAT_MAX."""
    gcs.ready()
    gcs.stream(3.5, 0.0, 0.2, 0.0, mask=MASK_VEL_ONLY, frame=mavlink.MAV_FRAME_LOCAL_NED)
    x, y, yaw = emu.pose_ned()
    assert yaw == pytest.approx(math.pi / 2, abs=0.02) and emu.velocity[0] == pytest.approx(0.2)
    assert y > 0.3 and x > 0.0  # drove while it turned east


def test_a_set_point_with_accelerations_is_dropped_with_a_statustext(
    emu: MavlinkRoverEmulator, gcs: Gcs
) -> None:
    gcs.ready()
    gcs.stream(0.3, 0.2, 0.0, 0.0, mask=MASK_WITH_ACCEL)
    assert gcs.text("Ignoring SET_POSITION_TARGET_LOCAL_NED") is not None  # 50 characters in MAVLink 1
    assert emu.velocity == (0.0, 0.0, 0.0) and emu.pose_ned() == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("steering", ["skid", "ackermann"])
def test_turning_in_place_needs_skid_steering(steering: str) -> None:
    with MavlinkRoverEmulator(heartbeat_hz=5.0, params=RoverParams(steering=steering)) as emu:
        gcs = Gcs(emu)
        try:
            gcs.ready()
            gcs.stream(0.5, 0.0, 0.0, 0.5)
            yaw_in_place = emu.pose_ned()[2]
            gcs.stream(0.5, 0.3, 0.0, 1.0)  # 1 rad/s asked at 0.3 m/s
            rate = emu.velocity[2]
        finally:
            gcs.close()
    if steering == "skid":
        assert yaw_in_place > 0.15 and rate == pytest.approx(1.0)
    else:  # no turn without speed; at speed no tighter than TURN_RADIUS 0.9 m
        assert yaw_in_place == 0.0 and rate == pytest.approx(0.3 / 0.9)


# ---- the position estimate and the EKF origin ---------------------------------------------------------
def test_no_origin_no_motion(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    assert eventually(emu.position_ok, 2.0)
    assert gcs.set_mode(GUIDED) == ACCEPTED and gcs.arm() == ACCEPTED  # motion capture: a position
    gcs.stream(1.0, 0.2, 0.0, 0.0)
    assert emu.pose_ned() == (0.0, 0.0, 0.0) and emu.velocity == (0.0, 0.0, 0.0)
    assert {r.reason for r in emu.setpoint_records()} == {"no EKF origin"}
    assert gcs.set_origin() is not None  # once set, the same set-points drive
    gcs.stream(0.5, 0.2, 0.0, 0.0)
    assert emu.velocity[0] == pytest.approx(0.2)


def test_the_origin_is_set_once_and_reported(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 49) == ACCEPTED  # no origin yet: nothing sent
    assert gcs.recv("GPS_GLOBAL_ORIGIN", timeout=0.5) is None
    m = gcs.set_origin()
    assert (m.latitude, m.longitude, m.altitude) == LAB_ORIGIN
    gcs.send("set_gps_global_origin", 1, 0, 0, 0)  # a second origin in the same boot is ignored
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 49) == ACCEPTED
    m = gcs.recv("GPS_GLOBAL_ORIGIN")
    assert m is not None and (m.latitude, m.longitude, m.altitude) == LAB_ORIGIN


def test_a_starved_emulator_reads_every_queued_message_before_its_timeouts(
    emu: MavlinkRoverEmulator, gcs: Gcs, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The emulator's thread is not scheduled for 1.5 s (a busy test machine) right after a set-point
    arrived, while the pose estimates keep coming at 20 Hz: a real Rover reads them as they come and has
    no EKF failsafe; the emulator, reading one message per pass, had handled the set-point, checked the
    1 s position timeout with the estimates still queued, and held the robot (HOLD, "EKF failsafe")."""
    gcs.ready()
    gcs.stream(0.3, 0.05, 0.0, 0.0)
    real = emu._conn.recv_match
    starved = threading.Event()

    def recv_match(*args: Any, **kwargs: Any) -> Any:
        if not starved.is_set() and threading.current_thread() is emu._thread:
            starved.set()
            target = (0, 0, 0, 0.05, 0.0, 0, 0, 0, 0, 0, 0.0)
            gcs.send(
                "set_position_target_local_ned",
                0,
                1,
                1,
                mavlink.MAV_FRAME_BODY_NED,
                MASK_VEL_YAWRATE,
                *target,
            )
            time.sleep(1.5)  # descheduled: the link keeps delivering
        return real(*args, **kwargs)

    monkeypatch.setattr(emu._conn, "recv_match", recv_match)
    assert eventually(starved.is_set, 2.0)
    gcs.stream(2.0, 0.05, 0.0, 0.0)
    assert emu.mode == GUIDED, emu.statustexts
    assert not [t for t in emu.statustexts if "EKF failsafe" in t[2]], emu.statustexts


def test_no_position_estimate_no_guided_and_no_motion(emu: MavlinkRoverEmulator) -> None:
    gcs = Gcs(emu, mocap=False)
    try:
        gcs.heartbeat_once()
        assert gcs.set_origin() is not None and not emu.position_ok()
        assert gcs.set_mode(GUIDED) == ACCEPTED  # disarmed: Mode::enter skips its checks ...
        assert gcs.arm() == FAILED and not emu.armed  # ... and arming refuses
        assert gcs.text("PreArm: Need Position Estimate") is not None
        gcs.stream(0.5, 0.2, 0.0, 0.0)
        assert emu.pose_ned() == (0.0, 0.0, 0.0)
        assert gcs.set_mode(MANUAL) == ACCEPTED and gcs.arm() == ACCEPTED  # MANUAL needs no position
        assert gcs.set_mode(GUIDED) == FAILED and emu.mode == MANUAL  # armed: GUIDED refused
        assert gcs.text("Flight mode change failed") is not None
    finally:
        gcs.close()


@pytest.mark.parametrize(("name", "value", "refusal"), [
    ("EK3_SRC1_VELXY", 3.0, "PreArm: AHRS: EK3 sources require GPS"),  # ArduPilot's default, no GPS fitted
    ("EK3_SRC1_VELZ", 3.0, "PreArm: AHRS: EK3 sources require GPS"),
    ("EK3_SRC1_POSZ", 0.0, "PreArm: AHRS: Check EK3_SRC1_POSZ"),
])  # fmt: skip
def test_ekf_sources_that_need_a_gps_refuse_arming(
    emu: MavlinkRoverEmulator, gcs: Gcs, name: str, value: float, refusal: str
) -> None:
    """AP_NavEKF_Source::pre_arm_check: with motion capture and an origin, a source left on GPS (or POSZ None)
    refuses arming in GUIDED; set back to the lab's value, the same vehicle arms."""
    gcs.heartbeat_once()
    assert gcs.set_origin() is not None and eventually(emu.position_ok, 2.0)
    lab_value = emu.param(name)
    gcs.send("param_set", 1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_INT8)
    assert gcs.recv("PARAM_VALUE", lambda m: m.param_id == name) is not None
    assert gcs.set_mode(GUIDED) == ACCEPTED and gcs.arm() == FAILED and not emu.armed
    assert gcs.text(refusal) is not None
    gcs.send("param_set", 1, 1, name.encode(), lab_value, mavlink.MAV_PARAM_TYPE_INT8)
    assert gcs.recv("PARAM_VALUE", lambda m: m.param_id == name) is not None
    assert gcs.arm() == ACCEPTED and emu.armed


def test_an_injected_arm_or_disarm_refusal_answers_failed(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    """The fault switches reject_arm / reject_disarm answer as ArduPilot answers an arm or disarm that fails:
    FAILED (4), not DENIED (2) (GCS_MAVLINK::handle_command_component_arm_disarm), and change nothing."""
    gcs.ready()
    emu.faults.reject_disarm = True
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0) == FAILED == 4 and emu.armed
    emu.faults.reject_disarm = False
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0) == ACCEPTED and not emu.armed
    emu.faults.reject_arm = True
    assert gcs.arm() == FAILED and not emu.armed


def test_losing_motion_capture_while_driving_holds(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    """The estimate is dropped 1 s after the last VISION_POSITION_ESTIMATE; then the EKF failsafe: HOLD."""
    gcs.ready()
    gcs.stream(0.5, 0.2, 0.0, 0.0)
    gcs.mocap = False
    t_lost = time.monotonic()
    gcs.stream(1.0 + SLACK_S, 0.2, 0.0, 0.0)
    assert emu.mode == HOLD and emu.velocity == (0.0, 0.0, 0.0)
    assert emu.system_status() == mavlink.MAV_STATE_CRITICAL
    texts = [(t, s) for t, _, s in emu.statustexts if s == "EKF failsafe"]
    assert texts and 0.9 <= texts[0][0] - t_lost <= 1.0 + SLACK_S  # last sent <= 50 ms before
    print(f"EKF failsafe {texts[0][0] - t_lost:.2f} s after the last vision message")


# ---- the GUIDED timeout ---------------------------------------------------------------------------------
def test_guided_timeout_stops_with_ardupilots_statustext(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.ready()
    gcs.stream(0.5, 0.2, 0.0, 0.0)
    m = gcs.text("target not received last 3.0 secs, stopping", timeout=3.0 + SLACK_S + 1.0)
    t_text = next(t for t, _, s in emu.statustexts if s.startswith("target not received"))
    took = t_text - emu.setpoint_records()[-1].t  # both on the emulator's clock
    print(f"stopped {took:.2f} s after the last set-point (GUID_TIMEOUT 3 s)")
    assert m is not None and m.severity == mavlink.MAV_SEVERITY_WARNING
    assert 3.0 <= took <= 3.0 + SLACK_S and emu.velocity == (0.0, 0.0, 0.0) and emu.mode == GUIDED


# ---- protocol details -----------------------------------------------------------------------------------
def test_param_set_is_applied_and_echoed(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    gcs.send("param_set", 1, 1, b"FS_TIMEOUT", 2.0, mavlink.MAV_PARAM_TYPE_REAL32)
    m = gcs.recv("PARAM_VALUE", lambda m: m.param_id == "FS_TIMEOUT")
    assert m is not None and m.param_value == 2.0 and m.param_type == mavlink.MAV_PARAM_TYPE_REAL32
    assert emu.param("FS_TIMEOUT") == 2.0
    gcs.send("param_set", 1, 1, b"FS_ACTION", 1.2, mavlink.MAV_PARAM_TYPE_INT8)  # an integer: rounded
    m = gcs.recv("PARAM_VALUE", lambda m: m.param_id == "FS_ACTION")
    assert m is not None and m.param_value == 1.0 and emu.param("FS_ACTION") == 1.0
    gcs.send("param_set", 1, 1, b"NO_SUCH_PARAM", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert gcs.recv("PARAM_VALUE", timeout=0.5) is None


def test_mode_list_result_codes_and_base_mode(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    assert gcs.set_mode(99) == FAILED and gcs.text("No such mode 99") is not None
    for mode in (ACRO, STEERING):
        assert gcs.set_mode(mode) == ACCEPTED
        hb = gcs.recv("HEARTBEAT", lambda m, mode=mode: m.custom_mode == mode)
        assert hb is not None and hb.base_mode & mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    assert (
        gcs.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)
        == ACCEPTED
    )
    hb = gcs.recv("HEARTBEAT", lambda m: m.custom_mode == GUIDED)
    assert hb is not None and hb.base_mode & mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    assert hb.system_status == mavlink.MAV_STATE_ACTIVE  # HOLD is STANDBY, any other mode ACTIVE


def test_an_active_failsafe_is_critical(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    for name, value in (("FS_GCS_TIMEOUT", 1.0), ("FS_TIMEOUT", 0.5)):
        gcs.send("param_set", 1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)
        assert gcs.recv("PARAM_VALUE", lambda m, name=name: m.param_id == name) is not None
    gcs.ready()
    gcs.stream(0.5, 0.2, 0.0, 0.0)
    gcs.beating = False  # motion capture and set-points go on, our heartbeats stop
    gcs.stream(1.0 + 0.5 + SLACK_S, 0.2, 0.0, 0.0)
    hb = gcs.recv("HEARTBEAT", lambda m: m.system_status == mavlink.MAV_STATE_CRITICAL)
    assert hb is not None and hb.custom_mode == HOLD and emu.velocity == (0.0, 0.0, 0.0)
    assert any(s == "GCS Failsafe" for _, _, s in emu.statustexts)
    gcs.beating = True
    assert gcs.text("GCS Failsafe Cleared", timeout=1.0 + SLACK_S) is not None
    assert gcs.recv("HEARTBEAT", lambda m: m.system_status == mavlink.MAV_STATE_STANDBY) is not None


def test_message_requests_and_intervals(emu: MavlinkRoverEmulator, gcs: Gcs) -> None:
    gcs.heartbeat_once()
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 148) == ACCEPTED
    assert gcs.recv("AUTOPILOT_VERSION") is not None
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 9999) == FAILED
    gcs.set_origin()
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 32, 100_000) == ACCEPTED  # 10 Hz
    t0, n = time.monotonic(), 0
    while time.monotonic() - t0 < 1.0:
        n += gcs.recv("LOCAL_POSITION_NED", timeout=0.3) is not None
    print(f"LOCAL_POSITION_NED at 10 Hz: {n} in 1 s")
    assert 7 <= n <= 13
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 32, -1) == ACCEPTED
    time.sleep(0.3)
    while gcs.conn.recv_match(type="LOCAL_POSITION_NED", blocking=False) is not None:
        pass
    assert gcs.recv("LOCAL_POSITION_NED", timeout=0.5) is None


# ---- MAVProxy as a second client ------------------------------------------------------------------------
def mavproxy() -> str:
    found = shutil.which("mavproxy.py") or str(Path(sys.executable).with_name("mavproxy.py"))
    if not Path(found).exists():
        skip_or_fail_in_ci("MAVProxy not installed: pip install MAVProxy==1.8.75")
    return found


def test_mavproxy_sets_a_parameter_and_acro(emu: MavlinkRoverEmulator, gcs: Gcs, tmp_path: Path) -> None:
    """MAVProxy's shell driven through a pipe (no terminal, no GUI). Not ``--non-interactive --cmd``: MAVProxy
    runs --cmd before its first HEARTBEAT and parameter download ("Unable to find parameter", and a mode
    number from its default mapping)."""
    gcs.heartbeat_once()  # our own ground station stays connected: MAVProxy is the second client
    proc = subprocess.Popen(
        [mavproxy(), f"--master=udpout:127.0.0.1:{emu.port}", "--no-state", "--source-system=254",
         "--default-modules=param,mode,cmdlong"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    out: list[str] = []
    reader = threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout or []], daemon=True)
    reader.start()

    def seen(words: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                out.append(lines.get(timeout=0.1))
            except queue.Empty:
                continue
            if words in out[-1]:
                return True
        return any(words in ln for ln in out)

    try:
        assert proc.stdin is not None
        assert seen("parameters", 20.0), "".join(out)  # "Received 34 parameters"
        proc.stdin.write("param set FS_TIMEOUT 2\nmode ACRO\n")
        proc.stdin.flush()
        assert eventually(lambda: emu.param("FS_TIMEOUT") == 2.0 and emu.mode == ACRO, 10.0)
        assert seen("DO_SET_MODE: ACCEPTED", 5.0), "".join(out)
        proc.stdin.write("param show FS_TIMEOUT\n")
        proc.stdin.flush()
        assert seen("FS_TIMEOUT       2.0", 5.0) or any("FS_TIMEOUT" in ln and "2.0" in ln for ln in out), out
        assert not any("Failed to set" in ln for ln in out)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5.0)
    print("".join(out))
