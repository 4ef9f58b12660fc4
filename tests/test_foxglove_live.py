"""`--viewer foxglove[:PORT]` (flightstack.viewer.foxglove_live): a WebSocket client (`websockets`,
speaking Foxglove's WebSocket protocol from its specification, not foxglove-sdk's client; foxglove-sdk
0.30's server accepts the subprotocol foxglove.sdk.v1 only, refusing foxglove.websocket.v1 with HTTP 400)
connects during a simulated flight, subscribes to every channel the server advertises and decodes at least
one message of each with the protobuf schema the advertisement carries."""

from __future__ import annotations

import base64
import json
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from flightstack.ports import free_port
from tests.conftest import REPO

pytestmark = pytest.mark.system
SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01  # binary opcode: subscription id u32, log time u64, payload


def _decoder(schema_name: str, schema_b64: str) -> Any:
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64)).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def test_a_client_decodes_every_advertised_channel_during_a_flight(tmp_path: Path) -> None:
    from websockets.sync.client import connect

    port = free_port("tcp")
    cmd = [sys.executable, "-m", "flightstack", "run", "paper_sim", "--modes", "none", "--duration", "120",
           "--no-progress", "--no-live-mcap", "--out", str(tmp_path / "run"),
           "--viewer", f"foxglove:{port}"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    channels: dict[int, dict[str, Any]] = {}
    decoded: dict[str, list[Any]] = {}
    try:
        deadline = time.monotonic() + 60
        ws = None
        while ws is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=2)  # type: ignore[list-item]
            except OSError:
                time.sleep(0.05)
        assert ws is not None, proc.communicate(timeout=60)
        with ws:
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
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert f"viewer: live at ws://127.0.0.1:{port}" in err
    topics = {ch["topic"]: ch["schemaName"] for ch in channels.values()}
    assert topics == {
        "/none/tick": "flightstack.Tick",
        "/none/drone1": "flightstack.DroneState", "/none/drone2": "flightstack.DroneState",
        "/none/drone3": "flightstack.DroneState",
        "/none/tf": "foxglove.FrameTransforms", "/none/events": "foxglove.Log",
    }  # fmt: skip
    assert set(decoded) == set(topics), {t: len(v) for t, v in decoded.items()}
    ticks = [m for _, m in decoded["/none/tick"]]
    assert all(0.0 <= m.t <= 120.0 for m in ticks) and [m.t for m in ticks] == sorted(m.t for m in ticks)
    assert {m.drone for _, m in decoded["/none/drone2"]} == {2}
    assert any("landed" in m.message for _, m in decoded["/none/events"])
    print(f"foxglove live: {', '.join(f'{t} {len(v)}' for t, v in sorted(decoded.items()))} messages decoded")
