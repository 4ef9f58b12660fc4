"""`--viewer foxglove[:PORT]` and `--viewer-host ADDR` (flightstack.viewer.foxglove_live, foxglove_server),
checked with WebSocket clients (`websockets`, speaking Foxglove's WebSocket protocol from its
specification, not any Foxglove library):

- during a simulated flight, a client offering only `foxglove.websocket.v1` (Lichtblick, Foxglove Studio)
  and one offering only `foxglove.sdk.v1` each subscribe to every advertised channel and decode messages
  of each with the protobuf schema the advertisement carries; one offering neither gets HTTP 400;
- the caps bind a client: connections beyond MAX_CLIENTS get HTTP 503, a message beyond MAX_MESSAGE_BYTES
  closes its connection (1009), subscriptions beyond MAX_SUBSCRIPTIONS, repeated or to unknown channels
  are refused and counted, and the log says so at most once a second per client address: on loopback,
  and from another network namespace to a flight serving `--viewer-host` there;
- a subscribe flood (138 messages of 5,000 unknown channels, the client reconnecting whenever it is cut
  off) during a real-time flight on the emulated lab leaves the loop's health, the flight process's CPU
  time and its stderr as in a clean flight measured in the same test.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from flightstack.config.mission import load_mission
from flightstack.hal import Frame
from flightstack.ports import free_port
from flightstack.viewer.foxglove_server import (
    MAX_CLIENTS,
    MAX_MESSAGE_BYTES,
    MAX_SUBSCRIPTIONS,
    REPORT_PERIOD_S,
    SUBPROTOCOLS,
)
from tests.conftest import MISSIONS, REPO, Bound, eventually, random_recording, skip_or_fail_in_ci

pytestmark = pytest.mark.system
MESSAGE_DATA = 0x01  # binary opcode: subscription id u32, log time u64, payload
TOPICS = {
    "/none/tick": "flightstack.Tick",
    "/none/drone1": "flightstack.DroneState", "/none/drone2": "flightstack.DroneState",
    "/none/drone3": "flightstack.DroneState",
    "/none/tf": "foxglove.FrameTransforms", "/none/events": "foxglove.Log",
    "/none/pose/target": "foxglove.PoseInFrame", "/none/pose/drones": "foxglove.PosesInFrame",
    "/none/pose/estimates": "foxglove.PosesInFrame", "/none/scene": "foxglove.SceneUpdate",
}  # fmt: skip
"""paper_experiment's (and paper_sim's) channels with mode none."""
FLOOD_MESSAGES, FLOOD_CHANNELS = 138, 5000
"""The flood seen from a local client: 138 subscribe messages of 5,000 unknown channels each."""


def _decoder(schema_name: str, schema_b64: str) -> Any:
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64)).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _fly(args: list[str], out: Path, netns: str | None = None) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "flightstack", "run", *args, "--no-progress", "--no-live-mcap",
           "--out", str(out)]  # fmt: skip
    if netns is not None:
        cmd = ["ip", "netns", "exec", netns, *cmd]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _connect(
    stack: contextlib.ExitStack,
    url: str,
    subprotocol: str,
    proc: subprocess.Popen[str] | None = None,
    wait_s: float = 60,
) -> Any:
    """A client connected to `url` offering only `subprotocol` (closed with `stack`), retried while the
    server is not up yet."""
    from websockets.sync.client import connect

    deadline = time.monotonic() + wait_s
    while True:
        try:
            return stack.enter_context(connect(url, subprotocols=[subprotocol], open_timeout=5))  # type: ignore[list-item]
        except OSError:
            if time.monotonic() > deadline or (proc is not None and proc.poll() is not None):
                raise
            time.sleep(0.05)


def _watch(ws: Any, proc: subprocess.Popen[str], seen: dict[str, Any]) -> None:
    """Subscribe to every channel `ws` is advertised and decode what comes until the flight ends; fills
    `seen` with `channels` (id -> advertisement) and `decoded` (topic -> [(log time, message)])."""
    channels: dict[int, dict[str, Any]] = seen.setdefault("channels", {})
    decoded: dict[str, list[Any]] = seen.setdefault("decoded", {})
    seen["subprotocol"] = ws.subprotocol
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            frame = ws.recv(timeout=1.0)
        except TimeoutError:
            if proc.poll() is not None:
                break
            continue
        except Exception:  # the server stopped with the flight
            break
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg.get("op") == "advertise":
                subs = []
                for ch in msg["channels"]:
                    assert ch["encoding"] == "protobuf" and ch["schemaEncoding"] == "protobuf", ch
                    ch["cls"] = _decoder(ch["schemaName"], ch["schema"])
                    channels[ch["id"]] = ch
                    subs.append({"id": ch["id"], "channelId": ch["id"]})
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            continue
        assert frame[0] == MESSAGE_DATA, frame[:1]
        sub, log_ns = struct.unpack_from("<IQ", frame, 1)
        ch = channels[sub]
        decoded.setdefault(ch["topic"], []).append((log_ns, ch["cls"].FromString(frame[13:])))


def test_clients_offering_either_subprotocol_decode_every_channel_during_a_flight(tmp_path: Path) -> None:
    from websockets.exceptions import InvalidStatus

    port = free_port("tcp")
    proc = _fly(
        ["paper_sim", "--modes", "none", "--duration", "120", "--viewer", f"foxglove:{port}"],
        tmp_path / "run",
    )
    seen: dict[str, dict[str, Any]] = {name: {} for name in SUBPROTOCOLS}
    try:
        with contextlib.ExitStack() as stack:
            clients = {name: _connect(stack, f"ws://127.0.0.1:{port}", name, proc) for name in SUBPROTOCOLS}
            with pytest.raises(InvalidStatus) as refused:
                _connect(stack, f"ws://127.0.0.1:{port}", "something.else.v1", proc)
            threads = [threading.Thread(target=_watch, args=(ws, proc, seen[n])) for n, ws in clients.items()]
            for t in threads:
                t.start()
            for t in threads:
                t.join(timeout=150)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert refused.value.response.status_code == 400
    assert f"viewer: live at ws://127.0.0.1:{port}" in err and "warning: viewer" not in err
    for name, got in seen.items():
        assert got["subprotocol"] == name  # the reply names the one the client offered
        topics = {ch["topic"]: ch["schemaName"] for ch in got["channels"].values()}
        assert topics == TOPICS, name
        decoded = got["decoded"]
        assert set(decoded) == set(topics), (name, {t: len(v) for t, v in decoded.items()})
        ticks = [m for _, m in decoded["/none/tick"]]
        assert all(0.0 <= m.t <= 120.0 for m in ticks) and [m.t for m in ticks] == sorted(m.t for m in ticks)
        assert {m.drone for _, m in decoded["/none/drone2"]} == {2}
        assert any("landed" in m.message for _, m in decoded["/none/events"])
        print(f"{name}: {', '.join(f'{t} {len(v)}' for t, v in sorted(decoded.items()))} messages decoded")


def test_camera_images_are_encoded_only_for_a_client_that_subscribes() -> None:
    """The live view of a rig with image cameras (paper_experiment on lab-sim; stand-in cameras and a
    random recording fed to the tap as a flight would): while no client subscribes, no frame is encoded;
    a client subscribed to every channel decodes each camera's JPEG CompressedImages in its camera frame,
    at most IMAGE_HZ a second of mission time."""
    from flightstack.recording.camera_frames import IMAGE_HZ
    from flightstack.viewer.foxglove_live import FoxgloveTap

    mission = load_mission(MISSIONS / "paper_experiment.yaml", rig="lab-sim")
    ids = [d.id for d in mission.drones]
    rec = random_recording("none", ids, 400)
    clock = {"t": 0.0}
    picture = np.full((120, 160, 3), 90, np.uint8)
    agents = [
        SimpleNamespace(
            camera=SimpleNamespace(latest=lambda: Frame(clock["t"], picture, None)),
            cfg=SimpleNamespace(drone_id=i),
        )
        for i in ids
    ]
    fleet: Any = SimpleNamespace(agents=agents, g_d=np.zeros((len(ids), 4)))
    flying = {"on": True}
    flight: Any = SimpleNamespace(poll=lambda: None if flying["on"] else 0)

    def fly(k0: int, k1: int) -> None:
        for k in range(k0, k1):
            clock["t"] = float(rec.t[k])
            for a in agents:
                a.camera.latest()
            tap.on_tick(fleet, rec, k + 1)
            time.sleep(0.01)

    tap = FoxgloveTap(0, mission=mission)
    seen: dict[str, Any] = {}
    try:
        tap.start(fleet, rec)
        fly(0, 100)
        assert eventually(lambda: tap.frames_unwatched >= 2 * len(ids), 10.0)
        assert tap.frames_sent == 0
        with contextlib.ExitStack() as stack:
            ws = _connect(stack, f"ws://127.0.0.1:{tap.port}", SUBPROTOCOLS[0])
            watcher = threading.Thread(target=_watch, args=(ws, flight, seen))
            watcher.start()
            assert eventually(lambda: len(tap.server.wanted) >= len(ids), 10.0)  # every channel subscribed
            fly(100, 400)
            tap.close(rec)
            assert eventually(lambda: tap.frames_sent > 0 and tap._queue.empty(), 10.0)
            time.sleep(1.0)
            flying["on"] = False
            watcher.join(timeout=10)
    finally:
        tap.finish()
    for i in ids:
        msgs = seen["decoded"][f"/none/drone{i}/image"]
        assert msgs and all(m.format == "jpeg" and m.data[:2] == b"\xff\xd8" for _, m in msgs)
        assert {m.frame_id for _, m in msgs} == {f"none/drone{i}/camera"}
        assert np.all(np.diff([lt for lt, _ in msgs]) >= 1e9 / IMAGE_HZ - 1e3)
    assert tap.frames_sent == sum(len(seen["decoded"][f"/none/drone{i}/image"]) for i in ids)


# ---- the caps ----------------------------------------------------------------------------------------
def probe(host: str, port: int | str) -> dict[str, Any]:
    """Push against every cap of the server at host:port from this process (also run in another network
    namespace: `python -c 'from tests.test_foxglove_live import probe; ...'`); what the client saw."""
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    url = f"ws://{host}:{port}"
    out: dict[str, Any] = {}
    with contextlib.ExitStack() as stack:
        held = [_connect(stack, url, SUBPROTOCOLS[k % 2], wait_s=90) for k in range(MAX_CLIENTS)]
        first = held[0]
        ids: list[int] = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # serverInfo, then the channels as the flight opens them
            try:
                frame = first.recv(timeout=1)
            except TimeoutError:
                if ids:
                    break
                continue
            if isinstance(frame, str):
                ids += [ch["id"] for ch in json.loads(frame).get("channels", [])]
        out["channels"] = len(ids)
        try:
            _connect(stack, url, SUBPROTOCOLS[0])
            out["extra_client"] = 101
        except InvalidStatus as exc:
            out["extra_client"] = exc.response.status_code
        subs = [{"id": k, "channelId": ch} for k, ch in enumerate(ids)]
        repeated = [{"id": len(ids) + k, "channelId": ids[0]} for k in range(20)]
        unknown = [{"id": 10**6 + k, "channelId": 10**7 + k} for k in range(500)]
        for batch in (subs, repeated, unknown, [{"id": "x"}]):
            first.send(json.dumps({"op": "subscribe", "subscriptions": batch}))
        first.send(json.dumps({"op": "advertise", "channels": []}))  # clientPublish was not offered
        got: set[int] = set()
        deadline = time.monotonic() + 10
        while len(got) < min(len(ids) - 1, MAX_SUBSCRIPTIONS) and time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError):  # nothing to send for a moment
                frame = first.recv(timeout=1)
                if isinstance(frame, bytes):
                    got.add(struct.unpack_from("<I", frame, 1)[0])
        out["subscriptions_with_data"] = sorted(got)
        big = held[1]
        flood = {
            "op": "subscribe",
            "subscriptions": [{"id": k, "channelId": 10**7 + k} for k in range(FLOOD_CHANNELS)],
        }
        try:
            big.send(json.dumps(flood))
            while True:
                big.recv(timeout=10)
        except ConnectionClosed as exc:
            out["long_message_close"] = exc.rcvd.code if exc.rcvd is not None else None
        except TimeoutError:
            out["long_message_close"] = "still open"
    return out


def _check_probe(seen: dict[str, Any], log: str, host: str) -> None:
    assert seen["extra_client"] == 503, seen
    assert seen["long_message_close"] == 1009, seen
    assert set(seen["subscriptions_with_data"]) <= set(range(min(seen["channels"], MAX_SUBSCRIPTIONS))), seen
    lines = [line for line in log.splitlines() if f"live view client {host}:" in line]
    said = "\n".join(lines)
    assert "subscriptions to unknown channels: 500" in said, log[-3000:]
    assert "subscriptions malformed or repeated: 21" in said, said
    assert "messages not understood: 1" in said and "connections refused (server full): 1" in said, said
    assert f"messages longer than {MAX_MESSAGE_BYTES} B: 1" in said, said
    assert len(lines) <= 6, said  # at most one a second per client, whatever it sent


def test_the_caps_bind_a_local_client(caplog: pytest.LogCaptureFixture) -> None:
    """The server alone (no flight), with more channels than a client may subscribe to."""
    from foxglove.messages import Log

    from flightstack.viewer.foxglove_server import FoxgloveServer

    server = FoxgloveServer("127.0.0.1", 0, "caps")
    topics = [server.topic(f"/t{k}", Log.get_schema()) for k in range(MAX_SUBSCRIPTIONS + 30)]
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.05):
            for t in topics:
                t.log(Log(message="x"), log_time=time.time_ns())

    pub = threading.Thread(target=publish, daemon=True)
    pub.start()
    t0 = time.monotonic()
    try:
        seen = probe("127.0.0.1", server.port)
    finally:
        stop.set()
        pub.join(timeout=5)
        server.stop()
    log = caplog.text
    print(seen | {"subscriptions_with_data": len(seen["subscriptions_with_data"])}, log, sep="\n")
    assert (
        seen["channels"] == MAX_SUBSCRIPTIONS + 30
        and len(seen["subscriptions_with_data"]) == MAX_SUBSCRIPTIONS
    )
    assert f"subscriptions beyond {MAX_SUBSCRIPTIONS}: 30" in log, log
    _check_probe(seen, log, "127.0.0.1")
    lines = [line for line in log.splitlines() if "live view client 127.0.0.1:" in line]
    assert len(lines) <= 1 + (time.monotonic() - t0) / REPORT_PERIOD_S


@pytest.fixture
def two_namespaces() -> Iterator[tuple[str, str, str, str]]:
    """Two network namespaces joined by a veth pair: (server ns, its address, client ns, its address);
    deleted afterwards. Skipped without root and `ip` (fails under CI=true)."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        skip_or_fail_in_ci("needs root and iproute2's `ip netns` to create network namespaces")
    tag = uuid.uuid4().hex[:6]
    names = (f"fs_vs_{tag}", f"fs_vc_{tag}")
    octet = 1 + int(tag[:2], 16) % 250
    addrs = (f"10.213.{octet}.1", f"10.213.{octet}.2")
    made: list[str] = []

    def ip(*args: str) -> None:
        r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
        if r.returncode != 0:
            skip_or_fail_in_ci(
                f"cannot set up network namespaces here: ip {' '.join(args)}: {r.stderr.strip()}"
            )

    try:
        for ns in names:
            ip("netns", "add", ns)
            made.append(ns)
            ip("-n", ns, "link", "set", "lo", "up")
        ip(
            "-n",
            names[0],
            "link",
            "add",
            f"vs{tag}",
            "type",
            "veth",
            "peer",
            "name",
            f"vc{tag}",
            "netns",
            names[1],
        )
        for ns, dev, addr in ((names[0], f"vs{tag}", addrs[0]), (names[1], f"vc{tag}", addrs[1])):
            ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            ip("-n", ns, "link", "set", dev, "up")
        yield names[0], addrs[0], names[1], addrs[1]
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


def test_the_caps_bind_a_remote_client_on_viewer_host(
    tmp_path: Path, two_namespaces: tuple[str, str, str, str]
) -> None:
    """A flight serving `--viewer-host` on its namespace's address, probed from the other namespace. The
    probe is a process of its own and its steps take seconds, which the flight must outlive: the ideal rig
    flies paper_sim's 120 s in 0.5 s and closed the view 1.4 s after its channels appeared (in a
    fresh-clone CI run, and then on an idle machine, the probe met "going away"), so the flight is
    paper_experiment on the simulated lab, whose rendered cameras make 120 s take about 20 s."""
    server_ns, server_addr, client_ns, client_addr = two_namespaces
    port = 8765  # the default, free in a namespace of its own
    args = ["paper_experiment", "--rig", "lab-sim", "--modes", "none", "--duration", "120",
            "--viewer", "foxglove", "--viewer-host", server_addr]  # fmt: skip
    proc = _fly(args, tmp_path / "run", netns=server_ns)
    try:
        code = (
            "import json, sys; from tests.test_foxglove_live import probe; "
            "print(json.dumps(probe(*sys.argv[1:])))"
        )
        r = subprocess.run(
            ["ip", "netns", "exec", client_ns, sys.executable, "-c", code, server_addr, str(port)],
            cwd=REPO, capture_output=True, text=True, timeout=180,
        )  # fmt: skip
        _, err = proc.communicate(timeout=180)
    finally:
        proc.kill()
    assert r.returncode == 0, r.stderr[-3000:]
    assert proc.returncode == 0, err[-3000:]
    seen = json.loads(r.stdout.strip().splitlines()[-1])
    print(seen, err, sep="\n")
    assert f"viewer: live at ws://{server_addr}:{port}" in err
    assert f"warning: viewer: anyone on the networks of {server_addr} can connect" in err
    assert seen["channels"] >= len(TOPICS)  # and a camera's, advertised with its first frame
    _check_probe(seen, err, client_addr)


def test_a_viewer_host_that_is_not_this_machines_exits_2_in_one_line(tmp_path: Path) -> None:
    for host, why in (
        ("lab-pc", "is not an IP address"),
        ("192.0.2.77", "is not an address of this machine"),
    ):
        r = subprocess.run(
            [sys.executable, "-m", "flightstack", "run", "paper_sim", "--out", str(tmp_path / "run"),
             "--viewer", "foxglove", "--viewer-host", host],
            cwd=REPO, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and why in r.stderr, r.stderr
        assert r.stderr.startswith("error: --viewer-host: ") and "nothing took off" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "flightstack", "run", "paper_sim", "--out", str(tmp_path / "run"),
         "--viewer-host", "127.0.0.1"],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert (
        r.returncode == 2 and "add --viewer foxglove" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    )


# ---- the subscribe flood during a real-time flight ----------------------------------------------------
FLOOD_SECONDS = 8.0
"""How long each emulated-lab flight of the flood test lasts (s of mission time)."""
CPU_SLACK = 0.10
"""The flooded flight's process may use this fraction more CPU time than the clean one."""


def _cpu_s(pid: int) -> float:
    """utime + stime of process `pid` (s; its threads, not its children), 0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _flood(url: str, stop: threading.Event) -> int:
    """Send FLOOD_MESSAGES subscribes of FLOOD_CHANNELS unknown channels, reconnecting whenever the server
    cuts the client off; the messages sent."""
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    sent = 0
    while sent < FLOOD_MESSAGES and not stop.is_set():
        try:
            with contextlib.ExitStack() as stack:
                ws = _connect(stack, url, SUBPROTOCOLS[1], wait_s=5)
                while sent < FLOOD_MESSAGES:
                    subs = [
                        {"id": sent * FLOOD_CHANNELS + k, "channelId": 10**7 + k}
                        for k in range(FLOOD_CHANNELS)
                    ]
                    sent += 1
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        except (ConnectionClosed, InvalidStatus, OSError):
            time.sleep(0.01)
    return sent


def _lab_flight(tmp: Path, flood: bool) -> dict[str, Any]:
    """One emulated-lab flight with the live view on (flooded or not): its loop health, its process's CPU
    time (s), its stderr lines and the flood's messages sent."""
    port = free_port("tcp")
    args = ["paper_experiment", "--rig", "emulated-lab", "--modes", "none", "--duration", str(FLOOD_SECONDS),
            "--yes", "--viewer", f"foxglove:{port}"]  # fmt: skip
    proc = _fly(args, tmp, netns=None)
    stop = threading.Event()
    sent: list[int] = []
    flooder = threading.Thread(
        target=lambda: sent.append(_flood(f"ws://127.0.0.1:{port}", stop)), daemon=True
    )
    cpu = 0.0
    try:
        if flood:
            flooder.start()
        while proc.poll() is None:
            cpu = max(cpu, _cpu_s(proc.pid))
            time.sleep(0.1)
        _, err = proc.communicate(timeout=120)
    finally:
        stop.set()
        proc.kill()
    if flood:
        flooder.join(timeout=30)
    assert proc.returncode == 0, err[-3000:]
    health = json.loads((tmp / "metrics.json").read_text())["modes"]["none"]["loop_health"]
    return {
        "health": health,
        "cpu_s": cpu,
        "stderr_lines": len(err.splitlines()),
        "sent": sum(sent),
        "err": err,
    }


def test_a_subscribe_flood_leaves_the_flight_as_a_clean_one(tmp_path: Path, safety_bound: Bound) -> None:
    """The flood during a real-time flight on the emulated lab costs the flight nothing it measures: the
    flight process's CPU time within CPU_SLACK of the clean flight's, stderr at most 100 lines, overruns at
    most twice the clean flight's + 2, and the loop keeps dt when the clean flight kept it (a loaded CI
    machine's clean flight overran 4 % of its ticks: there the relative bounds judge). The clean flight is
    flown in this test, right before the flooded one; when any of these comparisons is off, the pair is flown
    once more and judged on that second pair (a cost of the view fails both; the machine's noise, seen as 2
    overruns of 159 ticks beside the unit tier and a CPU-bound process while the flood cost less CPU than
    the clean flight, not again)."""
    for attempt in range(2):
        clean = _lab_flight(tmp_path / f"clean{attempt}", flood=False)
        flooded = _lab_flight(tmp_path / f"flood{attempt}", flood=True)
        c, f = clean["health"], flooded["health"]
        print(f"clean: CPU {clean['cpu_s']:.2f} s, compute p99 {1e3 * c['compute_s']['p99']:.1f} ms, "
              f"overruns {c['overruns']}, stderr {clean['stderr_lines']} lines; flood ({flooded['sent']} "
              f"messages): CPU {flooded['cpu_s']:.2f} s, compute p99 {1e3 * f['compute_s']['p99']:.1f} ms, "
              f"overruns {f['overruns']}, stderr {flooded['stderr_lines']} lines")  # fmt: skip
        assert flooded["sent"] == FLOOD_MESSAGES
        assert "live view client 127.0.0.1:" in flooded["err"], flooded["err"][-2000:]
        within = (
            flooded["cpu_s"] <= (1 + CPU_SLACK) * clean["cpu_s"]
            and f["overruns"] <= 2 * c["overruns"] + 2
            and (f["keeps_dt"] or not c["keeps_dt"])
        )
        if within or attempt == 1:
            break
    safety_bound("overruns of the flooded flight", f["overruns"], 2 * c["overruns"] + 2, "ticks")
    assert f["keeps_dt"] or not c["keeps_dt"], (f, c)
    assert flooded["stderr_lines"] <= 100, flooded["err"][-3000:]
    assert flooded["cpu_s"] <= (1 + CPU_SLACK) * clean["cpu_s"], (flooded["cpu_s"], clean["cpu_s"])
