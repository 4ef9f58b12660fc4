"""Total decoders of the world and operator messages (world_messages.py, control.py), with hypothesis.

For each decoder (world tick, world cmd, control: abort, abort_ack, status): arbitrary bytes, arbitrary JSON
inside a valid frame, and mutations of valid messages (a field deleted, its type swapped, a number made
huge, negative, non-finite, or nested deeply) never raise, and every accepted message is usable by its
consumers without raising: the agent's RemoteDrone / RemoteCamera / RemotePoseSource / RemoteClock /
RemoteBackend.truth on a tick, the served world's receive_cmd → _apply on its simulated drones
(sim_ideal and sim_lab), `flightstack status`'s table, guard's step and the abort acknowledgement.
Valid values round-trip exactly. The crashes found before the decoders were total are regression tests
at the end. The profile (tests/conftest.py) is derandomized without deadline; max_examples are explicit.
"""

from __future__ import annotations

import copy
import json
import math
import re
import struct
import threading
from collections import defaultdict
from typing import Any

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from flightstack.cli.network import status_table
from flightstack.comms.control import (
    ABORT,
    ABORT_ACK,
    CONTROL_KINDS,
    MAX_CONTROL_BYTES,
    STATUS,
    AbortRequest,
    AckReport,
    ControlEvent,
    StatusReport,
    ack_payload,
    encode_control,
    parse_control,
    read_ack,
    status_report,
)
from flightstack.comms.identity import SessionBook
from flightstack.config.mission import load_mission
from flightstack.drivers.lab.guard import AgentWatch, Guard, GuardSummary
from flightstack.events import Event
from flightstack.hal import DroneState, Frame, StampedPose
from flightstack.runtime.rig import build_backend
from flightstack.sim_backend.served import messages as wm
from flightstack.sim_backend.served.client import (
    RemoteBackend,
    RemoteCamera,
    RemoteClock,
    RemoteDrone,
    RemotePoseSource,
    _Link,
)
from flightstack.sim_backend.served.server import WorldServer
from tests.conftest import MISSIONS

MISSION = "prop_test"


# ---- strategies ---------------------------------------------------------------------------------------
def bounded(b: float) -> st.SearchStrategy[float]:
    return st.floats(-b, b, allow_nan=False, allow_infinity=False)


FIN = st.floats(allow_nan=False, allow_infinity=False)
times, coords, angles = bounded(wm.MAX_TIME_S), bounded(wm.MAX_COORD_M), bounded(wm.MAX_ANGLE_RAD)
pose4 = st.tuples(coords, coords, coords, angles)
row5 = st.tuples(times, coords, coords, coords, angles)
bodies = st.sampled_from(["drone1", "target", "drone2"]) | st.text(min_size=1, max_size=wm.MAX_BODY_CHARS)


@st.composite
def frames(draw: st.DrawFn) -> tuple[wm.FrameHead, np.ndarray | None]:
    pairs = draw(st.none() | st.lists(st.tuples(FIN, FIN), max_size=8))
    features = None if pairs is None else tuple(x for p in pairs for x in p)
    shape = draw(st.none() | st.tuples(st.integers(1, 6), st.integers(1, 6)))
    image = None
    if shape is not None:
        raw = draw(st.binary(min_size=shape[0] * shape[1] * 3, max_size=shape[0] * shape[1] * 3))
        image = np.frombuffer(raw, dtype=np.uint8).reshape(shape[0], shape[1], 3)
    return wm.FrameHead(draw(times), features, shape), image


@st.composite
def ticks(draw: st.DrawFn) -> tuple[wm.WorldTick, np.ndarray | None]:
    state = wm.TickState(
        draw(st.floats(0.0, 100.0)),
        draw(coords),
        draw(st.booleans()),
        draw(st.booleans()),
        draw(st.sampled_from(sorted(wm.PHASES))),
    )
    poses = draw(st.dictionaries(bodies, row5, max_size=3))
    frame, image = draw(st.none() | frames()) or (None, None)
    tick = wm.make_tick(
        draw(st.integers(0, wm.MAX_TICK)),
        draw(times),
        state,
        poses,
        wm.Truth(draw(pose4), draw(pose4)),
        frame,
    )
    return tick, image


# a velocity in range: |(v_x, v_y, v_z)| ≤ √3 · 4.6 < 8 m/s, |ω| ≤ 5 rad/s
velocities = st.tuples(bounded(4.6), bounded(4.6), bounded(4.6), bounded(wm.MAX_YAW_RATE))
calls = st.sampled_from(sorted(wm.DRONE_CALLS - {wm.VELOCITY_CALL})).map(wm.DroneCall) | velocities.map(
    lambda v: wm.DroneCall(wm.VELOCITY_CALL, v)
)
cmds = st.builds(wm.WorldCmd, st.integers(-1, wm.MAX_TICK), st.lists(calls, max_size=8).map(tuple))

# what str.isprintable() accepts: no "Other" or "Separator" character but the ASCII space
printable = st.text(
    st.characters(
        exclude_categories=("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp", "Zs"), include_characters=" "
    ),
    max_size=20,
)
statuses = st.builds(
    StatusReport,
    drone=st.integers(0, 3) | st.integers(0, 2**16 - 1),
    mode=st.sampled_from(["none", "local", "dgp", "oracle"])
    | st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True),
    t=bounded(1e9),
    tick=st.integers(0, 2**53),
    battery_pct=st.floats(0.0, 100.0),
    flying=st.booleans(),
    link_alive=st.booleans(),
    visible=st.booleans(),
    n_fused=st.integers(0, 2**53),
    pose_fresh=st.booleans(),
    rejection=st.none() | printable,
    dropped=st.dictionaries(printable, st.integers(0, 2**53), max_size=4).map(lambda d: tuple(d.items())),
    restarts=st.dictionaries(printable, st.integers(0, 2**53), max_size=4).map(lambda d: tuple(d.items())),
)
aborts = st.builds(AbortRequest, printable, st.text("0123456789abcdef", min_size=1, max_size=32))
acks = st.builds(
    AckReport,
    st.none() | st.text("0123456789abcdef", max_size=32),
    st.lists(st.integers(0, 2**16 - 1), min_size=1, max_size=4).map(tuple),
    st.integers(0, 2**22),
    printable,
)
payloads = (
    statuses.map(lambda s: (STATUS, s))
    | aborts.map(lambda a: (ABORT, a))
    | acks.map(lambda a: (ABORT_ACK, a))
)

KEYS = ["v", "k", "t", "state", "poses", "truth", "frame", "calls", "stamp", "features", "image", "phase"]
KEYS += ["battery_pct", "height_m", "flying", "drone", "target", "reason", "id", "mode", "dropped"]
EXTREMES: list[Any] = [0, -1, -0.0, 1e308, -1e308, 5e-324, 2**31, 2**53 + 1, 2**63, -(2**63), 10**400]
EXTREMES += [1e9 + 1, 101.0, 8.1, True, False, None, "", "NaN", [], {}, [0.0] * 5, [[[]]]]
leaves = (
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | FIN
    | st.text(max_size=8)
    | st.sampled_from(EXTREMES)
    | st.sampled_from(sorted(wm.DRONE_CALLS | wm.PHASES))
)
json_values = st.recursive(
    leaves,
    lambda c: (
        st.lists(c, max_size=5) | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=6), c, max_size=5)
    ),
    max_leaves=25,
)


def tick_header(**changes: Any) -> dict[str, Any]:
    """A valid tick as the world wrote it before the typed decoders (served.py's dict)."""
    header = {
        "v": 1,
        "k": 3,
        "t": 0.3,
        "state": {
            "battery_pct": 88.5,
            "height_m": 1.0,
            "link_alive": True,
            "flying": True,
            "phase": "flying",
        },
        "poses": {"drone1": [0.3, 1.0, -2.0, 0.5, 3.1]},
        "truth": {"target": [0.0, 0.0, 0.0, 0.0], "drone": [1.0, 2.0, 3.0, 0.1]},
        "frame": {"stamp": 0.3, "features": [0.1, -0.2] * 4, "image": None},
    }
    return {**header, **changes}


def base_ticks() -> list[tuple[dict[str, Any], np.ndarray | None]]:
    """Valid ticks to mutate: no frame and no pose; features and two bodies; an image; edge values."""
    image = np.arange(18, dtype=np.uint8).reshape(2, 3, 3)
    state = {"battery_pct": 0.0, "height_m": -0.5, "link_alive": False, "flying": False, "phase": "landing"}
    return [
        (tick_header(poses={}, frame=None), None),
        (
            tick_header(poses={"drone1": [0.3, 1.0, -2.0, 0.5, 3.1], "target": [0.2, 0.0, 0.0, 0.0, -3.1]}),
            None,
        ),
        (tick_header(frame={"stamp": 0.25, "features": None, "image": [2, 3]}), image),
        (tick_header(k=0, t=0.0, state=state, frame={"stamp": -0.1, "features": [], "image": None}), None),
    ]


BASE_CMDS = [
    {"v": 1, "k": -1, "calls": []},
    {"v": 1, "k": 2, "calls": [["connect"], ["takeoff"]]},
    {"v": 1, "k": 9, "calls": [["send_body_velocity", [0.5, -0.2, 0.1, 0.3]], ["land"], ["emergency_stop"]]},
    {"v": 1, "k": 9, "calls": [["close"], ["send_body_velocity", [0, 0, 0, 0]]]},
    {"v": 1, "k": 4, "calls": [["send_body_velocity", [0.1 * i, -0.2, 0.05 * i, 0.4]] for i in range(4)]},
]
GOOD_STATUS = StatusReport(1, "dgp", 1.0, 20, 80.0, True, True, True, 1, True, None, (), ()).to_payload()
BASE_CONTROL = [
    (STATUS, GOOD_STATUS),
    (
        STATUS,
        {
            **GOOD_STATUS,
            "drone": 2,
            "rejection": "3 blobs",
            "dropped": {"stale": 4, "control: bad status": 1},
            "restarts": {"agent-1": 2},
        },
    ),
    (ABORT, {"reason": "operator abort", "id": "0123abcd"}),
    (ABORT_ACK, {"abort_id": "0123abcd", "drones": [1, 2], "pid": 4242, "host": "lab-pc"}),
    (ABORT_ACK, {"abort_id": None, "drones": [3], "pid": 1, "host": ""}),
]


def paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path from the root to a node of a JSON structure (the root is ())."""
    out = [prefix]
    if isinstance(obj, dict):
        for key, v in obj.items():
            out += paths(v, (*prefix, key))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += paths(v, (*prefix, i))
    return out


@st.composite
def mutated(draw: st.DrawFn, header: dict[str, Any]) -> dict[str, Any]:
    """`header` with one or two nodes deleted, or replaced by any JSON, an extreme value, another number,
    another type, or nested deeply."""
    doc = json.loads(json.dumps(header))
    for _ in range(draw(st.integers(1, 2))):
        if isinstance(doc, dict | list) and doc:
            doc = _mutate_once(draw, doc)
    return doc


def _mutate_once(draw: st.DrawFn, doc: Any) -> Any:
    path = draw(st.sampled_from(paths(doc)[1:]))
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    old = parent[path[-1]]
    how = draw(st.sampled_from(["delete", "replace", "extreme", "number", "swap", "nest"]))
    if how == "delete":
        del parent[path[-1]]
    elif how == "replace":  # copies: EXTREMES holds lists and dicts that a later mutation must not change
        parent[path[-1]] = copy.deepcopy(draw(json_values))
    elif how == "extreme":
        parent[path[-1]] = copy.deepcopy(draw(st.sampled_from(EXTREMES)))
    elif how == "number":  # often still valid: the consumers must cope with any accepted value
        parent[path[-1]] = draw(st.integers(-3, 3) | st.floats(-20.0, 20.0) | st.floats(-1e12, 1e12))
    elif how == "swap":
        parent[path[-1]] = draw(st.sampled_from([str(old), [old], {"x": old}, bool(old) if old != [] else 1]))
    else:
        for _ in range(draw(st.integers(1, 40))):
            old = [old]
        parent[path[-1]] = old
    return doc


NUMBER = re.compile(rb"(?<=[:\[,])-?\d+(\.\d+)?([eE][-+]?\d+)?")


@st.composite
def non_finite(draw: st.DrawFn, data: bytes) -> bytes:
    """`data` (a packed header) with one of its numbers replaced by NaN, ±Infinity or an overflowing 1e999."""
    (n,) = struct.unpack_from("<I", data)
    head, tail = data[4 : 4 + n], data[4 + n :]
    spans = [m.span() for m in NUMBER.finditer(head)]
    if not spans:
        return data
    a, b = draw(st.sampled_from(spans))
    word = draw(st.sampled_from([b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e999"]))
    head = head[:a] + word + head[b:]
    return struct.pack("<I", len(head)) + head + tail


def framed(header: Any) -> bytes:
    return wm.pack(header)


def raw(head: bytes) -> bytes:
    """A world message frame around any header bytes."""
    return struct.pack("<I", len(head)) + head


# ---- consumers ----------------------------------------------------------------------------------------
class FakePublisher:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, data: bytes, **_: Any) -> None:
        self.sent.append(bytes(data))

    def undeclare(self) -> None:
        pass


class FakeSession:
    """What _Link declares on a zenoh session."""

    def __init__(self) -> None:
        self.pub = FakePublisher()

    def declare_publisher(self, key: str, **_: Any) -> FakePublisher:
        return self.pub

    def declare_subscriber(self, key: str, callback: Any) -> FakePublisher:
        return FakePublisher()


def consume_tick(data: bytes) -> str | None:
    """What an agent process does with one tick message: _Link.receive, then every accessor."""
    link = _Link(FakeSession(), "p", MISSION, 1, 1.0)
    reason = link.receive(data)
    if reason is not None:
        assert link.dropped == {reason: 1} and link._tick is None
        return reason
    tick = link.tick()
    state = RemoteDrone(link).state()
    assert isinstance(state, DroneState) and state.phase == RemoteDrone(link).phase in wm.PHASES
    assert math.isfinite(state.battery_pct) and math.isfinite(state.height_m)
    frame = RemoteCamera(link).latest()
    assert frame is None or isinstance(frame, Frame)
    if frame is not None and frame.image is not None:
        assert frame.image.shape == (*tick.frame.image_shape, 3)  # type: ignore[union-attr]
    for body in [*tick.poses, "drone1", "target", "nobody"]:
        sp = RemotePoseSource(link).latest(body)
        assert sp is None or (isinstance(sp, StampedPose) and np.all(np.isfinite(sp.pose.as_vector())))
    backend = object.__new__(RemoteBackend)
    backend.link, backend.drone_id = link, 1
    g_w0, g_wis = backend.truth()
    assert np.all(np.isfinite(g_w0.as_vector())) and np.all(np.isfinite(g_wis[1].as_vector()))
    assert RemoteClock(link).now() == tick.t
    assert link.receive(data) == "old tick"  # the same tick again
    return None


def served_world(mission_file: str) -> WorldServer:
    """The served world's cmd path (receive_cmd → _apply) on a real simulated backend, without Zenoh."""
    mission = load_mission(MISSIONS / mission_file)
    srv = object.__new__(WorldServer)
    srv.mission, srv.ids, srv.backend = mission, [d.id for d in mission.drones], build_backend(mission)
    srv._cond, srv._queued = threading.Condition(), defaultdict(list)
    srv._done_k, srv._tick_k, srv._dropped = {i: -2 for i in srv.ids}, wm.MAX_TICK, {}
    srv._sessions = SessionBook("sends commands as")
    return srv


WORLDS: dict[str, WorldServer] = {}


def worlds() -> list[WorldServer]:
    if not WORLDS:
        WORLDS.update({f: served_world(f) for f in ("paper_sim.yaml", "paper_experiment.yaml")})
    return list(WORLDS.values())


def consume_cmd(data: bytes) -> str | None:
    """What the served world does with one cmd message from agent 1: receive, apply, advance one dt."""
    reasons = set()
    for srv in worlds():
        reasons.add(srv.receive_cmd("p/m/world/cmd/1", data))
        srv._apply()
        clock = srv.backend.clock
        clock.sleep_until(clock.now() + srv.mission.dt_s)
    assert len(reasons) == 1
    return reasons.pop()


class FakeGuardBus:
    def __init__(self, events: list[ControlEvent]) -> None:
        self.events = events
        self.presence_events: list[Event] = []

    def control_events(self) -> list[ControlEvent]:
        out, self.events = self.events, []
        return out


def guard_step(ev: ControlEvent) -> None:
    """Guard's watch over one event (its status reading), with no landers."""
    g = object.__new__(Guard)
    g.bus, g.log, g._n_presence = FakeGuardBus([ev]), lambda _: None, 0
    g.agents = {i: AgentWatch(present=True) for i in range(4)}
    g.active, g.landers, g.summary, g.status_fresh_s = {}, {}, GuardSummary(), 2.0
    g.step(ev.time)


def consume_control(data: bytes, kinds: frozenset[str] = CONTROL_KINDS) -> str | None:
    ev, reason = parse_control(data, MISSION, 5.0, kinds)
    if ev is None:
        assert isinstance(reason, str) and reason.startswith("control: ")
        return reason
    if ev.kind == STATUS:
        report = status_report(ev)
        assert report is not None and report.to_payload() == ev.payload
        table = status_table({report.drone: (report, 1.0)}, {report.drone}, [report.drone, 99], 5.0, {})
        assert "\x1b" not in table and len(table.splitlines()) == 3
        guard_step(ev)
    elif ev.kind == ABORT:
        abort = AbortRequest.from_payload(ev.payload)
        assert abort is not None and abort.to_payload() == ev.payload
        ack = encode_control(MISSION, ABORT_ACK, ack_payload(ev, {1, 2}), [1, 2])  # what every bus sends
        echo, why = parse_control(ack, MISSION, 6.0)
        assert echo is not None and read_ack(echo, abort.id, {1, 2}, "zenoh") is not None, why
    else:
        ack = AckReport.from_payload(ev.payload)
        assert ack is not None and ack.to_payload() == ev.payload
        read_ack(ev, "x" if ack.abort_id is None else ack.abort_id, set(ack.drones), "zenoh")
    return None


def control(kind: str, payload: Any, origin: Any = None, mission: str = MISSION) -> bytes:
    """A control message as JSON text, whatever its parts (origin default [1])."""
    body = {"mission": mission, "kind": kind, "payload": payload, "origin": [1] if origin is None else origin}
    return json.dumps(body).encode()


# ---- every decoder: arbitrary bytes -------------------------------------------------------------------
@settings(max_examples=5000)
@given(st.binary(max_size=400))
@example(struct.pack("<I", 100_000) + b"[" * 100_000)
@example(struct.pack("<I", 2) + b"[]")
@example(b"[" * 60_000)
@example(b'{"mission": "prop_test", "kind": "status", "payload": {"drone": 1, "t": []}, "origin": [1]}')
def test_arbitrary_bytes(data: bytes) -> None:
    """The same bytes as a tick (and its consumers), a cmd, and a control message."""
    consume_tick(data)
    cmd, reason = wm.decode_cmd(data)
    assert (cmd is None) == (reason is not None)
    consume_control(data)


@settings(max_examples=1500)
@given(st.binary(max_size=300))
def test_arbitrary_bytes_in_a_valid_length_frame(head: bytes) -> None:
    data = struct.pack("<I", len(head)) + head
    consume_tick(data)
    cmd, reason = wm.decode_cmd(data)
    assert (cmd is None) == (reason is not None)


# ---- world tick ---------------------------------------------------------------------------------------
@settings(max_examples=400)
@given(json_values, st.integers(-2, 5))
def test_tick_arbitrary_json_in_a_valid_frame(value: Any, k: int) -> None:
    consume_tick(framed(value))
    if isinstance(value, dict):
        consume_tick(framed({**value, "v": 1, "k": k}))


@settings(max_examples=800)
@given(st.data())
def test_tick_mutations(data: st.DataObject) -> None:
    header, image = data.draw(st.sampled_from(base_ticks()))
    assert consume_tick(wm.pack(header, image)) is None
    consume_tick(wm.pack(data.draw(mutated(header)), image))
    consume_tick(data.draw(non_finite(wm.pack(header, image))))


@settings(max_examples=400)
@given(ticks())
def test_tick_round_trip(value: tuple[wm.WorldTick, np.ndarray | None]) -> None:
    tick, image = value
    data = wm.encode_tick(tick, image)
    got, got_image, reason = wm.decode_tick(data)
    assert reason is None and got == tick
    assert (got_image is None and image is None) or np.array_equal(got_image, image)  # type: ignore[arg-type]
    assert got.header() == json.loads(data[4 : 4 + struct.unpack_from("<I", data)[0]])  # type: ignore[union-attr]
    assert consume_tick(data) is None


# ---- world cmd ----------------------------------------------------------------------------------------
@settings(max_examples=300)
@given(json_values, st.integers(-2, 5))
@example([[{}]], 5)
def test_cmd_arbitrary_json_in_a_valid_frame(value: Any, k: int) -> None:
    consume_cmd(framed({"v": 1, "k": k, "calls": value}))
    consume_cmd(framed({"v": 1, "k": k, "calls": [value]}))
    consume_cmd(framed(value))


@settings(max_examples=400)
@given(st.sampled_from(BASE_CMDS), st.data())
def test_cmd_mutations(header: dict[str, Any], data: st.DataObject) -> None:
    consume_cmd(wm.pack(data.draw(mutated(header))))
    consume_cmd(data.draw(non_finite(wm.pack(header))))


@settings(max_examples=400)
@given(cmds)
def test_cmd_round_trip_and_apply(cmd: wm.WorldCmd) -> None:
    data = wm.encode_cmd(cmd)
    assert wm.decode_cmd(data) == (cmd, None)
    assert consume_cmd(data) is None


@settings(max_examples=600)
@given(st.lists(st.floats() | st.integers(-(10**30), 10**30), min_size=4, max_size=4))
def test_saturated_velocity_is_accepted_and_unchanged_in_range(v: list[float]) -> None:
    sat = wm.saturate_velocity(np.array(v, dtype=float))
    cmd = wm.WorldCmd(0, (wm.DroneCall(wm.VELOCITY_CALL, sat),))
    assert wm.decode_cmd(wm.encode_cmd(cmd)) == (cmd, None)
    f = [float(x) for x in v]
    if all(map(math.isfinite, f)) and math.hypot(*f[:3]) <= wm.MAX_SPEED_MPS and abs(f[3]) <= wm.MAX_YAW_RATE:
        assert sat == tuple(f)  # the agents' commands (≤ 1 m/s) pass bit for bit


# ---- control: abort, abort_ack, status ----------------------------------------------------------------
@settings(max_examples=300)
@given(st.sampled_from(sorted(CONTROL_KINDS)), json_values, json_values)
def test_control_arbitrary_json_in_a_valid_envelope(kind: str, payload: Any, origin: Any) -> None:
    consume_control(control(kind, payload))
    consume_control(control(kind, {"drone": 1, "reason": "r", "id": "i", "x": payload}, origin))
    consume_control(json.dumps(payload).encode())


@settings(max_examples=800)
@given(st.sampled_from(BASE_CONTROL), st.data())
def test_control_mutations(base: tuple[str, dict[str, Any]], data: st.DataObject) -> None:
    kind, payload = base
    origin = [payload["drone"]] if kind == STATUS else [1, 2]
    doc = {"mission": MISSION, "kind": kind, "payload": payload, "origin": origin}
    assert consume_control(json.dumps(doc).encode()) is None
    consume_control(json.dumps(data.draw(mutated(doc))).encode())
    consume_control(json.dumps(doc).replace(": 1", ": NaN", 1).encode())


@settings(max_examples=400)
@given(payloads, st.lists(st.integers(0, 2**16 - 1), max_size=3))
def test_control_round_trip(value: tuple[str, Any], origin: list[int]) -> None:
    kind, typed = value
    ev, reason = parse_control(encode_control(MISSION, kind, typed.to_payload(), origin), MISSION, 1.0)
    assert reason is None and ev is not None
    assert (ev.kind, ev.payload, ev.origin) == (kind, typed.to_payload(), tuple(sorted(origin)))
    assert type(typed).from_payload(ev.payload) == typed
    if kind == STATUS:
        consume_control(encode_control(MISSION, kind, typed.to_payload(), [typed.drone]))


# ---- regressions: each crash found before the decoders were total -------------------------------------
def test_regression_unhashable_call_name() -> None:
    """decode_cmd on [[{}]]: TypeError (unhashable dict in `c[0] in DRONE_CALLS`)."""
    assert wm.decode_cmd(framed({"v": 1, "k": 5, "calls": [[{}]]})) == (None, "unknown call")
    assert wm.decode_cmd(framed({"v": 1, "k": 5, "calls": [[["land"]]]})) == (None, "unknown call")


def test_regression_image_shapes() -> None:
    """An image shape [-2, 0] (reshape ValueError), non-int sizes (TypeError), oversized images."""
    for shape in ([-2, 0], [0, 0], ["2", 1], [1.5, 2], [True, 1], [1, 2, 3], [wm.MAX_IMAGE_SIDE + 1, 1]):
        frame = {"stamp": 0.3, "features": None, "image": shape}
        assert wm.decode_tick(framed(tick_header(frame=frame)))[2] == "bad image", shape
    frame = {"stamp": 0.3, "features": None, "image": [1, wm.MAX_IMAGE_SIDE]}
    ok = wm.pack(tick_header(frame=frame), np.zeros((1, wm.MAX_IMAGE_SIDE, 3), np.uint8))
    assert consume_tick(ok) is None
    assert consume_tick(wm.pack(tick_header(), np.zeros((1, 1, 3), np.uint8))) == "bad image"  # no shape


def test_regression_deep_nesting() -> None:
    """100k `[`: RecursionError out of json.loads (not a ValueError)."""
    deep = b"[" * 100_000
    assert wm.decode_tick(struct.pack("<I", len(deep)) + deep) == (None, None, "too deep")
    assert wm.decode_cmd(struct.pack("<I", len(deep)) + deep) == (None, "too deep")
    nested = framed({"v": 1, "k": 1, "calls": json.loads("[" * 900 + "]" * 900)})
    assert wm.decode_cmd(nested) == (None, "too deep")
    assert parse_control(b"[" * 60_000, MISSION, 0.0) == (None, "control: malformed")
    assert parse_control(b"[" * (MAX_CONTROL_BYTES + 1), MISSION, 0.0) == (None, "control: too large")


def test_regression_forged_tick_with_empty_state_keeps_the_agent_running() -> None:
    """`"state": {}` crashed the agent in RemoteDrone.state() (KeyError) and it wrote no recording."""
    link = _Link(FakeSession(), "p", MISSION, 1, 1.0)
    assert link.receive(framed(tick_header())) is None
    assert link.receive(framed(tick_header(k=4, state={}))) == "bad state"
    for state in (
        {"battery_pct": "x"},
        {**tick_header()["state"], "phase": 3},
        {**tick_header()["state"], "flying": 1},
    ):
        assert link.receive(framed(tick_header(k=4, state=state))) == "bad state"
    cam = {"stamp": None, "features": None, "image": None}
    assert link.receive(framed(tick_header(k=4, frame=cam))) == "bad frame"  # RemoteCamera KeyError/TypeError
    assert link.receive(framed(tick_header(k=4, frame={"features": None, "image": None}))) == "bad frame"
    assert RemoteDrone(link).state() == DroneState(88.5, 1.0, True, True, "flying")  # the last good tick
    assert link.receive(framed(tick_header(k=5, t=0.1))) == "tick time went back"
    assert link.dropped == {"bad state": 4, "bad frame": 2, "tick time went back": 1}


def test_regression_status_fields_of_the_wrong_type() -> None:
    """`"t": []` crashed `flightstack status` (format of a list); so did a dropped that is not a dict
    (AttributeError) and a str n_fused (ValueError); a status missing a field is refused too."""
    good = GOOD_STATUS
    bad = [{"t": []}, {"dropped": [1]}, {"n_fused": "1"}, {"battery_pct": 101}, {"mode": "\x1b[2J"}]
    bad += [{"rejection": "x\x1b[31m"}, {"flying": 1}, {"t": 1e10}, {"dropped": {"a": -1}}, {"drone": True}]
    for change in bad:
        assert parse_control(control(STATUS, {**good, **change}), MISSION, 0.0) == (
            None,
            "control: bad status",
        )
    partial = {k: v for k, v in good.items() if k != "rejection"}
    assert parse_control(control(STATUS, partial), MISSION, 0.0) == (None, "control: bad status")
    ev, _ = parse_control(control(STATUS, {**good, "extra": [1]}), MISSION, 0.0)  # unknown fields: ignored
    assert ev is not None and ev.payload == good
    assert consume_control(control(STATUS, good)) is None


def test_regression_abort_and_ack_payloads() -> None:
    assert consume_control(control(ABORT, {"reason": "r", "id": "a1"})) is None
    for bad in (
        {"reason": "r"},
        {"reason": 1, "id": "a"},
        {"reason": "r" * 1025, "id": "a"},
        {"reason": "r", "id": "\n"},
    ):
        assert parse_control(control(ABORT, bad), MISSION, 0.0) == (None, "control: bad abort")
    ev, _ = parse_control(control(ABORT, {"reason": "a\x1b[2J\nb", "id": "a2"}), MISSION, 0.0)
    assert ev is not None and ev.payload == {"reason": "a\ufffd[2J\ufffdb", "id": "a2"}  # obeyed, printable
    good = {"abort_id": "a1", "drones": [1], "pid": 7, "host": "h"}
    assert consume_control(control(ABORT_ACK, good)) is None
    for change in ({"drones": []}, {"drones": [-1]}, {"pid": "7"}, {"host": "h\x1b"}, {"abort_id": 5}):
        assert parse_control(control(ABORT_ACK, {**good, **change}), MISSION, 0.0) == (
            None,
            "control: bad abort_ack",
        )
    assert (
        parse_control(control(ABORT, {"reason": "r", "id": "a"}, origin=[-1]), MISSION, 0.0)[1]
        == "control: malformed"
    )


def test_regression_forged_world_commands() -> None:
    """A 50 m/s velocity was applied; so was an emergency_stop from any key. Now: out-of-range velocities
    and cmds of an unknown sender or of a tick not yet published are refused and counted; a well-formed
    cmd on an agent's own key is authenticated by the transport (mutual TLS + ACL), not here."""
    fast = framed({"v": 1, "k": 1, "calls": [["send_body_velocity", [50.0, 0.0, 0.0, 0.0]]]})
    spin = framed({"v": 1, "k": 1, "calls": [["send_body_velocity", [0.0, 0.0, 0.0, 5.5]]]})
    assert wm.decode_cmd(fast) == wm.decode_cmd(spin) == (None, "velocity out of range")
    assert wm.decode_cmd(framed({"v": 1, "k": 1, "calls": [["land", 1]]})) == (None, "bad call")
    stop = framed({"v": 1, "k": 1, "calls": [["emergency_stop"]]})
    srv = served_world("paper_sim.yaml")
    srv._tick_k = 0
    assert srv.receive_cmd("p/m/world/cmd/7", stop) == "unknown sender"
    assert srv.receive_cmd("p/m/world/cmd/x", stop) == "unknown sender"
    assert srv.receive_cmd("", stop) == "unknown sender"
    for key in ("p/m/world/cmd/01", "p/m/world/cmd/+1", "p/m/world/cmd/1_0", "p/m/world/cmd/" + "1" * 5000):
        assert srv.receive_cmd(key, stop) == "unknown sender"  # only the agent's own key names it
    assert srv.receive_cmd("p/m/world/cmd/1", stop) == "cmd of a future tick"  # would pin lock-step
    assert srv.receive_cmd("p/m/world/cmd/1", fast) == "velocity out of range"
    assert srv._dropped == {"unknown sender": 7, "cmd of a future tick": 1, "velocity out of range": 1}
    assert srv._done_k[1] == -2 and not srv._queued


def test_regression_non_finite_and_huge_numbers() -> None:
    head = json.dumps(tick_header()).encode()
    for word, reason in ((b"NaN", "not JSON"), (b"-Infinity", "not JSON"), (b"1e999", "bad state")):
        assert wm.decode_tick(raw(head.replace(b"88.5", word)))[2] == reason  # 1e999 parses as inf
    huge = framed(
        tick_header(poses={"drone1": [0.3, 10**400, 0.0, 0.0, 0.0]})
    )  # int beyond float: no OverflowError
    assert wm.decode_tick(huge)[2] == "bad poses"
    assert wm.decode_tick(framed(tick_header(t=10**400)))[2] == "bad tick"
    assert wm.decode_cmd(framed({"v": 1, "k": 1, "calls": [["send_body_velocity", [10**400, 0, 0, 0]]]}))[1]
    assert wm.decode_tick(framed(tick_header(v=True)))[2] == "bad header"


def test_old_world_messages_decode_to_the_same_values() -> None:
    """A tick and a cmd as the encoders before the typed decoders wrote them decode to the same values."""
    header = tick_header()
    tick, _, reason = wm.decode_tick(framed(header))
    assert reason is None and tick is not None and tick.header() == header
    cmd = {"v": 1, "k": 7, "calls": [["connect"], ["takeoff"], ["send_body_velocity", [0.1, -0.2, 0.0, 0.3]]]}
    got, reason = wm.decode_cmd(framed(cmd))
    assert reason is None and got is not None and got.header() == cmd


def test_a_backlog_of_calls_is_sent_in_decodable_cmds() -> None:
    """After the world was lost, the final flush may carry more than MAX_CALLS calls: sent in order, in
    cmds the world accepts."""
    session = FakeSession()
    link = _Link(session, "p", MISSION, 1, 1.0)
    assert link.receive(framed(tick_header())) is None
    for _ in range(2 * wm.MAX_CALLS + 3):
        RemoteDrone(link).send_body_velocity(np.array([100.0, 0.0, 0.0, np.nan]))  # saturated: accepted
    RemoteDrone(link).land()
    link.flush()
    got = [wm.decode_cmd(d) for d in session.pub.sent]
    assert [len(c.calls) for c, _ in got] == [wm.MAX_CALLS, wm.MAX_CALLS, 4]  # type: ignore[union-attr]
    assert got[-1][0].calls[-1] == wm.DroneCall("land")  # type: ignore[union-attr]
    assert all(c is not None and c.k == 3 for c, _ in got)
