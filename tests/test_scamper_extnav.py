"""The Scamper driver gives ArduPilot what it needs to move indoors: the EKF origin (SET_GPS_GLOBAL_ORIGIN,
confirmed by GPS_GLOBAL_ORIGIN), the motion-capture pose as VISION_POSITION_ESTIMATE, both again after a
reboot; and the raw .tlog of the link.

The vehicle here is `SpecRover` (flightstack/faults/spec_rover.py), written from the MAVLink specification
and ArduPilot's source (not from the driver), because the project's emulator does not answer
GPS_GLOBAL_ORIGIN yet (branch p39-emu adds it). The .tlog test runs against the current emulator
(sim_backend/emulators/rover/) as the acceptance asks: it needs p39-emu's emulator (which
reports the origin) to pass — marked below.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil

from flightstack.drivers.scamper.driver import ScamperCommandError, ScamperConfig, ScamperDriver
from flightstack.drivers.scamper.nav import ORIGIN_RETRY_S
from flightstack.faults.spec_rover import HOLD, SpecRover
from flightstack.hal import StampedPose
from flightstack.paper.geometry import Pose

mavlink = mavutil.mavlink
pytestmark = pytest.mark.system

TYPES = "HEARTBEAT,SET_POSITION_TARGET_LOCAL_NED,COMMAND_ACK"


class MovingPose:
    """The robot's motion-capture pose: lab (1, 2) facing +x, stamped now (time.monotonic())."""

    def __init__(self) -> None:
        self.frozen_at: float | None = None

    def __call__(self) -> StampedPose | None:
        t = time.monotonic() if self.frozen_at is None else self.frozen_at
        return StampedPose(t, Pose.make([1.0, 2.0, 0.0], 0.0))


@pytest.fixture
def rover() -> Iterator[SpecRover]:
    r = SpecRover()
    yield r
    r.close()


def _cfg(port: int, **kw: float) -> ScamperConfig:
    return ScamperConfig(url=f"udpout:127.0.0.1:{port}", heartbeat_timeout_s=3.0, **kw)  # type: ignore[arg-type]


def test_origin_then_vision_then_guided(rover: SpecRover) -> None:
    pose = MovingPose()
    drv = ScamperDriver(_cfg(rover.port), pose_source=pose)
    drv.connect()
    try:
        state = drv.robot_state()
        assert state.ready and state.origin_confirmed
        assert rover.origin == drv.origin.as_mavlink()
        assert rover.refused == []  # the vision stream ran before GUIDED was asked for
        time.sleep(1.0)
        with rover.lock:
            recent = [(t, m) for t, m in rover.vision if t > time.monotonic() - 1.0]
        rate = len(recent) / 1.0
        print(f"vision messages in the last 1 s: {rate:.0f} (configured {drv.config.vision_hz:g} Hz)")
        assert rate >= 10.0  # >= 10 Hz asked; ArduPilot's docs ask >= 4 Hz
        m = recent[-1][1]
        assert (m.x, m.y, m.z, m.yaw) == pytest.approx((1.0, -2.0, 0.0, 0.0), abs=1e-6)  # type: ignore[attr-defined]
        assert abs(m.usec / 1e6 - time.monotonic()) < 1.0  # type: ignore[attr-defined]
        assert any(e.kind == "origin_confirmed" for e in drv.events)
    finally:
        drv.close()


def test_stale_pose_is_not_sent(rover: SpecRover) -> None:
    pose = MovingPose()
    drv = ScamperDriver(_cfg(rover.port), pose_source=pose)
    drv.connect()
    try:
        pose.frozen_at = time.monotonic()  # motion capture lost the body: its last pose ages
        time.sleep(0.5)
        with rover.lock:
            n0 = len(rover.vision)
        time.sleep(0.5)
        with rover.lock:
            n1 = len(rover.vision)
        assert n1 == n0, "a pose older than vision_max_age_s was sent"
        assert drv.counts["vision_stale"] > 0
        pose.frozen_at = None  # body back: sent again, reset_counter bumped
        time.sleep(0.5)
        with rover.lock:
            last = rover.vision[-1][1]
        assert drv.vision_reset_counter == 1
        assert getattr(last, "reset_counter", 1) == 1  # a MAVLink 1 frame does not carry it
    finally:
        drv.close()


def test_no_origin_reported_refuses_to_connect_in_one_line() -> None:
    r = SpecRover(answer_origin=False)
    try:
        drv = ScamperDriver(_cfg(r.port, origin_timeout_s=1.5), pose_source=MovingPose())
        t0 = time.monotonic()
        with pytest.raises(ScamperCommandError) as exc:
            drv.connect()
        took = time.monotonic() - t0
        print(f"connect failed after {took:.2f} s: {exc.value}")
        assert "EKF origin not confirmed" in str(exc.value) and "\n" not in str(exc.value)
        assert r.origin_sets >= 1 and r.mode == HOLD and not r.armed
        # one try ORIGIN_RETRY_S after the last, whatever the ticker's phase (connect's own try included)
        assert r.origin_sets <= 1 + int(took / ORIGIN_RETRY_S), r.origin_sets
        assert drv.threads_alive() == {}
    finally:
        r.close()


def test_reboot_sets_the_origin_again(rover: SpecRover) -> None:
    drv = ScamperDriver(_cfg(rover.port), pose_source=MovingPose())
    drv.connect()
    try:
        rover.reboot()  # time_boot_ms goes back, origin forgotten
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            with rover.lock:
                if rover.origin is not None:
                    break
            time.sleep(0.05)
        assert rover.origin == drv.origin.as_mavlink()
        kinds = [e.kind for e in drv.events]
        assert "origin_forgotten" in kinds and kinds.count("origin_confirmed") == 2
        time.sleep(0.3)
        assert drv.robot_state().origin_confirmed
        assert not drv.robot_state().ready  # rebooted into HOLD, disarmed: not driving
    finally:
        drv.close()


def _path_without_shims() -> str:
    import os

    return os.pathsep.join(p for p in os.environ.get("PATH", "").split(os.pathsep) if "shims" not in p)


def _mavlogdump() -> str:
    """pymavlink's mavlogdump.py beside this Python, or on PATH (the lead's venv at its end)."""
    here = Path(sys.executable).parent / "mavlogdump.py"
    found = str(here) if here.is_file() else shutil.which("mavlogdump.py", path=_path_without_shims())
    if not found:
        from tests.conftest import skip_or_fail_in_ci

        skip_or_fail_in_ci("mavlogdump.py not found: pip install pymavlink")
    return found


def _emulator_reports_origin(url: str) -> bool:
    """Does the rover emulator answer SET_GPS_GLOBAL_ORIGIN + REQUEST_MESSAGE(49) with GPS_GLOBAL_ORIGIN?"""
    from flightstack.drivers.scamper.link import open_connection, wait_vehicle_heartbeat
    from flightstack.drivers.scamper.nav import LabOrigin
    from flightstack.drivers.scamper.params import confirm_origin

    cfg = ScamperConfig(url=url, heartbeat_timeout_s=3.0)
    conn = open_connection(cfg)
    try:
        _, target = wait_vehicle_heartbeat(conn, cfg)
        return confirm_origin(conn, target, LabOrigin(52.0, 4.0, 0.0), 2.0).reported is not None
    finally:
        conn.close()


def test_tlog_both_directions_against_the_emulator(tmp_path: Path) -> None:
    """The acceptance run on the project's rover emulator. It needs an emulator that reports the EKF
    origin (branch p39-emu): against one that does not, the driver rightly refuses to connect, and the
    test is marked xfail naming that, instead of passing."""
    from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator

    with MavlinkRoverEmulator(heartbeat_hz=10.0) as emu:
        url = f"udpout:127.0.0.1:{emu.port}"
        if not _emulator_reports_origin(url):
            pytest.xfail("needs p39-emu's emulator: this one never reports GPS_GLOBAL_ORIGIN")
        _tlog_run(url, tmp_path)


def test_tlog_both_directions_against_the_spec_rover(rover: SpecRover, tmp_path: Path) -> None:
    _tlog_run(f"udpout:127.0.0.1:{rover.port}", tmp_path)


def _tlog_run(url: str, tmp_path: Path) -> None:
    path = tmp_path / "devices" / "scamper_mode.tlog"
    t_start = time.time()
    drv = ScamperDriver(
        ScamperConfig(url=url, heartbeat_timeout_s=3.0), pose_source=MovingPose(), tlog_path=path
    )
    drv.connect()
    for k in range(10):
        drv.send_body_velocity(np.array([0.05 * k, 0.0, 0.0, 0.0]))
        time.sleep(0.05)
    drv.close()
    t_end = time.time()
    sent = drv.counts["setpoint_sent"]
    out = subprocess.run(
        [sys.executable, _mavlogdump(), "--types", TYPES, str(path)],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    lines = out.splitlines()
    sp = [ln for ln in lines if "SET_POSITION_TARGET_LOCAL_NED" in ln]
    ours = [ln for ln in lines if "HEARTBEAT {type : 6," in ln]  # MAV_TYPE_GCS
    theirs = [ln for ln in lines if "HEARTBEAT {type : 10," in ln]  # MAV_TYPE_GROUND_ROVER
    acks = [ln for ln in lines if "COMMAND_ACK" in ln]
    print(
        f"tlog: {len(sp)} set-points (driver counted {sent}), "
        f"{len(ours)} GCS / {len(theirs)} rover heartbeats"
    )
    assert abs(len(sp) - sent) <= 1 and sent > 0
    assert ours and theirs and acks
    # mavlogdump prints local wall time; read the stamps back with pymavlink instead of parsing them
    log = mavutil.mavlink_connection(str(path))
    stamps = []
    while (m := log.recv_match()) is not None:
        stamps.append(m._timestamp)
    assert stamps and t_start - 0.01 <= min(stamps) and max(stamps) <= t_end + 0.01
    assert all(math.isfinite(s) for s in stamps)


def _preflight(rover: SpecRover) -> dict[str, tuple[str, str]]:
    from flightstack.drivers.lab.preflight import robot_rows

    rows = robot_rows(_cfg(rover.port))
    return {r.check: (r.status, r.detail) for r in rows}


def test_preflight_passes_a_rover_set_up_as_docs_say(rover: SpecRover) -> None:
    rows = _preflight(rover)
    print(rows)
    for check in ("heartbeat", "GCS failsafe", "external navigation", "GUIDED timeout", "kinematics"):
        assert rows[check][0] == "PASS", (check, rows[check])
    assert rows["EKF origin"][0] == "PASS" and rows["kinematics"][1].startswith("differential")
    assert rover.mode == HOLD and not rover.armed  # nothing moved, nothing armed


def test_preflight_refuses_default_sources_in_one_line() -> None:
    from flightstack.faults.spec_rover import ARDUPILOT_DEFAULTS

    r = SpecRover(params=ARDUPILOT_DEFAULTS)
    try:
        status, detail = _preflight(r)["external navigation"]
    finally:
        r.close()
    print(detail)
    assert status == "FAIL" and "\n" not in detail
    assert detail.startswith("no external position source: set on the vehicle EK3_SRC1_POSXY 6 (now 3)")


def test_preflight_refuses_a_vehicle_without_origin() -> None:
    r = SpecRover(answer_origin=False)
    try:
        status, detail = _preflight(r)["EKF origin"]
    finally:
        r.close()
    print(detail)
    assert status == "FAIL" and detail.startswith("no EKF origin") and "\n" not in detail
