"""The emulated lab: `flightstack preflight`, `target` and `fly` against loopback emulators of two Tellos, a
NatNet (OptiTrack) server and a MAVLink rover, through the real client libraries.

All traffic stays on 127.0.0.0/8: the Tello emulators own 127.0.0.6 and 127.0.0.7 (other test modules
use .2–.5), NatNet and the rover use 127.0.0.1 with OS-assigned ports. The lab is in station mode: both
Tello emulators send their state streams to one free port of 127.0.0.1 (`hardware.state_port`).
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from flightstack.config.rig import resolved_document

pytest.importorskip("av")
pytest.importorskip("motioncapture")
pytest.importorskip("pymavlink")

from flightstack.cli.app import main
from flightstack.comms.certs import create_mission_certs, participants
from flightstack.paper.geometry import Pose, compose
from flightstack.ports import free_udp_port
from flightstack.safety.rules import SafetyLimits
from flightstack.sim_backend.emulators.natnet import NatNetEmulator
from flightstack.sim_backend.emulators.rover.emulator import MavlinkRoverEmulator
from flightstack.sim_backend.emulators.tello.base import FAST_TAKEOFF_S
from flightstack.sim_backend.emulators.tello.emulator import TelloEmulator
from flightstack.vision.camera_file import load_calibration
from tests.conftest import MISSIONS, run_cli
from tests.test_tello_driver import marker_frame

CAL_SRC = MISSIONS / "cameras" / "tello_down_sim.yaml"
LEVEL = (1.0, 0.0, 0.0, 0.0)  # quaternion (w, x, y, z) of a level body facing world x


def q_yaw(theta: float) -> tuple[float, float, float, float]:
    return (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))


def rover_mocap_pose(rover: MavlinkRoverEmulator) -> tuple[object, tuple[float, float, float, float]]:
    """The rover's pose in the mocap world: its start is the square's corner (-0.5, -0.5), θ = 0."""
    g = compose(Pose.make([-0.5, -0.5, 0.0], 0.0), rover.pose_flu())
    return g.p, q_yaw(g.theta)


DRONE_STARTS = {1: Pose.make([-0.5, -0.5, 0.05], 0.0), 2: Pose.make([-0.5, 0.2, 0.05], 0.3)}


def tello_mocap_pose(emu: TelloEmulator, start: Pose) -> tuple[object, tuple[float, float, float, float]]:
    """The emulated Tello's pose in the mocap world. The emulator integrates from its takeoff point in
    (x forward, y right, z up) cm with yaw clockwise in degrees; the world is FLU (y left, yaw ccw)."""
    x, y, z = emu.position_cm
    g = compose(start, Pose.make([x / 100.0, -y / 100.0, z / 100.0], -math.radians(emu.yaw_deg)))
    return g.p, q_yaw(g.theta)


@dataclass
class Lab:
    tellos: dict[int, TelloEmulator]
    natnet: NatNetEmulator
    rover: MavlinkRoverEmulator
    mission: Path


def write_mission(
    tmp: Path, lab_tellos: dict[int, TelloEmulator], natnet: NatNetEmulator, rover_url: str
) -> Path:
    """The paper experiment's mission, re-pointed at the emulators (backend tello)."""
    cal = load_calibration(CAL_SRC).to_dict()
    cal["rms_px"] = 0.3  # a measured calibration (preflight fails on the never-measured templates)
    cal["device"] = "emulated tello"
    (tmp / "cal.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
    m = resolved_document("paper_experiment")
    m["name"] = "emulated_lab"
    # a free port for the abort listener of this in-process hardware mission: the name-derived default
    # (21183) was once found taken on a CI machine, failing every flight of this file
    m.setdefault("bus", {})["operator_port"] = free_udp_port()
    m["backend"] = "tello"
    del m["sim"]
    for d in m["drones"]:
        d["camera"] = {"calibration": "cal.yaml", "mount": "down"}
    m["drones"][1]["desired_pose"] = {"p": [0.0, 0.7, -1.0], "theta": 0.0}
    m["hardware"] = {
        "topology": "station",
        "state_port": next(iter(lab_tellos.values())).state_port,
        "drones": [
            {
                "id": i,
                "ip": emu.ip,
                "control_port": emu.address[1],
                "video_port": emu.video_port,
                "connect_timeout_s": 2.0,
                "command_timeout_s": 1.0,
                "frame_timeout_s": 5.0,
            }
            for i, emu in lab_tellos.items()
        ],
        "mocap": {
            "system": "optitrack",
            "settings": natnet.settings(),
            "bodies": {"drone1": "tello_a", "drone2": "tello_b", "target": "scamper"},
            "connect_timeout_s": 1.0,
        },
        "target": {"url": rover_url, "heartbeat_timeout_s": 3.0},
    }
    path = tmp / "mission.yaml"
    path.write_text(yaml.safe_dump(m, sort_keys=False))
    ids = [d["id"] for d in m["drones"]]
    create_mission_certs(m["name"], participants(ids, None), tmp / "certs")  # what bus.certs names
    return path


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[Lab]:
    state_port = free_udp_port()
    tellos = {
        i: TelloEmulator(
            ip,
            state_port=state_port,
            video_port=free_udp_port(),
            frame_source=marker_frame,
            video_size=(320, 240),
            takeoff_s=FAST_TAKEOFF_S,  # a pursuit, not a takeoff test: the recorded 8.7 s would add 8.4 s
        )
        for i, ip in ((1, "127.0.0.6"), (2, "127.0.0.7"))
    }
    natnet = NatNetEmulator(
        {
            "tello_a": (DRONE_STARTS[1].p, q_yaw(DRONE_STARTS[1].theta)),
            "tello_b": (DRONE_STARTS[2].p, q_yaw(DRONE_STARTS[2].theta)),
            "scamper": ((-0.5, -0.5, 0.0), LEVEL),
        },
        rate_hz=100.0,
    )
    rover = MavlinkRoverEmulator(heartbeat_hz=5.0)
    natnet.set_pose_provider("scamper", lambda: rover_mocap_pose(rover))  # the robot is where the rover is
    for i, body in ((1, "tello_a"), (2, "tello_b")):  # each drone is where its emulator flies it
        natnet.set_pose_provider(body, lambda e=tellos[i], s=DRONE_STARTS[i]: tello_mocap_pose(e, s))
    try:
        for e in tellos.values():
            e.start()
        natnet.start()
        yield Lab(tellos, natnet, rover, write_mission(tmp_path, tellos, natnet, rover.url))
    finally:
        for e in tellos.values():
            e.close()
        natnet.close()
        rover.close()


def run_preflight(mission: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, float]:
    t0 = time.monotonic()
    code = main(["preflight", str(mission)])
    return code, capsys.readouterr().out, time.monotonic() - t0


def test_all_devices_pass(lab: Lab, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_preflight(lab.mission, capsys)
    assert code == 0, out
    assert "preflight: ALL PASS" in out, out
    for expected in (
        "drone 1 (127.0.0.6)",
        "drone 2 (127.0.0.7)",
        "body drone1 = tello_a",
        "body target = scamper",
    ):
        assert expected in out
    assert "320x240" in out  # the camera check decoded a frame of the calibrated size
    assert not lab.rover.armed  # preflight only listens to the robot
    assert not any(e.flying for e in lab.tellos.values())


@pytest.mark.parametrize("device", ["tello 2", "natnet", "rover"])
def test_stopped_device_is_named_and_fails_fast(
    lab: Lab, device: str, capsys: pytest.CaptureFixture[str]
) -> None:
    if device == "tello 2":
        lab.tellos[2].close()
        name = "drone 2 (127.0.0.7)"
    elif device == "natnet":
        lab.natnet.close()
        name = "mocap (optitrack)"
    else:
        lab.rover.close()
        name = "robot (udpout:127.0.0.1"
    code, out, elapsed = run_preflight(lab.mission, capsys)
    assert code == 1, out
    print(f"preflight with {device} down: {elapsed:.1f} s")
    failing = [line for line in out.splitlines() if "  FAIL  " in line]
    assert failing and all(line.startswith(name) for line in failing), out
    assert "do not fly" in out


def test_body_outside_fence_and_uncalibrated_camera_fail(
    lab: Lab, capsys: pytest.CaptureFixture[str]
) -> None:
    lab.natnet.set_body("tello_b", (3.5, 0.0, 0.05), LEVEL)  # the fence is x, y in [-2, 2]
    cal = yaml.safe_load((lab.mission.parent / "cal.yaml").read_text())
    cal["rms_px"] = None
    (lab.mission.parent / "cal.yaml").write_text(yaml.safe_dump(cal))
    code, out, _ = run_preflight(lab.mission, capsys)
    assert code == 1
    assert any(
        "body drone2 = tello_b" in ln and "FAIL" in ln and "OUTSIDE" in ln for ln in out.splitlines()
    ), out
    assert "never measured" in out


def test_a_video_setting_the_firmware_refuses_fails_preflight_in_one_line(
    lab: Lab, capsys: pytest.CaptureFixture[str]
) -> None:
    """The lab file asks `setfps high` of every drone; drone 2's firmware does not know it (DJITelloPy #144,
    #219): one FAIL line names the key, the drone, its reply and the fix; drone 1 confirmed it."""
    m = yaml.safe_load(lab.mission.read_text())
    m["hardware"]["video"] = {"fps": "high"}
    lab.mission.write_text(yaml.safe_dump(m, sort_keys=False))
    lab.tellos[2].faults.unknown_commands = {"setfps"}
    code, out, _ = run_preflight(lab.mission, capsys)
    assert code == 1, out
    lines = out.splitlines()
    rows = [ln for ln in lines if " video fps " in ln]
    assert len(rows) == 2, out  # one row per drone
    ok, bad = rows
    assert ok.startswith("drone 1 (127.0.0.6)") and "  PASS  " in ok and "`setfps high` confirmed (ok)" in ok
    assert bad.startswith("drone 2 (127.0.0.7)") and "  FAIL  " in bad
    assert bad.endswith(
        "hardware.video.fps (`setfps high`): Tello 127.0.0.7 answered 'unknown command: setfps'; remove the "
        "key or update the firmware (the SDK 3.0 video settings need a Tello EDU or Talent)"
    )
    failing = [ln for ln in lines if "  FAIL  " in ln]
    assert failing == [bad, *[ln for ln in failing if "camera" in ln and "not started" in ln]], out
    assert lab.tellos[1].fps == 30.0 and "streamon" not in lab.tellos[2].command_texts()


def test_a_plain_tello_as_the_drone_that_looks_down_is_refused_in_one_line(
    lab: Lab, capsys: pytest.CaptureFixture[str]
) -> None:
    """paper_experiment's drone 1 finds the target with its downward camera (`downvision`: SDK 3.0, a
    Tello EDU's); a plain Tello there (SDK 2.0) is refused by one FAIL line naming the drone, its firmware
    and the fix, and nothing of its camera is started."""
    lab.tellos[1].faults.sdk_version = "20"
    code, out, _ = run_preflight(lab.mission, capsys)
    assert code == 1, out
    failing = [ln for ln in out.splitlines() if "  FAIL  " in ln]
    assert len(failing) == 1, out
    (line,) = failing
    assert line.startswith("drone 1 (127.0.0.6)") and "  firmware  " in line, line
    assert "SDK 2.0" in line and "downward camera (`downvision`)" in line and "Tello EDU" in line, line
    assert not any(t.startswith(("downvision", "streamon")) for t in lab.tellos[1].command_texts())


def test_fly_runs_preflight_then_refuses_without_confirmation(
    lab: Lab, capsys: pytest.CaptureFixture[str]
) -> None:
    """Non-interactive `fly` without --yes: preflight passes, nothing takes off, nothing is armed."""
    code = main(["fly", str(lab.mission), "--out", str(lab.mission.parent / "run")])
    out, err = capsys.readouterr()
    assert code == 1
    assert "preflight: ALL PASS" in out and "pass --yes" in err
    assert not any(e.flying for e in lab.tellos.values()) and not lab.rover.armed
    assert not (lab.mission.parent / "run").exists()


def test_target_command_drives_a_quarter_lap(lab: Lab, capsys: pytest.CaptureFixture[str]) -> None:
    """`flightstack target` closes the loop rover → NatNet → square law → MAVLink, then disarms: the rig's
    robot is differential, so the law is the unicycle square (one side, then a turn in place)."""
    m = yaml.safe_load(lab.mission.read_text())
    m["target"]["square"] = {"side_m": 1.0, "speed_mps": 0.3}  # the lab's law, 3x faster on its sides
    lab.mission.write_text(yaml.safe_dump(m))
    code = main(["target", str(lab.mission), "--laps", "0.25", "--yes"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "ended by duration" in out
    x, y = (float(v) for v in rover_mocap_pose(lab.rover)[0][:2])
    print(f"quarter lap ended at ({x:.3f}, {y:.3f}) m")
    assert abs(x - 0.5) < 0.05 and abs(y + 0.5) < 0.05  # one side of the square: (-0.5,-0.5) → (0.5,-0.5)
    assert not lab.rover.armed  # stopped and disarmed on exit


def test_target_opens_the_emulated_lab_rig_like_every_command() -> None:
    """`flightstack target EXPERIMENT --rig emulated-lab` starts the rig's emulators itself (Rig.open), as
    `run` does, and drives the emulated robot a quarter lap of paper_experiment's square."""
    res = run_cli(
        "target", "mission_configs/paper_experiment.yaml", "--rig", "emulated-lab", "--laps", "0.25", "--yes",
        timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    summary = next(line for line in res.stdout.splitlines() if "laps in" in line)
    print(summary)
    measured, commanded = (float(v) for v in re.findall(r"([\d.]+) m (?:measured|commanded)", summary))
    assert "ended by duration" in summary and abs(measured - commanded) < 0.05 * commanded


def test_fly_a_short_mission_on_the_emulated_lab(lab: Lab, capsys: pytest.CaptureFixture[str]) -> None:
    """`flightstack fly --yes`: preflight, takeoff, pursuit with rc commands, landing, a recording."""
    import numpy as np

    m = yaml.safe_load(lab.mission.read_text())
    m["compare_modes"] = ["none"]
    m["target"]["square"]["speed_mps"] = 0.1
    lab.mission.write_text(yaml.safe_dump(m))
    out_dir = lab.mission.parent / "run"
    code = main(["fly", str(lab.mission), "--out", str(out_dir), "--duration", "3", "--yes", "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 0, out + err
    assert "preflight: ALL PASS" in out
    assert all(len(e.rc_history) > 20 for e in lab.tellos.values())  # 20 Hz control for 3 s
    assert not any(e.flying for e in lab.tellos.values())  # every drone landed
    assert not lab.rover.armed  # the robot was driven, then stopped and disarmed
    assert not [e for e in lab.rover.failsafe_events if e.armed]  # its GCS failsafe never acted while armed
    assert lab.rover.setpoint_records
    rec = np.load(out_dir / "timeseries_none.npz")
    assert np.all(np.isfinite(rec["g_wi"])) and rec["g_wi"].shape[0] == 60
    assert np.all(rec["g_wi"][:, :, 2] > 0.3)  # airborne (mocap z) for the whole pursuit
    events = (out_dir / "events.jsonl").read_text()
    assert events.count('"event": "landed"') == 2 and "NOT LANDED" not in events
    # a clean flight: no pose judged stale, frozen or disagreeing with the drone's height (pose_check)
    suspect = ("pose_stale_hover", "pose_stale_land", "pose_frozen", "pose_disagrees", "robot_pose_suspect")
    assert not [k for k in suspect if f'"kind": "{k}"' in events], events
    # loop health: every tick after the first timed, real time, the ages of what was used
    health = json.loads((out_dir / "metrics.json").read_text())["modes"]["none"]["loop_health"]
    assert health["real_time"] and health["dt_s"] == 0.05
    assert health["period_s"]["n"] == 59 and health["compute_s"]["n"] == 60
    assert health["period_s"]["p50"] > 0.045  # sleeps until start + dt: never much less than dt
    # each period holds the previous tick's compute (a loop overrunning on a loaded machine: period ≈ compute)
    assert health["compute_s"]["p50"] > 0
    assert np.all(rec["loop_period"][1:] >= rec["loop_compute"][:-1] - 1e-3)
    assert health["overruns"] == int((rec["loop_period"][1:] > health["overrun_above_s"]).sum())
    # a tick without a decoded frame yet uses none (the camera thread can miss one on a loaded machine)
    print(f"ticks with a frame: {health['frame_age_s']['n']} of 120")
    assert health["frame_age_s"]["n"] >= 117 and 0 <= health["frame_age_s"]["p50"] < 0.5  # 320x240 video
    # a tick whose own pose is older than pose_timeout uses none (that drone hovers): on a loaded machine
    # the mocap thread can miss one. Motion capture hands out no pose older than 0.1 s when read; at the
    # tick's time, or as the last admitted pose while a newer stamp is refused, the pose used may be older
    # (0.109 s seen in a fresh-clone run): never past pose_timeout
    ages = health["pose_age_s"]
    print(f"ticks with a fresh own pose: {ages['n']} of 120, oldest {ages['max']:.3f} s")
    assert ages["n"] >= 117 and 0 <= ages["max"] <= SafetyLimits().pose_timeout
    assert (out_dir / "loop_health.png").stat().st_size > 10_000
    assert "loop kept dt" in out or "loop DID NOT keep dt" in out, out
    assert "x real time" not in out  # a wall-clock run has no simulation speed to report


def test_fly_with_a_drone_losing_its_link(lab: Lab, capsys: pytest.CaptureFixture[str]) -> None:
    """Drone 2's state stream stops for 1.6 s in pursuit: its driver reports the link lost after 1 s,
    the safety layer lands it once the link is back; drone 1 flies the mission to its end."""
    import json
    import threading

    m = yaml.safe_load(lab.mission.read_text())
    m["compare_modes"] = ["none"]
    lab.mission.write_text(yaml.safe_dump(m))
    emu2 = lab.tellos[2]

    def drop_state() -> None:
        deadline = time.monotonic() + 30
        while len(emu2.rc_history) < 20 and time.monotonic() < deadline:  # ~1 s into pursuit
            time.sleep(0.02)
        emu2.faults.drop_state = True
        time.sleep(1.6)
        emu2.faults.drop_state = False

    fault = threading.Thread(target=drop_state, daemon=True)
    fault.start()
    out_dir = lab.mission.parent / "run"
    code = main(["fly", str(lab.mission), "--out", str(out_dir), "--duration", "5", "--yes", "--no-progress"])
    fault.join(timeout=5)
    out, err = capsys.readouterr()
    assert code == 0, out + err
    events = [json.loads(x) for x in (out_dir / "events.jsonl").read_text().splitlines()]
    safety = [e for e in events if e.get("event") == "safety"]
    lost = [e for e in safety if e["kind"] == "link_lost" and e["drone"] == 2]
    land2 = [e for e in safety if e["kind"] == "land" and e["drone"] == 2]
    assert lost and land2 and land2[0]["t"] > lost[0]["t"], safety
    assert "link_lost" in land2[0]["detail"]  # landed because of the link loss, not at the mission's end
    assert not [
        e for e in safety if e["kind"] in ("link_lost", "land") and e["drone"] == 1 and e["t"] < land2[0]["t"]
    ]
    assert not any(e.flying for e in lab.tellos.values())
    assert [e["event"] for e in events if e.get("drone") in (1, 2) and "LANDED" in e["event"].upper()] == [
        "landed",
        "landed",
    ]


def test_fly_with_motion_capture_frames_stopping(lab: Lab, capsys: pytest.CaptureFixture[str]) -> None:
    """The NatNet server stops sending frames in pursuit: every drone hovers after pose_timeout, lands after
    pose_land_after (both from its last pose), and the run ends when they are down."""
    import json
    import threading

    m = yaml.safe_load(lab.mission.read_text())
    m["compare_modes"] = ["none"]
    lab.mission.write_text(yaml.safe_dump(m))

    rc_before = len(lab.tellos[1].rc_history)  # the lab serves every test of this module

    def stop_frames() -> None:
        deadline = time.monotonic() + 30
        while len(lab.tellos[1].rc_history) < rc_before + 20 and time.monotonic() < deadline:
            time.sleep(0.02)
        lab.natnet.faults.drop_frames = True

    threading.Thread(target=stop_frames, daemon=True).start()
    out_dir = lab.mission.parent / "run"
    code = main(
        ["fly", str(lab.mission), "--out", str(out_dir), "--duration", "20", "--yes", "--no-progress"]
    )
    lab.natnet.faults.drop_frames = False
    out, err = capsys.readouterr()
    assert code == 0, out + err
    events = [json.loads(x) for x in (out_dir / "events.jsonl").read_text().splitlines()]
    kinds = [(e["kind"], e["drone"]) for e in events if e.get("event") == "safety"]
    for i in (1, 2):
        assert ("pose_stale_hover", i) in kinds and ("pose_stale_land", i) in kinds, kinds
    end = next(e for e in events if e.get("event") == "end")
    assert end["reason"] == "every drone landed"  # well before the 20 s mission would have ended
    assert not any(e.flying for e in lab.tellos.values())
