"""The NatNet emulator's Motive options (sim_backend/emulators/natnet.py: NatNet 3.0 or 4.1, Up Axis z or y,
unicast to the data port, Motive-style unicast to the command socket, multicast) read by OptiTrack's own
client (natnetsdk 4.1.1, an independent reader) and by the project's (drivers/mocap.py on
libmotioncapture 1.1). Loopback only; multicast through the loopback interface with TTL 0."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

from flightstack.drivers.mocap import MocapConfig, MocapPoseSource, quaternion_to_planar
from flightstack.sim_backend.emulators.natnet import NatNetEmulator, frame_packet, model_def_packet, y_up
from tests.conftest import skip_or_fail_in_ci
from tests.test_natnet_replay import close_source, stop_natnetsdk, wait_for

pytestmark = pytest.mark.system  # emulator threads and a responder process

pytest.importorskip("motioncapture")

V30, V41 = (3, 0, 0, 0), (4, 1, 0, 0)
POSE = ((1.25, -0.5, 0.75), (math.cos(0.35), 0.0, 0.0, math.sin(0.35)))  # level, yawed 0.7 rad about z


def natnetsdk() -> Any:
    try:
        from natnetsdk.NatNetClient import NatNetClient
    except ImportError:
        skip_or_fail_in_ci("natnetsdk is not installed (pip install natnetsdk==4.1.1)")
    client = NatNetClient()
    client.set_print_level(0)
    return client


@pytest.mark.parametrize("version", [V30, V41], ids=["3.0", "4.1"])
@pytest.mark.parametrize("delivery", ["unicast", "multicast"])
def test_project_client_reads_the_emulator(version: tuple[int, ...], delivery: str) -> None:
    with NatNetEmulator({"cf1": POSE}, natnet_version=version, delivery=delivery) as emu:
        src = MocapPoseSource(
            MocapConfig("optitrack", emu.settings(), connect_timeout_s=3.0, stale_after_s=1.0)
        )
        src.start()
        try:
            assert src.server_info is not None
            assert src.server_info.natnet_version == version
            assert src.server_info.multicast == (delivery == "multicast")
            # the first frame may compile the planar geometry (seconds holding the GIL on a cold cache)
            assert wait_for(lambda: src.stats()["frames"] >= 10 and src.latest("cf1") is not None, 15.0)
            sp = src.latest("cf1")
            assert sp is not None, src.stats()
            want, _ = quaternion_to_planar(*POSE[:1], *POSE[1])
            np.testing.assert_allclose(sp.pose.p, want.p, atol=1e-6)
            assert sp.pose.theta == pytest.approx(0.7, abs=1e-6)
        finally:
            close_source(src, emu.data_port)


def test_project_client_reads_no_motive_style_unicast() -> None:
    """Frames to the client's command socket (as Motive sends unicast): libmotioncapture 1.1 never reads
    that socket again after connect, so nothing arrives."""
    with NatNetEmulator({"cf1": POSE}, delivery="unicast_command") as emu:
        src = MocapPoseSource(MocapConfig("optitrack", emu.settings(), connect_timeout_s=3.0))
        src.start()
        try:
            assert wait_for(lambda: emu.frames_sent >= 50, 5.0)
            assert src.stats()["frames"] == 0 and src.latest("cf1") is None
        finally:
            close_source(src, emu.data_port)


@pytest.mark.parametrize("version", [V30, V41], ids=["3.0", "4.1"])
def test_natnetsdk_reads_motive_style_unicast(version: tuple[int, ...]) -> None:
    """OptiTrack's client in unicast (its default on Linux: its multicast data socket binds the local
    address, where Linux delivers no group datagram) reads the emulator's frames on its command socket."""
    client = natnetsdk()
    client.use_multicast = False
    got: list[tuple[int, Any, Any]] = []
    client.rigid_body_listener = lambda i, p, r: got.append((i, p, r))
    with NatNetEmulator({"cf1": POSE}, natnet_version=version, delivery="unicast_command") as emu:
        client.command_port, client.data_port = emu.command_port, emu.data_port
        try:
            assert client.run()
            assert wait_for(lambda: len(got) >= 20, 5.0), f"natnetsdk read {len(got)} frames"
        finally:
            stop_natnetsdk(client)
    assert client.get_nat_net_version_server()[:2] == list(version[:2])
    body_id, p, r = got[-1]
    assert body_id == 1
    np.testing.assert_allclose(p, POSE[0], atol=1e-6)
    w, x, y, z = POSE[1]
    np.testing.assert_allclose(r, (x, y, z, w), atol=1e-6)


@pytest.mark.parametrize("version", [V30, V41], ids=["3.0", "4.1"])
def test_natnetsdk_parser_consumes_every_byte(version: tuple[int, ...]) -> None:
    """natnetsdk's own unpacking of the emulator's frame and model definitions ends exactly at the end of
    each packet (the frame's last 4 bytes: the end-of-data tag it does not read)."""
    client = natnetsdk()
    major, minor = version[:2]
    frame = frame_packet(
        7, 1.25, [(1, POSE[0], POSE[1], True), (2, (0.0, 0.0, 0.1), (1, 0, 0, 0), False)], version
    )
    offset, data = client._NatNetClient__unpack_mocap_data(frame[4:], len(frame) - 4, major, minor)
    assert offset == len(frame) - 4 - 4
    bodies = data.rigid_body_data.rigid_body_list
    assert [(b.id_num, b.tracking_valid) for b in bodies] == [(1, True), (2, False)]
    assert data.suffix_data.timestamp == 1.25
    defs = model_def_packet([("cf1", 1), ("target", 2)], version)
    offset, descriptions = client._NatNetClient__unpack_data_descriptions(
        defs[4:], len(defs) - 4, major, minor
    )
    assert offset == len(defs) - 4
    names = [d.sz_name for d in descriptions.rigid_body_list]
    assert names == [b"cf1", b"target"]


def test_y_up_option_streams_as_motive_does() -> None:
    """Up Axis = Y: a level body yawed 0.7 rad about z, 0.75 m up, streams 0.75 m along y, rotated 0.7 rad
    about y (as the recorded frame 162734): the driver reads it as tilted 0.7 rad."""
    with NatNetEmulator({"cf1": POSE}, up_axis="y") as emu:
        src = MocapPoseSource(
            MocapConfig("optitrack", emu.settings(), connect_timeout_s=3.0, stale_after_s=1.0)
        )
        src.start()
        try:
            assert wait_for(lambda: src.sample("cf1") is not None, 3.0)
            time.sleep(0.05)
            sample = src.sample("cf1")
            assert sample is not None
            (x, y, z), q = sample
            assert (x, y, z) == pytest.approx((1.25, 0.75, 0.5), abs=1e-6)
            assert q == pytest.approx(y_up(*POSE)[1], abs=1e-6)
            assert src.tilt("cf1") == pytest.approx(0.7, abs=1e-5)
        finally:
            close_source(src, emu.data_port)
