"""Scamper MAVLink driver against the loopback rover emulator (sim_backend/emulators/rover/).

Each fault test flips one `RoverFaults` switch (or `pilot_override`) and checks the outcome at the emulator
(its mode / armed state, the commands it received, the ACKs it sent) and in the driver's events.  The
emulator heartbeats at 10 Hz to keep the tests short, except where ArduPilot's real 1 Hz matters.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil

from flightstack.drivers.scamper.driver import (
    ROVER_GUIDED_MODE,
    TYPE_MASK_VEL_YAWRATE,
    ScamperCommandError,
    ScamperConfig,
    ScamperDriver,
    ScamperLinkError,
    probe_heartbeat,
)
from flightstack.hal import GroundRobot
from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator
from flightstack.sim_backend.emulators.rover.modes import HOLD
from tests.conftest import Bound, eventually
from tests.robot_pose import still_pose

mavlink = mavutil.mavlink
SET_MODE = mavlink.MAV_CMD_DO_SET_MODE  # 176
ARM_DISARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM  # 400
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED


@pytest.fixture
def emu() -> Iterator[MavlinkRoverEmulator]:
    e = MavlinkRoverEmulator(heartbeat_hz=10.0)
    yield e
    e.close()


def make_driver(emu: MavlinkRoverEmulator, **kw: float) -> ScamperDriver:
    cfg = ScamperConfig(url=emu.url, heartbeat_timeout_s=kw.pop("heartbeat_timeout_s", 3.0), **kw)
    return ScamperDriver(cfg, pose_source=still_pose())


ORIGIN_KINDS = (
    "origin_confirmed",
    "origin_forgotten",
)  # the origin's own events: tests/test_scamper_extnav.py


def kinds(drv: ScamperDriver) -> list[str]:
    """The driver's events but the EKF origin's."""
    return [e.kind for e in drv.events if e.kind not in ORIGIN_KINDS]


def mode_arm_commands(emu: MavlinkRoverEmulator) -> list[tuple[int, float, int]]:
    """The COMMAND_LONGs the emulator got but the driver's REQUEST_MESSAGE for the EKF origin."""
    return [c for c in emu.commands if c[0] != mavlink.MAV_CMD_REQUEST_MESSAGE]


def details(drv: ScamperDriver, kind: str) -> list[str]:
    return [e.detail for e in drv.events if e.kind == kind]


def sent(emu: MavlinkRoverEmulator, command: int, param: float | None = None) -> int:
    """How many times the emulator received `command` (with that param, if given)."""
    return sum(c == command and (param is None or p == param) for c, p, _ in mode_arm_commands(emu))


def test_connect_sets_guided_and_arms_at_ardupilots_1hz_heartbeat() -> None:
    # 1 Hz HEARTBEAT, as ArduPilot: each change waits for the next one
    with MavlinkRoverEmulator() as emu:
        drv = make_driver(emu)
        assert isinstance(drv, GroundRobot)
        t0 = time.monotonic()
        drv.connect()
        t_connect = time.monotonic() - t0
        try:
            assert emu.mode == ROVER_GUIDED_MODE and emu.armed
            assert mode_arm_commands(emu) == [(SET_MODE, 15.0, ACCEPTED), (ARM_DISARM, 1.0, ACCEPTED)]
            assert drv.link_alive()
            st = drv.robot_state()
            assert st.custom_mode == ROVER_GUIDED_MODE and st.armed and st.ready and st.age_s < 1.5
            assert kinds(drv) == ["connected"]
            assert t_connect < 3.0  # two changes, each confirmed by a heartbeat <= 1 s after its ACK
        finally:
            drv.close()
        assert not emu.armed and mode_arm_commands(emu)[-1] == (ARM_DISARM, 0.0, ACCEPTED)  # close() disarms
        assert kinds(drv) == ["connected"]
        drv.close()  # idempotent


def test_body_velocity_signs_and_motion(safety_bound: Bound, emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu, stream_hz=10.0)
    drv.connect()
    try:
        t0 = time.monotonic()
        drv.send_body_velocity(np.array([0.2, 0.1, 0.0, 0.3]))  # forward, left, ccw (FLU)
        safety_bound(
            "send_body_velocity returns (never blocks the loop)", 1e3 * (time.monotonic() - t0), 50.0
        )
        assert eventually(lambda: emu.velocity != (0.0, 0.0, 0.0), 1.0)
        n0 = len(emu.setpoint_records())
        time.sleep(1.0)
        recs = emu.setpoint_records()
        # streamed at ~stream_hz (>= 1 Hz required by the rover)
        assert len(recs) - n0 >= 7
        last = recs[-1]
        assert last.frame == 8 and last.type_mask == TYPE_MASK_VEL_YAWRATE and last.applied
        assert last.vx == pytest.approx(0.2, abs=1e-6)
        assert last.vy == pytest.approx(-0.1, abs=1e-6)  # NED body: y right
        assert last.yaw_rate == pytest.approx(-0.3, abs=1e-6)  # NED: clockwise positive
        # FLU pose: turned ccw on an arc. ArduPilot Rover drives speed |(vx, vy)| along its heading
        # (GCS_MAVLINK_Rover::handle_set_position_target_local_ned), never sideways: a unicycle
        assert emu.velocity[0] == pytest.approx(math.hypot(0.2, 0.1)) and emu.velocity[1] == 0.0
        pose = emu.pose_flu()
        th = pose.theta
        assert 0.25 < th < 0.45  # ~0.3 rad/s for ~1.0-1.2 s
        w, v = 0.3, math.hypot(0.2, 0.1)
        x_exp = v * math.sin(th) / w
        y_exp = v * (1.0 - math.cos(th)) / w
        assert pose.p[0] == pytest.approx(x_exp, abs=1e-3)
        assert pose.p[1] == pytest.approx(y_exp, abs=1e-3)
        assert pose.p[0] > 0.15 and pose.p[1] > 0.02

        drv.stop()
        assert eventually(lambda: emu.velocity == (0.0, 0.0, 0.0), 0.5)
        p_stop = emu.pose_flu()
        time.sleep(0.3)
        assert np.allclose(emu.pose_flu().p, p_stop.p) and emu.velocity == (0.0, 0.0, 0.0)

        drv.send_body_velocity(np.array([np.nan, 0.0, 0.0, 0.0]))  # non-finite -> zero
        assert np.array_equal(drv.setpoint_ned, np.zeros(3))
    finally:
        drv.close()


def test_close_zeroes_even_if_disarm_rejected(emu: MavlinkRoverEmulator) -> None:
    emu.faults.reject_disarm = True  # close() cannot disarm: it must still have sent a zero set-point
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    drv.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
    time.sleep(0.3)
    drv.close()
    assert any("FAILED" in d for d in details(drv, "disarm_failed"))
    assert emu.armed and emu.velocity == (0.0, 0.0, 0.0)


def test_rover_holds_by_itself_when_its_companion_dies(emu: MavlinkRoverEmulator) -> None:
    """A dead companion computer sends neither a zero set-point nor more motion-capture poses: ArduPilot's
    EKF loses its external position 1 s after the last pose and holds (FS_EKF_ACTION 1), before its 3 s
    GUIDED timeout would (that timeout alone: tests/test_rover_ardupilot.py)."""
    emu.faults.reject_disarm = True
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    drv.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
    assert eventually(lambda: emu.velocity[0] == pytest.approx(0.3), 1.0)
    # Simulate a dead companion computer: the I/O thread and socket vanish without a zero set-point.
    drv._shutdown()
    t_stop = time.monotonic()
    assert eventually(lambda: emu.velocity == (0.0, 0.0, 0.0), 4.0)
    dt = time.monotonic() - t_stop
    print(f"rover stopped {dt:.2f} s after its companion died")
    assert 0.7 < dt < 2.5 and emu.mode == HOLD and emu.armed and not emu.stopped_by_timeout


def test_no_heartbeat_raises_link_error_naming_url(emu: MavlinkRoverEmulator) -> None:
    emu.faults.no_heartbeat = True
    drv = make_driver(emu, heartbeat_timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(ScamperLinkError, match=emu.url):
        drv.connect()
    assert time.monotonic() - t0 < 1.0 + 2.0  # its heartbeat timeout (2 s: scheduling)
    assert not emu.armed
    drv.close()


def test_reject_arm_raises_command_error_fast(emu: MavlinkRoverEmulator) -> None:
    emu.faults.reject_arm = True
    drv = make_driver(emu)  # ack_timeout_s 2 s: an explicit FAILED must not wait for it
    t0 = time.monotonic()
    with pytest.raises(ScamperCommandError, match=r"arm \(MAV_CMD_COMPONENT_ARM_DISARM\).*FAILED.*disarmed"):
        drv.connect()
    assert time.monotonic() - t0 < 2.0  # on the FAILED, not after the 2 s ack timeout
    assert not emu.armed and emu.mode == ROVER_GUIDED_MODE
    assert sent(emu, ARM_DISARM) == 1  # not re-sent, and no disarm: the heartbeat shows disarmed
    drv.close()


def test_link_loss_and_restore(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu, link_timeout_s=1.0)
    drv.connect()
    try:
        emu.faults.no_heartbeat = True
        assert eventually(lambda: not drv.link_alive(), 2.5)
        assert [e.kind for e in drv.events][-1] == "link_lost"
        emu.faults.no_heartbeat = False
        assert eventually(drv.link_alive, 1.5)
        assert [e.kind for e in drv.events][-1] == "link_restored"
    finally:
        drv.close()


def test_no_threads_left_after_close(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu)
    drv.connect()
    drv.close()
    emu.close()
    names = [t.name for t in threading.enumerate()]
    assert "scamper-io" not in names and "mavlink-rover-emu" not in names


# ---------------------------------------------------------------------------------------- ACK faults
@pytest.mark.parametrize(
    "lost", [{SET_MODE}, {ARM_DISARM}, {SET_MODE, ARM_DISARM}], ids=["set_mode", "arm", "both"]
)
def test_lost_ack_is_confirmed_by_heartbeat(emu: MavlinkRoverEmulator, lost: set[int]) -> None:
    emu.faults.lost_acks = set(lost)
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()  # no exception: the heartbeat shows GUIDED / armed
    try:
        assert emu.mode == ROVER_GUIDED_MODE and emu.armed
        assert sent(emu, SET_MODE) == 1 and sent(emu, ARM_DISARM, 1.0) == 1 and drv.resends == 0
        assert not any(c in lost for c, _ in emu.acks_sent)  # the ACKs really were never sent
        confirmed = details(drv, "ack_lost_confirmed_by_heartbeat")
        assert len(confirmed) == len(lost)
        assert ("set GUIDED" in confirmed[0]) == (SET_MODE in lost)
        assert drv.robot_state().ready
    finally:
        drv.close()
    assert not emu.armed


def test_lost_ack_to_disarm_at_close_still_disarms(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    emu.faults.lost_acks = {ARM_DISARM}
    drv.close()
    assert not emu.armed
    assert sent(emu, ARM_DISARM, 0.0) == 1
    # the arm's ACK only, the disarm's was lost (a MAV_CMD_REQUEST_MESSAGE the driver sends when a message
    # is late, as it may on a loaded machine, has an ACK of its own)
    assert [a for a in emu.acks_sent if a[0] == ARM_DISARM] == [(ARM_DISARM, ACCEPTED)]
    assert any(d.startswith("disarm") for d in details(drv, "ack_lost_confirmed_by_heartbeat"))
    assert "disarm_failed" not in kinds(drv)


@pytest.mark.parametrize(
    ("command", "label"),
    [
        (SET_MODE, r"set GUIDED \(MAV_CMD_DO_SET_MODE\)"),
        (ARM_DISARM, r"arm \(MAV_CMD_COMPONENT_ARM_DISARM\)"),
    ],
    ids=["set_mode", "arm"],
)
def test_accepted_but_ignored_is_not_trusted(emu: MavlinkRoverEmulator, command: int, label: str) -> None:
    emu.faults.ack_accepted_but_ignored = {command}
    drv = make_driver(emu, ack_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(
        ScamperCommandError, match=label + r".*ACCEPTED.*not trusted.*heartbeat shows (HOLD|GUIDED)"
    ):
        drv.connect()
    dt = time.monotonic() - t0
    assert 0.3 < dt < 1.5  # ack_timeout_s + 2 heartbeat periods (0.1 s) after the send, plus the first change
    assert sent(emu, command) == 1  # an ACCEPTED is not re-sent
    assert not emu.armed
    if command == SET_MODE:
        assert emu.mode == HOLD and sent(emu, ARM_DISARM) == 0  # never armed outside GUIDED
    else:
        assert emu.mode == ROVER_GUIDED_MODE
    assert not drv.link_alive()  # closed again
    drv.close()


def test_duplicate_acks_are_harmless(emu: MavlinkRoverEmulator) -> None:
    emu.faults.duplicate_acks = True
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    drv.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
    assert eventually(lambda: emu.velocity[0] == pytest.approx(0.2), 1.0)
    drv.close()
    # the mode's and arm's ACKs (a loaded machine can add the EKF origin's REQUEST_MESSAGE, acked twice too)
    acks = [a for a in emu.acks_sent if a[0] in (SET_MODE, ARM_DISARM)]
    assert acks == [(SET_MODE, ACCEPTED)] * 2 + [(ARM_DISARM, ACCEPTED)] * 4
    assert [c for c, _, _ in mode_arm_commands(emu)] == [SET_MODE, ARM_DISARM, ARM_DISARM]  # each sent once
    assert not emu.armed and emu.velocity == (0.0, 0.0, 0.0)
    assert kinds(drv) == ["connected"]


def test_late_acks_are_harmless(emu: MavlinkRoverEmulator) -> None:
    emu.faults.ack_delay_s = 0.8  # later than ack_timeout_s: the heartbeat decides before any ACK
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    assert emu.mode == ROVER_GUIDED_MODE and emu.armed and drv.resends == 0
    assert len(details(drv, "ack_lost_confirmed_by_heartbeat")) == 2
    drv.close()  # the arm's late ACCEPTED (same command id as the disarm) may land meanwhile
    assert not emu.armed and "disarm_failed" not in kinds(drv)
    assert sent(emu, ARM_DISARM, 0.0) == 1


def test_unanswered_command_is_resent(emu: MavlinkRoverEmulator) -> None:
    emu.faults.drop_commands = 1  # the first DO_SET_MODE never arrives
    # only that command: on a loaded machine the EKF origin's REQUEST_MESSAGE can come first
    emu.faults.drop_command_ids = {SET_MODE}
    drv = make_driver(emu, ack_timeout_s=0.3)
    drv.connect()
    try:
        assert emu.dropped_commands == [SET_MODE]
        assert drv.resends == 1 and any("send 2/3" in d for d in details(drv, "command_resent"))
        assert emu.mode == ROVER_GUIDED_MODE and emu.armed
    finally:
        drv.close()


def test_unanswered_command_fails_after_bounded_resends(emu: MavlinkRoverEmulator) -> None:
    emu.faults.drop_commands = 1000
    emu.faults.drop_command_ids = {SET_MODE}  # the EKF origin's REQUEST_MESSAGE still gets through
    drv = make_driver(emu, ack_timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(
        ScamperCommandError, match=r"set GUIDED.*no COMMAND_ACK and no heartbeat change after 3"
    ):
        drv.connect()
    dt = time.monotonic() - t0
    assert 0.6 < dt < 1.6  # 3 sends 0.2 s apart, then 0.2 s + 2 heartbeat periods
    assert emu.dropped_commands == [SET_MODE] * 3 and drv.resends == 2
    assert emu.mode == HOLD and not emu.armed
    drv.close()


# ---------------------------------------------------------------------------------------- robot state
def test_already_guided_and_armed_sends_nothing(emu: MavlinkRoverEmulator) -> None:
    emu.pilot_override(mode=ROVER_GUIDED_MODE, armed=True)
    drv = make_driver(emu)
    drv.connect()
    assert mode_arm_commands(emu) == []
    assert kinds(drv) == ["no_command_needed", "no_command_needed", "connected"]
    drv.close()
    assert mode_arm_commands(emu) == [(ARM_DISARM, 0.0, ACCEPTED)] and not emu.armed


def test_robot_leaving_guided_mid_run_is_reported(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu)
    drv.connect()
    try:
        drv.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.3]))
        assert eventually(lambda: emu.velocity != (0.0, 0.0, 0.0), 1.0)
        emu.pilot_override(mode=HOLD)  # an RC mode switch / failsafe
        assert eventually(lambda: "mode_changed" in kinds(drv), 1.0)
        st = drv.robot_state()
        assert st.custom_mode == HOLD and st.mode_name == "HOLD" and st.armed and not st.ready
        assert "GUIDED -> HOLD" in details(drv, "mode_changed")[0]
        line = drv.state_line()  # what the motion check quotes when the robot did not move
        assert line.startswith("heartbeat shows HOLD (4), armed") and "last change by the robot" in line
        assert "GUIDED -> HOLD" in line
        n0 = len(emu.setpoint_records())
        time.sleep(0.5)
        recs = emu.setpoint_records()[n0:]
        assert len(recs) >= 3 and not any(r.applied for r in recs)  # still streamed, ignored by the robot
        assert emu.mode == HOLD and emu.velocity == (0.0, 0.0, 0.0)  # the driver did not fight the switch
        assert kinds(drv).count("mode_changed") == 1  # once, not once per heartbeat
        emu.pilot_override(armed=False)
        assert eventually(lambda: "disarmed_by_robot" in kinds(drv), 1.0)
        assert drv.robot_state().armed is False
        time.sleep(0.3)
        assert kinds(drv).count("disarmed_by_robot") == 1
    finally:
        drv.close()
    assert sent(emu, ARM_DISARM, 0.0) == 0  # already disarmed per the heartbeat: nothing to send


def test_companion_heartbeats_are_not_the_robot(emu: MavlinkRoverEmulator) -> None:
    emu.faults.companion_heartbeat = True  # mode 0, disarmed, from component 191
    drv = make_driver(emu, link_timeout_s=0.5, ack_timeout_s=0.3)
    drv.connect()
    try:
        time.sleep(0.5)
        assert drv.robot_state().ready and "mode_changed" not in kinds(drv)
        emu.faults.no_heartbeat = True  # the autopilot falls silent, the companion does not
        assert eventually(lambda: not drv.link_alive(), 1.5)
    finally:
        drv.close()
    # the disarm was ACCEPTED (and applied) but no heartbeat confirmed it: reported, not trusted
    assert not emu.armed and any("not trusted" in d for d in details(drv, "disarm_failed"))


def test_companion_alone_is_no_robot(emu: MavlinkRoverEmulator) -> None:
    emu.faults.companion_heartbeat = True
    emu.faults.no_heartbeat = True
    cfg = ScamperConfig(url=emu.url, heartbeat_timeout_s=0.6)
    with pytest.raises(ScamperLinkError):
        probe_heartbeat(cfg)
    drv = ScamperDriver(cfg)
    with pytest.raises(ScamperLinkError):
        drv.connect()
    assert mode_arm_commands(emu) == []
    drv.close()
