"""The lab file's SDK 3.0 video settings (flightstack/config/tello_video.py), without a drone: every
argument of the SDK 3.0 guide is accepted and nothing else (`flightstack validate` exits 2 naming the key
and the valid arguments), a drone's own keys override the lab's, the driver's settings carry them (and
need SDK 3.0), and the emulator's encoder holds the `setbitrate` target. The settings against the
emulator: tests/test_tello_driver.py (connect, preflight, camera), tests/test_tello_emulator.py (the
emulator's answers), tests/test_emulated_camera.py (the camera process), tests/test_emulated_lab.py
(`flightstack preflight`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from flightstack.cli.app import main
from flightstack.config.hardware import HardwareSpec
from flightstack.config.mission import load_mission
from flightstack.config.rig import resolved_document
from flightstack.config.tello_video import TelloVideoSpec
from flightstack.drivers.tello.sdk_video import (
    BITRATE_ARGS,
    FPS_ARGS,
    RESOLUTION_ARGS,
    VideoSetting,
    bit_rate_bps,
    parse_argument,
)
from tests.conftest import MISSIONS


def lab_with(tmp_path: Path, video: dict | None = None, drone1: dict | None = None) -> Path:
    """The lab template as a file in tmp_path (camera paths absolute) with `hardware.video` = `video` and
    drone 1's own `video` = `drone1`."""
    doc = yaml.safe_load((MISSIONS / "rigs" / "lab.yaml").read_text())
    for d in doc["drones"]:
        d["camera"] = str((MISSIONS / "rigs" / d["camera"]).resolve())
    if video is not None:
        doc["hardware"]["video"] = video
    if drone1 is not None:
        doc["hardware"]["drones"][0]["video"] = drone1
    path = tmp_path / "my_lab.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_every_sdk30_argument_is_accepted_and_means_what_the_guide_says() -> None:
    for fps in ("high", "middle", "low"):
        assert TelloVideoSpec(fps=fps).fps == fps
    for res in ("high", "low"):
        assert TelloVideoSpec(resolution=res).resolution == res
    for n in range(6):
        assert TelloVideoSpec(bitrate=n).bitrate == n
    assert FPS_ARGS == {"high": 30.0, "middle": 15.0, "low": 5.0}
    assert RESOLUTION_ARGS["high"] == (960, 720) and RESOLUTION_ARGS["low"] == (648, 478)
    assert list(BITRATE_ARGS) == [0, 1, 2, 3, 4, 5]
    assert bit_rate_bps(0) is None and bit_rate_bps(3) == 3_000_000
    assert parse_argument("setfps", "middle") == "middle" and parse_argument("setbitrate", "5") == 5
    for verb, arg in (("setfps", "30"), ("setresolution", "720p"), ("setbitrate", "6"), ("setbitrate", "-1")):
        assert parse_argument(verb, arg) is None
    assert parse_argument("downvision", "1") is None


@pytest.mark.parametrize(
    ("video", "drone1", "key", "reason"),
    [
        ({"fps": "fast"}, None, "hardware.video.fps", "'fast' is no `setfps` argument"),
        ({"fps": 30}, None, "hardware.video.fps", "valid: high (30 frames/s), middle (15), low (5)"),
        ({"resolution": "720p"}, None, "hardware.video.resolution", "valid: high (720P), low (480P)"),
        ({"bitrate": 6}, None, "hardware.video.bitrate", "valid: 0 (auto) or 1-5 (Mbit/s)"),
        ({"bitrate": True}, None, "hardware.video.bitrate", "True is no `setbitrate` argument"),
        (None, {"bitrate": "3"}, "hardware.drones.0.video.bitrate", "'3' is no `setbitrate` argument"),
        ({"fps": "high", "keyframe": 1}, None, "hardware.video.keyframe", "unknown key"),
    ],
)
def test_an_invalid_video_setting_exits_2_naming_the_key(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    video: dict | None,
    drone1: dict | None,
    key: str,
    reason: str,
) -> None:
    lab = lab_with(tmp_path, video, drone1)
    assert main(["validate", str(lab)]) == 2  # the lab file on its own
    err = capsys.readouterr().err
    assert f"{key}: " in err and reason in err, err
    assert main(["validate", "paper_experiment", "--rig", str(lab)]) == 2  # an experiment on it
    err = capsys.readouterr().err
    assert f"{key}: " in err and reason in err, err


def test_a_drones_own_keys_override_the_labs_and_reach_its_driver(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from flightstack.drivers.lab.hardware import tello_config

    lab = lab_with(tmp_path, {"fps": "high", "bitrate": 3}, {"fps": "low", "resolution": "low"})
    assert main(["validate", "paper_experiment", "--rig", str(lab)]) == 0
    out = capsys.readouterr().out
    l1 = "1 at 192.168.10.1:8889 via wlan1 (video 11111, `setresolution low`, `setfps low`, `setbitrate 3`)"
    assert l1 in out
    assert "2 at 192.168.10.1:8889 via wlan2 (video 11111, `setfps high`, `setbitrate 3`)" in out
    m = load_mission("paper_experiment", rig=str(lab), check_files=False)
    one, two = tello_config(m, 1), tello_config(m, 2)
    assert one.video_settings == (
        VideoSetting("hardware.drones[id 1].video.resolution", "setresolution low"),
        VideoSetting("hardware.drones[id 1].video.fps", "setfps low"),
        VideoSetting("hardware.video.bitrate", "setbitrate 3"),
    )
    assert two.video_settings == (
        VideoSetting("hardware.video.fps", "setfps high"),
        VideoSetting("hardware.video.bitrate", "setbitrate 3"),
    )
    assert "video settings (`setfps high`, `setbitrate 3`)" in two.sdk3_features  # refused below SDK 3.0


def test_without_video_keys_nothing_is_sent_and_no_sdk30_is_needed() -> None:
    from flightstack.drivers.lab.hardware import tello_config

    m = load_mission("paper_experiment", rig="lab", check_files=False)
    assert m.hardware is not None and m.hardware.video is None
    for d in m.hardware.drones:
        cfg = tello_config(m, d.id)
        assert cfg.video_settings == () and not any("video settings" in f for f in cfg.sdk3_features)
    doc = resolved_document("paper_experiment", "lab")["hardware"]
    assert HardwareSpec(**doc).video_settings(2) == ()


def test_the_emulators_encoder_holds_the_setbitrate_target() -> None:
    """libx264 through PyAV, as the emulator streams: with `setbitrate n` a picture that needs far more
    (changing noise: about 5 Mbit/s at libx264's default at 320 × 240) comes out near n Mbit/s; without one
    (auto), near the Tello's own rate (video.AUTO_BIT_RATE_BPS, 3 Mbit/s)."""
    pytest.importorskip("av")
    from flightstack.sim_backend.emulators.tello.video import frame_datagrams, make_encoder

    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (240, 320, 3))
    frames = [np.clip(base + rng.integers(-40, 40, base.shape), 0, 255).astype(np.uint8) for _ in range(60)]
    fps = 30.0

    def rate_mbps(bit_rate: int | None) -> float:
        enc = make_encoder((320, 240), fps, 67, bit_rate)
        n = sum(len(d) for i, img in enumerate(frames) for d in frame_datagrams(enc, img, i))
        return 8 * n / (len(frames) / fps) / 1e6

    one, three, auto = rate_mbps(bit_rate_bps(1)), rate_mbps(bit_rate_bps(3)), rate_mbps(bit_rate_bps(0))
    print(f"setbitrate 1: {one:.2f} Mbit/s, 3: {three:.2f} Mbit/s, 0 (auto): {auto:.2f} Mbit/s")
    assert 0.6 < one < 1.6 and 2.0 < three < 4.2 and 2.0 < auto < 4.2, (one, three, auto)
