"""What a received prediction may claim (flightstack/comms/acceptance.py, freshness.py).

The forgeries that once worked, against the receive path of both buses, in both time bases: one
message with seq 2³²−1 and stamp 1e300 took over a sender's slot for good; a variance of 5e-324 made the
fused μ NaN. Now they are counted by reason, never raise, and the real sender is heard again within
`restart_after` messages.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flightstack.comms.acceptance import AcceptanceBounds
from flightstack.comms.bus import InProcBus
from flightstack.comms.freshness import Freshness
from flightstack.comms.messages import PredictionMessage
from flightstack.paper.fusion import FUSION_RULES, fuse
from tests.attacker_peer import prediction

MISSION = "acc"
KNOWN = {1, 2}


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def real(sender: int, seq: int, stamp: float, var: float = 0.01) -> bytes:
    return prediction(MISSION, sender, seq, stamp, var)


def test_slot_takeover_is_bounded_in_lockstep() -> None:
    book = Freshness(MISSION, KNOWN, "stamps")
    assert book.accept(real(2, 1, 0.01)) is not None
    assert book.accept(real(2, 2**32 - 1, 1e300)) is None  # a jump of 4e9 sequence numbers
    assert book.dropped == {"seq jump": 1}
    for k in range(2, 50):
        assert book.accept(real(2, k, 0.01 * k)) is not None
    assert book.latest(2, 0.49, 0.5).seq == 49  # type: ignore[union-attr]


def test_a_forged_first_message_is_refused_and_locks_nobody_out() -> None:
    """Forged before the real sender's first message (seq 2³²−1): refused as a seq jump, since a sender
    counts from 0 or 1 (issue 18: once accepted, it held the slot for `restart_after` ticks and changed a
    flight); repeating it never makes a restart run. The real sender is heard from its first message."""
    bounds = AcceptanceBounds()
    book = Freshness(MISSION, KNOWN, "stamps", bounds=bounds)
    for _ in range(2 * bounds.restart_after):
        assert book.accept(real(2, 2**32 - 1, 1e300)) is None
    assert book.dropped["seq jump"] == 2 * bounds.restart_after and book.latest(2, 0.0, 0.5) is None
    assert all(book.accept(real(2, k, 0.01 * k)) is not None for k in range(1, 10))
    assert book.restarts[2] == 0 and book.dropped["old or duplicate seq"] == 0
    assert book.latest(2, 0.09, 0.5).seq == 9  # type: ignore[union-attr]


def test_joining_a_live_sender_takes_it_after_a_restart_run() -> None:
    """A receiver that starts while a sender is already at seq 5000 (its first message is beyond
    max_seq_jump): taken on the `restart_after`-th consecutive increasing message."""
    bounds = AcceptanceBounds()
    book = Freshness(MISSION, KNOWN, "stamps", bounds=bounds)
    accepted = [book.accept(real(2, 5000 + k, 0.01 * k)) is not None for k in range(6)]
    assert accepted == [False] * (bounds.restart_after - 1) + [True] * (6 - bounds.restart_after + 1)
    assert book.restarts[2] == 1


def test_forged_stamp_cannot_become_the_learned_offset() -> None:
    """Time base "receiver": the forged stamp arrives first in the join window; the offset is learned
    from the real messages, and the forged one is never used."""
    clock = Clock()
    book = Freshness(MISSION, KNOWN, "receiver", clock)
    skew = 600.0  # the sender's clock is 10 min ahead
    assert book.accept(real(2, 2**32 - 1, 1e300)) is None  # first, but not a sender's first seq
    seen = []
    for k in range(1, 40):
        clock.t += 0.02
        book.accept(real(2, k, clock.t + skew - 0.002))
        seen.append(book.latest(2, math.nan, 0.5))
    offset = book.offset(2)
    assert offset is not None and abs(offset - (-skew + 0.002)) < 1e-6
    assert seen[-1] is not None and seen[-1].seq == 39
    clock.t += 0.02
    assert book.accept(real(2, 40, 1e300)) is None  # later: refused outright
    assert book.dropped["stamp ahead"] + book.dropped["stamp outlier"] >= 1


def test_values_outside_the_bounds_are_dropped_and_fusion_stays_finite() -> None:
    bus = InProcBus(MISSION, KNOWN)
    bus.publish_raw(real(1, 1, 0.0, var=5e-324))
    bus.publish_raw(prediction(MISSION, 2, 1, 0.0, 0.01, mu=1e6))
    assert bus.latest(1, 0.0, 0.5) is None and bus.latest(2, 0.0, 0.5) is None
    assert bus.dropped == {"variance out of bounds": 1, "mu out of bounds": 1}
    # the smallest accepted variance cannot overflow any fusion rule
    tiny = AcceptanceBounds().var_floor
    mu = np.array([[0.3, -0.2, 0.0, 0.1], [0.1, 0.0, 0.0, 0.0]])
    var = np.array([[tiny] * 4, [0.01] * 4])
    prior = np.ones((2, 4))
    for rule in FUSION_RULES:
        m, v = fuse(mu, var, rule, prior)
        assert np.all(np.isfinite(m)) and np.all(np.isfinite(v)), rule


forged = st.builds(
    lambda seq, stamp, var, mu: prediction(MISSION, 2, seq, stamp, var, mu),
    st.integers(0, 2**32 - 1),
    st.one_of(st.floats(-1e300, 1e300), st.sampled_from([0.0, 1e300, -1e300])),
    st.one_of(st.floats(5e-324, 1e300), st.just(5e-324)),
    st.floats(-1e6, 1e6),
)


@pytest.mark.system  # long (emulator or fuzzing): the system tier
@settings(max_examples=1500)
@given(st.lists(forged, max_size=20), st.integers(0, 40), st.sampled_from(["stamps", "receiver"]))
def test_no_forged_stream_locks_out_the_real_sender(bad: list[bytes], start: int, base: str) -> None:
    """Arbitrary forgeries interleaved with a real sender: nothing raises, every message used satisfies
    the bounds, and once the forgeries stop the real sender is used again within restart_after + 1."""
    bounds = AcceptanceBounds()
    clock = Clock(50.0)
    book = Freshness(MISSION, KNOWN, base, clock, bounds=bounds)  # type: ignore[arg-type]
    k = start
    for data in bad:
        k += 1
        clock.t += 0.02
        book.accept(real(2, k, clock.t))
        book.accept(data)
        m = book.latest(2, clock.t, 0.5)
        if m is not None:
            assert bounds.violation(m.g_bar_w, m.mu, m.var, m.prior_var) is None
            assert m.stamp - clock.t <= bounds.stamp_ahead_s + 1e-9 or base == "receiver"
    used = None
    for _ in range(bounds.restart_after + 1):
        k += 1
        clock.t += 0.02
        book.accept(real(2, k, clock.t))
        used = book.latest(2, clock.t, 0.5)
    assert isinstance(used, PredictionMessage) and used.seq == k
