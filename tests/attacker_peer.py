"""A peer that is not (or must not act as) a participant of a mission, for tests/test_attacker.py.

    python -m tests.attacker_peer SPEC.json

SPEC: {"mission", "prefix", "connect": [endpoints], "tls": null | {zenoh tls keys}, "duration_s",
"period_s", "forgeries": [names of FORGERIES], "copy_labels": optional bool}. It opens one Zenoh
session (peer mode, connecting to every endpoint; plaintext, or TLS with whatever certificate it was
given) and puts every forgery every `period_s` until `duration_s` has passed; then prints one JSON
line: {"sent": {forgery: count}, "max_peers": the most peers its session ever saw}. Every message is
built by hand (struct, json), not with the project's encoders, which refuse to produce most of them.
With "copy_labels" it also listens to the predictions and puts each forged one with the session label
(Zenoh attachment, flightstack/comms/identity.py) the real sender of that key used last: on plaintext a
label is no authentication. With "copy_stream": {"sender": i, "lead": d, "mu": m} it is a second agent
i: for every prediction the real agent i puts it puts one of its own right after, under the real one's
label, with seq (real + d) and the real stamp, in-bounds values and μ = (m, m, 0, 0) ("copied stream"),
once it has seen the liveliness token of every agent in "await" (default []: at once). With "every": n
it puts one only after every n-th real message (a low-rate copy); with "cycle": true only once the real
sender has passed its last one (one message `d` ahead, again when the real stream is back). A token is
declared after its agent's subscribers (flightstack/comms/zenoh_bus.py) and peers do not relay for each
other, so seeing agent j's token means j's subscribers are known here and every copy is routed to j;
a peer count alone does not say that.
Loopback only; stops by itself, or at SIGTERM (then reports as at the end).
"""

from __future__ import annotations

import json
import signal
import struct
import sys
import time
from collections import Counter
from typing import Any

import zenoh

_HEAD = struct.Struct("<4sBBHIdB")
_BODY = struct.Struct("<16d")


def prediction(mission: str, sender: int, seq: int, stamp: float, var: float, mu: float = 0.0) -> bytes:
    name = mission.encode()
    head = _HEAD.pack(b"FSPM", 1, 1, sender, seq, stamp, len(name))
    body = _BODY.pack(0.0, 0.0, 0.0, 0.0, mu, mu, 0.0, 0.0, *([var] * 4), *([1.0] * 4))
    return head + name + body


def world(header: dict[str, Any]) -> bytes:
    head = json.dumps(header).encode()
    return struct.pack("<I", len(head)) + head


def control(mission: str, kind: str, payload: dict[str, Any], origin: list[int]) -> bytes:
    return json.dumps({"mission": mission, "kind": kind, "payload": payload, "origin": origin}).encode()


def forgeries(mission: str, prefix: str, k: int) -> dict[str, tuple[str, bytes]]:
    """name → (key, payload) of every forgery the issue reports, for tick/sequence counter k."""
    base = f"{prefix}/{mission}"
    return {
        # one message that took over sender 2's slot (all real ones after it dropped as old)
        "pred slot takeover": (f"{base}/pred/2", prediction(mission, 2, 2**32 - 1, 1e300, 0.01)),
        # a variance that made the fused mean NaN
        "pred tiny variance": (f"{base}/pred/1", prediction(mission, 1, 10**6 + k, 0.0, 5e-324)),
        "pred huge mean": (f"{base}/pred/3", prediction(mission, 3, 10**6 + k, 0.0, 0.01, mu=1e6)),
        "abort": (
            f"{base}/control/abort",
            control(mission, "abort", {"reason": "forged", "id": f"f{k}"}, []),
        ),
        "status": (
            f"{base}/control/status/1",
            control(mission, "status", {"drone": 1, "t": [], "mode": "dgp"}, [1]),
        ),
        "world cmd stop": (
            f"{base}/world/cmd/1",
            world({"v": 1, "k": k, "calls": [["emergency_stop"]]}),
        ),
        "world cmd 50 m/s": (
            f"{base}/world/cmd/2",
            world({"v": 1, "k": k, "calls": [["send_body_velocity", [50.0, 0.0, 0.0, 0.0]]]}),
        ),
        "world tick": (f"{base}/world/tick/3", world({"v": 1, "k": 10**6 + k, "t": 1.0, "state": {}})),
        "world cmd crash": (f"{base}/world/cmd/3", world({"v": 1, "k": k, "calls": [[{}]]})),
    }


def main(spec_path: str) -> int:
    with open(spec_path, encoding="utf-8") as f:
        spec = json.load(f)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(spec["connect"]))
    # it only connects out: no listener, no gossip, so that no agent connects back to it at the same time
    # (with both links racing, an agent's declarations were lost: the copier never saw agent 2's token)
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/gossip/enabled", "false")
    for key, value in (spec.get("tls") or {}).items():
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    sent: Counter[str] = Counter()
    max_peers = 0
    fewest_peers = 1 << 30  # while copying
    session = zenoh.open(conf)
    labels: dict[str, bytes] = {}  # pred key -> the attachment its real sender put last

    def learn(sample: Any) -> None:
        if sample.attachment is not None:
            labels[str(sample.key_expr)] = bytes(sample.attachment.to_bytes())

    if spec.get("copy_labels"):
        session.declare_subscriber(f"{spec['prefix']}/{spec['mission']}/pred/*", learn)
    copy = spec.get("copy_stream")
    heard: list[tuple[int, float, bytes | None]] = []  # the real sender's (seq, stamp, label), unsent
    tokens: set[str] = set()  # agent ids whose liveliness token this session has seen
    t_open = time.monotonic()
    t_copying: float | None = None  # s after open when every awaited token was seen
    forged: set[int] = set()
    real_seen = 0  # real messages heard while copying

    def copy_of(sample: Any) -> None:
        data = bytes(sample.payload.to_bytes())
        if len(data) < _HEAD.size:
            return
        seq, stamp = _HEAD.unpack_from(data)[4:6]
        if seq not in forged:  # our own puts come back to us
            att = sample.attachment
            heard.append((seq, stamp, None if att is None else bytes(att.to_bytes())))

    def alive(sample: Any) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            tokens.add(str(sample.key_expr).rsplit("/", 1)[-1])

    if copy:
        key = f"{spec['prefix']}/{spec['mission']}/pred/{copy['sender']}"
        session.declare_subscriber(key, copy_of)
        awaited = {str(i) for i in copy.get("await", [])}
        alive_keys = f"{spec['prefix']}/{spec['mission']}/alive/*"
        session.liveliness().declare_subscriber(alive_keys, alive, history=True)
    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda signum, _frame: stop.append(signum))
    try:
        t_end = time.monotonic() + float(spec["duration_s"])
        k = 0
        while time.monotonic() < t_end and not stop:
            peers = len(list(session.info.peers_zid()))
            max_peers = max(max_peers, peers)
            if copy and sent["copied stream"]:
                fewest_peers = min(fewest_peers, peers)
            if copy and t_copying is None:
                if not awaited <= tokens:
                    heard.clear()  # not every receiver known yet (a loaded machine connects late)
                    time.sleep(0.01)
                    continue
                t_copying = time.monotonic() - t_open
            while copy and heard:
                seq, stamp, label = heard.pop(0)
                real_seen += 1
                if copy.get("every") and (real_seen - 1) % int(copy["every"]):
                    continue
                if copy.get("cycle") and forged and seq <= max(forged):
                    continue
                forged.add(seq + copy["lead"])
                data = prediction(
                    spec["mission"], copy["sender"], seq + copy["lead"], stamp, 0.01, copy["mu"]
                )
                session.put(key, data, attachment=label)
                sent["copied stream"] += 1
            if copy:
                time.sleep(0.001)  # the same rate as the real sender: one put per real one
                continue
            for name, (key, data) in forgeries(spec["mission"], spec["prefix"], k).items():
                if name in spec["forgeries"]:
                    session.put(key, data, attachment=labels.get(key))
                    sent[name] += 1
                    sent["with a copied label"] += key in labels
            k += 1
            time.sleep(float(spec["period_s"]))
    finally:
        session.close()
    report: dict[str, Any] = {"sent": dict(sent), "max_peers": max_peers}
    if copy:
        report["fewest_peers_while_copying"] = fewest_peers if sent["copied stream"] else 0
        report["tokens_seen"] = sorted(tokens)
        report["copying_after_s"] = t_copying
    print(json.dumps(report), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
