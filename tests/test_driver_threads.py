"""Driver threads that cannot die, and the guardian's mute hook.

Each test injects errors into one background thread of a driver, through the thread's own socket (a
`FaultySocket` proxy whose recv/recvfrom/send raise OSError(ENETUNREACH) a given number of times) or
through the pymavlink connection's `write`, and checks at an emulator that the thread is still alive AND
still does its job afterwards, that the errors were counted and that they were logged once, not per error.
Everything runs on 127.0.0.x with OS-assigned ports; every thread started here is stopped by its
driver's close (bounded joins) and every wait is bounded.
"""

from __future__ import annotations

import errno
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from flightstack.drivers.mocap import MocapConfig, MocapPoseSource
from flightstack.drivers.tello.link import CommandChannel
from flightstack.faults.rows_lab_drivers import FaultySocket
from tests.conftest import tello_config


def wait_for(pred: Callable[[], bool], timeout: float = 3.0, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


def warnings_about(caplog: pytest.LogCaptureFixture, kind: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if f": {kind} #" in r.getMessage()]


def thread_names() -> set[str]:
    return {t.name for t in threading.enumerate()}


# ---- Tello: state receiver, command channel, driver monitor, video -------------------------------------
@pytest.fixture
def tello() -> Iterator[Any]:
    pytest.importorskip("av")
    from flightstack.ports import free_udp_port
    from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator

    emu = TelloEmulator(
        "127.0.0.31", state_port=free_udp_port(), video_port=free_udp_port(), fps=30.0, video_size=(320, 240)
    )
    emu.start()
    try:
        yield emu
    finally:
        emu.close()


def tello_driver(emu: Any) -> Any:
    from flightstack.drivers.tello.driver import TelloDriver
    from flightstack.drivers.tello.rc import RcGains

    return TelloDriver(tello_config(emu, link_timeout_s=0.5, keepalive_s=1.0, rc_gains=RcGains()))


def test_tello_state_receiver_survives_socket_and_parse_errors(
    tello: Any, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    import flightstack.drivers.tello.link as tello_link

    caplog.set_level(logging.WARNING, "flightstack.tello")
    d = tello_driver(tello)
    try:
        d.connect()
        rx = d.link.rx
        rx._sock = FaultySocket(rx._sock, recvfrom=8)
        assert wait_for(lambda: rx.counts["recv_error"] == 8)
        # an unexpected exception from parsing (not a rejected datagram) does not end the thread either
        real_parse, boom = tello_link.parse_state, [0]

        def parse(data: bytes, t: float) -> Any:
            if boom[0] < 3:
                boom[0] += 1
                raise RuntimeError("parser bug (injected)")
            return real_parse(data, t)

        monkeypatch.setattr(tello_link, "parse_state", parse)
        assert wait_for(lambda: rx.counts["receiver_error"] == 3)
        # still delivering: later state packets reach the driver, which reads the link as alive
        n = rx.counts["delivered"]
        t_before = time.monotonic()
        assert wait_for(lambda: rx.counts["delivered"] >= n + 5)
        assert d.current_state() and d.status.last_state_t > t_before and d.state().link_alive
        assert rx._thread.is_alive()
        assert rx.counts["thread_error"] == 11
        assert len(warnings_about(caplog, "recv_error")) == 1  # the first, not one per error
        assert len(warnings_about(caplog, "receiver_error")) == 1
        assert "unreachable" in warnings_about(caplog, "recv_error")[0]  # logged with its reason
    finally:
        d.close()


def test_tello_command_channel_and_monitor_survive_errors(
    tello: Any, caplog: pytest.LogCaptureFixture
) -> None:
    from flightstack.drivers.tello.config import parse_int_reply

    caplog.set_level(logging.WARNING, "flightstack.tello")
    d = tello_driver(tello)
    try:
        d.connect()
        chan = d.link.chan
        chan._sock = FaultySocket(chan._sock, recv=6, send=4)
        assert wait_for(lambda: chan.counts["recv_error"] == 6)
        for _ in range(4):  # a network error on send is counted and reported, never raised
            assert chan.send("battery?") is False
        assert chan.counts["send_error"] == 4
        assert len(warnings_about(caplog, "send_error")) == 1
        # the reader still files replies: a query is answered
        assert d.query("battery?", parse_int_reply) is not None
        assert chan._thread.is_alive() and chan.counts["thread_error"] == 6
        # the monitor (drivers/tello/watchdog.py): errors raised in a step are counted; it still watches
        real_step, boom = d.watchdog.step, [0]

        def step(now: float) -> None:
            if boom[0] < 3:
                boom[0] += 1
                raise OSError(errno.ENETUNREACH, "injected")
            real_step(now)

        d.watchdog.step = step
        assert wait_for(lambda: d.counts["monitor_error"] == 3)

        def kinds() -> list[str]:
            return [e.kind for e in d.events]

        tello.faults.drop_state = True  # the monitor (not the age check of state()) reports the loss
        assert wait_for(lambda: "link_lost" in kinds(), 2.0)
        tello.faults.drop_state = False
        assert wait_for(lambda: "link_restored" in kinds()[kinds().index("link_lost") :], 2.0)
        assert d.watchdog.running() and d.state().link_alive
    finally:
        d.close()


def test_tello_video_reader_survives_socket_and_decoder_errors(
    tello: Any, caplog: pytest.LogCaptureFixture
) -> None:
    from flightstack.drivers.tello.camera import TelloCamera

    caplog.set_level(logging.WARNING, "flightstack.tello")
    d = tello_driver(tello)
    cam = TelloCamera(d, frame_timeout_s=10.0)
    try:
        d.connect()
        cam.start()
        rx = cam._rx
        assert wait_for(lambda: cam.latest() is not None and cam.counts["frames"] >= 5, 10.0)
        rx._sock = FaultySocket(rx._sock, recvfrom=10)
        assert wait_for(lambda: rx.counts["recv_error"] == 10)
        real_decode, boom = rx._decode, [0]

        def decode(data: bytes) -> None:
            if boom[0] < 3:
                boom[0] += 1
                raise RuntimeError("decoder bug (injected)")
            real_decode(data)

        rx._decode = decode
        assert wait_for(lambda: cam.counts["reader_error"] == 3)
        # still decoding: new frames after the errors (the decoder was rebuilt: next keyframe), 240 x 320
        n = cam.counts["frames"]
        assert wait_for(lambda: cam.counts["frames"] >= n + 15, 10.0)
        seen = cam.frames_seen
        frame = cam.latest()
        assert frame is not None and frame.image is not None and frame.image.shape == (240, 320, 3)
        assert cam.frames_seen == seen + 1 and time.monotonic() - frame.stamp < 1.0
        assert rx.alive() and cam.counts["thread_error"] == 13
        assert len(warnings_about(caplog, "recv_error")) == 1
        assert len(warnings_about(caplog, "reader_error")) == 1
    finally:
        cam.stop()
        d.close()
    assert f"tello-video-{tello.video_port}" not in thread_names()


def test_command_channel_mute() -> None:
    drone = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    drone.bind(("127.0.0.1", 0))
    drone.settimeout(0.3)
    muted = [False]
    chan = CommandChannel("127.0.0.1", drone.getsockname()[1], "127.0.0.1", muted=lambda: muted[0])

    def received() -> list[bytes]:
        got = []
        try:
            while True:
                got.append(drone.recv(64))
        except TimeoutError:
            return got

    try:
        assert chan.send("rc 0 10 0 0") and received() == [b"rc 0 10 0 0"]
        muted[0] = True  # checked at every send: the very next one is suppressed
        assert chan.send("rc 0 20 0 0") is False and chan.send("land") is False
        assert received() == [] and chan.counts["muted"] == 2 and chan.counts["sent"] == 1
        muted[0] = False
        assert chan.send("rc 0 0 0 0") and received() == [b"rc 0 0 0 0"]

        def broken() -> bool:
            raise RuntimeError("check failed")

        chan.muted = broken  # settable after construction; a check that raises does not mute
        assert chan.send("rc 0 0 0 0") and chan.counts["muted_check_error"] == 1
        chan.muted = lambda: True
        assert chan.send("rc 0 0 0 0") is False and received() == [b"rc 0 0 0 0"]
        assert chan.counts["muted"] == 3
    finally:
        chan.close()
        drone.close()


# ---- motion capture ------------------------------------------------------------------------------------
class FlakyMocap:
    """Wraps a motioncapture object: waitForNextFrame raises ENETUNREACH on calls number first..last."""

    def __init__(self, inner: Any, first: int, last: int) -> None:
        self.inner, self.first, self.last = inner, first, last
        self.calls = 0

    def waitForNextFrame(self) -> None:
        self.calls += 1
        if self.first <= self.calls <= self.last:
            raise OSError(errno.ENETUNREACH, "Network is unreachable (injected)")
        self.inner.waitForNextFrame()

    @property
    def rigidBodies(self) -> Any:
        return self.inner.rigidBodies


def check_mocap_survives(src: MocapPoseSource, flaky: list[FlakyMocap], body: str, n_errors: int) -> None:
    assert wait_for(lambda: flaky and flaky[0].calls > flaky[0].last, 5.0)
    assert src.counts["reader_error"] == n_errors and src.counts["thread_error"] == n_errors
    frames = src.stats()["frames"]
    assert wait_for(lambda: src.stats()["frames"] >= frames + 10)
    st = src.stats()
    assert st["reader_alive"] and not st["reader_failing"] and "unreachable" in str(st["reader_error"])
    assert src.latest(body) is not None
    kinds = [e.kind for e in src.events]
    assert kinds.count("reader_error") == 1 and kinds.count("reader_recovered") == 1


def test_mocap_reader_survives_errors_fake_backend(caplog: pytest.LogCaptureFixture) -> None:
    from types import SimpleNamespace

    caplog.set_level(logging.WARNING, "flightstack.mocap")

    class Fake:
        def __init__(self) -> None:
            rot = SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0)
            self.rigidBodies = {"cf1": SimpleNamespace(position=np.array([1.0, 2.0, 0.5]), rotation=rot)}

        def waitForNextFrame(self) -> None:
            time.sleep(0.005)

    flaky: list[FlakyMocap] = []

    def connect(system: str, settings: dict[str, str]) -> FlakyMocap:
        flaky.append(FlakyMocap(Fake(), 20, 44))
        return flaky[0]

    src = MocapPoseSource(MocapConfig(system="fake"), connect)
    src.start()
    try:
        check_mocap_survives(src, flaky, "cf1", 25)
        assert len(warnings_about(caplog, "reader_error")) == 1
    finally:
        src.close()
    assert not src.stats()["reader_alive"]


def test_mocap_reader_survives_errors_natnet_emulator() -> None:
    motioncapture = pytest.importorskip("motioncapture")
    from flightstack.sim_backend.emulators.natnet import NatNetEmulator

    flaky: list[FlakyMocap] = []

    def connect(system: str, settings: dict[str, str]) -> FlakyMocap:
        flaky.append(FlakyMocap(motioncapture.connect(system, settings), 30, 34))
        return flaky[0]

    with NatNetEmulator({"cf1": ((1.0, -2.0, 0.5), (1.0, 0.0, 0.0, 0.0))}, rate_hz=100.0) as emu:
        src = MocapPoseSource(MocapConfig("optitrack", emu.settings(), connect_timeout_s=2.0), connect)
        src.start()
        try:
            check_mocap_survives(src, flaky, "cf1", 5)
            sp = src.latest("cf1")
            assert sp is not None and np.allclose(sp.pose.p, [1.0, -2.0, 0.5], atol=1e-5)
        finally:
            src.close()  # while the emulator still streams: waitForNextFrame returns


# ---- Scamper (MAVLink) ---------------------------------------------------------------------------------
@pytest.fixture
def rover() -> Iterator[Any]:
    pytest.importorskip("pymavlink")
    from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator

    # the driver's threads under injected send and receive errors, which also cut its pose stream: the
    # emulator's EKF rule (a hold 1 s after the last pose) would end the run the tests look at, so it is off
    emu = MavlinkRoverEmulator(heartbeat_hz=10.0, requires_position_estimate=False)
    try:
        yield emu
    finally:
        emu.close()


def scamper(emu: Any) -> Any:
    from flightstack.drivers.scamper.driver import ScamperConfig, ScamperDriver
    from tests.robot_pose import still_pose

    cfg = ScamperConfig(url=emu.url, heartbeat_timeout_s=3.0, ack_timeout_s=0.5)
    return ScamperDriver(cfg, pose_source=still_pose())


def test_scamper_threads_survive_send_receive_and_handler_errors(
    rover: Any, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, "flightstack.scamper")
    drv = scamper(rover)
    drv.connect()
    try:
        link = drv._link
        assert drv.threads_alive() == {"scamper-rx": True, "scamper-tx": True}
        drv.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
        assert wait_for(lambda: rover.velocity == pytest.approx((0.3, 0.0, 0.0)))
        # sender: the next 12 writes (streamed set-points, GCS heartbeat) fail with ENETUNREACH
        real_write, boom = link.conn.write, [0]

        def write(buf: bytes) -> None:
            if boom[0] < 12:
                boom[0] += 1
                raise OSError(errno.ENETUNREACH, "Network is unreachable (injected)")
            real_write(buf)

        link.conn.write = write
        assert wait_for(lambda: drv.counts["send_error"] == 12, 3.0)
        n_sp, n_hb = len(rover.setpoint_records()), rover.gcs_heartbeat_count()
        drv.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.5]))  # later set-points still reach the robot
        assert wait_for(lambda: len(rover.setpoint_records()) >= n_sp + 5)
        assert wait_for(lambda: rover.velocity == pytest.approx((0.1, 0.0, -0.5)))
        assert wait_for(lambda: rover.gcs_heartbeat_count() > n_hb, 2.5)  # and heartbeats
        # receiver: recvfrom fails 10 times, the handler raises twice
        link.conn.port = FaultySocket(link.conn.port, recvfrom=10)
        assert wait_for(lambda: drv.counts["recv_error"] == 10)
        real_handle, hboom = drv._handle, [0]

        def handle(msg: Any, now: float) -> None:
            if hboom[0] < 2:
                hboom[0] += 1
                raise RuntimeError("handler bug (injected)")
            real_handle(msg, now)

        drv._handle = handle
        assert wait_for(lambda: drv.counts["rx_error"] == 2)
        # the heartbeat thread's own step raises twice
        real_hb, tboom = link.send_heartbeat, [0]

        def send_heartbeat() -> str:
            if tboom[0] < 2:
                tboom[0] += 1
                raise RuntimeError("heartbeat bug (injected)")
            return real_hb()

        link.send_heartbeat = send_heartbeat
        assert wait_for(lambda: drv.counts["tx_error"] == 2, 3.0)
        # still receiving: a pilot's mode switch is seen, the heartbeat stays fresh, the link alive
        rover.pilot_override(mode=4)
        assert wait_for(lambda: drv.robot_state().custom_mode == 4)
        assert "mode_changed" in [e.kind for e in drv.events]
        assert drv.link_alive() and drv.robot_state().age_s < 0.5
        assert drv.threads_alive() == {"scamper-rx": True, "scamper-tx": True}
        assert drv.counts["thread_error"] == 14  # recv 10, handler 2, tx 2; send errors: own count
        for kind in ("send_error", "recv_error", "rx_error", "tx_error"):
            assert len(warnings_about(caplog, kind)) == 1, kind
    finally:
        drv.close()
    assert not {"scamper-rx", "scamper-tx"} & thread_names()


def test_scamper_mute_stops_every_send(rover: Any) -> None:
    from pymavlink import mavutil

    from flightstack.drivers.scamper.driver import ScamperCommandError

    arm_disarm = mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM

    drv = scamper(rover)
    drv.connect()
    muted = threading.Event()
    try:
        drv.set_muted(muted.is_set)
        drv.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
        assert wait_for(lambda: rover.velocity == pytest.approx((0.3, 0.0, 0.0)))
        muted.set()  # the takeover: checked right before each write, from the caller's and the threads'
        n_sp, n_hb = len(rover.setpoint_records()), rover.gcs_heartbeat_count()
        drv.send_body_velocity(np.array([0.5, 0.0, 0.0, 0.0]))
        drv.stop()
        time.sleep(1.3)  # > 10 stream periods and one GCS heartbeat period
        assert len(rover.setpoint_records()) == n_sp and rover.gcs_heartbeat_count() == n_hb
        assert drv.counts["muted"] >= 13 and drv.is_muted()
        with pytest.raises(ScamperCommandError, match="muted"):  # no mode/arm command either, at once
            drv._ensure("set HOLD", 176, 1.0, 4.0, lambda mode, armed: mode == 4)
        n_cmd = len(rover.commands)
    finally:
        drv.close()  # zero set-point and disarm: not sent, the process that took over is in charge
    assert len(rover.setpoint_records()) == n_sp and len(rover.commands) == n_cmd
    assert not any(c == arm_disarm and p == 0.0 for c, p, _ in rover.commands)
    assert rover.armed and "disarm_skipped_muted" in [e.kind for e in drv.events]


def test_scamper_mute_set_before_connect_and_lifted(rover: Any) -> None:
    from flightstack.drivers.scamper.driver import ScamperConfig, ScamperDriver

    flag = [False]
    from tests.robot_pose import still_pose

    cfg = ScamperConfig(url=rover.url, heartbeat_timeout_s=3.0)
    drv = ScamperDriver(cfg, muted=lambda: flag[0], pose_source=still_pose())
    drv.connect()
    try:
        flag[0] = True
        time.sleep(0.05)
        n_sp = len(rover.setpoint_records())
        time.sleep(0.5)
        assert len(rover.setpoint_records()) == n_sp
        drv.set_muted(None)  # removed: streaming resumes
        assert wait_for(lambda: len(rover.setpoint_records()) >= n_sp + 3)
    finally:
        drv.close()
    assert not rover.armed
