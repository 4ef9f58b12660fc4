"""Two streams under one identity and label (flightstack/comms/streams.py), and what the Zenoh bus does
about them (identity.py: the id quarantined for the run, reported once by name).

Unit: the receive path (Freshness) against an honest sender whose messages the network repeats or
reorders (never evidence), a sender counting again from 0 (one restart, no evidence of two streams), and
copies that keep their seq 1, 2, 20, 500 or 1000 ahead of the real sender, or behind it, at the same
rate with in-bounds values: each is found, and the number of the copy's messages accepted before is
bounded (`max_reorder` + 2).
"""

from __future__ import annotations

import random

import numpy as np
import pytest

from flightstack.comms.acceptance import AcceptanceBounds
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
    assert "interleaved with accepted messages" in book.streams.found[1]


def test_evidence_alone_or_long_apart_is_not_two_streams() -> None:
    w = StreamWatch(window=100, max_reorder=4)
    for q in range(40, 51, 2):
        w.accepted(1, q, digest(b"%d" % q))
    assert w.refused_old(1, 47, b"x", 50) is None  # late (3 behind), remembered
    assert w.refused_old(1, 47, b"x", 50) == DUPLICATE
    assert w.refused_old(1, 10, b"x", 50) == "seq 10 arrived 40 behind the newest"
    assert w.refused_old(1, 11, b"y", 50) == "seq 11 arrived 39 behind the newest"  # nothing accepted between
    assert w.found == {}
    for q in range(51, 202):  # more than a window of accepted messages
        w.accepted(1, q, digest(b"%d" % q))
    assert w.refused_old(1, 150, b"z", 201) == "two payloads under seq 150"
    assert w.found == {}
    w.accepted(1, 202, digest(b"202"))
    assert w.refused_old(1, 202, digest(b"202"), 202) == DUPLICATE
    assert w.refused_old(1, 199, digest(b"other"), 202) == "two payloads under seq 199"
    assert w.found == {1: "two payloads under seq 199, interleaved with accepted messages (4 refused)"}
    w.accepted(1, 203, digest(b"203"))
    assert w.refused_old(1, 47, b"other", 203) not in (None, DUPLICATE)  # evidence, kept or not
    with pytest.raises(ValueError):
        StreamWatch(window=4, max_reorder=5)


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
        book.accept(_msg(q))
        if 1 in book.streams.found:
            break
    assert 1 in book.streams.found, book.dropped
    print(f"faster copy: found after {q - 100} real messages; {forged_used} forged accepted")
    assert forged_used <= 6  # two restart runs of the copy per real message, until found
