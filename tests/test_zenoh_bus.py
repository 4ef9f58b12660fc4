"""ZenohBus: exchange, loopback, validation and drop counting, lock-step wait, staleness, presence.

Every session listens on a port picked free at runtime on 127.0.0.1 (multicast scouting off) and every
test closes its buses in `finally`; subprocess peers stop by themselves after 60 s if orphaned.
"""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from flightstack.comms.acl import ack_key, status_key
from flightstack.comms.bus import InProcBus
from flightstack.comms.control import encode_control
from flightstack.comms.factory import free_loopback_endpoints
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.comms.zenoh_bus import ZenohBus, ZenohBusConfig, zenoh_config
from tests.conftest import eventually, status_payload

REPO = Path(__file__).resolve().parents[1]
MISSION = "zb_test"
KNOWN = {0, 1, 2}
PREFIX = "flightstack"
LEASE_MS = 500  # presence tests: a hung peer is dropped after ~0.5 s; a killed one on TCP close (~0.1 s)
DETECT_BOUND_S = 1.0  # issue requirement: a killed agent leaves fusion within 1 s


def make_msg(sender: int, seq: int, stamp: float = 1.0, mission: str = MISSION, seed: int = 0):
    rng = np.random.default_rng(seed * 1000 + sender * 100 + seq)
    return PredictionMessage(
        mission,
        sender,
        seq,
        stamp,
        bool(seq % 2),
        rng.normal(size=4),
        rng.normal(size=4),
        rng.uniform(0.01, 2.0, size=4),
        rng.uniform(0.5, 2.0, size=4),
    )


def same(a: PredictionMessage | None, b: PredictionMessage | None) -> bool:
    assert a is not None and b is not None
    return (a.mission, a.sender, a.seq, a.stamp, a.visible) == (
        b.mission,
        b.sender,
        b.seq,
        b.stamp,
        b.visible,
    ) and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("g_bar_w", "mu", "var", "prior_var"))


@contextmanager
def mesh(*self_ids: set[int], lease_ms: int = 1000) -> Iterator[list[ZenohBus]]:
    """One bus per entry, full mesh (each listens on its own port and connects to all others)."""
    eps = free_loopback_endpoints(len(self_ids))
    buses: list[ZenohBus] = []
    try:
        for k, ids in enumerate(self_ids):
            others = [e for j, e in enumerate(eps) if j != k]
            buses.append(ZenohBus(ZenohBusConfig(MISSION, ids, KNOWN, [eps[k]], others, lease_ms=lease_ms)))
        everyone = set().union(*self_ids)
        for b in buses:
            assert b.wait_alive(everyone, 20.0) == set(), "mesh did not come up"
        yield buses
    finally:
        for b in buses:
            b.close()


@pytest.fixture(autouse=True)
def no_leftover_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    assert eventually(lambda: not [t for t in threading.enumerate() if t not in before], 5.0), (
        f"threads left running: {[t.name for t in threading.enumerate() if t not in before]}"
    )


# ---------------------------------------------------------------------------------------------- config
def test_config_builds_and_rejects_bad_keys(tmp_path: Path) -> None:
    ok = ZenohBusConfig(MISSION, {0}, KNOWN, [free_loopback_endpoints()[0]], [], usrpwd=("u", "p"))
    zenoh_config(ok)
    for f in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / f).write_text("dummy")
    tls = {
        "root_ca_certificate": str(tmp_path / "ca.pem"),
        "listen_certificate": str(tmp_path / "cert.pem"),
        "listen_private_key": str(tmp_path / "key.pem"),
        "connect_certificate": str(tmp_path / "cert.pem"),
        "connect_private_key": str(tmp_path / "key.pem"),
        "enable_mtls": True,
    }
    zenoh_config(ZenohBusConfig(MISSION, {0}, KNOWN, ["tls/127.0.0.1:0"], [], tls=tls))
    wide = ZenohBusConfig(MISSION, {0}, KNOWN, ["tcp/0.0.0.0:0"], [], allow_all_interfaces=True)
    zenoh_config(wide)
    zenoh_config(ZenohBusConfig(MISSION, {0}, KNOWN, [], [], extra_json5={"access_control/enabled": "false"}))
    bad = [
        ({"listen": ["nonsense"]}, "listen"),
        ({"connect": "tcp/127.0.0.1:1"}, "connect"),
        ({"self_ids": {5}}, "self_ids"),
        ({"lease_ms": 0}, "lease_ms"),
        ({"mission": "a/b"}, "mission"),
        ({"mission": "a*"}, "mission"),
        ({"key_prefix": "fs/**"}, "key_prefix"),
        ({"tls": {**tls, "root_ca_certificate": str(tmp_path / "missing.pem")}}, "tls.root_ca_certificate"),
        ({"tls": {**tls, "bogus": "x"}}, "tls.bogus"),
        # nothing runs less secured than it says
        ({"tls": tls, "listen": ["tcp/127.0.0.1:1"]}, "plaintext beside TLS"),
        ({"tls": tls, "connect": ["tls/127.0.0.1:1", "tcp/127.0.0.1:2"]}, "plaintext beside TLS"),
        ({"tls": {**tls, "enable_mtls": False}}, "without client authentication"),
        ({"tls": {k: v for k, v in tls.items() if k != "connect_private_key"}}, "tls.connect_private_key"),
        ({"connect": ["tls/127.0.0.1:1"]}, "needs certificates"),
        ({"listen": ["tcp/0.0.0.0:7447"]}, "every interface"),
        ({"listen": ["tcp/[::]:7447"]}, "every interface"),
        ({"usrpwd": ("u",)}, "usrpwd"),
        ({"extra_json5": {"no/such/key": "1"}}, "no/such/key"),
        ({"extra_json5": {"transport/link/tx/lease": "not json"}}, "transport/link/tx/lease"),
    ]
    base = {"mission": MISSION, "self_ids": {0}, "known_senders": KNOWN, "listen": [], "connect": []}
    for change, key in bad:
        with pytest.raises(ValueError, match=key.replace("*", r"\*")):
            zenoh_config(ZenohBusConfig(**{**base, **change}))


# -------------------------------------------------------------------------------------------- exchange
def test_two_buses_exchange_identical_to_inproc() -> None:
    ref = InProcBus(MISSION, KNOWN)
    with mesh({0}, {1, 2}) as (a, b):
        for seq in (1, 2, 3):
            sent = {i: make_msg(i, seq, stamp=0.1 * seq) for i in KNOWN}
            a.publish(sent[0])
            b.publish(sent[1])
            b.publish(sent[2])
            for m in sent.values():
                ref.publish(m)
            expected = dict.fromkeys(KNOWN, seq)
            assert a.wait_for(expected, 10.0) == set()
            assert b.wait_for(expected, 10.0) == set()
            for bus in (a, b):  # remote and own-process messages alike
                for i in KNOWN:
                    got = bus.latest(i, 0.1 * seq, 1.0)
                    assert same(got, sent[i])
                    assert same(got, ref.latest(i, 0.1 * seq, 1.0))
        assert a.delivered == b.delivered == ref.delivered == 9
        assert a.dropped == b.dropped == Counter()


def test_own_publications_loop_back_without_peers() -> None:
    bus = ZenohBus(ZenohBusConfig(MISSION, {0, 1}, KNOWN, [free_loopback_endpoints()[0]], []))
    try:
        msg = make_msg(1, 7)
        bus.publish(msg)
        assert bus.wait_for({1: 7}, 10.0) == set()
        assert same(bus.latest(1, 1.0, 1.0), msg)
        assert bus.latest(0, 1.0, 1.0) is None  # nothing published yet
        assert bus.alive() == {0, 1}
    finally:
        bus.close()


def _nan_payload() -> bytes:
    data = bytearray(encode(make_msg(1, 50)))
    struct.pack_into("<d", data, len(data) - 8 * 12, float("nan"))  # first element of mu
    return bytes(data)


def test_bad_messages_dropped_and_counted_like_inproc() -> None:
    with mesh({0}, {1}) as (a, b):
        ref = InProcBus(MISSION, KNOWN)
        bad = [
            b"",
            b"garbage that is not a message",
            encode(make_msg(1, 10))[:-3],
            encode(make_msg(1, 11, mission="other_mission")),
            encode(make_msg(9, 12)),  # unknown sender (valid on the wire)
            _nan_payload(),
        ]
        b.publish(make_msg(1, 5))
        assert a.wait_for({1: 5}, 10.0) == set()
        ref.publish(make_msg(1, 5))
        for data in [*bad, encode(make_msg(1, 3)), encode(make_msg(1, 5))]:  # ... old, duplicate seq
            b.publish_raw(data)
            ref.publish_raw(data)
        b.publish_raw(encode(make_msg(1, 20)), key_sender=2)  # key says 2, payload says 1
        expected = ref.dropped + Counter({"key sender mismatch": 1})
        assert eventually(lambda: a.dropped == expected), (a.dropped, expected)
        assert set(expected) >= {
            "truncated header",
            "bad magic",
            "wrong length",
            "other mission",
            "unknown sender",
            "non-finite mu",
            "old or duplicate seq",
        }
        good = make_msg(1, 6)
        b.publish(good)  # the loop goes on
        assert a.wait_for({1: 6}, 10.0) == set()
        assert same(a.latest(1, 1.0, 1.0), good)
        assert a.latest(2, 1.0, 1.0) is None  # the mismatched message was not stored under 2
        with pytest.raises(ValueError):
            b.publish(make_msg(1, 7, stamp=float("nan")))  # never sends garbage itself


# ---------------------------------------------------------------------------------- lock-step, staleness
def test_wait_for_returns_on_arrival_and_times_out_bounded() -> None:
    with mesh({0}, {1}) as (a, b):
        t0 = time.monotonic()
        assert a.wait_for({1: 1}, 0.3) == {1}
        assert 0.3 <= time.monotonic() - t0 < 3.0
        timer = threading.Timer(0.2, lambda: b.publish(make_msg(1, 1)))
        t0 = time.monotonic()
        timer.start()
        try:
            assert a.wait_for({1: 1}, 20.0) == set()  # wakes up on arrival, not on the timeout
            assert 0.15 <= time.monotonic() - t0 < 5.0
        finally:
            timer.join()
        t0 = time.monotonic()
        assert a.wait_for({1: 1, 0: 1}, 0.3) == {0}  # 1 is there, 0 never published
        assert 0.3 <= time.monotonic() - t0 < 3.0
        b.publish(make_msg(1, 2))
        t0 = time.monotonic()
        assert a.wait_for({1: 2}, 20.0) == set()
        assert time.monotonic() - t0 < 5.0
        assert a.wait_for({1: 1}, 0.0) == set()  # already satisfied: no wait


def test_stale_messages_read_as_none_and_counted() -> None:
    with mesh({0}, {1}) as (a, b):
        b.publish(make_msg(1, 1, stamp=10.0))
        assert a.wait_for({1: 1}, 10.0) == set()
        assert a.latest(1, 10.4, 0.5) is not None
        assert a.latest(1, 10.6, 0.5) is None
        assert a.dropped["stale"] == 1
        b.publish(make_msg(1, 2, stamp=10.5))
        assert a.wait_for({1: 2}, 10.0) == set()
        assert a.latest(1, 10.6, 0.5) is not None


# ------------------------------------------------------------------------------------------- presence
def test_closed_bus_is_seen_left_within_one_second() -> None:
    with mesh({0}, {1, 2}, lease_ms=LEASE_MS) as (a, b):
        b.publish(make_msg(1, 1))
        assert a.wait_for({1: 1}, 10.0) == set()
        t_close = time.monotonic()
        b.close()
        assert eventually(lambda: a.alive() == {0}, 5.0)
        left = {e.drone: e.t for e in a.presence_events if e.kind == "left"}
        assert set(left) == {1, 2}
        assert max(left.values()) - t_close < DETECT_BOUND_S, left
        assert a.latest(1, 1.0, 1.0) is None
        assert a.dropped["left"] == 1
        t0 = time.monotonic()
        assert a.wait_for({1: 2}, 20.0) == {1}  # returns at once for a sender that has left
        assert time.monotonic() - t0 < 1.0


def test_restarted_agent_is_accepted_with_fresh_seq() -> None:
    ep_a = free_loopback_endpoints()[0]
    a = ZenohBus(ZenohBusConfig(MISSION, {0}, KNOWN, [ep_a], [], lease_ms=LEASE_MS))
    try:
        for run, seq in ((1, 40), (2, 1)):  # the second run of agent 1 counts from 1 again
            ep_b = free_loopback_endpoints()
            b = ZenohBus(ZenohBusConfig(MISSION, {1}, KNOWN, ep_b, [ep_a], lease_ms=LEASE_MS))
            try:
                assert a.wait_alive({1}, 20.0) == set()
                msg = make_msg(1, seq, seed=run)
                b.publish(msg)
                assert a.wait_for({1: seq}, 10.0) == set()
                assert same(a.latest(1, 1.0, 1.0), msg)
            finally:
                b.close()
            assert eventually(lambda: 1 not in a.alive(), 5.0)
        assert [(e.drone, e.kind) for e in a.presence_events if e.drone == 1] == [
            (1, "joined"),
            (1, "left"),
            (1, "joined"),
            (1, "left"),
        ]
        assert a.dropped["old or duplicate seq"] == 0
    finally:
        a.close()


PEER = r"""
import sys, time
import numpy as np
from flightstack.comms.messages import PredictionMessage
from flightstack.comms.zenoh_bus import ZenohBus, ZenohBusConfig
mission, listen, connect, lease = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
bus = ZenohBus(ZenohBusConfig(mission, {2}, {0, 1, 2}, [listen], [connect], lease_ms=lease))
try:
    seq, t_end = 0, time.monotonic() + 60.0
    print("ready", flush=True)
    while time.monotonic() < t_end:
        seq += 1
        one = np.ones(4)
        bus.publish(PredictionMessage(mission, 2, seq, time.monotonic(), True, one, one, one, one))
        time.sleep(0.02)
finally:
    bus.close()
"""


@contextmanager
def peer_process(listen: str, connect: str) -> Iterator[subprocess.Popen]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(
        [sys.executable, "-c", PEER, MISSION, listen, connect, str(LEASE_MS)],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)


def _peer_is_up(a: ZenohBus, proc: subprocess.Popen) -> None:
    ok = a.wait_alive({2}, 30.0) == set() and a.wait_for({2: 3}, 30.0) == set()
    assert ok, proc.stderr.read().decode() if proc.poll() is not None and proc.stderr else "peer not up"
    assert a.latest(2, time.monotonic(), 5.0) is not None


@pytest.mark.parametrize("how", ["SIGKILL", "SIGSTOP"])
def test_killed_or_hung_peer_process_is_dropped(how: str) -> None:
    """SIGKILL: the kernel closes the peer's sockets, detection ≈ 0.1-0.2 s. SIGSTOP (hung peer): only the
    lease expires, detection ≈ LEASE_MS. Both must drop the peer from fusion within 1 s."""
    ep_a, ep_peer = free_loopback_endpoints(2)
    a = ZenohBus(ZenohBusConfig(MISSION, {0}, KNOWN, [ep_a], [ep_peer], lease_ms=LEASE_MS))
    try:
        with peer_process(ep_peer, ep_a) as proc:
            _peer_is_up(a, proc)
            t_kill = time.monotonic()
            os.kill(proc.pid, getattr(signal, how))
            try:
                assert eventually(lambda: 2 not in a.alive(), 10.0)
                t_left = next(e.t for e in a.presence_events if e.drone == 2 and e.kind == "left")
                detect = t_left - t_kill
                print(f"{how}: peer seen left after {detect * 1e3:.0f} ms (lease {LEASE_MS} ms)")
                assert detect < DETECT_BOUND_S
                assert a.latest(2, time.monotonic(), 5.0) is None
                assert a.dropped["left"] >= 1
            finally:
                proc.kill()
    finally:
        a.close()


# ------------------------------------------------------------------------------------------- control
def collect_control(bus: ZenohBus, n: int, timeout_s: float = 10.0) -> list:
    """Drain `bus.control_events()` until n events have arrived (or the timeout)."""
    got: list = []
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        got += bus.control_events()
        time.sleep(0.005)
    return got


STATUS = status_payload(1, t=1.0, tick=20)


def test_control_channel() -> None:
    with mesh({0}, {1}) as (a, b):
        b.publish_control("abort", {"reason": "operator", "id": "x1"})
        b.publish_control_raw(b"{not json")
        b.publish_control_raw(b'{"mission": "zb_test", "kind": "dance", "payload": {}}')
        b.publish_control_raw(b'{"mission": "other", "kind": "abort", "payload": {}}')
        b.publish_control_raw(b'{"mission": "zb_test", "kind": "status", "payload": [1]}')
        b.publish_control("status", STATUS)
        # the key says what a control message may be (the ACL authenticates keys): a status on
        # the abort key, an acknowledgement naming a drone its participant does not host, a status of
        # drone 0 on drone 1's key are all dropped
        b.publish_control_raw(encode_control(MISSION, "status", STATUS, [1]))
        fake_ack = {"abort_id": "x1", "drones": [0], "pid": 1, "host": "h"}
        b.publish_control_raw(
            encode_control(MISSION, "abort_ack", fake_ack, [1]), ack_key(PREFIX, MISSION, "agent-1")
        )
        b.publish_control_raw(
            encode_control(MISSION, "status", {**STATUS, "drone": 0}, [1]), status_key(PREFIX, MISSION, 1)
        )
        got = collect_control(a, 4)  # the abort, the status, and the abort's two acknowledgements
        assert eventually(lambda: a.dropped.total() >= 7)
        assert [(e.kind, e.payload, e.origin) for e in got if e.kind != "abort_ack"] == [
            ("abort", {"reason": "operator", "id": "x1"}, (1,)),
            ("status", STATUS, (1,)),
        ]
        # every process hosting agents acknowledges an abort as soon as its bus has it
        acks = sorted((e.origin, e.payload["drones"]) for e in got if e.kind == "abort_ack")
        assert acks == [((0,), [0]), ((1,), [1])]
        assert a.dropped == Counter(
            {
                "control: malformed": 2,
                "control: unknown kind": 1,
                "control: other mission": 1,
                "control: status on the wrong key": 2,
                "control: abort_ack on the wrong key": 1,
            }
        )
        assert a.control_events() == []  # drained
        assert len(collect_control(b, 4)) == 4  # own process sees its commands (and acks) too
        with pytest.raises(ValueError):
            a.publish_control("dance", {})
        with pytest.raises(ValueError):
            a.publish_control("status", {"drone": 0, "x": float("nan")})
        with pytest.raises(ValueError, match="must name a drone this process hosts"):
            a.publish_control("status", STATUS)  # a hosts drone 0, not 1


def test_closed_bus_refuses_to_publish() -> None:
    bus = ZenohBus(ZenohBusConfig(MISSION, {0}, KNOWN, [free_loopback_endpoints()[0]], []))
    bus.close()
    bus.close()  # idempotent
    with pytest.raises(RuntimeError):
        bus.publish(make_msg(0, 1))
    assert bus.wait_for({0: 1}, 5.0) == {0}  # does not block on a closed bus


def test_free_loopback_endpoints_never_repeat() -> None:
    eps = free_loopback_endpoints(20) + [free_loopback_endpoints()[0] for _ in range(20)]
    assert len(set(eps)) == 40 and all(e.startswith("tcp/127.0.0.1:") for e in eps)
