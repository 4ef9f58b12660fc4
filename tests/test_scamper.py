"""Scamper MAVLink driver against the loopback rover emulator (tests/emulators/mavlink_rover.py)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from drivers.scamper import (
    ROVER_GUIDED_MODE,
    TYPE_MASK_VEL_YAWRATE,
    ScamperCommandError,
    ScamperConfig,
    ScamperDriver,
    ScamperLinkError,
)
from flightstack.hal import GroundRobot
from tests.emulators.mavlink_rover import MavlinkRoverEmulator


def wait_for(pred: Callable[[], bool], timeout: float, step: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


@pytest.fixture
def emu() -> Iterator[MavlinkRoverEmulator]:
    e = MavlinkRoverEmulator()
    yield e
    e.close()


def make_driver(emu: MavlinkRoverEmulator, **kw: float) -> ScamperDriver:
    cfg = ScamperConfig(url=emu.url, heartbeat_timeout_s=kw.pop("heartbeat_timeout_s", 3.0), **kw)
    return ScamperDriver(cfg)


def test_connect_sets_guided_and_arms(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu)
    assert isinstance(drv, GroundRobot)
    drv.connect()
    try:
        assert emu.mode == ROVER_GUIDED_MODE
        assert emu.armed
        assert drv.link_alive()
        assert [k for _, k, _ in drv.events] == ["connected"]
    finally:
        drv.close()
    assert not emu.armed  # close() disarms
    drv.close()  # idempotent


def test_body_velocity_signs_and_motion(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu, stream_hz=10.0)
    drv.connect()
    try:
        t0 = time.monotonic()
        drv.send_body_velocity(np.array([0.2, 0.1, 0.0, 0.3]))  # forward, left, ccw (FLU)
        assert time.monotonic() - t0 < 0.05  # never blocks the caller
        assert wait_for(lambda: emu.velocity != (0.0, 0.0, 0.0), 1.0)
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
        # FLU pose: turned ccw, moved forward and left, consistent with a constant twist
        pose = emu.pose_flu()
        th = pose.theta
        assert 0.25 < th < 0.45  # ~0.3 rad/s for ~1.0-1.2 s
        w = 0.3
        x_exp = (0.2 * math.sin(th) + 0.1 * (math.cos(th) - 1.0)) / w
        y_exp = (0.2 * (1.0 - math.cos(th)) + 0.1 * math.sin(th)) / w
        assert pose.p[0] == pytest.approx(x_exp, abs=1e-3)
        assert pose.p[1] == pytest.approx(y_exp, abs=1e-3)
        assert pose.p[0] > 0.15 and pose.p[1] > 0.1

        drv.stop()
        assert wait_for(lambda: emu.velocity == (0.0, 0.0, 0.0), 0.5)
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
    assert any(k == "disarm_failed" for _, k, _ in drv.events)
    assert emu.armed and emu.velocity == (0.0, 0.0, 0.0)


def test_rover_stops_by_itself_3s_after_stream_stops(emu: MavlinkRoverEmulator) -> None:
    emu.faults.reject_disarm = True
    drv = make_driver(emu, ack_timeout_s=0.5)
    drv.connect()
    drv.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
    assert wait_for(lambda: emu.velocity[0] == pytest.approx(0.3), 1.0)
    # Simulate a dead companion computer: the I/O thread and socket vanish without a zero set-point.
    drv._shutdown()
    t_stop = time.monotonic()
    assert wait_for(lambda: emu.stopped_by_timeout, 4.0)
    dt = time.monotonic() - t_stop
    assert 2.5 < dt < 3.6
    assert emu.velocity == (0.0, 0.0, 0.0) and emu.armed


def test_no_heartbeat_raises_link_error_naming_url(emu: MavlinkRoverEmulator) -> None:
    emu.faults.no_heartbeat = True
    drv = make_driver(emu, heartbeat_timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(ScamperLinkError, match=emu.url):
        drv.connect()
    assert time.monotonic() - t0 < 1.5
    assert not emu.armed
    drv.close()


def test_reject_arm_raises_command_error(emu: MavlinkRoverEmulator) -> None:
    emu.faults.reject_arm = True
    drv = make_driver(emu)
    with pytest.raises(ScamperCommandError, match="DENIED"):
        drv.connect()
    assert not emu.armed
    drv.close()


def test_link_loss_and_restore(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu, link_timeout_s=1.0)
    drv.connect()
    try:
        emu.faults.no_heartbeat = True
        assert wait_for(lambda: not drv.link_alive(), 2.5)
        assert [k for _, k, _ in drv.events][-1] == "link_lost"
        emu.faults.no_heartbeat = False
        assert wait_for(drv.link_alive, 1.5)
        assert [k for _, k, _ in drv.events][-1] == "link_restored"
    finally:
        drv.close()


def test_no_threads_left_after_close(emu: MavlinkRoverEmulator) -> None:
    drv = make_driver(emu)
    drv.connect()
    drv.close()
    emu.close()
    names = [t.name for t in threading.enumerate()]
    assert "scamper-io" not in names and "mavlink-rover-emu" not in names
