"""Every certificate of a mission tries every key on a live mutual-TLS network (loopback): only a key's
owner is heard (docs/security.md).

One Zenoh session per certificate, each opened as its participant opens it (factory.zenoh_bus_config:
the mission CA, its own pair, the generated access control; listening on its endpoint if the mission
names it, connecting to every endpoint). Each session records, with a raw subscriber on the whole
mission key space and a liveliness subscriber on `alive/**`, everything that reaches it. Then every
certificate puts a real prediction and a real status on every drone's key, an acknowledgement on every
participant's ack key, an abort, and world ticks and commands for every drone, and declares a liveliness
token for every drone it does not own (a session sees its own tokens locally, so each forged token is
watched by the sessions that did not declare it: always the drone's own agent). The expected owners
are written out below from the table of docs/security.md, not read from acl.py.

Two missions of drones 1, 2, 3: one whose endpoints name the shared `agents` process (and the world), and
one whose processes are one agent each (and the world), where the folder still holds a valid `agents`
pair of the same CA from an older `certs` run: that certificate connects like an attacker would.

Checked: a message reaches a receiver only if its certificate may publish that key; every permitted
message reaches every participant it has a link with (the positive control that makes the absences
mean something), and so does each owner's liveliness token after the forged ones were not seen.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from flightstack.comms.certs import files_of
from flightstack.comms.control import encode_control
from flightstack.comms.factory import tls_settings, zenoh_bus_config
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.config.mission import load_mission
from tests.conftest import MISSIONS, eventually, secured_bus, status_payload

zenoh = pytest.importorskip("zenoh")

SIM = MISSIONS / "paper_sim.yaml"
IDS = (1, 2, 3)
AGENTS = tuple(f"agent-{i}" for i in IDS)
EVERY_NAME = (*AGENTS, "agents", "world", "operator", "guard")


def may_put(cn: str, key: str, shared: bool) -> bool:
    """The table of docs/security.md: may certificate `cn` put on `key` (relative to the mission's key space)?
    `shared`: the mission's endpoints name `agents`. Both test missions name `world`."""
    kind, _, arg = key.rpartition("/")
    own_drone = cn == f"agent-{arg}"
    if kind in ("pred", "control/status"):
        return own_drone or (shared and cn == "agents")
    if kind == "control/ack":
        return cn == arg and (arg in AGENTS or (shared and arg == "agents"))
    if kind == "world/cmd":
        return own_drone
    if kind == "world/tick":
        return cn == "world"
    assert key == "control/abort", key
    return cn == "operator"


def may_declare_token(cn: str, drone: int, shared: bool) -> bool:
    return cn == f"agent-{drone}" or (shared and cn == "agents")


def _keys() -> list[str]:
    per_drone = [f"{k}/{i}" for i in IDS for k in ("pred", "control/status", "world/cmd", "world/tick")]
    return [*per_drone, *(f"control/ack/{n}" for n in EVERY_NAME), "control/abort"]


def _payload(name: str, key: str, seq: int) -> bytes:
    """A well-formed message for `key` (what the receiving bus would act on had the ACL let it in)."""
    kind, _, arg = key.rpartition("/")
    if kind == "pred":
        z = np.zeros(4)
        return encode(PredictionMessage(name, int(arg), seq, 0.01 * seq, True, z, z, np.ones(4), np.ones(4)))
    if kind == "control/status":
        return encode_control(name, "status", status_payload(int(arg), flying=False), [int(arg)])
    if kind == "control/ack":
        return encode_control(name, "abort_ack", {"id": "forged", "drones": list(IDS)}, list(IDS))
    if kind == "control/abort":
        return encode_control(name, "abort", {"reason": "forged", "id": f"f{seq}"}, [])
    return b'{"forged": true}'


class Peer:
    """One certificate's Zenoh session and what reached it: (key relative to the space, sender tag)."""

    def __init__(self, cn: str, session: Any, space: str) -> None:
        self.cn, self.session, self.space = cn, session, space
        self.got: set[tuple[str, str]] = set()
        self.tokens: set[str] = set()
        self._lock = threading.Lock()
        self._subs = [
            session.declare_subscriber(f"{space}/**", self._on_sample),
            session.liveliness().declare_subscriber(f"{space}/alive/**", self._on_token),
        ]
        self._tokens: list[Any] = []
        self.declared: set[str] = set()  # its own tokens: its subscriber sees them locally, ACL-free

    def _rel(self, key: object) -> str:
        return str(key)[len(self.space) + 1 :]

    def _on_sample(self, sample: Any) -> None:
        tag = sample.attachment.to_bytes().decode() if sample.attachment is not None else "?"
        with self._lock:
            self.got.add((self._rel(sample.key_expr), tag))

    def _on_token(self, sample: Any) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            with self._lock:
                self.tokens.add(self._rel(sample.key_expr))

    def received(self) -> tuple[set[tuple[str, str]], set[str]]:
        with self._lock:
            return set(self.got), set(self.tokens)

    def put_all(self, name: str, seq: int) -> None:
        for key in _keys():
            self.session.put(f"{self.space}/{key}", _payload(name, key, seq), attachment=self.cn.encode())

    def declare_token(self, drone: int) -> None:
        self._tokens.append(self.session.liveliness().declare_token(f"{self.space}/alive/{drone}"))
        self.declared.add(f"alive/{drone}")

    def close(self) -> None:
        for t in self._tokens:
            t.undeclare()
        self.session.close()


def _arg(cn: str) -> tuple[str, set[int]]:
    """factory.make_bus's participant argument and hosted drones for certificate `cn`."""
    if cn.startswith("agent-"):
        return cn[6:], {int(cn[6:])}
    return cn, (set(IDS) if cn == "agents" else set())


def _open_all(tmp: Path, endpoints: tuple[str, ...], stale: tuple[str, ...]) -> tuple[dict[str, Peer], Any]:
    """A session per participant of a mission whose endpoints are `endpoints`; `stale`: certificates an
    older `certs` run left in the folder (same CA), connecting to every endpoint without being named."""
    from flightstack.comms.zenoh_config import ZenohBusConfig, zenoh_config

    name = load_mission(SIM).name
    certs = tmp / "certs"
    bus = secured_bus(certs, name, list(IDS), (*endpoints, *stale), lease_ms=1000)
    for s in stale:  # the mission was edited since: it no longer names them
        del bus["zenoh"]["endpoints"][s]
    mission = load_mission(SIM, {"bus": bus})
    space = f"flightstack/{name}"
    participants = [*AGENTS, *(n for n in ("agents", "world") if n in endpoints), "operator", "guard"]
    peers: dict[str, Peer] = {}
    try:
        for cn in participants:
            peers[cn] = Peer(cn, zenoh.open(zenoh_config(zenoh_bus_config(mission, *_arg(cn)))), space)
        for cn in stale:
            cfg = ZenohBusConfig(
                mission=name,
                self_ids=set(IDS),
                known_senders=set(IDS),
                connect=list(bus["zenoh"]["endpoints"].values()),
                tls=dict(tls_settings(files_of(certs, cn))),
                participant=cn,
            )
            peers[f"stale {cn}"] = Peer(cn, zenoh.open(zenoh_config(cfg)), space)
    except BaseException:
        for p in peers.values():
            p.close()
        raise
    return peers, mission


def _run_matrix(tmp: Path, endpoints: tuple[str, ...], stale: tuple[str, ...] = ()) -> None:
    t0 = time.monotonic()
    peers, mission = _open_all(tmp, endpoints, stale)
    shared = "agents" in endpoints
    listeners = {("agent-" + n if n.isdigit() else n) for n in endpoints}
    members = {k: p for k, p in peers.items() if not k.startswith("stale ")}

    def linked(a: Peer, b: Peer) -> bool:
        return a is not b and (a.cn in listeners or b.cn in listeners) and a.cn != b.cn

    try:
        # links: a listener has a link with every other session, a connecting-only one with the listeners
        def meshed() -> bool:
            return all(
                len(list(p.session.info.peers_zid())) >= sum(linked(p, q) for q in peers.values())
                for p in peers.values()
            )

        assert eventually(meshed, 20.0), {k: len(list(p.session.info.peers_zid())) for k, p in peers.items()}
        # forged tokens first, so they have had the whole put phase to (not) arrive
        for p in peers.values():
            for i in IDS:
                if not (p in members.values() and may_declare_token(p.cn, i, shared)):
                    p.declare_token(i)
        keys = _keys()
        wanted = {
            (r.cn, key, p.cn)
            for p in members.values()
            for r in members.values()
            for key in keys
            if linked(p, r) and may_put(p.cn, key, shared)
        }

        def missing() -> set[tuple[str, str, str]]:
            return {(r, k, s) for r, k, s in wanted if (k, s) not in members[r].received()[0]}

        seq, deadline = 0, time.monotonic() + 20.0
        while missing() and time.monotonic() < deadline:
            seq += 1
            for p in peers.values():
                p.put_all(mission.name, seq)
            time.sleep(0.05)
        for _ in range(3):  # a few more rounds after the last permitted message arrived
            seq += 1
            for p in peers.values():
                p.put_all(mission.name, seq)
            time.sleep(0.05)
        time.sleep(0.3)
        t_puts = time.monotonic() - t0
        assert not missing(), f"permitted messages that never arrived: {sorted(missing())[:10]}"
        for r in peers.values():
            got, tokens = r.received()
            foreign = {(k, s) for k, s in got if s != r.cn}  # its own puts reach it locally, ACL-free
            allowed = {(k, s) for k, s in foreign if may_put(s, k, shared) and s in members}
            assert foreign == allowed, f"{r.cn} heard forgeries: {sorted(foreign - allowed)}"
            # every certificate declared each token it does not own, so each forged (certificate, drone)
            # is watched at least by that drone's agent, which declared none and has a link to everyone
            forged = sorted(tokens - r.declared)
            assert not forged, f"{r.cn} saw forged liveliness tokens {forged}"
        for k in (k for k in peers if k.startswith("stale ")):  # a stale certificate may not even read
            got, tokens = peers[k].received()
            assert {m for m in got if m[1] != peers[k].cn} == set() and tokens <= peers[k].declared, got
        n_sent = seq * len(peers) * len(keys)
        # positive control for tokens: each drone's own agent declares its token, and every participant
        # with a link to it sees it
        for i in IDS:
            members[f"agent-{i}"].declare_token(i)
        expected_tokens = {f"alive/{i}" for i in IDS}
        assert eventually(
            lambda: all(p.received()[1] >= expected_tokens - {f"alive/{p.cn[6:]}"} for p in members.values()),
            10.0,
        ), {k: p.received()[1] for k, p in members.items()}
        print(
            f"endpoints {endpoints} stale {stale}: {len(peers)} certificates x {len(keys)} keys, "
            f"{seq} rounds ({n_sent} puts), {len(wanted)} permitted deliveries all arrived, no forgery "
            f"heard; {t_puts:.1f} s to the last put, {time.monotonic() - t0:.1f} s in all"
        )
    finally:
        for p in peers.values():
            p.close()


def test_where_the_mission_names_agents_only_the_owner_and_agents_are_heard(tmp_path: Path) -> None:
    _run_matrix(tmp_path, ("agents", "world", "1", "2", "3"))


def test_a_mission_of_one_agent_each_hears_a_drone_only_from_its_own_agent(tmp_path: Path) -> None:
    _run_matrix(tmp_path, ("world", "1", "2", "3"), stale=("agents",))


def test_a_certificate_the_mission_does_not_name_reads_nothing_while_it_connects(tmp_path: Path) -> None:
    """A Zenoh peer sends data on a new link before that link's subscriber declarations are settled: the
    moment a stale certificate connects is when a participant already publishing could leak to it."""
    peers, mission = _open_all(tmp_path, ("world", "1", "2", "3"), ("agents",))
    peers.pop("stale agents").close()  # its certificate stays in the folder
    space = f"flightstack/{mission.name}"
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            for p in peers.values():
                p.put_all(mission.name, seq)
            time.sleep(0.002)

    from flightstack.comms.zenoh_config import ZenohBusConfig, zenoh_config

    bus = mission.bus.zenoh
    thread = threading.Thread(target=publish, daemon=True)
    stale: list[Peer] = []
    try:
        thread.start()
        for _ in range(5):  # five connections, each with its own settling window
            cfg = ZenohBusConfig(
                mission=mission.name,
                self_ids=set(IDS),
                known_senders=set(IDS),
                connect=list(bus.endpoints.values()),
                tls=dict(tls_settings(files_of(tmp_path / "certs", "agents"))),
                participant="agents",
            )
            stale.append(Peer("agents", zenoh.open(zenoh_config(cfg)), space))
        assert eventually(lambda: all(len(list(s.session.info.peers_zid())) >= 4 for s in stale), 20.0)
        time.sleep(1.0)
    finally:
        stop.set()
        thread.join(5.0)
        for s in stale:
            s.close()
        for p in peers.values():
            p.close()
    heard = [sorted(m for m in s.received()[0] if m[1] != "agents") for s in stale]
    assert all(not h for h in heard), heard
