"""Real Motive packets (../shared/data/peers/natnet/, read in place) replayed over loopback through the
project's client (drivers/mocap.py on libmotioncapture) and through OptiTrack's own client (natnetsdk).

The recordings (../shared/data/peers/README.md): traffic.pcapng, a Motive 2.1 / NatNet 3.0 session of 518
multicast frames, and the single packets *_v3.bin (server info, model definitions, two frames). Every
frame is checked against tests/natnet_strict.py, a strict parse written from the NatNet layout. Without
the folder the tests skip; under CI=true they fail (tests.conftest.skip_or_fail_in_ci).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from flightstack.drivers.mocap import MocapConfig, MocapPoseSource, quaternion_to_planar
from flightstack.sim_backend.emulators.natnet_replay import (
    NatNetRecording,
    NatNetReplayer,
    read_packets,
    read_pcapng,
    udp_payloads,
)
from tests.conftest import PEERS, skip_or_fail_in_ci
from tests.natnet_strict import Frame, parse_frame, parse_model_def

pytestmark = pytest.mark.system  # loopback sockets, a responder process, real-time replays

NATNET = PEERS / "natnet" / "python_natnet"
TRAFFIC = "traffic.pcapng"
PACKETS = "packets_v3"  # the single *_v3.bin packets, replayed as one session
FRAMES = {TRAFFIC: 518, PACKETS: 2}  # what the README says each holds (520 in all)
TIME_TOL_S = 0.25  # how late a frame may leave after its recorded offset on a loaded 2-core machine (s)
STEP_TIMEOUT_S = 5.0  # the longest a stepped frame may take to reach the client (s)
# ../shared/data/peers/README.md: frame 162734, body id 2 "RaceQuad"
README_POSITION = (0.1744, 1.4471, -0.7343)  # m
README_QUAT_XYZW = (-0.0546, 0.5099, 0.0437, -0.8574)


def recording(name: str) -> NatNetRecording:
    """Recording `name` read in place; skip (fail under CI=true) without it."""
    path = NATNET / (TRAFFIC if name == TRAFFIC else "modeldef_packet_v3.bin")
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    if name == TRAFFIC:
        return read_pcapng(path)
    return read_packets(
        NATNET / "serverinfo_packet_v3.bin",
        NATNET / "modeldef_packet_v3.bin",
        [NATNET / "mocapframe_packet_v3.bin", NATNET / "mocapframe_packet_occluded_v3.bin"],
    )


@dataclass
class Tap:
    """A libmotioncapture client whose every frame's rigid bodies are kept as read (name -> position
    float32 (3,), rotation (w, x, y, z) float32), before drivers/mocap.py reduces them."""

    frames: list[dict[str, tuple[np.ndarray, np.ndarray]]] = field(default_factory=list)
    mc: Any = None

    def connect(self, system: str, settings: dict[str, str]) -> Tap:
        import motioncapture

        self.mc = motioncapture.connect(system, settings)
        return self

    def waitForNextFrame(self) -> None:
        self.mc.waitForNextFrame()

    @property
    def rigidBodies(self) -> dict[str, Any]:
        bodies = self.mc.rigidBodies
        self.frames.append(
            {
                name: (
                    np.asarray(rb.position, dtype=np.float32).copy(),
                    np.array([rb.rotation.w, rb.rotation.x, rb.rotation.y, rb.rotation.z], dtype=np.float32),
                )
                for name, rb in bodies.items()
            }
        )
        return dict(bodies)


def wait_for(pred: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.002)
    return pred()


@pytest.fixture
def closing() -> Iterator[list[tuple[MocapPoseSource, int]]]:
    """Sources to close at the end: the reader sits in waitForNextFrame (no timeout), so each close is
    accompanied by 4-byte datagrams to its data port (parsed as nothing) until the reader has left."""
    sources: list[tuple[MocapPoseSource, int]] = []
    yield sources
    for src, port in sources:
        close_source(src, port)


def close_source(src: MocapPoseSource, port: int) -> None:
    """Close `src`, waking a reader that waits in waitForNextFrame with 4-byte datagrams to its port."""
    closer = threading.Thread(target=src.close, args=(3.0,))
    closer.start()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        while closer.is_alive():
            s.sendto(b"\0\0\0\0", ("127.0.0.1", port))
            closer.join(0.02)
    assert not src.stats()["reader_alive"]


def expected_bodies(rec: NatNetRecording, frame: Frame) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """What the client must give for `frame` by the strict parse: tracked bodies named by the model
    definitions ('' for an id they do not define), position + offset in float32, rotation (w, x, y, z)."""
    defs = {d.body_id: d for d in parse_model_def(rec.model_def)}
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for b in frame.bodies:
        if not b.tracked:
            continue
        d = defs.get(b.body_id)
        offset = np.zeros(3, np.float32) if d is None else d.offset
        name = "" if d is None else d.name
        out.setdefault(name, (b.position + offset, b.quaternion_xyzw[[3, 0, 1, 2]]))
    return out


def test_pcapng_reader_matches_dpkt() -> None:
    """The small pcapng reader gives every UDP datagram dpkt (a maintained reader) gives, with its time."""
    path = NATNET / TRAFFIC
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    try:
        import dpkt
    except ImportError:
        skip_or_fail_in_ci("dpkt is not installed (pip install dpkt)")
    ours = udp_payloads(path.read_bytes())
    theirs = []
    with path.open("rb") as f:
        for ts, buf in dpkt.pcapng.Reader(f):
            ip = dpkt.ethernet.Ethernet(buf).data
            u = ip.data
            theirs.append(
                (
                    float(ts),
                    socket.inet_ntoa(ip.src),
                    u.sport,
                    socket.inet_ntoa(ip.dst),
                    u.dport,
                    bytes(u.data),
                )
            )
    assert [p[1:] for p in ours] == [p[1:] for p in theirs]
    assert max(abs(a[0] - b[0]) for a, b in zip(ours, theirs, strict=True)) < 1e-6
    frames = [p for p in ours if p[5][:2] == b"\x07\x00"]
    assert len(frames) == FRAMES[TRAFFIC]
    assert {(p[3], p[4]) for p in frames} == {("239.255.42.99", 1511)}  # multicast, Motive's default


@pytest.mark.parametrize("name", [TRAFFIC, PACKETS])
def test_recordings_parse_strictly(name: str) -> None:
    """Every recorded frame and model definition parses strictly; frame 162734 holds the README's values."""
    rec = recording(name)
    assert len(rec.frames) == FRAMES[name]
    assert rec.natnet_version == (3, 0, 0, 0) and rec.multicast_group == "239.255.42.99"
    assert rec.server_info[4:10] == b"Motive"
    defs = parse_model_def(rec.model_def)
    assert [(d.name, d.body_id) for d in defs] == [("RaceQuad", 2)]
    frames = [parse_frame(p) for _, p in rec.frames]
    first = frames[0]
    assert first.frame == 162734 and [b.body_id for b in first.bodies] == [2]
    assert np.allclose(first.bodies[0].position, README_POSITION, atol=5e-5)
    assert np.allclose(first.bodies[0].quaternion_xyzw, README_QUAT_XYZW, atol=5e-5)
    if name == PACKETS:  # the occluded-marker frame: body 7, which the model definitions do not define
        assert [b.body_id for b in frames[1].bodies] == [7]
    else:
        numbers = [f.frame for f in frames]
        assert numbers == list(range(162734, 162734 + len(frames)))  # no frame lost in the capture


@pytest.mark.parametrize("delivery", ["multicast", "unicast"])
@pytest.mark.parametrize("name", [TRAFFIC, PACKETS])
def test_every_frame_reaches_the_client_bit_identical(
    name: str, delivery: str, closing: list[tuple[MocapPoseSource, int]]
) -> None:
    """Each recorded frame, sent one at a time, reaches drivers/mocap.py through libmotioncapture exactly as
    the strict parse reads it (float32 bits of position and quaternion; names from the model definitions),
    and the planar pose the driver keeps is quaternion_to_planar of those values."""
    rec = recording(name)
    tap = Tap()
    with NatNetReplayer(rec, delivery=delivery, pace="step") as rep:  # type: ignore[arg-type]
        src = MocapPoseSource(
            MocapConfig("optitrack", rep.settings(), connect_timeout_s=5.0, stale_after_s=60.0), tap.connect
        )
        src.start()
        closing.append((src, rep.data_port))
        assert rep.wait_for_client(5.0)
        for k in range(len(rec.frames)):
            assert rep.step() is not None
            assert wait_for(lambda k=k: len(tap.frames) > k, STEP_TIMEOUT_S), f"frame {k} never arrived"
        assert rep.counts["frames"] == len(rec.frames) == FRAMES[name]
    assert len(tap.frames) == len(rec.frames)
    for k, ((_, packet), got) in enumerate(zip(rec.frames, tap.frames, strict=True)):
        want = expected_bodies(rec, parse_frame(packet))
        assert got.keys() == want.keys(), f"frame {k}"
        for body, (p, q) in want.items():
            assert got[body][0].tobytes() == p.tobytes(), f"frame {k} body {body!r} position"
            assert got[body][1].tobytes() == q.tobytes(), f"frame {k} body {body!r} rotation"
    last = expected_bodies(rec, parse_frame(rec.frames[-1][1]))
    for body, (p, q) in last.items():
        pose, tilt = quaternion_to_planar(p, *(float(v) for v in q))
        assert src.tilt(body) == tilt
        assert src.stats()["bodies"][body]["tilt_rad"] == tilt
        sp = src.latest(body)
        if tilt <= src.cfg.max_tilt_rad:
            assert sp is not None and np.array_equal(sp.pose.p, pose.p) and sp.pose.theta == pose.theta
    if name == PACKETS:  # body 7 of the occluded frame is unknown to the model definitions: named ''
        assert list(tap.frames[1]) == [""]


def test_frame_162734_is_read_as_tilted_y_up(closing: list[tuple[MocapPoseSource, int]]) -> None:
    """The README's frame: RaceQuad 1.447 m up along Motive's y (Y-up, Motive's default), which the driver,
    reading z as up, takes for a body tilted 1.077 rad and refuses."""
    rec = recording(PACKETS)
    with NatNetReplayer(rec, delivery="multicast", pace="step") as rep:
        src = MocapPoseSource(MocapConfig("optitrack", rep.settings(), stale_after_s=60.0))
        src.start()
        closing.append((src, rep.data_port))
        assert rep.wait_for_client(5.0)
        rep.step()
        assert wait_for(lambda: src.tilt("RaceQuad") is not None, STEP_TIMEOUT_S)
    tilt = src.tilt("RaceQuad")
    assert tilt is not None and abs(tilt - 1.077) < 0.001, tilt
    assert src.latest("RaceQuad") is None  # refused: tilted beyond max_tilt_rad
    assert ("tilt_refused", "RaceQuad") in [(e.kind, e.detail) for e in src.events]


def test_recorded_timing_multicast(closing: list[tuple[MocapPoseSource, int]]) -> None:
    """At the recorded timing (120 Hz, 4.3 s) every frame leaves within TIME_TOL_S of its recorded
    offset, and what the client reads is a recorded frame, in order (libmotioncapture keeps only the
    newest of the frames waiting, so a loaded machine may skip some: the count is reported)."""
    rec = recording(TRAFFIC)
    tap = Tap()
    with NatNetReplayer(rec, delivery="multicast", start_delay_s=0.3) as rep:
        src = MocapPoseSource(MocapConfig("optitrack", rep.settings(), stale_after_s=60.0), tap.connect)
        src.start()
        closing.append((src, rep.data_port))
        assert rep.wait_for_client(5.0)
        duration = rec.frames[-1][0]
        assert wait_for(lambda: rep.frames_left == 0, duration + 5.0)
        time.sleep(0.2)
    sent = list(rep.sent)
    assert [s.index for s in sent] == list(range(len(rec.frames)))
    t0 = sent[0].t - sent[0].rec_t
    lateness = [s.t - (t0 + s.rec_t) for s in sent]
    print(f"lateness: median {np.median(lateness) * 1e3:.1f} ms, max {max(lateness) * 1e3:.1f} ms")
    assert max(lateness) <= TIME_TOL_S
    by_bits = {
        expected_bodies(rec, parse_frame(p))["RaceQuad"][0].tobytes(): k
        for k, (_, p) in enumerate(rec.frames)
    }
    read = [by_bits.get(f["RaceQuad"][0].tobytes()) for f in tap.frames if "RaceQuad" in f]
    assert None not in read and read == sorted(read), "the client read a frame that was not recorded"
    print(f"client read {len(read)} of {len(rec.frames)} frames ({len(set(read))} distinct)")
    assert len(set(read)) >= len(rec.frames) // 2, f"the client read only {len(set(read))} frames"


def test_motive_style_unicast_reaches_natnetsdk_not_libmotioncapture(
    closing: list[tuple[MocapPoseSource, int]],
) -> None:
    """Unicast as Motive sends it (frames to the client's command socket): OptiTrack's own client
    (natnetsdk 4.1.1) reads every frame; libmotioncapture 1.1, which reads only its data port, reads
    none. So the project's client needs multicast (drivers/lab/preflight.py refuses a unicast lab file)."""
    rec = recording(TRAFFIC)
    tap = Tap()
    with NatNetReplayer(rec, delivery="unicast_command", pace="step") as rep:
        src = MocapPoseSource(MocapConfig("optitrack", rep.settings(), stale_after_s=60.0), tap.connect)
        src.start()
        closing.append((src, rep.data_port))
        assert rep.wait_for_client(5.0)
        for _ in range(50):
            assert rep.step() is not None
            time.sleep(0.002)
        time.sleep(0.5)
        assert rep.counts["frames"] == 50
        assert tap.frames == [], f"libmotioncapture read {len(tap.frames)} Motive-style unicast frames"
    numbers = natnetsdk_frames(rec, "unicast_command", count=50)
    assert numbers == [parse_frame(p).frame for _, p in rec.frames[:50]]


def natnetsdk_frames(rec: NatNetRecording, delivery: str, count: int) -> list[int]:
    """Frame numbers natnetsdk's NatNetClient (unicast) reads from a replay of `count` stepped frames."""
    try:
        from natnetsdk.NatNetClient import NatNetClient
    except ImportError:
        skip_or_fail_in_ci("natnetsdk is not installed (pip install natnetsdk==4.1.1)")
    numbers: list[int] = []
    client = NatNetClient()
    client.set_print_level(0)
    client.use_multicast = False
    client.new_frame_listener = lambda d: numbers.append(int(d["frame_number"]))
    with NatNetReplayer(rec, delivery=delivery, pace="step") as rep:  # type: ignore[arg-type]
        client.command_port = rep.command_port
        client.data_port = rep.data_port
        try:
            assert client.run()
            assert wait_for(lambda: rep.client is not None, 5.0)
            client.send_request(
                client.command_socket, client.NAT_REQUEST_MODELDEF, "", ("127.0.0.1", rep.command_port)
            )
            assert rep.wait_for_client(5.0)
            for k in range(count):
                rep.step()
                assert wait_for(lambda k=k: len(numbers) > k, STEP_TIMEOUT_S), f"natnetsdk: frame {k}"
        finally:
            stop_natnetsdk(client)
    return numbers


def stop_natnetsdk(client: Any) -> None:
    """Stop natnetsdk's (non-daemon) threads: its data thread blocks in recvfrom without a timeout, so a
    datagram wakes it after the stop flag is set."""
    client.stop_threads = True
    for sock in (client.data_socket, client.command_socket):
        if sock is None:
            continue
        port = sock.getsockname()[1]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"", ("127.0.0.1", port))  # empty: its threads skip it and look at the stop flag
    for th in (client.data_thread, client.command_thread):
        if th is not None:
            th.join(3.0)
            assert not th.is_alive(), "natnetsdk thread did not stop"
    for sock in (client.data_socket, client.command_socket):
        if sock is not None:
            sock.close()


def test_y_up_tilt_angle_reads_as_the_readme_says() -> None:
    """Cross-check of the README's 1.077 rad: the recorded quaternion's body z axis vs Motive's z."""
    w, x, y, z = README_QUAT_XYZW[3], *README_QUAT_XYZW[:3]
    _, tilt = quaternion_to_planar(README_POSITION, w, x, y, z)
    assert math.isclose(tilt, 1.077, abs_tol=0.001)
