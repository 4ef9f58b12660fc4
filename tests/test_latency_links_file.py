"""The measured links file (flightstack.calibration.latency_report) and its inclusion by a rig
(`links: {include: FILE}`): the resolved mission holds the file's links, a link the rig writes out beside
`include` wins, and a bad file is refused with its path."""

from __future__ import annotations

import datetime
from pathlib import Path

import pytest
import yaml

from flightstack.calibration.latency import DelayEstimate, ResponseEstimate
from flightstack.calibration.latency_report import links_text, write_links_file
from flightstack.config.links import LinksSpec
from flightstack.config.rig import MISSION_CONFIGS, RigError, resolved_document

VIDEO = DelayEstimate(0.384, 0.0263, 0.34, 0.43, 0.382, 0.999, 160, 172, 0.001)
RC = ResponseEstimate(0.061, 0.0085, 0.1, 1.0, 0.062, 20)
WHEN = datetime.datetime(2026, 11, 26, 19, 40, tzinfo=datetime.UTC)


def rig_with_links(tmp_path: Path, links: dict[str, object]) -> Path:
    """The emulated lab's rig with these links, written beside the links file (cameras made absolute)."""
    rig = yaml.safe_load((MISSION_CONFIGS / "rigs" / "emulated-lab.yaml").read_text())
    base = MISSION_CONFIGS / "rigs"
    rig["cameras"] = {k: str((base / v).resolve()) for k, v in rig["cameras"].items()}
    rig["links"] = links
    path = tmp_path / "my-lab.yaml"
    path.write_text("# the lab's own comment\n" + yaml.safe_dump(rig))
    return path


def test_the_links_file_says_what_was_measured_and_how_to_include_it(tmp_path: Path) -> None:
    text = links_text(VIDEO, RC, WHEN, "emulated Tello 1")
    doc = yaml.safe_load(text)
    assert "links: {include: THIS_FILE}" in text and "2026-11-26T19:40:00Z" in text
    video = doc["links"]["video"]
    assert video["latency_s"] + video["jitter_s"] / 2 == pytest.approx(0.384, abs=2e-4)
    assert doc["measured"]["video"]["frames_timed"] == 160 and doc["measured"]["rc"]["tau_s"] == 0.1
    LinksSpec(**doc["links"])  # the links are valid as they are
    with pytest.raises(ValueError):
        links_text(when=WHEN)


def test_a_rig_includes_the_measured_links_and_its_own_win(tmp_path: Path) -> None:
    write_links_file(tmp_path / "measured.yaml", links_text(VIDEO, RC, WHEN))
    rc_own = {"latency_s": 0.07, "jitter_s": 0.01}
    rig = rig_with_links(tmp_path, {"profile": "tello", "include": "measured.yaml", "rc": rc_own})
    links = LinksSpec(**resolved_document("paper_experiment", rig)["links"])
    assert links.profile == "tello"
    assert links.link("video").latency_s == pytest.approx(VIDEO.as_link()[0], abs=1e-4)
    assert links.link("rc").latency_s == 0.07  # the rig's own
    assert links.link("state").rate_hz == 10.0  # the profile's
    assert rig.read_text().startswith("# the lab's own comment")


@pytest.mark.parametrize(
    ("content", "why"),
    [(None, "measured.yaml"), ("links: {video: {latency_s: 0.1}}\nextra: 1\n", "extra"),
     ("links: {include: other.yaml}\n", "without its own include")],
)  # fmt: skip
def test_a_bad_links_file_is_refused_with_its_path(tmp_path: Path, content: str | None, why: str) -> None:
    if content is not None:
        (tmp_path / "measured.yaml").write_text(content)
    rig = rig_with_links(tmp_path, {"include": "measured.yaml"})
    with pytest.raises(RigError, match=why):
        resolved_document("paper_experiment", rig)
