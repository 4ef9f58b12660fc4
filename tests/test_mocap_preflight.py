"""drivers/lab/preflight.py check_mocap against what a real Motive may stream: its default Y-up frame (the
recorded session of ../shared/data/peers/natnet/ and synthetic Y-up streams), a body missing from the
model definitions, and unicast frames libmotioncapture cannot receive. Each stream is served by
sim_backend/emulators/natnet_replay.py on loopback (multicast through the loopback interface, TTL 0)."""

from __future__ import annotations

import math
import socket
from collections.abc import Sequence

import pytest

from flightstack.config.mission import Mission, parse_mission
from flightstack.config.rig import resolved_document
from flightstack.drivers.lab.preflight import UNICAST_FIX, UP_AXIS_FIX, CheckRow, check_mocap, y_up_signs
from flightstack.sim_backend.emulators.natnet import frame_packet, model_def_packet, server_info_packet
from flightstack.sim_backend.emulators.natnet_replay import NatNetRecording, NatNetReplayer, read_pcapng
from tests.conftest import PEERS, skip_or_fail_in_ci

pytestmark = pytest.mark.system  # a responder process, loopback multicast

pytest.importorskip("motioncapture")

BODIES = {"drone1": "cf1", "drone2": "cf2", "target": "rover"}
IDS = {"cf1": 1, "cf2": 2, "rover": 3}
LEVEL = (1.0, 0.0, 0.0, 0.0)


def q_about(axis: str, angle: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by `angle` (rad) about Motive's `axis`."""
    c, s = math.cos(angle / 2), math.sin(angle / 2)
    return {"x": (c, s, 0.0, 0.0), "y": (c, 0.0, s, 0.0), "z": (c, 0.0, 0.0, s)}[axis]


def synthetic(
    bodies: dict[str, tuple[Sequence[float], Sequence[float]]],
    extra: Sequence[tuple[int, Sequence[float]]] = (),
) -> NatNetRecording:
    """2 s of 100 Hz NatNet 3.0 frames of fixed bodies (name -> position m, quaternion (w, x, y, z)); the
    model definitions define them; `extra` (id, position) bodies are streamed level but not defined."""
    defs = [(name, IDS[name]) for name in bodies]
    rows = [(IDS[n], p, q, True) for n, (p, q) in bodies.items()] + [(i, p, LEVEL, True) for i, p in extra]
    frames = tuple((k / 100.0, frame_packet(k + 1, k / 100.0, rows)) for k in range(200))
    info = bytearray(server_info_packet(1511))
    info[279:283] = bytes([239, 255, 42, 99])  # the replayer sets DataPort and IsMulticast
    return NatNetRecording("synthetic", bytes(info), model_def_packet(defs), frames)


def mission(settings: dict[str, str], bodies: dict[str, str] = BODIES) -> Mission:
    m = resolved_document("paper_experiment", "lab")
    m["hardware"]["mocap"]["settings"] = settings
    m["hardware"]["mocap"]["bodies"] = dict(bodies)
    m["hardware"]["mocap"]["connect_timeout_s"] = 3.0
    return parse_mission(m, "test")


def preflight(
    rec: NatNetRecording, delivery: str = "multicast", bodies: dict[str, str] = BODIES
) -> list[CheckRow]:
    with NatNetReplayer(rec, delivery=delivery, start_delay_s=0.05) as rep:  # type: ignore[arg-type]
        rows = check_mocap(mission(rep.settings(), bodies))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # wakes a reader that got no frame
            s.sendto(b"", ("127.0.0.1", rep.data_port))
        return rows


def fails(rows: list[CheckRow]) -> list[CheckRow]:
    return [r for r in rows if r.status == "FAIL"]


ON_FLOOR = {  # a Z-up stream: drones standing on the floor, the target on it
    "cf1": ((-0.5, -0.5, 0.05), q_about("z", 0.4)),
    "cf2": ((-0.5, 0.2, 0.05), q_about("z", -2.0)),
    "rover": ((0.5, 0.5, 0.1), LEVEL),
}


def test_z_up_stream_passes() -> None:
    rows = preflight(synthetic(ON_FLOOR))
    assert not fails(rows), rows
    assert "multicast 239.255.42.99" in rows[0].detail and "NatNet 3.0.0.0" in rows[0].detail


def test_recorded_y_up_stream_is_refused_with_one_line() -> None:
    """The recorded Motive session (Y-up, Motive's default): RaceQuad 1.447 m up along y."""
    path = PEERS / "natnet" / "python_natnet" / "traffic.pcapng"
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    rows = preflight(read_pcapng(path), bodies={"drone1": "RaceQuad", "drone2": "cf2", "target": "rover"})
    bad = fails(rows)
    assert len(bad) == 1 and bad[0].check == "up axis", rows
    assert UP_AXIS_FIX in bad[0].detail and "Up Axis to Z Axis" in bad[0].detail
    assert "drone1 = RaceQuad is level about y but tilted 62° from z" in bad[0].detail
    assert "below the floor" in bad[0].detail
    print(bad[0].detail)


@pytest.mark.parametrize("yaw_deg", [0.0, 15.0, -15.0])
@pytest.mark.parametrize("horizontal_z", [0.8, -0.6])
def test_synthetic_y_up_level_body_at_1m_is_refused(yaw_deg: float, horizontal_z: float) -> None:
    """A Y-up stream: drone cf1 level, 1.0 m up along Motive's y, yawed about y (its heading from Motive's x
    axis); the other bodies on the floor of the Y-up world (y = 0.05 m). Before the up-axis check, the
    ±15° and 0° cases passed (tilt under 20°, y = 1.0 inside the fence)."""
    yaw = math.radians(yaw_deg)
    rec = synthetic(
        {
            "cf1": ((0.5, 1.0, horizontal_z), q_about("y", yaw)),
            "cf2": ((-0.5, 0.05, 0.05), LEVEL),
            "rover": ((0.5, 0.05, 0.1), LEVEL),
        }
    )
    rows = preflight(rec)
    bad = fails(rows)
    assert len(bad) == 1 and bad[0].check == "up axis", rows
    assert bad[0].detail.endswith(UP_AXIS_FIX)


def test_y_up_signs_and_their_blind_spot() -> None:
    """The signs one by one, and the case no frame can tell: a level Y-up body yawed 0° standing within
    [-0.1, landed_height] m of Motive's x-y plane reads exactly as a Z-up body on the floor."""
    assert y_up_signs("d", (0.0, 1.0, 0.0), q_about("y", math.radians(15)), True, 0.15)
    assert y_up_signs("d", (0.0, 1.0, 0.0), q_about("y", math.radians(90)), False, 0.15)  # "tilted 90°"
    assert y_up_signs("t", (0.0, 1.0, -0.5), LEVEL, False, 0.15)
    assert y_up_signs("d", (0.0, 1.0, 0.8), LEVEL, True, 0.15)
    assert not y_up_signs("t", (0.0, 1.0, 0.8), LEVEL, False, 0.15)  # a target may stand high
    assert not y_up_signs("d", (0.0, 1.0, 0.05), LEVEL, True, 0.15)  # the blind spot
    assert not y_up_signs("d", (0.3, -0.2, 0.05), q_about("z", 2.5), True, 0.15)  # Z-up, yawed: fine


def test_body_missing_from_the_model_definitions_is_refused() -> None:
    """Body id 7 streamed but not defined (as in the recorded occluded-marker frame): libmotioncapture
    names it ''; preflight refuses with one line naming the fix."""
    rows = preflight(synthetic(ON_FLOOR, extra=[(7, (0.2, 0.3, 0.05))]))
    bad = fails(rows)
    assert len(bad) == 1 and bad[0].check == "bodies", rows
    assert "define the rigid body in Motive before `fly` starts, or reconnect" in bad[0].detail
    assert "at (0.20, 0.30, 0.05) m" in bad[0].detail


def test_motive_style_unicast_is_refused() -> None:
    """Unicast as Motive sends it (to the client's command socket): libmotioncapture reads no frame."""
    rows = preflight(synthetic(ON_FLOOR), delivery="unicast_command")
    bad = fails(rows)
    assert len(bad) == 1 and bad[0].check == "transmission", rows
    assert UNICAST_FIX in bad[0].detail


@pytest.mark.parametrize(
    ("position", "quaternion"),
    [((math.nan,) * 3, LEVEL), ((0.0, 0.0, math.inf), LEVEL), ((0.5, 0.5, 0.1), (math.nan,) * 4)],
    ids=["NaN position", "inf height", "NaN quaternion"],
)
def test_a_body_streaming_non_finite_poses_is_named_so(
    position: tuple[float, float, float], quaternion: tuple[float, float, float, float]
) -> None:
    """The target streamed with a non-finite pose in every frame: its row says it streams non-finite poses
    (it said "never seen", which sends one looking for a body Motive does not stream)."""
    rows = preflight(synthetic({**ON_FLOOR, "rover": (position, quaternion)}))
    bad = fails(rows)
    assert len(bad) == 1 and bad[0].check == "body target = rover", rows
    assert bad[0].detail.startswith("streams non-finite poses: its last "), bad[0].detail
