"""The robot's own GCS failsafe on loopback: preflight reads it (drivers/scamper/params.py, judged by
drivers/scamper/failsafe.py) from the rover emulator, and the emulator takes FS_ACTION as ArduPilot Rover
does when the ground station's heartbeats stop (sim_backend/emulators/rover/)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil

from flightstack.drivers.lab.preflight import robot_rows
from flightstack.drivers.scamper.driver import ROVER_GUIDED_MODE, ScamperConfig, ScamperDriver
from flightstack.drivers.scamper.failsafe import PARAMETERS, enough, judge_gcs_failsafe
from flightstack.drivers.scamper.params import probe_parameters
from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator
from flightstack.sim_backend.emulators.rover.modes import GUIDED, HOLD, RTL
from flightstack.sim_backend.emulators.rover.params import RoverParams
from tests.conftest import eventually
from tests.robot_pose import still_pose

pytestmark = pytest.mark.system
mavlink = mavutil.mavlink
SLACK_S = 1.5  # scheduling allowance on a loaded 2-core machine (s)
FAST = {"fs_gcs_timeout_s": 2.0, "fs_timeout_s": 1.0}  # a 3 s failsafe keeps the tests short


@contextmanager
def rover(params: RoverParams | None = None) -> Iterator[MavlinkRoverEmulator]:
    # the GCS failsafe alone: the bare ground station below sends no position estimate, so the emulator's
    # EKF rule (no GUIDED, and a hold 1 s after the last pose) is off; tests/test_rover_ardupilot.py has it
    emu = MavlinkRoverEmulator(heartbeat_hz=10.0, params=params, requires_position_estimate=False)
    try:
        yield emu
    finally:
        emu.close()


def config(emu: MavlinkRoverEmulator) -> ScamperConfig:
    return ScamperConfig(url=emu.url, heartbeat_timeout_s=3.0)


# ---- preflight: reading and judging the parameters ---------------------------------------------------------
def test_preflight_passes_the_lab_settings_and_changes_nothing() -> None:
    with rover() as emu:
        rows = robot_rows(config(emu))
        assert [(r.check, r.status) for r in rows[:2]] == [("heartbeat", "PASS"), ("GCS failsafe", "PASS")], (
            rows
        )
        assert "FS_ACTION 2 (Hold)" in rows[1].detail and "SYSID_MYGCS 255 = our system id" in rows[1].detail
        # the rows of drivers/scamper/vehicle.py and the origin: tests/test_scamper_extnav.py
        assert [r.check for r in rows[2:]] == [
            "external navigation",
            "GUIDED timeout",
            "kinematics",
            "EKF origin",
        ]
        assert emu.mode == HOLD and not emu.armed  # read, and the origin asked for: nothing armed or moded
        assert {c for c, _, _ in emu.commands} <= {mavlink.MAV_CMD_REQUEST_MESSAGE}, emu.commands


def test_preflight_reads_newer_firmware_names() -> None:
    with rover(RoverParams(gcs_sysid_name="MAV_GCS_SYSID", gcs_sysid=250, gcs_sysid_hi=255)) as emu:
        row = robot_rows(config(emu))[1]
        assert row.status == "PASS" and "MAV_GCS_SYSID 250..MAV_GCS_SYSID_HI 255" in row.detail


@pytest.mark.parametrize(
    ("params", "words"),
    [
        (RoverParams(fs_gcs_enable=0), "FS_GCS_ENABLE = 0 (disabled"),
        (RoverParams(fs_action=0), "FS_ACTION = 0 (Nothing"),
        (RoverParams(fs_action=1), "FS_ACTION = 1 (RTL"),
        (RoverParams(fs_action=3), "FS_ACTION = 3 (SmartRTL"),
        (RoverParams(fs_gcs_timeout_s=5.0, fs_timeout_s=1.5), "= 6.5 s from our last heartbeat"),
        (RoverParams(gcs_sysid=1), "SYSID_MYGCS 1 (the failsafe watches another ground station"),
        (RoverParams(absent=frozenset({"FS_GCS_TIMEOUT"})), "could not read FS_GCS_TIMEOUT"),
        (
            RoverParams(absent=frozenset({"FS_GCS_ENABLE", "SYSID_MYGCS"})),
            "could not read FS_GCS_ENABLE, SYSID",
        ),
    ],
)
def test_preflight_fails_each_bad_setting_naming_it(params: RoverParams, words: str) -> None:
    with rover(params) as emu:
        rows = robot_rows(config(emu))
        assert rows[0].status == "PASS" and rows[1].check == "GCS failsafe"
        assert rows[1].status == "FAIL" and words in rows[1].detail, rows[1].detail


def test_lost_replies_are_asked_again() -> None:
    with rover() as emu:
        emu.faults.drop_param_replies = 3
        _, read = probe_parameters(config(emu), PARAMETERS, enough=enough, reply_timeout_s=0.5)
        assert enough(read.values) and judge_gcs_failsafe(read.values, {"us": 255}).status == "PASS"
        assert read.requests > len(PARAMETERS)  # a second round asked for the lost ones
        assert read.elapsed_s >= 0.5  # waited one reply timeout before asking again


def test_duplicated_replies_count_once() -> None:
    with rover() as emu:
        emu.faults.duplicate_param_replies = True
        _, read = probe_parameters(config(emu), PARAMETERS, enough=enough)
        assert read.values["FS_ACTION"] == 2.0 and read.values["FS_GCS_TIMEOUT"] == 3.0
        assert read.dropped["duplicate"] >= 1 and emu.param_replies >= 2 * len(read.values)


def test_a_silent_robot_is_given_up_on_in_bounded_time() -> None:
    with rover() as emu:
        emu.faults.drop_param_replies = 10_000
        t0 = time.monotonic()
        _, read = probe_parameters(config(emu), PARAMETERS, enough=enough, reply_timeout_s=0.3, attempts=3)
        took = time.monotonic() - t0
        assert read.values == {} and set(read.missing) == set(PARAMETERS)
        assert read.requests == 3 * len(PARAMETERS) and took >= 0.9  # three rounds of 0.3 s, not more
        verdict = judge_gcs_failsafe(read.values, {"us": 255})
        assert verdict.status == "FAIL" and "could not read FS_GCS_ENABLE, FS_ACTION" in verdict.detail


# ---- the emulator's parameter protocol and its failsafe, from a bare ground station ----------------------
class BareGcs:
    """A pymavlink ground station on loopback that chooses when to send heartbeats and set-points."""

    def __init__(self, emu: MavlinkRoverEmulator, sysid: int = 255) -> None:
        self.conn: Any = mavutil.mavlink_connection(emu.url, source_system=sysid, source_component=190)
        self.emu = emu

    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def guided_and_armed(self) -> None:
        self.heartbeat()
        for cmd, p1, p2 in ((mavlink.MAV_CMD_DO_SET_MODE, 1, ROVER_GUIDED_MODE), (400, 1, 0)):
            self.conn.mav.command_long_send(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0)
        assert eventually(lambda: self.emu.mode == GUIDED and self.emu.armed, 2.0)

    def drive(self, seconds: float, vx: float, heartbeats: bool) -> None:
        """Stream vx (m/s) at 10 Hz for `seconds`, with 1 Hz heartbeats or none."""
        end, next_hb = time.monotonic() + seconds, 0.0
        while (now := time.monotonic()) < end:
            if heartbeats and now >= next_hb:
                next_hb = now + 1.0
                self.heartbeat()
            self.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 1511, 0, 0, 0, vx, 0, 0, 0, 0, 0, 0, 0
            )
            time.sleep(0.1)

    def close(self) -> None:
        self.conn.close()


def test_emulator_answers_by_name_by_index_and_the_whole_list() -> None:
    with rover() as emu:
        gcs = BareGcs(emu)
        try:
            gcs.heartbeat()
            assert gcs.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0) is not None
            gcs.conn.mav.param_request_list_send(1, 1)
            got = {}
            while (m := gcs.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)) is not None:
                got[m.param_index] = (m.param_id, m.param_value, m.param_count)
                if len(got) == m.param_count:
                    break
            names = [got[i][0] for i in sorted(got)]
            assert names == [n for n, _, _ in emu.params.table(1)] and "FS_GCS_TIMEOUT" in names
            i = names.index("FS_ACTION")
            gcs.conn.mav.param_request_read_send(1, 1, b"", i)
            m = gcs.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
            assert m is not None and (m.param_id, m.param_value, m.param_type) == ("FS_ACTION", 2.0, 2)
            gcs.conn.mav.param_request_read_send(1, 1, b"NO_SUCH_PARAM", -1)
            gcs.conn.mav.param_request_read_send(7, 1, b"FS_ACTION", -1)  # another system's
            assert gcs.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5) is None
        finally:
            gcs.close()


@pytest.mark.parametrize(
    "params",
    [
        RoverParams(**FAST),
        RoverParams(absent=frozenset({"FS_GCS_TIMEOUT"}), fs_gcs_timeout_s=99.0, fs_timeout_s=1.0),
    ],
    ids=["FS_GCS_TIMEOUT 2", "older firmware: fixed 2 s"],
)
def test_failsafe_holds_a_guided_rover_when_our_heartbeats_stop(params: RoverParams) -> None:
    """Set-points keep coming, heartbeats stop: HOLD, zero velocity, still armed, after 2 + 1 s."""
    with rover(params) as emu:
        gcs, stranger = BareGcs(emu), BareGcs(emu, sysid=254)
        try:
            gcs.guided_and_armed()
            gcs.drive(1.5, 0.5, heartbeats=True)
            assert emu.velocity[0] == 0.5 and emu.failsafe_t is None
            last_hb = emu.gcs_last_seen
            assert last_hb is not None
            end = time.monotonic() + 3.0 + SLACK_S
            while time.monotonic() < end and emu.mode != HOLD:
                gcs.drive(0.2, 0.5, heartbeats=False)
                stranger.heartbeat()  # another system's heartbeats do not count
            assert emu.mode == HOLD and emu.velocity == (0.0, 0.0, 0.0) and emu.armed
            assert emu.failsafe_action == 2 and emu.failsafe_t is not None
            assert 3.0 < emu.failsafe_t - last_hb <= 3.0 + SLACK_S
            gcs.drive(0.5, 0.5, heartbeats=True)  # our heartbeats are back: HOLD stays, set-points ignored
            assert emu.mode == HOLD and emu.velocity == (0.0, 0.0, 0.0) and len(emu.failsafe_events) == 1
        finally:
            gcs.close()
            stranger.close()


def test_failsafe_action_nothing_keeps_driving() -> None:
    with rover(RoverParams(fs_action=0, **FAST)) as emu:
        gcs = BareGcs(emu)
        try:
            gcs.guided_and_armed()
            gcs.drive(1.5, 0.5, heartbeats=True)
            gcs.drive(3.0, 0.5, heartbeats=False)
            assert eventually(lambda: emu.failsafe_t is not None, SLACK_S)  # it triggered ...
            gcs.drive(0.5, 0.5, heartbeats=False)
            assert (
                emu.failsafe_action == 0 and emu.mode == GUIDED and emu.velocity[0] == 0.5
            )  # ... and drove on
        finally:
            gcs.close()


def test_failsafe_rtl_drives_home() -> None:
    with rover(RoverParams(fs_action=1, wp_radius_m=0.05, **FAST)) as emu:
        gcs = BareGcs(emu)
        try:
            gcs.guided_and_armed()
            gcs.drive(1.5, 0.5, heartbeats=True)
            time.sleep(3.0)
            assert eventually(lambda: emu.mode == RTL, SLACK_S)
            x0 = emu.pose_ned()[0]
            assert x0 > 0.3 and emu.velocity[0] > 0.0  # away from home, driving back
            assert eventually(lambda: emu.pose_ned()[0] < x0 - 0.1, 2.0)
        finally:
            gcs.close()


def test_the_driver_streaming_normally_never_trips_it_and_a_muted_one_does() -> None:
    """ScamperDriver's 1 Hz heartbeats keep a 2 + 1 s failsafe quiet; muted (guardian takeover), it acts."""
    with rover(RoverParams(**FAST)) as emu:
        drv = ScamperDriver(config(emu), pose_source=still_pose())
        muted = False
        drv.set_muted(lambda: muted)
        drv.connect()
        try:
            drv.send_body_velocity([0.3, 0.0, 0.0, 0.0])
            time.sleep(4.5)
            assert emu.failsafe_t is None and emu.mode == GUIDED and emu.velocity[0] == pytest.approx(0.3)
            muted = True
            t_mute = time.monotonic()
            assert eventually(lambda: emu.mode == HOLD, 3.0 + 1.0 + SLACK_S)
            assert emu.failsafe_t is not None and emu.failsafe_t - t_mute <= 3.0 + 1.0 + SLACK_S
        finally:
            muted = False
            drv.close()
