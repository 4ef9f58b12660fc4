"""`flightstack draw-lab`: the picture of a lab file (flightstack/cli/draw_lab.py). The one in
docs/real-lab.md (docs/lab.svg) is the lab template's as the code draws it now; each topology draws its
computers, interfaces, processes, drones and ports; a lab file that is not valid is refused naming the
key."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from flightstack.cli.app import main
from flightstack.cli.draw_lab import draw
from flightstack.config.rig import MISSION_CONFIGS
from tests.conftest import REPO

DOCS_SVG = REPO / "docs" / "lab.svg"
TEMPLATE = MISSION_CONFIGS / "rigs" / "lab.yaml"


def texts(svg: str) -> list[str]:
    """Every text element of a well-formed SVG, in order."""
    root = ET.fromstring(svg)
    return [t.text or "" for t in root.iter("{http://www.w3.org/2000/svg}text")]


def lab_file(tmp_path: Path, edit: object = None) -> Path:
    """The template, its camera files named absolutely, edited by `edit(doc)`, written to tmp_path."""
    doc = yaml.safe_load(TEMPLATE.read_text())
    for d in doc["drones"]:
        d["camera"] = str((TEMPLATE.parent / d["camera"]).resolve())
    if callable(edit):
        edit(doc)
    path = tmp_path / "my_lab.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_docs_picture_is_the_template_as_drawn_now() -> None:
    assert DOCS_SVG.read_text(encoding="utf-8") == draw("lab"), (
        "docs/lab.svg is stale: flightstack draw-lab lab --out docs/lab.svg"
    )
    assert "![" in (page := (REPO / "docs" / "real-lab.md").read_text()) and "(lab.svg)" in page


def test_the_template_draws_one_computer_an_adapter_per_tello_and_every_port() -> None:
    words = texts(draw("lab"))
    joined = "\n".join(words)
    assert words.count("the flight computer") == 1 and "drone 1's computer" not in joined
    for expected in (
        "Tello 1",
        "Tello 2",
        "wlan1",
        "wlan2",
        "lab interface",
        "flightstack fly MISSION --rig LAB",
        "tello-guardian (started by it)",
        "Tello 1 via wlan1: -> 192.168.10.1:8889; <- :8890, :11111",
        "Tello 2 via wlan2: -> 192.168.10.1:8889; <- :8890, :11111",
        "192.168.1.2",
        "NatNet: commands UDP 1510, frames on Motive's data port",
        "udpout:192.168.1.50:14550",
        "abort: UDP 127.0.0.1 operator port (signed)",
        "lab network",
    ):
        assert expected in words, (expected, words)
    assert words.count("192.168.10.0/24") == 2  # each Tello's own Wi-Fi


def test_a_computer_per_drone_and_station_mode_draw_as_they_fly(tmp_path: Path) -> None:
    def per_computer(doc: dict) -> None:
        for d in doc["hardware"]["drones"]:
            del d["interface"]
        doc["bus"] = {"kind": "zenoh", "zenoh": {"endpoints": {"1": "tls/192.168.1.11:7447"}}}

    words = texts(draw(str(lab_file(tmp_path, per_computer))))
    assert "drone 1's computer" in words and "drone 2's computer" in words
    assert "flightstack agent MISSION --rig LAB --id 2" in words and "flightstack target MISSION" in words
    assert "Zenoh (mtls): 1 tls/192.168.1.11:7447" in words and "the flight computer" not in words

    def station(doc: dict) -> None:
        doc["hardware"]["topology"] = "station"
        for k, d in enumerate(doc["hardware"]["drones"]):
            del d["interface"]
            d.update(ip=f"192.168.1.{101 + k}", video_port=11111 + k)

    words = texts(draw(str(lab_file(tmp_path, station))))
    assert words.count("lab Wi-Fi") == 1 and "Tello 2: -> 192.168.1.102:8889; <- :8890, :11112" in words


def test_an_invalid_lab_file_is_refused_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def bad(doc: dict) -> None:
        doc["hardware"]["drones"][1]["interface"] = "wlan 2"

    assert main(["draw-lab", str(lab_file(tmp_path, bad)), "--out", str(tmp_path / "x.svg")]) == 2
    assert "hardware.drones.1.interface" in capsys.readouterr().err
    assert not (tmp_path / "x.svg").exists()
    assert main(["draw-lab", "lab-sim"]) == 2 and "no devices to draw" in capsys.readouterr().err


def test_the_command_writes_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "lab.svg"
    assert main(["draw-lab", "lab", "--out", str(out)]) == 0
    assert out.read_text() == draw("lab") and f"wrote {out}" in capsys.readouterr().out
