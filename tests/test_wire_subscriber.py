"""An independent Zenoh subscriber (a plain zenoh session, none of the project's bus classes) on every key
of a served run (`flightstack world` + three `flightstack agent` processes on loopback, then `flightstack
abort`): it hears every key docs/wire-format.md lists and no other, each with the encoding the page
names (JSON on control/status, binary on pred/*), and decodes the predictions it heard with nothing but the
page's byte table, equal to the project's decoding. And a peer that declares no encoding (an older
version) is still heard."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
import yaml

from flightstack.comms import wire
from flightstack.comms.messages import decode
from flightstack.faults.rows_processes import ServedRun, served_ids, served_mission
from tests.conftest import REPO
from tests.wire_page import decode_with_page, prediction_layout, same_as_project

IDS = served_ids()
"""The served mission's drones (its agents)."""

zenoh = pytest.importorskip("zenoh")
pytestmark = pytest.mark.system


class Listener:
    """A plain zenoh peer connected to every participant's endpoint, subscribed to `**`: per key, the
    encodings heard and a few payloads."""

    def __init__(self, endpoints: list[str]) -> None:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        self.lock = threading.Lock()
        self.encodings: dict[str, set[str]] = defaultdict(set)
        self.payloads: dict[str, list[bytes]] = defaultdict(list)
        self.session = zenoh.open(conf)
        self.sub = self.session.declare_subscriber("**", self._on)

    def _on(self, sample: Any) -> None:
        key, enc, data = str(sample.key_expr), str(sample.encoding), bytes(sample.payload.to_bytes())
        with self.lock:
            self.encodings[key].add(enc)
            if len(self.payloads[key]) < 50:
                self.payloads[key].append(data)

    def keys(self) -> set[str]:
        with self.lock:
            return set(self.encodings)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _pattern(c: wire.Channel, mission: str) -> re.Pattern[str]:
    text = re.escape(c.builder("flightstack", mission, *("\0" for _ in c.placeholders)))
    return re.compile(text.replace("\0", "[^/]+") + "$")


def test_an_independent_subscriber_sees_each_keys_encoding(tmp_path: Path) -> None:
    mission = served_mission(tmp_path, duration_s=120.0, name="wire_check")
    endpoints = list(yaml.safe_load(mission.read_text())["bus"]["zenoh"]["endpoints"].values())
    listener = Listener(endpoints)
    try:
        with ServedRun(mission, tmp_path) as run:
            base = "flightstack/wire_check"
            kinds = ("pred", "control/status", "world/tick", "world/cmd")
            wanted = {f"{base}/{k}/{i}" for i in IDS for k in kinds}
            deadline = time.monotonic() + 150  # agents start slowly on a loaded machine
            while not wanted <= listener.keys() and time.monotonic() < deadline and run.world.poll() is None:
                time.sleep(0.2)
            assert wanted <= listener.keys(), (sorted(wanted - listener.keys()), run.world_lines.rest())
            abort = subprocess.run(
                [sys.executable, "-m", "flightstack.cli.app", "abort", str(mission), "--timeout", "10"],
                cwd=REPO,
                capture_output=True,
                text=True,
                timeout=60,
            )
            codes = {i: a.wait(timeout=30) for i, a in run.agents.items()}
            run.world.wait(timeout=30)
        time.sleep(0.2)  # the last samples in flight
    finally:
        listener.close()
    assert abort.returncode == 0, abort.stdout + abort.stderr
    assert codes == {1: 1, 2: 1, 3: 1}  # ended by the operator
    heard = dict(listener.encodings)
    print({k: sorted(v) for k, v in sorted(heard.items())})
    # every key heard is one the page lists, with exactly the encoding it names
    patterns = [(c, _pattern(c, "wire_check")) for c in wire.CHANNELS if c.encoding is not None]
    for key, encs in heard.items():
        matched = [c for c, p in patterns if p.match(key)]
        assert len(matched) == 1, f"{key}: not a key of docs/wire-format.md"
        assert encs == {matched[0].encoding}, (key, encs)
    assert heard[f"{base}/control/status/1"] == {"application/json"}
    assert all(heard[f"{base}/pred/{i}"] == {"application/octet-stream;flightstack-pred"} for i in IDS)
    # the abort comes from the operator's own fresh session, which connects only to the mission's
    # endpoints; peers do not relay, so this listener hears it only when gossip linked the two (in CI it
    # did not, once): checked when heard, as every key above (and in test_wire_format without a network)
    assert heard.get(f"{base}/control/abort", {"application/json"}) == {"application/json"}
    assert any(k.startswith(f"{base}/control/ack/") for k in heard)
    # the predictions heard, decoded with the page's table alone, equal the project's decoding
    layout = prediction_layout()
    n = 0
    for i in IDS:
        for data in listener.payloads[f"{base}/pred/{i}"]:
            msg, why = decode(data, "wire_check", set(IDS))
            assert msg is not None, why
            assert same_as_project(decode_with_page(data, layout), msg) == []
            n += 1
    assert n >= 3 * 10
    print(f"{n} predictions heard decoded from the page alone")


def test_a_peer_that_declares_no_encoding_is_still_heard() -> None:
    """An older peer puts without an encoding (zenoh/bytes): its prediction and its status are accepted as
    before (receivers never look at the encoding)."""
    import numpy as np

    from flightstack.comms.control import STATUS, encode_control
    from flightstack.comms.factory import free_loopback_endpoints
    from flightstack.comms.messages import PredictionMessage, encode
    from flightstack.comms.zenoh_bus import ZenohBus, ZenohBusConfig

    (ep,) = free_loopback_endpoints(1)
    bus = ZenohBus(ZenohBusConfig("wire_old", {0}, {0, 1}, [ep], []))
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([ep]))
    old = zenoh.open(conf)
    try:
        status = {"drone": 1, "mode": "dgp", "t": 1.0, "tick": 100, "battery_pct": 90.0, "flying": True,
                  "link_alive": True, "visible": True, "n_fused": 2, "pose_fresh": True, "rejection": None,
                  "dropped": {}, "restarts": {}}  # fmt: skip
        heard: list[Any] = []
        deadline = time.monotonic() + 30
        seq = 0
        while time.monotonic() < deadline and not (bus.delivered and heard):
            msg = PredictionMessage.of_body("wire_old", 1, seq, 0.01 * seq, True, np.ones(16))
            old.put("flightstack/wire_old/pred/1", encode(msg), attachment=b"old peer")
            old.put("flightstack/wire_old/control/status/1", encode_control("wire_old", STATUS, status, [1]))
            seq += 1
            time.sleep(0.1)
            heard += [e for e in bus.control_events() if e.kind == STATUS]
        assert bus.delivered > 0 and heard, (bus.dropped, seq)
        assert heard[0].payload == status
        assert sum(bus.dropped.values()) == 0, bus.dropped
        print(f"heard after {seq} puts without an encoding")
    finally:
        old.close()
        bus.close()
