"""The Tello video stream check (flightstack.drivers.tello.video_check) on a real x264 stream cut into
Tello datagrams: which access units it calls damaged after each kind of loss, and when it resyncs."""

from __future__ import annotations

from collections import Counter
from fractions import Fraction

import numpy as np
import pytest

from flightstack.drivers.tello.video_check import TELLO_DATAGRAM_BYTES, StreamCheck, split_nals

pytestmark = pytest.mark.unit
av = pytest.importorskip("av")

GOP = 10
N_FRAMES = 40


@pytest.fixture(scope="module")
def stream() -> list[tuple[int, bytes]]:
    """(frame index, datagram) of 40 frames of 160×120 noise + a moving bar, keyframe every 10 frames."""
    ctx = av.CodecContext.create("libx264", "w")
    ctx.width, ctx.height, ctx.pix_fmt = 160, 120, "yuv420p"
    ctx.framerate, ctx.time_base, ctx.gop_size = Fraction(15), Fraction(1, 15), GOP
    ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "x264-params": "repeat-headers=1"}
    rng = np.random.default_rng(0)
    out = []
    for i in range(N_FRAMES):
        img = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
        frame = av.VideoFrame.from_ndarray(img, format="rgb24")
        frame.pts = i
        for packet in ctx.encode(frame):
            data = bytes(packet)
            for k in range(0, len(data), TELLO_DATAGRAM_BYTES):
                out.append((i, data[k : k + TELLO_DATAGRAM_BYTES]))
    assert len({i for i, d in out if len(d) == TELLO_DATAGRAM_BYTES}) > N_FRAMES // 2  # frames span datagrams
    return out


def _verdicts(datagrams: list[tuple[int, bytes]]) -> tuple[dict[int, bool], Counter[str]]:
    """Frame index -> intact, as the receiver judges it (the parser's access units, in order)."""
    counts: Counter[str] = Counter()
    check = StreamCheck(counts)
    parser = av.CodecContext.create("h264", "r")
    out: dict[int, bool] = {}
    units = []
    for _, data in datagrams:
        check.datagram(data)
        for packet in parser.parse(data):
            units.append(check.access_unit(bytes(packet)))
    for packet in parser.parse(b""):  # flush the last access unit
        units.append(check.access_unit(bytes(packet)))
    present = sorted({i for i, _ in datagrams})
    assert len(units) == len(present), (len(units), len(present))
    out = dict(zip(present, units, strict=True))
    return out, counts


def _frame_datagrams(stream: list[tuple[int, bytes]], i: int) -> list[int]:
    return [k for k, (j, _) in enumerate(stream) if j == i]


def test_intact_stream_is_clean_from_its_first_keyframe(stream: list[tuple[int, bytes]]) -> None:
    verdicts, counts = _verdicts(stream)
    assert all(verdicts.values())
    assert counts["resync"] == 1 and counts["lost_head"] == counts["lost_tail"] == counts["frame_gap"] == 0


def _without(stream: list[tuple[int, bytes]], drop: set[int]) -> list[tuple[int, bytes]]:
    return [x for k, x in enumerate(stream) if k not in drop]


@pytest.mark.parametrize("where", ["head", "tail", "whole"])
def test_a_loss_damages_every_frame_up_to_the_next_keyframe(
    stream: list[tuple[int, bytes]], where: str
) -> None:
    lost = 13  # a P frame; the next keyframe is frame 20
    ks = _frame_datagrams(stream, lost)
    assert len(ks) >= 2
    drop = {"head": {ks[0]}, "tail": {ks[-1]}, "whole": set(ks)}[where]
    verdicts, counts = _verdicts(_without(stream, drop))
    damaged = sorted(i for i, ok in verdicts.items() if not ok)
    first_bad = lost - 1 if where == "head" else lost  # a lost head merges its frame into the one before
    assert damaged == [i for i in range(first_bad, 20) if i in verdicts]
    assert verdicts[20] and counts["resync"] == 2
    expected = {"head": "lost_head", "tail": "lost_tail", "whole": "frame_gap"}[where]
    assert counts[expected] >= 1


def test_a_reordered_datagram_is_a_loss(stream: list[tuple[int, bytes]]) -> None:
    ks = _frame_datagrams(stream, 24)
    order = list(range(len(stream)))
    a, b = ks[-1], ks[-1] + 1  # the frame's last datagram swapped with the next frame's first
    order[a], order[b] = order[b], order[a]
    verdicts, _ = _verdicts([stream[k] for k in order])
    assert not verdicts[25] and verdicts[30]


def test_a_stream_not_framed_like_a_tello_switches_the_framing_rule_off(
    stream: list[tuple[int, bytes]],
) -> None:
    """Re-cut into 1000-byte datagrams regardless of frames: the framing rule would see losses everywhere;
    it switches itself off instead of condemning every frame."""
    blob = b"".join(d for _, d in stream)
    recut = [(0, blob[k : k + 1000]) for k in range(0, len(blob), 1000)]
    counts: Counter[str] = Counter()
    check = StreamCheck(counts)
    parser = av.CodecContext.create("h264", "r")
    intact = []
    for _, data in recut:
        check.datagram(data)
        intact += [check.access_unit(bytes(p)) for p in parser.parse(data)]
    assert counts["framing_off"] == 1
    assert sum(intact) >= N_FRAMES - GOP - 2  # clean again from the first keyframe after it switched off


def test_split_nals() -> None:
    au = b"\x00\x00\x00\x01\x67\xaa\x00\x00\x01\x68\xbb\x00\x00\x00\x01\x65\xcc"
    assert split_nals(au) == [b"\x67\xaa", b"\x68\xbb", b"\x65\xcc"]
