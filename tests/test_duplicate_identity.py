"""One identity, one session (flightstack/comms/identity.py) and the world-tick bounds at the agent
(sim_backend/served/tick_gate.py).

Unit: the session book, the world's cmd path with two sessions for one drone, and the tick gate (future
tick, t ≠ k·dt, gap, old tick: counted by reason, later valid ticks still accepted).
System: the same id from two Zenoh sessions on loopback (buses in this process), and a served flight
that a second `flightstack agent --id 1` process joins: it is reported by name, and the run completes
with its recordings and metrics.
"""

from __future__ import annotations

import threading
from collections import defaultdict

import pytest

from flightstack.comms.identity import MAX_LABEL_CHARS, UNLABELLED, SessionBook, parse_label
from flightstack.config.mission import load_mission
from flightstack.runtime.backends import build_backend
from flightstack.sim_backend.served import messages as wm
from flightstack.sim_backend.served.client import _Link
from flightstack.sim_backend.served.server import WorldServer
from flightstack.sim_backend.served.tick_gate import TickBounds, tick_refusal
from tests.conftest import MISSIONS
from tests.test_world_messages import tick_header

DT = 0.01
STEP_S = 2.0  # the world's lock-step timeout (s): it goes on without an agent's cmd after this long


class FakeSession:
    """What _Link declares on a zenoh session; the publisher keeps what was put, with its attachment."""

    def __init__(self) -> None:
        self.sent: list[tuple[bytes, object]] = []

    def declare_publisher(self, key: str, **_: object) -> FakeSession:
        return self

    def declare_subscriber(self, key: str, callback: object) -> FakeSession:
        return self

    def put(self, data: bytes, attachment: object = None) -> None:
        self.sent.append((bytes(data), attachment))

    def undeclare(self) -> None:
        pass


# ---------------------------------------------------------------- session book (unit)
def test_the_first_session_keeps_the_id_and_a_second_is_reported_once() -> None:
    book = SessionBook()
    assert book.admit(1, "A", 0.0)  # nobody owns 1 yet
    book.claim(1, "A", 0.0)
    assert book.admit(1, "A", 0.1)
    assert not book.admit(1, "B pid 7 on x", 0.2)
    assert not book.admit(1, "B pid 7 on x", 0.3)
    assert book.admit(2, "B pid 7 on x", 0.3)  # another id: B may claim it
    book.claim(2, "B pid 7 on x", 0.3)
    assert book.dropped == {1: 2}
    assert [(e.sender, e.kind, e.session, e.owner) for e in book.events] == [
        (1, "second session", "B pid 7 on x", "A")
    ]
    assert book.events[0].text.startswith("agent-1: a second session (B pid 7 on x) publishes as drone 1")
    assert book.contested(1) and not book.contested(2)
    assert book.silent_for(1, 5.0) == pytest.approx(4.9)  # the owner was last heard at 0.1 s
    book.forget(1)  # every session of 1 left the bus: the next one to speak claims it
    assert book.admit(1, "C", 6.0) and book.owner(1) is None
    book.claim(1, "C", 6.0)
    assert book.owner(1) == "C"


def test_a_refused_message_never_claims_an_id() -> None:
    """The bus claims an id only after its receive checks passed (a forged first message must not lock
    the real sender out); `own` claims the process's own ids before anything is heard."""
    book = SessionBook()
    book.own(3, "me", 0.0)
    assert not book.admit(3, "other", 0.1) and book.owner(3) == "me"
    assert book.admit(4, "forger", 0.1)  # admitted to the checks, which refuse it: no claim
    assert book.owner(4) is None


def test_labels_are_bounded_printable_ascii() -> None:
    assert parse_label(b"0123abcd pid 12 on host") == "0123abcd pid 12 on host"
    for bad in (None, b"", b"\xff\xfe", b"a\nb", b"x" * (MAX_LABEL_CHARS + 1)):
        assert parse_label(bad) == UNLABELLED


# ---------------------------------------------------------------- the world's cmd path (unit)
def _world() -> WorldServer:
    """The world's cmd bookkeeping on a real simulated backend, without Zenoh (as in
    tests/test_decoders_property.served_world)."""
    mission = load_mission(MISSIONS / "paper_sim.yaml")
    srv = object.__new__(WorldServer)
    srv.mission, srv.ids, srv.backend = mission, [d.id for d in mission.drones], build_backend(mission)
    srv._cond, srv._queued = threading.Condition(), defaultdict(list)
    srv._done_k, srv._tick_k, srv._dropped = {i: -2 for i in srv.ids}, 5, {}
    srv._sessions, srv._n_reported = SessionBook("sends commands as"), 0
    from flightstack.sim_backend.served.server import WorldSummary

    srv.summary = WorldSummary()
    srv.log = srv.summary.events.append  # type: ignore[method-assign,assignment]
    return srv


def _cmd(k: int, *calls: str) -> bytes:
    return wm.encode_cmd(wm.WorldCmd(k, tuple(wm.DroneCall(c) for c in calls)))


def test_the_world_obeys_the_session_that_said_hello_first() -> None:
    srv = _world()
    key = "flightstack/m/world/cmd/1"
    assert srv.receive_cmd(key, _cmd(-1), "genuine") is None  # hello: claims drone 1
    assert srv.receive_cmd(key, _cmd(-1), "dup pid 9 on h") == "second session"
    assert srv.receive_cmd(key, _cmd(3, "emergency_stop"), "dup pid 9 on h") == "second session"
    assert srv.receive_cmd(key, _cmd(3, "land"), "genuine") is None
    assert srv._done_k[1] == 3 and [c.calls[0].name for c in srv._queued[1][1:]] == ["land"]
    assert srv._dropped == {"second session": 2}
    srv._report_sessions(0.03)  # the main loop logs and records it once, naming the participant
    srv._report_sessions(0.04)
    assert len(srv.summary.events) == 2  # one Event, one log line
    ev = srv.summary.events[0]
    assert (
        ev.kind == "second session" and ev.drone == 1 and "agent-1: a second session (dup pid 9" in ev.detail
    )


# ---------------------------------------------------------------- world ticks at the agent (unit)
def _tick(k: int, t: float | None = None) -> bytes:
    h = tick_header(k)
    h["t"] = k * DT if t is None else t
    h["frame"]["stamp"] = h["t"]
    return wm.pack(h)


def test_tick_bounds_refuse_future_and_mistimed_ticks_without_poisoning_later_ones() -> None:
    bounds = TickBounds(DT, STEP_S)
    link = _Link(FakeSession(), "p", "m", 1, 1.0, bounds)
    link.hello(now=100.0)  # the reference of the first tick: the world starts after every hello
    assert link.receive(_tick(2**20), now=100.1) == "tick from the future"
    assert link.receive(_tick(0), now=100.2) is None
    assert link.receive(_tick(1), now=100.21) is None
    assert link.receive(_tick(7_000_000), now=100.22) == "tick from the future"  # today's poison
    assert link.receive(_tick(2), now=100.23) is None  # not made "old" by the refused one
    assert link.receive(_tick(3, t=0.5), now=100.24) == "tick time off its index"
    assert link.receive(_tick(3, t=3 * DT + 1e-9), now=100.25) is None  # rounding of t += dt
    assert link.receive(_tick(3), now=100.26) == "old tick"  # a duplicate
    assert link.receive(_tick(2), now=100.27) == "old tick"  # a replay
    # a gap within what the world can do: after 4.6 s without our cmd it can be ⌊(4.6 + 0.5)/2⌋ = 2
    # timed-out ticks further, plus the margin of 2 and the one our cmd allowed: at most 3 + 5 = 8
    assert link.receive(_tick(9), now=104.85) == "tick from the future"
    assert link.receive(_tick(8), now=104.85) is None
    assert link.receive(_tick(9), now=104.86) is None
    assert link.tick().k == 9 and link.tick().t == 9 * DT
    assert link.dropped == {"tick from the future": 3, "tick time off its index": 1, "old tick": 2}
    assert link.gaps == {"gaps": 1, "ticks skipped": 4}


def test_tick_bound_is_the_lockstep_protocol() -> None:
    """max_k against the protocol written out: one tick at once (our cmd), then one per timed-out wait."""
    b = TickBounds(DT, STEP_S, latency_s=0.0, margin_ticks=0)
    assert [b.max_k(10, s) for s in (0.0, 1.99, 2.0, 5.9, 6.0)] == [11, 11, 12, 13, 14]
    assert tick_refusal(None, wm.decode_tick(_tick(5))[0], b, 0.0, 0.0) == "tick from the future"  # type: ignore[arg-type]
    assert tick_refusal(None, wm.decode_tick(_tick(0))[0], b, 0.0, 0.0) is None  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        TickBounds(0.0, STEP_S)
