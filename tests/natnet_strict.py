"""A strict parser of NatNet 3.0 packets, written from the NatNet SDK's layout (PacketClient.cpp `Unpack`,
major version 3) independently of libmotioncapture, for checking what the project's client decodes.

Strict: every field is read with its declared count, the packet must end exactly where its header's byte
count says, and any unknown data type is an error (ValueError), never skipped.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np


class _Reader:
    def __init__(self, packet: bytes) -> None:
        if len(packet) < 4:
            raise ValueError("shorter than a NatNet header")
        self.message_id, size = struct.unpack_from("<HH", packet)
        if size != len(packet) - 4:
            raise ValueError(f"header says {size} payload bytes, the packet has {len(packet) - 4}")
        self.data, self.at = packet, 4

    def take(self, fmt: str) -> tuple[object, ...]:
        n = struct.calcsize("<" + fmt)
        if self.at + n > len(self.data):
            raise ValueError(f"truncated at byte {self.at} (needs {n} more)")
        out = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += n
        return out

    def int(self) -> int:
        (v,) = self.take("i")
        assert isinstance(v, int)
        if v < 0 or v > 100_000:
            raise ValueError(f"count {v} at byte {self.at - 4} is not plausible")
        return v

    def text(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise ValueError(f"unterminated string at byte {self.at}")
        s, self.at = self.data[self.at : end].decode("utf-8"), end + 1
        return s

    def done(self) -> None:
        if self.at != len(self.data):
            raise ValueError(f"{len(self.data) - self.at} bytes left over")


@dataclass(frozen=True)
class Body:
    """A rigid body of a frame: float32 position (m, Motive's frame) and quaternion (x, y, z, w)."""

    body_id: int
    position: np.ndarray  # (3,) float32
    quaternion_xyzw: np.ndarray  # (4,) float32
    mean_error: float
    tracked: bool


@dataclass(frozen=True)
class Frame:
    frame: int
    bodies: tuple[Body, ...]
    timestamp_s: float
    mid_exposure_ticks: int


def parse_frame(packet: bytes) -> Frame:
    """A NAT_FRAMEOFDATA packet of NatNet 3.0."""
    r = _Reader(packet)
    if r.message_id != 7:
        raise ValueError(f"message id {r.message_id} is not NAT_FRAMEOFDATA")
    (frame,) = r.take("i")
    for _ in range(r.int()):  # marker sets
        r.text()
        r.take(f"{3 * r.int()}f")
    r.take(f"{3 * r.int()}f")  # other (unlabeled) markers
    bodies = tuple(_body(r) for _ in range(r.int()))
    for _ in range(r.int()):  # skeletons: id, then rigid bodies
        r.take("i")
        for _ in range(r.int()):
            _body(r)
    for _ in range(r.int()):  # labeled markers: id, x, y, z, size, params, residual
        r.take("i4fhf")
    for _ in range(2):  # force plates, then devices: id, channels of frames of float32
        for _ in range(r.int()):
            r.take("i")
            for _ in range(r.int()):
                r.take(f"{r.int()}f")
    _tc, _sub, timestamp, mid, _received, _transmit, _params = r.take("IIdQQQh")
    (eod,) = r.take("i")
    if eod != 0:
        raise ValueError(f"end-of-data marker {eod}, not 0")
    r.done()
    assert isinstance(frame, int) and isinstance(timestamp, float) and isinstance(mid, int)
    return Frame(frame, bodies, timestamp, mid)


def _body(r: _Reader) -> Body:
    body_id, x, y, z, qx, qy, qz, qw, err, params = r.take("i3f4ffh")
    assert isinstance(body_id, int) and isinstance(params, int) and isinstance(err, float)
    return Body(
        body_id,
        np.array([x, y, z], dtype=np.float32),
        np.array([qx, qy, qz, qw], dtype=np.float32),
        err,
        bool(params & 1),
    )


@dataclass(frozen=True)
class RigidBodyDef:
    name: str
    body_id: int
    parent_id: int
    offset: np.ndarray  # (3,) float32, m


def parse_model_def(packet: bytes) -> list[RigidBodyDef]:
    """The rigid bodies of a NAT_MODELDEF packet of NatNet 3.0 (marker sets and skeletons are checked and
    skipped; any other data type is an error)."""
    r = _Reader(packet)
    if r.message_id != 5:
        raise ValueError(f"message id {r.message_id} is not NAT_MODELDEF")
    out: list[RigidBodyDef] = []
    for _ in range(r.int()):
        (kind,) = r.take("i")
        if kind == 0:  # marker set: name, marker names
            r.text()
            for _ in range(r.int()):
                r.text()
        elif kind == 1:
            out.append(_body_def(r))
        elif kind == 2:  # skeleton: name, id, rigid bodies
            r.text()
            r.take("i")
            for _ in range(r.int()):
                _body_def(r)
        else:
            raise ValueError(f"data description type {kind} is not parsed here")
    r.done()
    return out


def _body_def(r: _Reader) -> RigidBodyDef:
    name = r.text()
    body_id, parent, ox, oy, oz = r.take("ii3f")
    n = r.int()
    r.take(f"{3 * n}f{n}i")  # marker positions, required active labels (NatNet 3.0)
    assert isinstance(body_id, int) and isinstance(parent, int)
    return RigidBodyDef(name, body_id, parent, np.array([ox, oy, oz], dtype=np.float32))
