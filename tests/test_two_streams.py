"""Two streams under one identity and label (flightstack/comms/streams.py), and what the Zenoh bus does
about them (identity.py: the id quarantined for the run, reported once by name).

Unit: the receive path (Freshness) against an honest sender whose messages the network repeats or
reorders (never evidence), a sender counting again from 0 (one restart, an event naming it, no evidence
of two streams), copies that keep their seq 1, 2, 20, 500 or 1000 ahead of the real sender, or behind it,
at the same rate with in-bounds values (each is found, and the number of the copy's messages accepted
before is bounded: `max_reorder` + 2), a holder of the key putting one message 1–20 ahead per cycle or
one per 1,001 (each read once, found at the second), a copy taking the id by the restart rule (the real
count resuming takes it back), and the restarts in an agent's status and `flightstack status`.
"""

from __future__ import annotations

import random

import numpy as np
import pytest

from flightstack.cli.network import status_table
from flightstack.comms.acceptance import AcceptanceBounds
from flightstack.comms.bus import InProcBus, restart_counts
from flightstack.comms.control import StatusReport
from flightstack.comms.freshness import Freshness
from flightstack.comms.identity import SessionBook
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.comms.streams import DUPLICATE, StreamWatch, digest

pytestmark = pytest.mark.unit

MISSION = "streams_test"
BOUNDS = AcceptanceBounds()


def _msg(seq: int, mu: float = 0.1, sender: int = 1) -> bytes:
    v = np.full(4, 0.1)
    m = np.array([mu, 0.0, 0.0, 0.0])
    return encode(PredictionMessage(MISSION, sender, seq, 0.01 * seq, True, v, m, v, v))


def _book() -> Freshness:
    return Freshness(MISSION, {1, 2}, "stamps", bounds=BOUNDS)


def test_duplicates_and_reordering_of_an_honest_sender_are_not_two_streams() -> None:
    book = _book()
    rng = random.Random(7)
    seqs = list(range(1, 3001))
    # the network: every message may come twice, pairs swap, some arrive up to max_reorder late
    out: list[int] = []
    i = 0
    while i < len(seqs):
        r = rng.random()
        if r < 0.2 and i + 1 < len(seqs):
            out += [seqs[i + 1], seqs[i]]
            i += 2
            continue
        if r < 0.25 and i + BOUNDS.max_reorder < len(seqs):
            late = seqs[i]
            out += [*seqs[i + 1 : i + 1 + BOUNDS.max_reorder], late]
            i += 1 + BOUNDS.max_reorder
            continue
        out.append(seqs[i])
        i += 1
    wire = []
    for q in out:
        wire.append(_msg(q, mu=0.001 * q))
        if rng.random() < 0.3:
            wire.append(_msg(q, mu=0.001 * q))  # an identical copy
    for _ in range(200):  # late duplicates, up to 500 messages after their original (the window: 1000)
        p = rng.randrange(1, len(wire))
        wire.insert(p, wire[rng.randrange(max(0, p - 500), p)])
    for data in wire:
        book.accept(data)
    assert book.streams.found == {}
    assert book.dropped["old or duplicate seq"] > 500
    assert book.newest[1].seq == 3000


def test_a_sender_counting_from_zero_again_under_one_label_is_not_two_streams() -> None:
    book = _book()
    for q in range(1, 301):
        book.accept(_msg(q))
    for q in range(1, 301):  # the same sender restarted its count (another mode): other payloads
        book.accept(_msg(q, mu=0.2))
    assert book.streams.found == {}
    assert book.restarts[1] == 1 and book.newest[1].seq == 300


@pytest.mark.parametrize("lead", [1, 2, 20, 500, 999, -1, -30])
def test_a_copy_ahead_or_behind_at_the_same_rate_is_found(lead: int) -> None:
    """Real sender and copy alternate (same rate); the copy sends seq real + lead with μ = 9.9 m/s."""
    book = _book()
    for q in range(1, 2001):  # a live sender first
        book.accept(_msg(q))
    forged_used = 0
    found_after = None
    for k, q in enumerate(range(2001, 4001)):
        book.accept(_msg(q + lead, mu=9.9))
        newest = book.newest[1]
        forged_used += newest.mu[0] == 9.9 and newest.seq == q + lead
        book.accept(_msg(q))
        if 1 in book.streams.found:
            found_after = k + 1
            break
    assert found_after is not None, (lead, book.dropped)
    print(f"lead {lead}: found after {found_after} real messages; {forged_used} forged accepted")
    assert forged_used <= BOUNDS.max_reorder + 2
    assert "two streams interleave" in book.streams.found[1]


def test_evidence_counts_when_the_streams_interleave_and_a_restart_discards_it() -> None:
    """A refused message's evidence waits for the sender's next accepted message: a plain one confirms it
    (the streams interleave), one taken by the restart rule discards it; confirmed pieces count however
    far apart they are."""
    w = StreamWatch(window=100, max_reorder=4, quarantine_after=2)
    for q in range(40, 51, 2):
        w.accepted(1, q, digest(b"%d" % q))
    assert w.refused_old(1, 47, b"x", 50) is None  # late (3 behind), remembered
    assert w.refused_old(1, 47, b"x", 50) == DUPLICATE
    assert w.refused_old(1, 10, b"x", 50) == "seq 10 arrived 40 behind the newest"
    assert w.refused_old(1, 11, b"y", 50) == "seq 11 arrived 39 behind the newest"
    w.accepted(1, 12, b"z", restart=True, left=50)  # the count before stopped: a restart, no evidence
    assert w.evidence.get(1, 0) == 0 and w.found == {}
    for q in range(13, 400):  # the new count passes where the old one stopped, and far beyond
        w.accepted(1, q, digest(b"%d" % q))
    assert w.refused_old(1, 350, b"other", 399) == "two payloads under seq 350"
    assert w.evidence.get(1, 0) == 0  # pending
    w.accepted(1, 400, digest(b"400"))  # the stream it fell behind goes on: confirmed
    assert w.evidence[1] == 1 and w.found == {}
    for q in range(401, 2000):  # more than a window apart
        w.accepted(1, q, digest(b"%d" % q))
    w.accepted(1, 2001, b"skip")  # a skip over 2000 (the gap rule of acceptance.py gives 2000 the id)
    w.accepted(1, 2000, digest(b"2000"))
    w.accepted(1, 2001, digest(b"2001"))  # the stream reaches the skipping seq with other bytes
    assert w.found == {1: "two payloads under seq 2001 (2 pieces of evidence: two streams interleave)"}
    with pytest.raises(ValueError):
        StreamWatch(window=4, max_reorder=5)


def test_a_count_resumed_after_a_restart_is_evidence() -> None:
    """A copy that takes the id through the restart rule (three messages below the real count, between two
    of the real sender's): the real count going on above it is evidence at once and takes the id back, so
    the copy is the newest on one reading per attempt; its second attempt establishes two streams."""
    book = _book()
    for q in range(1, 301):
        book.accept(_msg(q))
    forged_reads = 0
    for q in range(301, 320):
        if q in (301, 310):
            for c in (q - 200, q - 199, q - 198):  # the copy counts from 200 below the real sender again
                book.accept(_msg(c, mu=9.9))
            forged_reads += book.newest[1].mu[0] == 9.9  # a reading between the copy and the real one
        book.accept(_msg(q))
        forged_reads += book.newest[1].mu[0] == 9.9
        if 1 in book.streams.found:
            break
    assert book.restarts[1] == 2 and [e.kind for e in book.restart_events] == ["restart", "restart"]
    assert book.restart_events[0].detail.startswith("agent-1: taken again at seq 103 after 3 consecutive")
    assert "its newest was seq 300" in book.restart_events[0].detail
    assert book.streams.found[1].startswith("seq 310 resumes the count that stopped at 309 before a restart")
    assert forged_reads == 2 and book.newest[1].seq == 310 and book.newest[1].mu[0] == 0.1


def test_a_quarantined_id_is_refused_for_the_rest_of_the_run_and_reported_once() -> None:
    book = SessionBook()
    book.own(2, "me", 0.0)
    assert book.admit(1, "A", 0.0)
    book.claim(1, "A", 0.0)
    book.quarantine(1, "A", 1.0, "two payloads under seq 5, interleaved with accepted messages (2 refused)")
    book.quarantine(1, "A", 1.1, "again")
    assert not book.admit(1, "A", 1.2)
    book.forget(1)  # every session of it left: still quarantined
    assert not book.admit(1, "B", 2.0) and book.admit(2, "me", 2.0)
    assert book.dropped == {1: 2}
    assert [e.text for e in book.events] == [
        "agent-1: two sessions publish under one label (A) as drone 1: two payloads under seq 5, "
        "interleaved with accepted messages (2 refused); both dropped for the rest of the run"
    ]


def test_a_copy_beyond_the_seq_jump_bound_is_never_used() -> None:
    book = _book()
    for q in range(1, 4001):
        book.accept(_msg(q + 1000, mu=9.9))  # one more than max_seq_jump ahead of the newest
        book.accept(_msg(q))
    assert book.newest[1].seq == 4000 and book.streams.found == {}
    assert book.dropped == {"seq jump": 4000}


def test_a_faster_copy_that_restarts_itself_past_the_real_sender_is_found() -> None:
    """Three messages per real one, each 600 ahead of the last: runs of the restart rule take the copy."""
    book = _book()
    for q in range(1, 101):
        book.accept(_msg(q))
    c, forged_used = 2000, 0
    for q in range(101, 1101):
        for _ in range(3):
            c += 600
            book.accept(_msg(c, mu=9.9))
            forged_used += book.newest[1].seq == c
            if 1 in book.streams.found:
                break
        book.accept(_msg(q))
        if 1 in book.streams.found:
            break
    assert 1 in book.streams.found, book.dropped
    print(f"faster copy: found after {q - 100} real messages; {forged_used} forged accepted")
    assert forged_used <= 6  # two restart runs of the copy per real message, until found


def _one_ahead_per_cycle(jump: int, every: int | None, ticks: int) -> tuple[Freshness, dict[int, int], int]:
    """A live sender at one message per tick, and a holder of its key that puts one message `jump` seqs
    ahead of the real one right after it (μ = 9.9 m/s, the stamp the real sender will put on that seq),
    again when the real sender has passed it, or (`every`) once per that many real messages. The reading
    after each message is what a fusion would take. Returns the book, forged seq → readings, messages sent."""
    book = _book()
    for q in range(1, 101):
        book.accept(_msg(q))
    reads: dict[int, int] = {}
    forged, sent = None, 0
    for q in range(101, 101 + ticks):
        book.accept(_msg(q))
        newest = book.newest[1]
        if newest.mu[0] == 9.9:
            reads[newest.seq] = reads.get(newest.seq, 0) + 1
        due = (q - 101) % every == 0 if every else forged is None or q > forged
        if due and 1 not in book.streams.found:  # the bus quarantines a found id (zenoh_bus.py)
            forged, sent = q + jump, sent + 1
            book.accept(_msg(forged, mu=9.9))
        newest = book.newest[1]
        if newest.mu[0] == 9.9:  # a reading between the copy and the real sender's next message
            reads[newest.seq] = reads.get(newest.seq, 0) + 1
    return book, reads, sent


@pytest.mark.parametrize("jump", range(1, 21))
def test_one_message_ahead_per_cycle_is_read_once_and_found(jump: int) -> None:
    """One forged message 1–20 seqs ahead, again each time the real sender passes it (before: a jump of
    4–17 was taken back by the restart rule, which forgot the forged seq and recorded no evidence, so the
    copy was the newest at 3 of every `jump` readings for the whole run): each forged message is the
    newest on one reading, never a restart, and the second establishes two streams."""
    book, reads, sent = _one_ahead_per_cycle(jump, None, 3000)
    assert 1 in book.streams.found, (book.dropped, book.streams.evidence)
    assert sent <= BOUNDS.quarantine_after and max(reads.values()) == 1 and len(reads) == sent, reads
    assert book.restarts[1] == 0 and book.restart_events == []
    assert book.newest[1].seq == 3100 and book.newest[1].mu[0] == 0.1


def test_a_low_rate_copy_is_found_across_any_distance() -> None:
    """One forged message per 1,001 real ones, 5 ahead (before: its evidence lay more than a window apart
    and never established two streams): found at its second message, each read once."""
    book, reads, sent = _one_ahead_per_cycle(5, 1001, 3000)
    assert 1 in book.streams.found and sent == 2 and reads == {106: 1, 1107: 1}, (
        reads,
        book.streams.evidence,
    )


def test_every_restart_is_an_event_naming_the_sender() -> None:
    book = _book()
    for q in range(5000, 5003):  # a receiver joining a live sender
        book.accept(_msg(q, sender=2))
    for q in range(1, 301):
        book.accept(_msg(q))
    for q in range(1, 4):  # the same sender counting again (another mode)
        book.accept(_msg(q, mu=0.2))
    assert book.restarts == {2: 1, 1: 1}
    assert [(e.drone, e.kind, e.source) for e in book.restart_events] == [
        (2, "restart", "bus"),
        (1, "restart", "bus"),
    ]
    assert book.restart_events[0].detail == (
        "agent-2: taken again at seq 5002 after 3 consecutive messages outside the sequence rules "
        "(nothing heard before); restart 1"
    )
    assert (
        book.restart_events[1].detail.startswith("agent-1: taken again at seq 3 ") and not book.streams.found
    )


def test_a_status_shows_the_restarts_its_bus_took_by_name() -> None:
    """What an agent's status reports (fleet.StatusPublisher: restart_counts of its bus's events) and what
    `flightstack status` prints of it."""
    bus = InProcBus(MISSION, {1, 2})
    for q in range(1, 301):
        bus.publish_raw(_msg(q, sender=2))
    for q in range(1, 4):  # sender 2 counting again
        bus.publish_raw(_msg(q, mu=0.2, sender=2))
    counts = restart_counts(bus.presence_events)
    assert counts == {"agent-2": 1}
    payload = {
        "drone": 1, "mode": "dgp", "t": 3.0, "tick": 300, "battery_pct": 80.0, "flying": True,
        "link_alive": True, "visible": True, "n_fused": 2, "pose_fresh": True, "rejection": None,
        "dropped": dict(bus.dropped), "restarts": counts,
    }  # fmt: skip
    report = StatusReport.from_payload(payload)
    assert report is not None and report.restarts == (("agent-2", 1),)
    assert StatusReport.from_payload({**payload, "restarts": {"agent-2": -1}}) is None
    row = status_table({1: (report, 10.0)}, {1}, [1], 10.5).splitlines()[1]
    assert row.endswith("dropped old or duplicate seq: 2; restarts agent-2: 1"), row
