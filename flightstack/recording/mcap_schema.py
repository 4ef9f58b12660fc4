"""The typed messages of a run's MCAP: protobuf schemas `flightstack.Tick` and `flightstack.DroneState`,
derived from the recording's arrays (timeseries.ARRAY_LAYOUT), and their vectorised encoder.

    flightstack.Tick        one per tick: every per-tick array (t, wall_t, loop_period, loop_compute, g_w0)
    flightstack.DroneState  one per drone per tick: `t`, `drone` (its id), then every per-drone array

A float64 array is a `double` (one value) or a packed `repeated double` (a vector, in the recording's
order: [x, y, z, θ] for poses and twists); a bool array a `bool`; an integer array an `sfixed64`. Field
numbers follow ARRAY_LAYOUT's order, so a field added there is written without a change here (and old
readers skip it). Units and frames: FIELD_DOCS and docs/logs.md.

Why not the protobuf library's own encoder per message: a 40 s paper_sim run has 240 000 such messages,
about 1 s of CPU message by message, where these fixed-size messages are laid out for a whole block of
ticks at once with numpy (every field is always written, zeros included, which protobuf decoders accept:
proto3 leaves a zero out only to save bytes). The protobuf library builds the schema
(`file_descriptor_set`) and is the reference that tests decode every message with.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from google.protobuf import descriptor_pb2

from flightstack.recording.timeseries import ARRAY_LAYOUT

PACKAGE = "flightstack"
TICK = f"{PACKAGE}.Tick"
DRONE = f"{PACKAGE}.DroneState"
_DOUBLE = descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE
_BOOL = descriptor_pb2.FieldDescriptorProto.TYPE_BOOL
_SFIXED64 = descriptor_pb2.FieldDescriptorProto.TYPE_SFIXED64
_FIXED32 = descriptor_pb2.FieldDescriptorProto.TYPE_FIXED32

FIELD_DOCS = {
    "t": "mission clock of the tick (s)",
    "wall_t": "wall-clock time of the tick (s since the epoch; 0 where not measured)",
    "g_w0": "the target's true pose in Σw [x, y, z, θ] (m, rad)",
    "g_wi": "the drone's true pose in Σw [x, y, z, θ] (m, rad)",
    "g_bar_w": "the drone's estimate ḡ_w,i of the target's pose in Σw [x, y, z, θ] (m, rad)",
    "e_c": "control error vec(g_d⁻¹ ḡ_i0) of the drone (m, rad)",
    "e_e": "true estimation error vec(ḡ_i0⁻¹ g_i0) (m, rad)",
    "e_e_meas": "measured estimation error J⁺(f − f̄) (m, rad)",
    "u_e": "observer input u_e, a body velocity (m/s, rad/s)",
    "mu_used": "fused GP mean of the target's body velocity used by the drone (m/s, rad/s)",
    "var_own": "the drone's own GP expert's predictive variance ((m/s)², (rad/s)²)",
    "V_cmd": "body-velocity command sent, in the drone's frame [v_x, v_y, v_z, ω_z] (m/s, rad/s)",
    "visible": "the drone's camera saw the target this tick",
    "n_fused": "predictions fused (own + fresh neighbours)",
    "loop_period": "wall time from the previous tick's start to this one's (s); NaN: not measured",
    "loop_compute": "wall time of this tick's sensing, fusion, command and record (s); NaN: not measured",
    "frame_age": "age of the camera frame the tick used (s, mission clock); NaN: no frame",
    "pose_age": "age of the drone's own pose the tick used (s, mission clock); NaN: none",
    "drone": "the drone's id",
}
"""What each message field holds (units, frame); docs/logs.md lists them."""


def per_drone(field: str) -> bool:
    """True for an array with one value per drone per tick (shape (N, n, ...))."""
    shape = ARRAY_LAYOUT[field][0]
    return bool(shape) and shape[0] == "n"


TICK_FIELDS = tuple(f for f in ARRAY_LAYOUT if not per_drone(f))
"""The arrays of a flightstack.Tick, in field-number order (t first)."""
DRONE_FIELDS = ("t", "drone", *(f for f in ARRAY_LAYOUT if per_drone(f)))
"""The fields of a flightstack.DroneState, in field-number order."""


@dataclass(frozen=True)
class _Field:
    name: str
    number: int
    kind: str  # "f8" | "bool" | "i8" | "u4"
    width: int  # values per message (1: a scalar; >1: a packed repeated double)

    def prefix(self) -> bytes:
        """The bytes before the value: the tag (and a packed field's length)."""
        if self.width > 1:
            return _varint(self.number << 3 | 2) + _varint(8 * self.width)
        wire = {"f8": 1, "i8": 1, "bool": 0, "u4": 5}[self.kind]
        return _varint(self.number << 3 | wire)

    def value_bytes(self) -> int:
        return {"f8": 8, "i8": 8, "bool": 1, "u4": 4}[self.kind] * self.width


def _varint(x: int) -> bytes:
    out = bytearray()
    while True:
        b, x = x & 0x7F, x >> 7
        out.append(b | (0x80 if x else 0))
        if not x:
            return bytes(out)


def _fields(names: tuple[str, ...]) -> tuple[_Field, ...]:
    out = []
    for number, name in enumerate(names, start=1):
        if name == "drone":
            out.append(_Field(name, number, "u4", 1))
            continue
        shape, dtype, _ = ARRAY_LAYOUT[name]
        inner = [int(d) for d in shape if d != "n"]
        kind = {"b": "bool", "i": "i8", "u": "i8"}.get(np.dtype(dtype).kind, "f8")
        width = int(np.prod(inner)) if inner else 1
        if kind != "f8" and width != 1:
            raise ValueError(f"{name}: only float arrays may be vectors in a typed message")
        out.append(_Field(name, number, kind, width))
    return tuple(out)


_SCHEMAS = {TICK: _fields(TICK_FIELDS), DRONE: _fields(DRONE_FIELDS)}


@functools.cache
def file_descriptor_set() -> bytes:
    """The serialized google.protobuf.FileDescriptorSet holding both messages: an MCAP channel's
    `protobuf` schema data (Foxglove and the mcap-protobuf decoders read it)."""
    fd = descriptor_pb2.FileDescriptorProto(name="flightstack.proto", package=PACKAGE, syntax="proto3")
    types = {"f8": _DOUBLE, "bool": _BOOL, "i8": _SFIXED64, "u4": _FIXED32}
    for full, fields in _SCHEMAS.items():
        msg = fd.message_type.add(name=full.rsplit(".", 1)[1])
        for f in fields:
            label = (
                descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED
                if f.width > 1
                else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL
            )
            field = msg.field.add(name=f.name, number=f.number, type=types[f.kind], label=label)
            if f.width > 1:
                field.options.packed = True
    return descriptor_pb2.FileDescriptorSet(file=[fd]).SerializeToString()


def message_size(schema: str) -> int:
    """Bytes of every message of `schema` (TICK or DRONE): the layout is fixed."""
    return sum(len(f.prefix()) + f.value_bytes() for f in _SCHEMAS[schema])


def encode(schema: str, columns: Mapping[str, np.ndarray]) -> np.ndarray:
    """The messages of N ticks as an (N, message_size) uint8 array, row k message k.

    columns: every field of the schema (TICK_FIELDS or DRONE_FIELDS) as an array with N rows: (N,) for
    a scalar, (N, width) for a vector; for DRONE, `drone` is (N,) ids and the arrays are one drone's
    columns (rec.g_wi[:, j], ...)."""
    fields = _SCHEMAS[schema]
    n = len(columns["t"])
    out = np.empty((n, message_size(schema)), dtype=np.uint8)
    col = 0
    for f in fields:
        prefix = np.frombuffer(f.prefix(), dtype=np.uint8)
        out[:, col : col + len(prefix)] = prefix
        col += len(prefix)
        a = np.asarray(columns[f.name])
        if f.kind == "f8":
            v = np.ascontiguousarray(a, dtype="<f8").reshape(n, f.width)
        elif f.kind == "i8":
            v = np.ascontiguousarray(a, dtype="<i8").reshape(n, 1)
        elif f.kind == "u4":
            v = np.ascontiguousarray(a, dtype="<u4").reshape(n, 1)
        else:
            v = np.ascontiguousarray(a, dtype=bool).astype(np.uint8).reshape(n, 1)
        width = f.value_bytes()
        out[:, col : col + width] = v.view(np.uint8).reshape(n, width)
        col += width
    return out


__all__ = [
    "DRONE",
    "DRONE_FIELDS",
    "FIELD_DOCS",
    "TICK",
    "TICK_FIELDS",
    "encode",
    "file_descriptor_set",
    "message_size",
    "per_drone",
]
