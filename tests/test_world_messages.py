"""Messages of the served world (sim_backend/served/messages.py): exact round trips, and malformed
input refused with a reason, never an exception (fuzzed with hypothesis)."""

from __future__ import annotations

import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flightstack.sim_backend.served import messages as wm


def tick_header(k: int = 3, image: list[int] | None = None) -> dict:
    return {
        "v": wm.VERSION,
        "k": k,
        "t": 0.1 + 0.2,  # not representable exactly in decimal: JSON must keep every bit
        "state": {
            "battery_pct": 88.5,
            "height_m": 1.0,
            "link_alive": True,
            "flying": True,
            "phase": "flying",
        },
        "poses": {"drone1": [0.3, 1.0 / 3.0, -2.0, 0.5, np.pi]},
        "truth": {"target": [0.0, 0.0, 0.0, 0.0], "drone": [1.0, 2.0, 3.0, 0.1]},
        "frame": {"stamp": 0.3, "features": [0.1, -0.2] * 4, "image": image},
    }


def test_tick_round_trip_is_exact_with_image() -> None:
    img = np.random.default_rng(0).integers(0, 256, size=(6, 8, 3), dtype=np.uint8)
    tick, image, reason = wm.decode_tick(wm.pack(tick_header(image=[6, 8]), img))
    assert reason is None and tick is not None
    assert tick.t == 0.1 + 0.2 and tick.poses["drone1"][1] == 1.0 / 3.0
    assert tick.header() == tick_header(image=[6, 8])  # the same values under the same keys
    assert tick.frame is not None and tick.frame.image_shape == (6, 8)
    assert np.array_equal(image, img)


def test_cmd_round_trip_and_refusals() -> None:
    good = {"v": wm.VERSION, "k": 7, "calls": [["takeoff"], ["send_body_velocity", [0.1, -0.2, 0.0, 0.3]]]}
    cmd, reason = wm.decode_cmd(wm.pack(good))
    assert reason is None and cmd is not None and cmd.header() == good
    assert cmd.calls == (wm.DroneCall("takeoff"), wm.DroneCall("send_body_velocity", (0.1, -0.2, 0.0, 0.3)))
    cases = {
        "bad velocity": {**good, "calls": [["send_body_velocity", [0.1, 0.2, 0.3]]]},
        "unknown call": {**good, "calls": [["self_destruct"]]},
        "bad header": {**good, "v": 99},
        "no calls": {"v": wm.VERSION, "k": 1},
    }
    for want, doc in cases.items():
        assert wm.decode_cmd(wm.pack(doc)) == (None, want), want
    nan = wm.pack(good).replace(b"0.3]", b"NaN]")  # JSON with a NaN literal (Python's json reads it)
    assert wm.decode_cmd(nan) == (None, "not JSON")


def test_non_finite_or_mis_shaped_tick_fields_are_refused() -> None:
    short_pose = wm.pack({**tick_header(), "poses": {"drone1": [0.0, 1.0, 2.0]}})
    text_feature = wm.pack({**tick_header(), "frame": {"stamp": 0.0, "features": [0.1, "x"], "image": None}})
    infinite = wm.pack(tick_header()).replace(b"3.0,0.1]", b"Infinity,0.1]")  # truth.drone z = ∞
    assert b"Infinity" in infinite
    assert wm.decode_tick(short_pose)[2] == "bad poses"
    assert wm.decode_tick(text_feature)[2] == "bad features"
    assert wm.decode_tick(infinite)[2] == "not JSON"


def test_truncated_and_mis_sized_input() -> None:
    data = wm.pack(tick_header(image=[6, 8]), np.zeros((6, 8, 3), np.uint8))
    assert wm.decode_tick(data[:-1])[2] == "bad image"
    assert wm.decode_tick(data[:2])[2] == "truncated"
    assert wm.decode_tick(struct.pack("<I", 10**9) + b"{}")[2] == "bad length"
    assert wm.decode_tick(struct.pack("<I", 3) + b"\xff\xfe\xfd")[2] == "not JSON"


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=256))
def test_decoders_never_raise(data: bytes) -> None:
    tick, _, reason = wm.decode_tick(data)
    assert (tick is None) == (reason is not None)
    cmd, reason2 = wm.decode_cmd(data)
    assert (cmd is None) == (reason2 is not None)
