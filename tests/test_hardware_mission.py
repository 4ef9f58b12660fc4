"""The mission's hardware section (backend `tello`): schema errors name the key; the shipped real-lab
mission validates; hardware missions are refused by `flightstack sim`. No traffic is sent anywhere."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import resolved_document
from tests.conftest import MISSIONS, run_cli

REAL = MISSIONS / "paper_experiment.yaml"


def real() -> dict:
    """The paper experiment on the lab template rig, as one resolved document (absolute camera paths)."""
    return resolved_document("paper_experiment", "lab")


def write(tmp_path: Path, doc: dict) -> Path:
    for name in ("tello_down_template.yaml", "tello_front_template.yaml"):
        (tmp_path / "cameras").mkdir(exist_ok=True)
        (tmp_path / "cameras" / name).write_text((MISSIONS / "cameras" / name).read_text())
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def test_real_lab_mission_validates() -> None:
    m = load_mission(REAL, rig="lab")
    assert m.backend == "tello" and not m.simulated
    assert m.hardware is not None
    assert m.hardware.body("drone1") == "tello1" and m.hardware.body("target") == "scamper"
    assert m.hardware.body("unlisted") == "unlisted"
    # the documented topology: access point, each Tello its own Wi-Fi at 192.168.10.1 on the default
    # ports, one Wi-Fi adapter of this computer per Tello: one process flies both
    assert m.hardware.topology == "access_point"
    assert [(d.ip, d.video_port, d.interface) for d in m.hardware.drones] == [
        ("192.168.10.1", 11111, "wlan1"),
        ("192.168.10.1", 11111, "wlan2"),
    ]
    assert m.hardware.shared_by([1, 2]) is None


def test_drones_at_one_address_need_an_interface_each_to_fly_from_one_process(tmp_path: Path) -> None:
    doc = copy.deepcopy(real())
    doc["hardware"]["drones"][1]["interface"] = "wlan1"  # both behind one adapter: one address, one port
    m = load_mission(write(tmp_path, doc))
    assert m.hardware is not None and m.hardware.shared_by([1]) is None
    assert "through one interface" in str(m.hardware.shared_by([1, 2])), m.hardware.shared_by([1, 2])
    m = load_mission(write(tmp_path, without_interfaces(doc)))  # a computer per drone: --id N on each
    assert m.hardware is not None and "--id N" in str(m.hardware.shared_by([1, 2]))


def without_interfaces(doc: dict) -> dict:
    """`doc` with no drone naming its interface (the routing table picks: station mode, or a computer per
    drone)."""
    for d in doc["hardware"]["drones"]:
        d.pop("interface", None)
    return doc


def test_station_mode_needs_distinct_addresses_and_video_ports(tmp_path: Path) -> None:
    doc = without_interfaces(copy.deepcopy(real()))
    doc["hardware"]["topology"] = "station"
    with pytest.raises(MissionError, match="share an ip and port"):
        load_mission(write(tmp_path, doc))
    doc["hardware"]["drones"][1]["ip"] = "192.168.10.102"
    with pytest.raises(MissionError, match="each drone needs its own video_port"):
        load_mission(write(tmp_path, doc))
    doc["hardware"]["drones"][1]["video_port"] = 11112
    m = load_mission(write(tmp_path, doc))
    assert m.hardware is not None and m.hardware.shared_by([1, 2]) is None


def test_access_point_mission_flown_from_one_process_is_refused_before_any_traffic(tmp_path: Path) -> None:
    """Two drones at 192.168.10.1 and no interface named cannot be told apart from one computer: preflight
    FAILs naming the fixes (an adapter each, or a computer each)."""
    path = write(tmp_path, without_interfaces(copy.deepcopy(real())))
    r = run_cli("preflight", str(path), "--no-camera", "--deadline", "3", timeout=60)
    assert r.returncode == 1
    assert "share an address or video port" in r.stdout and "--id N" in r.stdout and "interface:" in r.stdout
    r = run_cli("preflight", str(REAL), "--rig", "lab", "--id", "9", timeout=60)
    assert r.returncode == 2 and "no drone [9]" in r.stderr


def _drop_hardware(d: dict) -> None:
    del d["hardware"]


def _wrong_ids(d: dict) -> None:
    d["hardware"]["drones"][1]["id"] = 7


def _same_video_port(d: dict) -> None:
    without_interfaces(d)
    d["hardware"]["topology"] = "station"
    d["hardware"]["drones"][1]["ip"] = "192.168.10.102"


def _bad_ip(d: dict) -> None:
    d["hardware"]["drones"][0]["ip"] = "tello-one"


def _unknown_system(d: dict) -> None:
    d["hardware"]["mocap"]["system"] = "kinect"


def _safety_off(d: dict) -> None:
    d["safety"]["enabled"] = False


def _hardware_on_sim(d: dict) -> None:
    d["backend"] = "sim_lab"


def _keepalive_too_long(d: dict) -> None:
    d["hardware"]["drones"][0]["keepalive_s"] = 20


def _bad_interface(d: dict) -> None:
    d["hardware"]["drones"][0]["interface"] = "wlan1; reboot"


def _one_interface(d: dict) -> None:
    del d["hardware"]["drones"][1]["interface"]


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (_drop_hardware, "needs a hardware section"),
        (_wrong_ids, "hardware.drones: ids [1, 7] must be exactly"),
        (_same_video_port, "hardware: drones: each drone needs its own video_port in station mode"),
        (_bad_ip, "hardware.drones.0.ip"),
        (_unknown_system, "hardware.mocap.system"),
        (_safety_off, "safety.enabled: false only on the ideal rig"),
        (_hardware_on_sim, "hardware: only used by a rig of devices"),
        (_keepalive_too_long, "hardware.drones.0.keepalive_s"),
        (_bad_interface, "hardware.drones.0.interface"),
        (_one_interface, "drones.1.interface: every drone names the interface it is reached through"),
    ],
)
def test_bad_hardware_sections_name_the_key(tmp_path: Path, mutate, expected: str) -> None:
    doc = copy.deepcopy(real())
    mutate(doc)
    with pytest.raises(MissionError) as err:
        load_mission(write(tmp_path, doc))
    assert expected in str(err.value)


def test_sim_refuses_a_hardware_mission_and_preflight_refuses_a_sim_mission(tmp_path: Path) -> None:
    r = run_cli("sim", str(REAL), "--rig", "lab", "--out", str(tmp_path / "run"), timeout=60)
    assert r.returncode == 2 and "flies real drones" in r.stderr
    assert not (tmp_path / "run").exists()
    r = run_cli("preflight", str(MISSIONS / "paper_sim.yaml"), timeout=60)
    assert r.returncode == 2 and "no hardware to check" in r.stderr


def test_target_needs_a_robot_in_the_mission() -> None:
    r = run_cli("target", str(MISSIONS / "paper_sim.yaml"), timeout=60)
    assert r.returncode == 2 and "hardware.target" in r.stderr
