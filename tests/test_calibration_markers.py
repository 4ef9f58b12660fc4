"""`flightstack calibrate markers`: HSV thresholds from regions, verified with flightstack.vision.markers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from flightstack.cli.app import main
from flightstack.sim_backend.scene.render import RenderOptions, render_markers
from flightstack.vision.camera_file import CameraCalibration, load_calibration
from flightstack.vision.markers import extract_markers
from tests.conftest import MISSIONS

PAINTED = load_calibration(MISSIONS / "cameras" / "tello_down_sim.yaml")  # 320x240, 4 painted markers
P0 = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]])


def _frames(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """n rendered frames (RGB, true marker pixels (4, 2)) of the target at random places, noise σ = 3."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        z = rng.uniform(0.9, 1.4)
        yaw = rng.uniform(0.0, 2.0 * np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        centres = P0 @ R.T + [rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1), z]
        img, px, in_view = render_markers(PAINTED, centres, None, RenderOptions(noise_std=3.0), rng)
        assert in_view.all()
        out.append((img, px))
    return out


@pytest.fixture()
def setup(tmp_path: Path) -> tuple[Path, Path, list[np.ndarray], list[str]]:
    """A calibration without markers, a folder of samples and one region per marker in sample 0."""
    cal = CameraCalibration(**{**PAINTED.__dict__, "markers": ()})
    cal_path = tmp_path / "cal.yaml"
    cal.save(cal_path)
    samples = tmp_path / "samples"
    samples.mkdir()
    frames = _frames(6)
    for k, (img, _) in enumerate(frames):
        cv2.imwrite(str(samples / f"s{k}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    regions = []
    for mk, (u, v) in zip(PAINTED.markers, frames[0][1], strict=True):
        regions.append(f"{mk.name}={int(u) - 12},{int(v) - 12},24,24")
    return cal_path, samples, [px for _, px in frames], regions


def test_markers_picked_and_verified(setup, tmp_path: Path, capsys) -> None:
    cal_path, samples, truth, regions = setup
    out = tmp_path / "with_markers.yaml"
    argv = [
        "calibrate",
        "markers",
        "--calibration",
        str(cal_path),
        "--images",
        str(samples),
        "--out",
        str(out),
    ]
    code = main([*argv, *(a for r in regions for a in ("--marker", r))])
    stdout = capsys.readouterr().out
    assert code == 0, stdout
    assert "verified: exactly 4 blobs in all 6 frames" in stdout
    cal = load_calibration(out)
    assert [m.name for m in cal.markers] == ["red", "green", "blue", "yellow"]
    assert cal.camera_matrix.tolist() == PAINTED.camera_matrix.tolist()  # intrinsics untouched
    # the independent reference: the renderer's ground-truth marker centres
    for k, path in enumerate(sorted(samples.iterdir())):
        det = extract_markers(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), cal)
        assert det.ok, det.reason
        assert np.abs(det.pixels - truth[k]).max() < 0.5
    for picked, painted in zip(cal.markers, PAINTED.markers, strict=True):
        assert np.abs(np.subtract(picked.rgb, painted.rgb)).max() < 15


def test_region_without_marker_is_bad_input(setup, tmp_path: Path, capsys) -> None:
    cal_path, samples, _, regions = setup
    before = cal_path.read_text()
    argv = ["calibrate", "markers", "--calibration", str(cal_path), "--images", str(samples)]
    code = main([*argv, "--marker", regions[0], "--marker", "grey=2,2,10,10"])
    err = capsys.readouterr().err
    assert code == 2 and "marker grey=2,2,10,10@0: the region holds no coloured marker" in err
    assert cal_path.read_text() == before  # nothing written
    assert main([*argv, "--marker", "red=1,2,3"]) == 2
    assert "expected NAME=X,Y,W,H[@FRAME]" in capsys.readouterr().err


def test_extra_blob_fails_the_verification(setup, tmp_path: Path, capsys) -> None:
    cal_path, samples, _, regions = setup
    img = cv2.imread(str(samples / "s3.png"))
    cv2.circle(img, (20, 20), 6, (25, 25, 225), -1)  # a second red blob (BGR) in one sample
    cv2.imwrite(str(samples / "s3.png"), img)
    argv = ["calibrate", "markers", "--calibration", str(cal_path), "--images", str(samples)]
    code = main([*argv, *(a for r in regions for a in ("--marker", r))])
    captured = capsys.readouterr()
    assert code == 1 and "s3.png: marker 'red': 2 blobs" in captured.out
    assert "no thresholds find exactly 4 blobs in every frame (best: 5 of 6 frames)" in captured.err
    assert load_calibration(cal_path).markers == ()
