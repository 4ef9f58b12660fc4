"""Prediction messages: round trip, strict validation, and a decoder that never raises (fuzzed)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flightstack.comms.bus import InProcBus
from flightstack.comms.messages import PredictionMessage, decode, encode

KNOWN = frozenset({1, 2, 3})


def msg(**kw) -> PredictionMessage:
    base = dict(
        mission="paper_sim",
        sender=2,
        seq=7,
        stamp=1.25,
        visible=True,
        g_bar_w=np.array([0.1, -0.2, 0.3, 0.4]),
        mu=np.array([0.5, 0.6, -0.7, 0.4]),
        var=np.array([0.01, 0.02, 0.03, 0.04]),
        prior_var=np.array([0.2, 0.2, 0.3, 0.3]),
    )
    base.update(kw)
    return PredictionMessage(**base)


def test_round_trip() -> None:
    m = msg()
    out, reason = decode(encode(m), "paper_sim", KNOWN)
    assert reason is None and out is not None
    assert (out.mission, out.sender, out.seq, out.stamp, out.visible) == ("paper_sim", 2, 7, 1.25, True)
    for f in ("g_bar_w", "mu", "var", "prior_var"):
        assert np.array_equal(getattr(out, f), getattr(m, f))


def test_rejections_name_the_reason() -> None:
    data = encode(msg())
    assert decode(data, "other", KNOWN) == (None, "other mission")
    assert decode(data, "paper_sim", frozenset({1})) == (None, "unknown sender")
    assert decode(data[:-1], "paper_sim", KNOWN)[1] == "wrong length"
    assert decode(b"XXXX" + data[4:], "paper_sim", KNOWN)[1] == "bad magic"
    assert decode(data[:4] + b"\x09" + data[5:], "paper_sim", KNOWN)[1] == "unsupported schema version 9"
    assert decode(data[:10], "paper_sim", KNOWN)[1] == "truncated header"
    # patch a NaN into μ and a negative variance, bypassing encode's own check
    body_off = len(data) - 16 * 8
    nan = data[: body_off + 4 * 8] + struct.pack("<d", float("nan")) + data[body_off + 5 * 8 :]
    assert decode(nan, "paper_sim", KNOWN)[1] == "non-finite mu"
    neg = data[: body_off + 8 * 8] + struct.pack("<d", -1.0) + data[body_off + 9 * 8 :]
    assert decode(neg, "paper_sim", KNOWN)[1] == "variance must be > 0"


def test_encode_refuses_invalid_messages() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        encode(msg(mu=np.array([0, np.inf, 0, 0])))
    with pytest.raises(ValueError, match="variance"):
        encode(msg(var=np.zeros(4)))


@given(st.binary(max_size=300))
@settings(max_examples=500)
def test_decoder_never_raises_on_random_bytes(data: bytes) -> None:
    out, reason = decode(data, "paper_sim", KNOWN)
    assert (out is None) != (reason is None)


@given(st.data())
@settings(max_examples=500)
def test_decoder_never_raises_on_mutated_messages(data: st.DataObject) -> None:
    raw = bytearray(encode(msg()))
    for _ in range(data.draw(st.integers(1, 8))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    out, reason = decode(bytes(raw), "paper_sim", KNOWN)
    assert (out is None) != (reason is None)
    if out is not None:  # whatever passes is fully valid
        assert np.all(np.isfinite(out.mu)) and np.all(out.var > 0) and out.sender in KNOWN


def test_inproc_bus_drops_and_counts() -> None:
    bus = InProcBus("paper_sim", {1, 2, 3})
    first = msg(seq=1, stamp=0.0)
    bus.publish(first)
    assert bus.latest(2, now=0.1, stale_after=0.5) is not None
    assert bus.latest(2, now=1.0, stale_after=0.5) is None  # stale
    bus.publish(first)  # the network repeated it: a duplicate
    bus.publish_raw(b"garbage")
    bus.publish(msg(mission="x", seq=5))
    assert bus.dropped == {"stale": 1, "old or duplicate seq": 1, "truncated header": 1, "other mission": 1}
    # other bytes under the newest seq: a second sender (evidence, comms/streams.py) whose message is the
    # newest until the next one, never dropped as a duplicate
    bus.publish(msg(seq=1, stamp=0.9))
    other = bus.latest(2, now=1.0, stale_after=0.5)
    assert other is not None and other.stamp == 0.9 and bus.dropped["old or duplicate seq"] == 1
    assert bus.latest(3, now=0.0, stale_after=1.0) is None
