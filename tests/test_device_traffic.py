"""Every flight records its devices' raw traffic, and a recorded flight replays to the driver.

- The driver against the Tello emulator: the traffic file holds every command that left the computer
  (the emulator received each), every reply and state datagram (also the ones the parser rejects), the
  video datagrams as counted by the receiver, and nothing that a muted driver did not send.
- A recording process killed (SIGKILL) leaves a file that reads back up to its last flush.
- An emulated-lab flight (`flightstack run paper_experiment --rig emulated-lab`): its run directory holds
  each drone's traffic (`devices/tello-<id>_<mode>.jsonl`) with plausible counts, and served by the
  replayer (sim_backend/emulators/tello/replay.py) to a fresh TelloDriver with the flight's settings, the
  recording reproduces the flight's takeoff and landing.

Loopback only: the emulator and the replayer on 127.0.0.8, the emulated lab on its own addresses, every
port a free one.
"""

from __future__ import annotations

import dataclasses
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

pytest.importorskip("av")

from flightstack.config.mission import load_mission
from flightstack.drivers.lab.hardware import tello_config as mission_tello_config
from flightstack.drivers.tello.camera import TelloCamera
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.phase import PhaseTracker
from flightstack.drivers.tello.state import parse_state
from flightstack.drivers.tello.traffic import TelloSession, TrafficWriter, read_traffic
from flightstack.hal import FlightPhase
from flightstack.ports import free_udp_port
from flightstack.recording.files import DEVICES_DIR, DeviceFiles
from tests.conftest import MISSIONS, run_cli, tello_config, tello_emulator

pytestmark = pytest.mark.system

IP = "127.0.0.8"


def kinds(s: TelloSession) -> Counter[str]:
    return Counter(r.kind for r in s.records)


def state_rate_hz(s: TelloSession) -> float:
    st = s.of("state")
    return (len(st) - 1) / (st[-1].t - st[0].t)


def test_the_driver_records_what_crossed_the_wire(tmp_path: Path) -> None:
    emu = tello_emulator(IP, fps=30.0, video_size=(320, 240))
    emu.start()
    path = DeviceFiles(tmp_path, "none").tello(1)
    w = TrafficWriter(path, emu.ip)
    d = TelloDriver(tello_config(emu), w)
    cam = TelloCamera(d, frame_timeout_s=10.0)
    muted = False
    try:
        d.connect()
        junk = b"\xff\xfe not a state line"
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as same_ip:
            same_ip.bind((emu.ip, 0))  # from the drone's address: its traffic, though the parser rejects it
            same_ip.sendto(junk, ("127.0.0.1", emu.state_port))
        d.takeoff()
        cam.start()
        time.sleep(1.0)
        cam.stop()
        d.set_muted(lambda: muted)
        muted = True  # the guardian took over: nothing more leaves this driver
        d.send_rc((10, 0, 0, 0))
        muted = False
        d.land()
    finally:
        d.close()
        w.close()
        emu.close()
    s = read_traffic(path)
    n = kinds(s)
    print(f"recorded {dict(n)}; state {state_rate_hz(s):.1f} Hz; writer errors {dict(w.errors)}")
    assert not s.dropped and not w.errors and w.written == len(s.records)
    sent = [r.text for r in s.of("sent")]
    assert sent[0] == "command" and "takeoff" in sent and "land" in sent and "streamon" in sent
    assert "rc 10 0 0 0" not in sent  # muted: not sent, so not recorded
    # every command recorded as sent reached the emulator, in order, no earlier than it was sent
    got = list(emu.commands)
    assert [text for _, text in got] == sent
    assert all(0.0 <= t_rx - r.t < 0.5 for (t_rx, _), r in zip(got, s.of("sent"), strict=True))
    # every reply the emulator sent was received and recorded, as sent
    replies = [text for _, text, _ in emu.replies_sent]
    assert [r.text.strip() for r in s.of("reply")] == [r.strip() for r in replies]
    assert any(r.text == junk.decode("ascii", "replace") for r in s.of("state"))  # the rejected line too
    assert 8.0 < state_rate_hz(s) < 12.0  # the emulator streams at 10 Hz
    assert n["video"] == cam.counts["datagrams"] > 0


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run directory of 2 s of mode none of the paper's experiment on the emulated lab."""
    out = tmp_path_factory.mktemp("lab") / "run"
    t0 = time.monotonic()
    r = run_cli(
        "run", str(MISSIONS / "paper_experiment.yaml"), "--rig", "emulated-lab", "--modes", "none",
        "--duration", "2", "--out", str(out), "--no-progress", timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    print(f"emulated-lab flight: {time.monotonic() - t0:.0f} s")
    return out


def test_an_emulated_lab_run_directory_holds_each_drones_raw_traffic(lab_run: Path) -> None:
    files = sorted(p.name for p in (lab_run / DEVICES_DIR).iterdir())
    assert files == ["scamper_none.tlog", "tello-1_none.jsonl", "tello-2_none.jsonl"]  # and the robot's link
    assert (lab_run / DEVICES_DIR / "scamper_none.tlog").stat().st_size > 0
    for name in files[1:]:  # the Tellos' (the .tlog: tests/test_scamper_extnav.py reads it with mavlogdump)
        s = read_traffic(lab_run / DEVICES_DIR / name)
        n = kinds(s)
        video = s.of("video")
        video_s = video[-1].t - video[0].t if len(video) > 1 else 0.0
        rate = len(video) / video_s
        print(f"{name}: {dict(n)}; state {state_rate_hz(s):.1f} Hz; video {rate:.0f} datagrams/s")
        assert not s.dropped
        sent = [r.text for r in s.of("sent")]
        assert sent[0] == "command" and sent.count("takeoff") == 1 and "land" in sent
        assert sum(t.startswith("rc ") for t in sent) >= 2 / 0.05 * 0.5  # the pursuit's sticks (20 Hz, 2 s)
        takeoff, land = s.first("sent", "takeoff"), s.first("sent", "land")
        assert takeoff is not None and land is not None and takeoff.t < land.t
        assert any(r.text.strip() == "ok" and r.t > takeoff.t for r in s.of("reply"))
        assert any(r.text.strip() == "ok" and r.t > land.t for r in s.of("reply"))
        assert 8.0 < state_rate_hz(s) < 12.0  # the Tello's state stream: 10 Hz
        assert n["video"] > 10 * video_s  # the camera streamed (30 fps rendered: fewer on a busy machine)


def flight_times(s: TelloSession) -> dict[str, float]:
    """What the flight's traffic shows (s after the command was sent): "takeoff", at most how long its
    takeoff() took (to the first `rc`: the driver sends none before takeoff() returns); "touchdown", when
    the state lines first showed the drone near the ground after `land` (PhaseTracker.low: by tof, as h
    drifts)."""
    takeoff, land = s.first("sent", "takeoff"), s.first("sent", "land")
    assert takeoff is not None and land is not None
    first_rc = next(r.t for r in s.of("sent") if r.t > takeoff.t and r.text.startswith("rc "))
    low = PhaseTracker().low
    down = next(r.t for r in s.of("state") if r.t > land.t and low(parse_state(r.text.encode(), r.t)))
    return {"takeoff": first_rc - takeoff.t, "touchdown": down - land.t}


@pytest.mark.parametrize("drone", [1, 2])
def test_a_recorded_emulated_lab_flight_replays_its_takeoff_and_landing(lab_run: Path, drone: int) -> None:
    """The flight's traffic served by the replayer to a fresh driver with the flight's settings: takeoff()
    returns airborne and land() on the ground, each confirmed by the recorded telemetry, each command sent
    as often as in the flight; takeoff() returns within the time the flight's took (+ 1 s), land() within
    3 s of the recorded touchdown (the driver's landing rule waits for the motors to stop: drivers/tello/
    phase.py). Times from the command's arrival at the replayer."""
    from flightstack.sim_backend.emulators.tello.replay import TelloReplayer

    s = read_traffic(lab_run / DEVICES_DIR / f"tello-{drone}_none.jsonl")
    flight = flight_times(s)
    mission = load_mission(lab_run / "mission_resolved.yaml")
    state_port = free_udp_port()
    with TelloReplayer(s, IP, state_port=state_port) as rep:
        cfg = dataclasses.replace(
            mission_tello_config(mission, drone),
            host=IP, control_port=rep.address[1], state_port=state_port, video_port=free_udp_port(),
        )  # fmt: skip
        d = TelloDriver(cfg)
        try:
            d.connect()
            d.takeoff()
            returned = {"takeoff": time.monotonic()}
            assert d.phase is FlightPhase.AIRBORNE
            d.land()
            returned["land"] = time.monotonic()
            assert d.phase is FlightPhase.GROUND
        finally:
            d.close()
        received = [r.text for r in rep.received]
        # from the command's arrival at the "drone" to the call's return, as measured in the flight
        replay = {c: t - next(r.t for r in rep.received if r.text == c) for c, t in returned.items()}
    events = Counter(e.kind for e in d.events)
    print(
        f"drone {drone}: replay takeoff {replay['takeoff']:.2f} s, land {replay['land']:.2f} s; flight: "
        f"takeoff at most {flight['takeoff']:.2f} s, touchdown {flight['touchdown']:.2f} s after land; "
        f"replayer {dict(rep.counts)}; driver {dict(events)}"
    )
    assert events["takeoff_confirmed"] == 1 and events["land_confirmed"] == 1, events
    for command in ("takeoff", "land"):
        assert received.count(command) == [r.text for r in s.of("sent")].count(command), received
    assert replay["takeoff"] < flight["takeoff"] + 1.0, (replay, flight)
    assert flight["touchdown"] <= replay["land"] < flight["touchdown"] + 3.0, (replay, flight)


KILLED_WRITER = """
import sys, time
from flightstack.drivers.tello.traffic import TrafficWriter
w = TrafficWriter(sys.argv[1], "127.0.0.8")
print("ready", flush=True)
while True:
    w.state(time.monotonic(), b"h:50;tof:60;bat:80;time:3;\\r\\n")
    time.sleep(0.001)
"""


def test_a_killed_flight_leaves_its_traffic_up_to_the_last_flush(tmp_path: Path) -> None:
    """SIGKILL a process recording ~1000 state lines/s (nothing is closed): the file reads back, its last
    line cut short or not, and holds every record older than the flush period (0.25 s) plus a margin for
    a loaded machine (0.5 s)."""
    path = tmp_path / "t.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILLED_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        time.sleep(1.5)
        t_kill = time.monotonic()
        proc.kill()
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    s = read_traffic(path)
    lost_s = t_kill - s.records[-1].t
    print(f"killed: {len(s.records)} records on file, the last {lost_s * 1e3:.0f} ms before the kill lost")
    assert set(s.dropped) <= {"not_json_object"} and sum(s.dropped.values()) <= 1
    assert len(s.records) > 300 and lost_s < 0.75
