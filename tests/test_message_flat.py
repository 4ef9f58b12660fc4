"""The prediction message as one float64 array, checked by one compiled kernel.

The layout, the checks and the drop reasons must be exactly those of the struct-based code it replaced:
`_old_*` below is that code (messages.py and AcceptanceBounds.violation before issue 18), kept here as
the reference. Expected bytes are built independently with struct.pack, as the old encoder did.
"""

from __future__ import annotations

import copy
import math
import pickle
import struct
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flightstack.comms.acceptance import AcceptanceBounds
from flightstack.comms.bus import InProcBus
from flightstack.comms.freshness import Freshness
from flightstack.comms.messages import REASONS, PredictionMessage, decode, decode_checked, encode
from flightstack.paper import kernels as kern

KNOWN = frozenset({1, 2, 3})
MISSION = "flat"
_HEAD = struct.Struct("<4sBBHIdB")
_BODY = struct.Struct("<16d")
FIELDS = ("g_bar_w", "mu", "var", "prior_var")


# ---- the reference: the code before issue 18 ------------------------------------------------------------
def _old_check_fields(
    sender: int, seq: int, stamp: float, g: Sequence[float], mu: Sequence[float], var: Sequence[float],
    prior_var: Sequence[float],
) -> str | None:  # fmt: skip
    if not (0 <= sender < 2**16) or not (0 <= seq < 2**32):
        return "sender or seq out of range"
    if not math.isfinite(stamp):
        return "non-finite stamp"
    for name, arr in (("g_bar_w", g), ("mu", mu), ("var", var), ("prior_var", prior_var)):
        if len(arr) != 4:
            return f"{name} must have 4 elements"
        if not all(map(math.isfinite, arr)):
            return f"non-finite {name}"
    if min(var) <= 0 or min(prior_var) <= 0:
        return "variance must be > 0"
    return None


def _old_encode(msg: PredictionMessage) -> bytes:
    name = msg.mission.encode("utf-8")
    if len(name) > 64:
        raise ValueError("mission name longer than 64 bytes")
    fields = [
        np.asarray(a, dtype=float).reshape(-1).tolist() for a in (msg.g_bar_w, msg.mu, msg.var, msg.prior_var)
    ]
    reason = _old_check_fields(msg.sender, msg.seq, msg.stamp, *fields)
    if reason:
        raise ValueError(f"refusing to encode invalid message: {reason}")
    head = _HEAD.pack(b"FSPM", 1, 1 if msg.visible else 0, msg.sender, msg.seq, msg.stamp, len(name))
    return head + name + _BODY.pack(*fields[0], *fields[1], *fields[2], *fields[3])


def _old_decode(data: bytes, mission: str, known: frozenset[int]) -> tuple[tuple | None, str | None]:
    """(mission, sender, seq, stamp, visible, 16 floats) or the reason."""
    if len(data) < _HEAD.size:
        return None, "truncated header"
    magic, version, flags, sender, seq, stamp, name_len = _HEAD.unpack_from(data, 0)
    if magic != b"FSPM":
        return None, "bad magic"
    if version != 1:
        return None, f"unsupported schema version {version}"
    if flags & ~1:
        return None, "unknown flag bits"
    if name_len > 64:
        return None, "mission name too long"
    end_name = _HEAD.size + name_len
    if len(data) != end_name + _BODY.size:
        return None, "wrong length"
    try:
        name = data[_HEAD.size : end_name].decode("utf-8")
    except UnicodeDecodeError:
        return None, "mission name not UTF-8"
    if name != mission:
        return None, "other mission"
    if sender not in known:
        return None, "unknown sender"
    vals = _BODY.unpack_from(data, end_name)
    reason = _old_check_fields(sender, seq, stamp, vals[0:4], vals[4:8], vals[8:12], vals[12:16])
    if reason:
        return None, reason
    return (name, sender, seq, stamp, bool(flags & 1), vals), None


def _old_violation(b: AcceptanceBounds, g, mu, var, prior_var) -> str | None:  # type: ignore[no-untyped-def]
    lo, hi = b.var_floor, b.var_ceiling
    if not all(lo <= v <= hi for v in (*var, *prior_var)):
        return "variance out of bounds"
    if max(abs(mu[0]), abs(mu[1]), abs(mu[2])) > b.max_speed_mps or abs(mu[3]) > b.max_yaw_rate_rps:
        return "mu out of bounds"
    if max(abs(g[0]), abs(g[1]), abs(g[2])) > b.max_position_m or abs(g[3]) > b.max_angle_rad:
        return "pose out of bounds"
    return None


# ---- strategies -----------------------------------------------------------------------------------------
SPECIAL = [0.0, -0.0, 5e-324, -5e-324, 1e-13, 1e-12, 1e12, 1.1e12, 9.99, 10.0, 10.01, 999.0, 1000.0, 1e300]
SPECIAL += [-x for x in SPECIAL] + [math.inf, -math.inf, math.nan]
any_float = st.one_of(st.sampled_from(SPECIAL), st.floats(allow_nan=True, allow_infinity=True))
valid_var = st.floats(min_value=5e-324, max_value=1e300)
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
names = st.text(max_size=20).filter(lambda s: len(s.encode("utf-8")) <= 64)


@st.composite
def valid_messages(draw: st.DrawFn) -> PredictionMessage:
    f = [draw(st.lists(finite, min_size=4, max_size=4)) for _ in range(2)]
    v = [draw(st.lists(valid_var, min_size=4, max_size=4)) for _ in range(2)]
    return PredictionMessage(
        draw(names), draw(st.integers(0, 2**16 - 1)), draw(st.integers(0, 2**32 - 1)),
        draw(st.floats(allow_nan=False, allow_infinity=False)), draw(st.booleans()),
        np.array(f[0]), np.array(f[1]), np.array(v[0]), np.array(v[1]),
    )  # fmt: skip


def expected_bytes(m: PredictionMessage) -> bytes:
    """The wire bytes as the struct-based encoder built them."""
    name = m.mission.encode("utf-8")
    head = _HEAD.pack(b"FSPM", 1, 1 if m.visible else 0, m.sender, m.seq, m.stamp, len(name))
    floats = [float(x) for a in (m.g_bar_w, m.mu, m.var, m.prior_var) for x in a]
    return head + name + struct.pack("<16d", *floats)


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# ---- tests ---------------------------------------------------------------------------------------------
@settings(max_examples=400)
@given(valid_messages())
def test_encode_is_byte_identical_and_decode_round_trips(m: PredictionMessage) -> None:
    data = encode(m)
    assert data == expected_bytes(m) == _old_encode(m)
    out, reason = decode(data, m.mission, frozenset({m.sender}))
    assert reason is None and out is not None
    assert (out.mission, out.sender, out.seq, out.stamp, out.visible) == (
        m.mission, m.sender, m.seq, m.stamp, m.visible,
    )  # fmt: skip
    for f in FIELDS:
        got = getattr(out, f)
        assert got.dtype == np.float64 and got.shape == (4,) and got.flags.writeable
        assert same_bits(got, getattr(m, f))  # exact, the sign of zero included
    body = out.body()
    assert body is not None and body.flags.c_contiguous and body.flags.owndata
    assert encode(out) == data  # re-encoding a decoded message (its one array) gives the same bytes
    again = PredictionMessage.of_body(m.mission, m.sender, m.seq, m.stamp, m.visible, body.copy())
    assert encode(again) == data


@settings(max_examples=1000)
@given(st.data())
def test_decode_rejects_exactly_what_it_rejected(data: st.DataObject) -> None:
    """Valid messages with fields and header bytes overwritten by special values: the same verdict and
    reason as the struct-based decoder, and for a bus the same drop reason (decode, then the bounds)."""
    m = PredictionMessage(MISSION, 2, 7, 1.25, True, *(np.array([0.1, 0.2, 0.3, 0.4]) for _ in range(4)))
    raw = bytearray(encode(m))
    body_off = len(raw) - _BODY.size
    for _ in range(data.draw(st.integers(0, 6))):
        struct.pack_into("<d", raw, body_off + 8 * data.draw(st.integers(0, 15)), data.draw(any_float))
    if data.draw(st.booleans()):
        struct.pack_into("<d", raw, 12, data.draw(any_float))  # the stamp
    if data.draw(st.booleans()):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    blob = bytes(raw)
    old, old_reason = _old_decode(blob, MISSION, KNOWN)
    new, reason = decode(blob, MISSION, KNOWN)
    assert reason == old_reason
    if old is None:
        assert new is None
        return
    assert new is not None
    assert (new.mission, new.sender, new.seq, new.stamp, new.visible) == old[:5]
    vals = old[5]
    assert np.concatenate([getattr(new, f) for f in FIELDS]).tobytes() == _BODY.pack(*vals)
    bounds = AcceptanceBounds(max_speed_mps=data.draw(st.sampled_from([0.05, 10.0])))
    _, _, bad = decode_checked(blob, MISSION, KNOWN, bounds.packed)
    assert bad == _old_violation(bounds, vals[0:4], vals[4:8], vals[8:12], vals[12:16])
    assert bad == bounds.violation(new.g_bar_w, new.mu, new.var, new.prior_var)


@st.composite
def bodies(draw: st.DrawFn) -> list[float]:
    """16 floats of a plausible message (ḡ_w and μ up to 20, variances in [1e-6, 10]), up to 3 of
    them replaced by anything (non-finite, zero, signed, tiny, huge)."""
    plain = st.floats(-20.0, 20.0)
    vals = [draw(plain) for _ in range(8)] + [draw(st.floats(1e-6, 10.0)) for _ in range(8)]
    for _ in range(draw(st.integers(0, 3))):
        vals[draw(st.integers(0, 15))] = draw(any_float)
    return vals


@settings(max_examples=1500)
@given(bodies(), st.sampled_from([AcceptanceBounds(), None]))
def test_the_kernel_decides_as_the_python_checks(vals: list[float], b: AcceptanceBounds | None) -> None:
    bounds = b or AcceptanceBounds(var_floor=1e-3, max_yaw_rate_rps=1.0, max_position_m=5.0)
    code = kern.message_check(np.array(vals), bounds.packed)
    g, mu, var, prior = vals[0:4], vals[4:8], vals[8:12], vals[12:16]
    expected = _old_check_fields(1, 1, 0.0, g, mu, var, prior) or _old_violation(bounds, g, mu, var, prior)
    assert REASONS[code] == expected


@settings(max_examples=300)
@given(
    st.lists(st.one_of(any_float, st.integers(-3, 3)), min_size=0, max_size=6),
    st.integers(0, 3),
    st.sampled_from([0, -1, 2**16, 5]),
    st.sampled_from([0, -1, 2**32, 9]),
    st.sampled_from([0.5, math.nan, math.inf]),
)
def test_encode_refuses_what_it_refused(
    field: list[float], which: int, sender: int, seq: int, stamp: float
) -> None:
    """One field replaced by an arbitrary list (any length, ints, non-finite): encode raises the same
    ValueError as the struct-based encoder, or gives the same bytes."""
    good = [np.array([0.1, 0.2, 0.3, 0.4]) for _ in range(4)]
    good[which] = field  # type: ignore[call-overload]
    m = PredictionMessage(MISSION, sender, seq, stamp, False, *good)
    try:
        expected: bytes | str = _old_encode(m)
    except (ValueError, struct.error) as exc:
        expected = f"{type(exc).__name__}: {exc}"
    try:
        got: bytes | str = encode(m)
    except (ValueError, struct.error) as exc:
        got = f"{type(exc).__name__}: {exc}"
    assert got == expected


def test_fields_are_views_of_one_array_and_copies_are_not() -> None:
    body = np.arange(1.0, 17.0)
    m = PredictionMessage.of_body(MISSION, 1, 1, 0.0, True, body)
    assert m.body() is body and all(getattr(m, f).base is body for f in FIELDS)
    assert np.array_equal(m.var, [9.0, 10.0, 11.0, 12.0])
    for other in (replace(m, seq=2), copy.deepcopy(m), pickle.loads(pickle.dumps(m))):
        assert other.body() is None  # separate arrays: encode flattens them again
        assert encode(other)[-_BODY.size :] == encode(m)[-_BODY.size :]
    shifted = replace(m, g_bar_w=m.g_bar_w + 1.0)  # the foreign_copy fault: never the stale body
    assert _BODY.unpack(encode(shifted)[-_BODY.size :])[0] == 2.0
    # anything but a writable float64 (16,) array that owns its data is copied into one
    view = np.arange(1.0, 33.0)[::2]
    for given_body in (view, np.arange(1, 17), np.arange(1.0, 17.0).reshape(4, 4)):
        mm = PredictionMessage.of_body(MISSION, 1, 1, 0.0, True, given_body)
        b = mm.body()
        assert b is not None and b.dtype == np.float64 and b.shape == (16,) and b.flags.owndata
    with pytest.raises(ValueError, match="non-finite mu"):
        encode(PredictionMessage.of_body(MISSION, 1, 1, 0.0, True, np.r_[np.ones(4), np.nan, np.ones(11)]))


def test_drop_reasons_keep_their_order_on_the_bus() -> None:
    """Decode reasons before the transport's sender check before the bounds (Freshness.accept)."""
    book = Freshness(MISSION, {1, 2})
    one, big = np.ones(4), np.full(4, 1e3)
    huge_mu = PredictionMessage(MISSION, 1, 1, 0.0, True, np.zeros(4), big, one, one)
    assert book.accept(encode(huge_mu), key_sender="2") is None  # mismatch decided before the bounds
    assert book.accept(encode(huge_mu)) is None
    nan = bytearray(encode(huge_mu))
    struct.pack_into("<d", nan, len(nan) - 8, math.nan)  # prior_var[3]
    assert book.accept(bytes(nan), key_sender="2") is None  # decode's reason before the sender check
    assert book.dropped == {"key sender mismatch": 1, "mu out of bounds": 1, "non-finite prior_var": 1}
    # bounds replaced on a live book are used from the next message on
    book.bounds = AcceptanceBounds(max_speed_mps=1e4, max_yaw_rate_rps=1e4)
    assert book.accept(encode(huge_mu)) is not None


def test_neighbour_messages_reach_the_agent_unchanged() -> None:
    """What the agent reads from the bus is the decoded array itself, bit for bit."""
    bus = InProcBus(MISSION, {1, 2})
    vals = np.array([0.1, -0.0, 1.5, 3.0, 0.2, -0.1, 0.0, 0.05, 1e-3, 2e-3, 3e-3, 4e-3, 1.0, 1.0, 0.5, 0.5])
    bus.publish(PredictionMessage.of_body(MISSION, 2, 1, 0.0, True, vals.copy()))
    got = bus.latest(2, 0.0, 0.5)
    assert got is not None and got.body() is not None
    assert got.body().tobytes() == vals.tobytes()  # type: ignore[union-attr]
