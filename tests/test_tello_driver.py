"""drivers/tello.py against the loopback Tello emulator, through the real djitellopy client.

Everything runs on 127.0.0.0/8; emulators own 127.0.0.3 and 127.0.0.4 (the emulator's own tests use
127.0.0.2). djitellopy binds ("", 8889) and ("", 8890) once per process: if another program holds
them, the module is skipped with the reason.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

pytest.importorskip("djitellopy")
pytest.importorskip("av")

from drivers.tello import TelloCamera, TelloCommandError, TelloConfig, TelloDriver, TelloLinkError
from flightstack.camera_calibration import load_calibration
from flightstack.geometry import Pose, rot_z
from flightstack.mission import CAMERA_MOUNTS
from flightstack.tello_rc import RcGains, velocity_to_rc
from flightstack.vision import extract_markers
from sim_backend.render import RenderOptions, render_markers
from tests.conftest import MISSIONS
from tests.emulators.tello import TelloEmulator, free_udp_port, wait_until

CAL = load_calibration(MISSIONS / "cameras" / "tello_down_sim.yaml")
P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
# the target 0.9 m below the drone (downward camera, as the observing drone flies), slightly yawed
G_I0 = Pose.make([0.05, -0.03, -0.9], 0.3)


def _ports_free() -> bool:
    from djitellopy import tello as djt

    if djt.threads_initialized:
        return True
    for port in (8889, 8890):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            s.bind(("", port))
        except OSError:
            return False
        finally:
            s.close()
    return True


pytestmark = pytest.mark.skipif(not _ports_free(), reason="UDP 8889/8890 are taken: djitellopy cannot bind")


def marker_truth() -> tuple[np.ndarray, np.ndarray]:
    """Centres and normals (the target's z axis) of the markers in the downward camera's frame."""
    R_ic = CAMERA_MOUNTS["down"]
    centres = (P0 @ rot_z(G_I0.theta).T + G_I0.p) @ R_ic
    normals = np.tile(R_ic.T @ np.array([0.0, 0.0, 1.0]), (4, 1))
    return centres, normals


def marker_frame(t: float, emu: TelloEmulator) -> np.ndarray:
    centres, normals = marker_truth()
    img, _, _ = render_markers(CAL, centres, normals, RenderOptions(marker_radius_m=0.03))
    return img


def config(emu: TelloEmulator, **kw: object) -> TelloConfig:
    base = dict(
        host=emu.ip,
        control_port=emu.address[1],
        video_port=emu.video_port,
        connect_timeout_s=2.0,
        command_timeout_s=1.0,
        takeoff_timeout_s=3.0,
        land_timeout_s=3.0,
        link_timeout_s=0.5,
        keepalive_s=1.0,
        rc_gains=RcGains(0.01, 0.01, 0.0175),
    )
    base.update(kw)
    return TelloConfig(**base)


@pytest.fixture
def emu():
    e = TelloEmulator(
        "127.0.0.3",
        video_port=free_udp_port(),
        frame_source=marker_frame,
        fps=30.0,
        video_size=(CAL.width, CAL.height),
    )
    e.start()
    yield e
    e.close()


def test_short_flight_rc_values_and_video(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu, downward_camera=True))
    try:
        d.connect()
        checks = {c.name: c for c in d.preflight()}
        assert all(c.ok for c in checks.values()), checks
        d.takeoff()
        assert emu.flying and d.state().flying and d.state().link_alive
        sent = []
        for V in ([0.3, 0.0, 0.0, 0.0], [0.0, -0.25, 0.1, 0.0], [0.1, 0.1, 0.0, 0.5], [0.0, 0.0, 0.0, -0.35]):
            t0 = time.monotonic()
            d.send_body_velocity(np.array(V))
            assert time.monotonic() - t0 < 0.01  # fire and forget: the loop never waits
            sent.append(velocity_to_rc(np.array(V), d.cfg.rc_gains))
            time.sleep(0.3)
        assert wait_until(lambda: len(emu.rc_history) >= 4, 2.0)
        got = [rc for _, rc in list(emu.rc_history)[-4:]]
        assert got == sent  # forward → b > 0, right (−v_y) → a > 0, ccw yaw → d < 0
        assert got[0] == (0, 30, 0, 0) and got[1] == (25, 0, 10, 0) and got[3][3] == 20
        # video: ≥ 30 decoded frames through djitellopy/PyAV, markers within 2 px of the render truth
        cam = TelloCamera(d, frame_timeout_s=10.0)
        cam.start()
        _, true_px, _ = render_markers(CAL, *marker_truth(), RenderOptions(marker_radius_m=0.03))
        errors = []
        deadline = time.monotonic() + 20
        while cam.frames_seen < 30 and time.monotonic() < deadline:
            f = cam.latest()
            if f is not None and f.image is not None and f.image.shape == (CAL.height, CAL.width, 3):
                det = extract_markers(f.image, CAL)
                if det.pixels is not None:
                    errors.append(np.linalg.norm(det.pixels - true_px, axis=1).max())
            time.sleep(0.01)
        cam.stop()
        assert emu.downvision  # the driver switched the EDU to its downward camera
        assert cam.frames_seen >= 30
        assert len(errors) >= 20 and max(errors) < 2.0, (len(errors), max(errors, default=None))
        d.land()
        assert not emu.flying and not d.state().flying
    finally:
        d.close()


def test_connect_to_a_silent_drone_fails_fast_naming_the_ip(emu: TelloEmulator) -> None:
    emu.faults.silent = True
    d = TelloDriver(config(emu, connect_timeout_s=1.0))
    t0 = time.monotonic()
    with pytest.raises(TelloLinkError, match=r"127\.0\.0\.3"):
        d.connect()
    assert time.monotonic() - t0 < 4.0
    d.close()


def test_error_replies_and_late_replies(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        emu.faults.error_replies = True
        with pytest.raises(TelloCommandError, match="takeoff"):
            d.takeoff()
        assert not emu.flying
        emu.faults.error_replies = False
        emu.faults.reply_delay_s = 1.5  # longer than the 1 s command timeout: the reply arrives late
        with pytest.raises(TelloCommandError):
            d._control("streamon", 1.0)
        emu.faults.reply_delay_s = 0.0
        time.sleep(1.0)  # the late 'ok' lands in djitellopy's queue now
        assert d._read("battery?").strip() == str(emu.battery)  # not the stale 'ok': the queue was cleared
    finally:
        d.close()


def test_state_stream_loss_is_detected_and_reported(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu))
    try:
        d.connect()
        assert d.state().link_alive
        emu.faults.drop_state = True
        assert wait_until(lambda: not d.state().link_alive, 2.0)
        assert wait_until(lambda: any(kind == "link_lost" for _, kind, _ in d.events), 1.0)
        emu.faults.drop_state = False
        assert wait_until(lambda: d.state().link_alive, 2.0)
        assert wait_until(lambda: any(kind == "link_restored" for _, kind, _ in d.events), 1.0)
    finally:
        d.close()


def test_low_battery_fails_preflight(emu: TelloEmulator) -> None:
    emu.faults.battery_pct = 12
    d = TelloDriver(config(emu))
    try:
        d.connect()
        assert wait_until(lambda: d.state().battery_pct == 12, 2.0)
        checks = {c.name: c for c in d.preflight()}
        assert not checks["battery"].ok and "12 %" in checks["battery"].detail
        assert checks["temperature"].ok and checks["state stream"].ok
    finally:
        d.close()


def test_keepalive_holds_a_silent_loop_in_hover(emu: TelloEmulator) -> None:
    d = TelloDriver(config(emu, keepalive_s=0.5))
    try:
        d.connect()
        d.takeoff()
        d.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
        n = len(emu.rc_history)
        assert wait_until(lambda: len(emu.rc_history) > n and emu.rc_history[-1][1] == (0, 0, 0, 0), 2.0)
        assert any(kind == "keepalive" for _, kind, _ in d.events)
        assert emu.flying and not emu.landed_by_timeout
        d.land()
    finally:
        d.close()


def test_two_drones_in_one_process() -> None:
    with (
        TelloEmulator("127.0.0.3", video_port=free_udp_port()) as a,
        TelloEmulator("127.0.0.4", video_port=free_udp_port()) as b,
    ):
        da, db = TelloDriver(config(a)), TelloDriver(config(b))
        try:
            da.connect()
            db.connect()
            da.takeoff()
            da.send_body_velocity(np.array([0.5, 0, 0, 0]))
            db.send_body_velocity(np.array([0, 0.5, 0, 0]))
            assert wait_until(lambda: a.rc_history and b.rc_history, 2.0)
            assert a.rc_history[-1][1] == (0, 50, 0, 0) and b.rc_history[-1][1] == (-50, 0, 0, 0)
            assert a.flying and not b.flying
            da.land()
        finally:
            da.close()
            db.close()
