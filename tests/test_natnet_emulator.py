"""flightstack.drivers.mocap with the real `motioncapture` optitrack backend against the loopback NatNet
emulator.

Everything runs on 127.0.0.1 with OS-assigned ports (sim_backend/emulators/natnet.py). Sources are closed
while
the emulator still streams, so the reader thread leaves `waitForNextFrame` (which has no timeout) at once.
"""

from __future__ import annotations

import math
import socket
import struct
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("motioncapture")

from flightstack.drivers.mocap import MocapConfig, MocapPoseSource, quaternion_to_planar
from flightstack.sim_backend.emulators.natnet import NAT_CONNECT, NAT_SERVERINFO, NatNetEmulator, NatNetFaults
from tests.conftest import Bound

REPO = Path(__file__).resolve().parents[1]
RATE_HZ = 100.0


def q_zyx(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


BODIES = {
    "cf1": ((1.25, -2.0, 0.75), q_zyx(0.7)),
    "target": ((-0.5, -0.5, 0.0), q_zyx(-2.9)),
    "tilted": ((0.1, 0.2, 0.3), q_zyx(1.1, pitch=0.2)),
}


def wait_for(pred: Callable[[], bool], timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


@pytest.fixture
def emu() -> Iterator[NatNetEmulator]:
    e = NatNetEmulator(dict(BODIES), rate_hz=RATE_HZ)
    e.start()
    try:
        yield e
    finally:
        e.close()


def make_source(emu: NatNetEmulator, **kw: Any) -> MocapPoseSource:
    kw.setdefault("connect_timeout_s", 2.0)
    return MocapPoseSource(MocapConfig(system="optitrack", settings=emu.settings(), **kw))


def assert_pose_matches(src: MocapPoseSource, name: str, p: Any, q: Any) -> None:
    sp = src.latest(name)
    assert sp is not None, name
    expected, tilt = quaternion_to_planar(p, *q)
    np.testing.assert_allclose(sp.pose.p, expected.p, atol=1e-5)
    assert abs(math.remainder(sp.pose.theta - expected.theta, 2 * math.pi)) < 1e-5
    assert src.tilt(name) == pytest.approx(tilt, abs=1e-5)


def test_settings_are_loopback_and_os_assigned(emu: NatNetEmulator) -> None:
    s = emu.settings()
    assert s["hostname"] == "127.0.0.1" and s["interface_ip"] == "127.0.0.1"
    assert int(s["port_command"]) not in (0, 1510) and emu.data_port not in (0, 1511)
    with pytest.raises(ValueError, match="loopback"):
        NatNetEmulator(host="10.0.0.2")


def test_poses_match_emulator(emu: NatNetEmulator) -> None:
    with make_source(emu) as src:
        assert wait_for(lambda: all(src.latest(n) is not None for n in ("cf1", "target", "tilted")))
        for name, (p, q) in BODIES.items():
            assert_pose_matches(src, name, p, q)
        assert src.tilt("tilted") == pytest.approx(0.2, abs=1e-5)
        # a moved body and a body streamed from a provider are seen at their new poses
        emu.set_body("cf1", (0.0, 1.0, 2.0), q_zyx(-1.5))
        emu.set_pose_provider("target", lambda: ((0.3, 0.4, 0.0), q_zyx(2.0)))
        assert wait_for(lambda: (sp := src.latest("cf1")) is not None and sp.pose.p[2] > 1.9)
        assert wait_for(lambda: (sp := src.latest("target")) is not None and sp.pose.p[0] > 0.29)
        time.sleep(0.03)
        assert_pose_matches(src, "cf1", (0.0, 1.0, 2.0), q_zyx(-1.5))
        assert_pose_matches(src, "target", (0.3, 0.4, 0.0), q_zyx(2.0))
        assert src.stats()["connected"]
    assert not src.stats()["reader_alive"]
    assert emu.frames_sent > 0 and not emu.provider_errors


def test_the_clients_own_connect_line_carries_a_level(
    emu: NatNetEmulator, capfd: pytest.CaptureFixture[str]
) -> None:
    """libmotioncapture's C++ prints "Using unicast from server …" on fd 1 while it connects: the console
    gets it on stderr as an `info:` line naming the system, stdout stays the run's data."""
    with make_source(emu) as src:
        assert wait_for(lambda: src.latest("cf1") is not None)
    out, err = capfd.readouterr()
    assert "Using unicast" not in out, out
    said = [ln for ln in err.splitlines() if "Using unicast from server" in ln]
    assert said and all(ln.startswith("info: mocap optitrack (libmotioncapture): ") for ln in said), err


@pytest.mark.parametrize("omit", [False, True], ids=["untracked", "omitted"])
def test_lost_body_goes_stale_and_returns(safety_bound: Bound, emu: NatNetEmulator, omit: bool) -> None:
    emu.faults.lost_omit = omit
    with make_source(emu, stale_after_s=0.1) as src:
        assert wait_for(lambda: src.latest("cf1") is not None and src.latest("target") is not None)
        emu.faults.lost_bodies.add("cf1")
        t_lost = time.monotonic()
        assert wait_for(lambda: any((e.kind, e.detail) == ("body_lost", "cf1") for e in src.events))
        assert wait_for(lambda: src.latest("cf1") is None)
        stale_ms = 1e3 * (time.monotonic() - t_lost)
        assert stale_ms >= 80.0  # stale after stale_after_s (0.1 s), not earlier
        safety_bound("a lost body's pose is stale (stale_after_s 0.1 s)", stale_ms, 600.0)
        assert src.latest("target") is not None  # the others are unaffected
        assert src.stats()["bodies"]["cf1"]["present"] is False
        emu.faults.lost_bodies.clear()
        assert wait_for(lambda: src.latest("cf1") is not None)
        assert any((e.kind, e.detail) == ("body_regained", "cf1") for e in src.events)


def test_dropped_frames_make_bodies_stale(emu: NatNetEmulator) -> None:
    with make_source(emu, stale_after_s=0.1) as src:
        assert wait_for(lambda: src.latest("cf1") is not None)
        emu.faults.drop_frames = True
        try:
            assert wait_for(lambda: src.latest("cf1") is None and src.latest("target") is None, 1.0)
            n = emu.frames_sent
            time.sleep(0.1)
            assert emu.frames_sent == n
            st = src.stats()
            assert st["last_frame_age_s"] > 0.09 and st["bodies"]["cf1"]["rate_hz"] == 0.0
            assert st["reader_alive"]  # blocked in waitForNextFrame, not dead
            # no "body_lost": the bodies were not reported missing, the stream stopped
            assert not any(e.kind == "body_lost" for e in src.events)
        finally:
            emu.faults.drop_frames = False  # lets the reader leave waitForNextFrame before close()
        assert wait_for(lambda: src.latest("cf1") is not None)


def test_rate_matches_emulator(emu: NatNetEmulator) -> None:
    with make_source(emu) as src:
        assert wait_for(lambda: src.latest("cf1") is not None)
        time.sleep(1.0)
        for name in BODIES:
            assert src.rate_hz(name) == pytest.approx(RATE_HZ, rel=0.3)
        assert src.stats()["frames"] == pytest.approx(RATE_HZ * 1.0, rel=0.3)


def test_silent_emulator_answers_nothing() -> None:
    with NatNetEmulator(dict(BODIES), faults=NatNetFaults(silent=True)) as emu:
        port = int(emu.settings()["port_command"])
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.settimeout(0.3)
            s.sendto(struct.pack("<HH", NAT_CONNECT, 0), ("127.0.0.1", port))
            with pytest.raises(TimeoutError):
                s.recvfrom(1024)
            n = emu.frames_sent
            time.sleep(0.05)
            assert emu.frames_sent == n == 0
            emu.faults.silent = False  # and it answers again once the switch is off
            assert wait_for(lambda: emu._sent_silent is False, 1.0)
            s.sendto(struct.pack("<HH", NAT_CONNECT, 0), ("127.0.0.1", port))
            data, _ = s.recvfrom(1024)
            assert struct.unpack_from("<H", data)[0] == NAT_SERVERINFO


_SILENT_CHILD = textwrap.dedent(
    """
    import sys, time
    from flightstack.drivers.mocap import MocapConfig, MocapError, MocapPoseSource
    cfg = MocapConfig("optitrack", {"hostname": "127.0.0.1", "port_command": sys.argv[1]},
                      connect_timeout_s=float(sys.argv[2]))
    t0 = time.monotonic()
    try:
        MocapPoseSource(cfg).start()
    except MocapError as exc:
        print(f"{time.monotonic() - t0:.3f} {exc}")
        sys.exit(0)
    sys.exit("connected to a silent server?!")
    """
)


def test_silent_server_times_out_stock_driver(safety_bound) -> None:
    """Silent server: MocapError naming the host within connect_timeout_s, no hang.

    Run in a subprocess: `motioncapture.connect` keeps the GIL while it waits for the server, so if the
    driver ever called it without its bounded probe (flightstack.drivers.mocap.probe_server) this process
    would freeze; the subprocess keeps pytest itself safe. The child times `start()` itself, so the
    interpreter's start-up and imports (seconds on a loaded machine) are outside the bound; a child that
    never answers is killed after HANG_S.
    """
    timeout, margin, hang_s = 0.5, 1.5, 60.0
    with NatNetEmulator(dict(BODIES), faults=NatNetFaults(silent=True)) as emu:
        port = emu.settings()["port_command"]
        try:
            out = subprocess.run(
                [sys.executable, "-c", _SILENT_CHILD, port, str(timeout)],
                cwd=REPO,
                capture_output=True,
                text=True,
                timeout=hang_s,
            )
        except subprocess.TimeoutExpired:
            pytest.fail(f"MocapPoseSource.start() hung on a silent optitrack server (> {hang_s} s)")
        assert out.returncode == 0, out.stderr
        elapsed, message = out.stdout.strip().split(" ", 1)
        assert "127.0.0.1" in message and port in message
        safety_bound(
            "start() on a silent server until MocapError", 1e3 * float(elapsed), 1e3 * (timeout + margin)
        )
        assert float(elapsed) >= timeout - 0.01  # waited its timeout
