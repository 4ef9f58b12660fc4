"""Reading an MCAP file as a user's tool would, independently of flightstack's writer: the `mcap`
package's readers, and every protobuf message decoded with classes built from the schema record the file
carries (google.protobuf's descriptor pool), not from flightstack's code."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader


@dataclass
class McapContents:
    """Per topic its messages [(log_time ns, decoded message)], schema name and encodings; attachments,
    metadata; `error`: why a stream read stopped early (None: the file ended properly)."""

    topics: dict[str, list[tuple[int, Any]]] = field(default_factory=lambda: defaultdict(list))
    schemas: dict[str, tuple[str, str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    error: str | None = None

    @property
    def messages(self) -> int:
        return sum(len(v) for v in self.topics.values())


class _Decoders:
    def __init__(self) -> None:
        self.classes: dict[int, Any] = {}

    def decode(self, schema: Schema, data: bytes) -> Any:
        if schema.encoding != "protobuf":
            raise AssertionError(f"schema {schema.name}: encoding {schema.encoding}, not protobuf")
        cls = self.classes.get(schema.id)
        if cls is None:
            pool = descriptor_pool.DescriptorPool()
            for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                pool.Add(fd)
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            self.classes[schema.id] = cls
        return cls.FromString(data)


def read_mcap(path: Path) -> McapContents:
    """Every message of a complete MCAP file (the summary's indexes), decoded."""
    out, dec = McapContents(), _Decoders()
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            assert schema is not None
            out.topics[channel.topic].append((msg.log_time, dec.decode(schema, msg.data)))
            out.schemas[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
        out.attachments = {a.name: a.data for a in reader.iter_attachments()}
        out.metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return out


def read_mcap_stream(path: Path) -> McapContents:
    """Every message of an MCAP file read front to back, as far as it goes (a file cut short by a
    kill: up to its last complete chunk); `error` says where it stopped."""
    out, dec = McapContents(), _Decoders()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels[rec.channel_id]
                    sc = schemas[ch.schema_id]
                    out.topics[ch.topic].append((rec.log_time, dec.decode(sc, rec.data)))
                    out.schemas[ch.topic] = (sc.name, sc.encoding, ch.message_encoding)
        except Exception as exc:  # the end of a file cut short
            out.error = f"{type(exc).__name__}: {exc}"
    return out


def _rotate(q: Any, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternion q (a foxglove Quaternion: x, y, z, w)."""
    u, w = np.array([q.x, q.y, q.z]), q.w
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def world_positions(msg: Any, root: str = "world") -> dict[str, np.ndarray]:
    """Each frame's origin (3,) in `root` from one foxglove.FrameTransforms message, composed along its
    parents as a 3-D panel does (a frame whose chain does not reach `root` is left out)."""
    by_child = {t.child_frame_id: t for t in msg.transforms}

    def origin(frame: str) -> np.ndarray | None:
        p, f = np.zeros(3), frame
        for _ in range(len(by_child) + 1):  # child to root: p_parent = R p_child + t
            if f == root:
                return p
            t = by_child.get(f)
            if t is None:
                return None
            p = _rotate(t.rotation, p) + np.array([t.translation.x, t.translation.y, t.translation.z])
            f = t.parent_frame_id
        return None  # a cycle

    found = {frame: origin(frame) for frame in by_child}
    return {frame: p for frame, p in found.items() if p is not None}


def _fields(msg: Any) -> list[tuple[str, bool]]:
    """A message's fields as (name, repeated), read from its descriptor's proto form: the Python
    descriptor's own API differs across the protobuf releases the bound admits (`label` is gone in 7,
    `is_repeated` came in 6.31)."""
    proto = descriptor_pb2.DescriptorProto()
    msg.DESCRIPTOR.CopyToProto(proto)
    assert [f.name for f in proto.field] == [f.name for f in msg.DESCRIPTOR.fields], proto
    return [(f.name, f.label == f.LABEL_REPEATED) for f in proto.field]


def _value(msg: Any, name: str, repeated: bool) -> Any:
    v = getattr(msg, name)
    return list(v) if repeated else v


def _same(got: Any, want: Any) -> bool:
    return bool(np.array_equal(np.asarray(got, dtype=float), np.asarray(want, dtype=float), equal_nan=True))


def assert_mcap_holds(recs: Mapping[str, Any], got: McapContents) -> None:
    """Every tick of every recording (flightstack Recordings by mode) is in `got`: /<mode>/tick with
    each per-tick array, /<mode>/drone<i> with each of drone i's arrays, by field name, value for value
    (NaN included), at log time int((base + t)·1e9) ns, base = first wall_t − first t (0 without wall_t);
    /<mode>/tf holds the poses of the ticks it has under `sigma_w` (a child of `world`), and
    /<mode>/pose/target, /<mode>/pose/drones, /<mode>/pose/estimates the same poses in `sigma_w`."""
    for mode, rec in recs.items():
        k = rec.ticks_done
        ticks = got.topics[f"/{mode}/tick"]
        assert len(ticks) == k, (mode, len(ticks), k)
        wall0, t0 = float(rec.wall_t[0]), float(rec.t[0])
        base = wall0 - t0 if wall0 != 0.0 and np.isfinite(wall0) else 0.0
        want_ns = np.maximum(0, ((base + rec.t[:k]) * 1e9).astype(np.int64))
        assert [lt for lt, _ in ticks] == want_ns.tolist(), mode
        for name, repeated in _fields(ticks[0][1]) if ticks else []:
            col = np.array([_value(m, name, repeated) for _, m in ticks])
            want = np.asarray(getattr(rec, name))[:k]
            assert _same(col.reshape(want.shape), want), (mode, name)
        for j, i in enumerate(rec.drone_ids):
            msgs = got.topics[f"/{mode}/drone{i}"]
            assert len(msgs) == k and [lt for lt, _ in msgs] == want_ns.tolist(), (mode, i)
            for name, repeated in _fields(msgs[0][1]) if msgs else []:
                col = np.array([_value(m, name, repeated) for _, m in msgs])
                if name == "drone":
                    assert set(col.tolist()) == {i}
                    continue
                if name == "t":
                    assert _same(col, rec.t[:k]), (mode, i)
                    continue
                want = np.asarray(getattr(rec, name))[:k, j]
                assert _same(col.reshape(want.shape), want), (mode, i, name)
        by_ns = dict(zip(want_ns.tolist(), range(k), strict=False))
        for lt, m in got.topics[f"/{mode}/tf"]:
            kk = by_ns[lt]
            poses = {t.child_frame_id: t for t in m.transforms}
            assert poses["sigma_w"].parent_frame_id == "world"
            frames = [(f"{mode}/target", rec.g_w0[kk])]
            for j, i in enumerate(rec.drone_ids):
                frames += [(f"{mode}/drone{i}", rec.g_wi[kk, j])]
                frames += [(f"{mode}/drone{i}/estimate", rec.g_bar_w[kk, j])]
            cameras = {c for c in poses if c.endswith("/camera")}
            assert sorted(poses) == sorted([c for c, _ in frames] + ["sigma_w", *cameras])
            for child, p in frames:
                tf = poses[child]
                assert tf.parent_frame_id == "sigma_w"
                assert [tf.translation.x, tf.translation.y, tf.translation.z] == p[:3].tolist()
                assert _same([tf.rotation.z, tf.rotation.w], [np.sin(p[3] / 2), np.cos(p[3] / 2)])
        _assert_poses(mode, rec, got, by_ns)


def _pose_values(pose: Any) -> list[float]:
    """[x, y, z, qz, qw] of a foxglove.Pose."""
    p, q = pose.position, pose.orientation
    return [p.x, p.y, p.z, q.z, q.w]


def _want(p: np.ndarray) -> list[float]:
    return [*p[:3].tolist(), float(np.sin(p[3] / 2)), float(np.cos(p[3] / 2))]


def _assert_poses(mode: str, rec: Any, got: McapContents, by_ns: Mapping[int, int]) -> None:
    """The PoseInFrame / PosesInFrame topics of `mode`: one message per transform message, each pose of
    the recording's tick at its log time, in `sigma_w`, drones in id order."""
    tf_times = [lt for lt, _ in got.topics[f"/{mode}/tf"]]
    topics = {"target": rec.g_w0, "drones": rec.g_wi, "estimates": rec.g_bar_w}
    for what, values in topics.items():
        msgs = got.topics[f"/{mode}/pose/{what}"]
        assert [lt for lt, _ in msgs] == tf_times, (mode, what)
        for lt, m in msgs:
            kk = by_ns[lt]
            assert m.frame_id == "sigma_w" and m.timestamp.seconds * 10**9 + m.timestamp.nanos == lt
            if what == "target":
                assert _same(_pose_values(m.pose), _want(values[kk])), (mode, lt)
            else:
                assert len(m.poses) == len(rec.drone_ids)
                for j, pose in enumerate(m.poses):
                    assert _same(_pose_values(pose), _want(values[kk, j])), (mode, what, lt, j)
