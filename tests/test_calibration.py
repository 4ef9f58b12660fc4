"""The camera calibration wizard (calibration/): real photos, synthetic round trip, bad input, check."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from flightstack.calibration import prompts
from flightstack.calibration.camera import CaptureOptions, run_camera_wizard
from flightstack.calibration.patterns import PatternSpec
from flightstack.calibration.solve import SolveError, SolveOptions, View, calibrate_views
from flightstack.calibration.sources import SourceFrame
from flightstack.calibration.synthetic import board_texture, random_poses, render_view
from flightstack.cli.app import main
from flightstack.vision.camera_file import (
    CalibrationError,
    calibration_from_dict,
    load_calibration,
)
from tests.conftest import MISSIONS, run_cli

SIM = load_calibration(MISSIONS / "cameras" / "tello_front_sim.yaml")  # 960x720, fx = fy = 700 px, k1 = -0.08
SIZE = (SIM.width, SIM.height)
BOARD = PatternSpec("chessboard", 7, 7, 0.03)


def _rms_from(stdout: str) -> float:
    m = re.search(r"RMS reprojection error: ([0-9.]+) px", stdout)
    assert m, stdout
    return float(m.group(1))


def _rejected(stdout: str) -> dict[str, str]:
    return dict(re.findall(r"^  rejected (.+?): (.+)$", stdout, flags=re.M))


def camera_cmd(
    source: list[str], pattern: str, cols: str, rows: str, square: str, out: str, *extra: str
) -> list[str]:
    """argv of `flightstack calibrate camera` with the given source options and pattern."""
    size = ["--cols", cols, "--rows", rows, "--square", square]
    return ["calibrate", "camera", *source, "--pattern", pattern, *size, "--out", out, *extra]


class ListSource:
    """An in-memory source of (name, grey or RGB image) pairs."""

    def __init__(self, frames: list[tuple[str, np.ndarray | None]]) -> None:
        self._frames = frames
        self.total, self.label, self.is_stream = len(frames), "memory", False

    def frames(self):
        for name, img in self._frames:
            if img is None:
                yield SourceFrame(name, None, "unreadable")
            else:
                yield SourceFrame(name, img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2RGB))


@pytest.fixture(scope="module")
def synthetic_views() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """12 rendered chessboard views (grey image, rvec, tvec) of the sim camera, sensor noise σ = 1."""
    rng = np.random.default_rng(7)
    poses = random_poses(BOARD, SIM.camera_matrix, SIM.dist_coeffs, SIZE, 12, rng)
    tex = board_texture(BOARD)
    return [
        (render_view(tex, SIM.camera_matrix, SIM.dist_coeffs, SIZE, r, t, noise_std=1.0, rng=rng), r, t)
        for r, t in poses
    ]


# ------------------------------------------------- photo-like sets with known ground truth (acceptance)
# The repository carries no photos: the licences of the public photo sets used before could not be
# established (tests/data/README.md). Instead each set is rendered here from a known webcam-like camera
# and degraded like a photo: defocus blur, a brightness gradient and vignetting, sensor noise and JPEG
# compression. The ground truth makes the checks stronger (recovered intrinsics against the truth, not
# only against another OpenCV pipeline); what is lost is real optics and a real print (a lab checks its
# own camera on real photos with `flightstack calibrate check`).
CHESS_SPEC = PatternSpec("chessboard", 7, 7, 0.0195)
CIRCLES_SPEC = PatternSpec("acircles", 4, 11, 0.01)
CHESS_CAM = (np.array([[610.0, 0, 322.0], [0, 608.0, 236.0], [0, 0, 1]]), np.array([-0.14, 0.09, 0, 0, 0]))
CIRCLES_CAM = (np.array([[560.0, 0, 318.0], [0, 560.0, 258.0], [0, 0, 1]]), np.array([-0.08, 0.03, 0, 0, 0]))


def _photo_like(grey: np.ndarray, rng: np.random.Generator, quality: int = 88) -> bytes:
    """Blur (σ 0.6..1.0 px), lighting gradient and vignetting (±15 %), noise (σ 2 grey levels), JPEG."""
    H, W = grey.shape
    img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), rng.uniform(0.6, 1.0))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    gx, gy = rng.uniform(-0.15, 0.15, 2)
    r2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / (W / 2) ** 2
    img *= (1.0 + gx * (xx / W - 0.5) + gy * (yy / H - 0.5)) * (1.0 - 0.15 * r2)
    img += rng.normal(0.0, 2.0, img.shape).astype(np.float32)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality]
    ok, jpg = cv2.imencode(".jpg", np.clip(np.round(img), 0, 255).astype(np.uint8), params)
    assert ok
    return jpg.tobytes()


def _write_set(
    folder: Path,
    spec: PatternSpec,
    cam: tuple[np.ndarray, np.ndarray],
    size: tuple[int, int],
    n: int,
    seed: int,
) -> Path:
    """n photo-like views left01.jpg ... of `spec` by `cam` (K, dist) at `size`; left02 repeats left01's
    pose (a near-duplicate the wizard must drop)."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    K, dist = cam
    poses = random_poses(spec, K, dist, size, n - 1, rng, fill=(0.35, 0.6))
    poses.insert(1, poses[0])
    tex = board_texture(spec)
    for k, (r, t) in enumerate(poses):
        grey = render_view(tex, K, dist, size, r, t, background=int(rng.integers(90, 160)))
        (folder / f"left{k + 1:02d}.jpg").write_bytes(_photo_like(grey, rng))
    return folder


@pytest.fixture(scope="module")
def photo_sets(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(chessboard 7x7 at 640x480, 18 views; asymmetric circles 4x11 at 640x512, 25 views)."""
    root = tmp_path_factory.mktemp("photo_sets")
    chess = _write_set(root / "chessboard_7x7_640x480", CHESS_SPEC, CHESS_CAM, (640, 480), 18, 11)
    circles = _write_set(root / "acircles_4x11_640x512", CIRCLES_SPEC, CIRCLES_CAM, (640, 512), 25, 12)
    return chess, circles


def test_chessboard_set_cli(tmp_path: Path, photo_sets: tuple[Path, Path]) -> None:
    CHESS = photo_sets[0]
    out = tmp_path / "cal.yaml"
    args = ["--pattern", "chessboard", "--cols", "7", "--rows", "7", "--square", "0.0195", "--out", str(out)]
    res = run_cli("calibrate", "camera", "--images", str(CHESS), *args, "--no-progress", timeout=120)
    assert res.returncode == 0, res.stderr
    rms = _rms_from(res.stdout)
    assert rms < 1.0
    assert "rejected views:" in res.stdout and "verdict: GOOD" in res.stdout
    cal = load_calibration(out)
    assert cal.rms_px == pytest.approx(rms, abs=1e-3) and (cal.width, cal.height) == (640, 480)
    assert cal.pattern == {"kind": "chessboard", "cols": 7, "rows": 7, "square_m": 0.0195}
    assert len(cal.views) + len(_rejected(res.stdout)) == 18
    # independent reference: OpenCV's other chessboard detector (findChessboardCornersSB) + calibrateCamera
    obj, img = [], []
    for f in sorted(CHESS.glob("*.jpg")):
        ok, c = cv2.findChessboardCornersSB(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (7, 7))
        if ok:
            obj.append(BOARD.object_points())
            img.append(c)
    _, K, *_ = cv2.calibrateCamera(obj, img, (640, 480), None, None)
    assert cal.fx == pytest.approx(K[0, 0], rel=0.01) and cal.fy == pytest.approx(K[1, 1], rel=0.01)
    # and the truth the views were rendered with
    K_true = CHESS_CAM[0]
    assert cal.fx == pytest.approx(K_true[0, 0], rel=0.01) and cal.fy == pytest.approx(K_true[1, 1], rel=0.01)
    assert cal.cx == pytest.approx(K_true[0, 2], abs=3.0) and cal.cy == pytest.approx(K_true[1, 2], abs=3.0)


def test_circle_grid_set_cli(tmp_path: Path, photo_sets: tuple[Path, Path]) -> None:
    CIRCLES = photo_sets[1]
    out = tmp_path / "cal.json"
    args = ["--pattern", "acircles", "--cols", "4", "--rows", "11", "--square", "0.01", "--out", str(out)]
    res = run_cli("calibrate", "camera", "--images", str(CIRCLES), *args, "--no-progress", timeout=120)
    assert res.returncode == 0, res.stderr
    assert _rms_from(res.stdout) < 1.0
    rejected = _rejected(res.stdout)
    # left01 and left02 show the board at almost the same place: one is dropped, and the wizard says why
    assert "left02.jpg" in rejected and rejected["left02.jpg"].startswith("near-duplicate of left01.jpg")
    cal = calibration_from_dict(json.loads(out.read_text()), str(out))  # --out *.json writes JSON
    assert {n for n, _ in cal.views} | set(rejected) == {f.name for f in CIRCLES.glob("*.jpg")}
    # independent reference: OpenCV's default circle-grid detector and calibrateCamera on all 25 photos
    spec = PatternSpec("acircles", 4, 11, 0.01)
    obj, img = [], []
    for f in sorted(CIRCLES.glob("*.jpg")):
        ok, c = cv2.findCirclesGrid(
            cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (4, 11), flags=cv2.CALIB_CB_ASYMMETRIC_GRID
        )
        assert ok
        obj.append(spec.object_points())
        img.append(c)
    rms_ref, K, *_ = cv2.calibrateCamera(obj, img, (640, 512), None, None)
    assert cal.fx == pytest.approx(K[0, 0], rel=0.005) and cal.cx == pytest.approx(K[0, 2], abs=2.0)
    assert cal.rms_px == pytest.approx(rms_ref, abs=0.05)
    K_true = CIRCLES_CAM[0]
    assert cal.fx == pytest.approx(K_true[0, 0], rel=0.01) and cal.fy == pytest.approx(K_true[1, 1], rel=0.01)
    assert cal.cx == pytest.approx(K_true[0, 2], abs=3.0) and cal.cy == pytest.approx(K_true[1, 2], abs=3.0)


def test_rejected_views_and_reasons(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], photo_sets: tuple[Path, Path]
) -> None:
    """Blurry, duplicate, pattern-less, unreadable and wrong-size frames are each reported with a reason."""
    files = [f for f in sorted(photo_sets[0].glob("*.jpg")) if f.name != "left02.jpg"][:10]
    for f in files:
        shutil.copy(f, tmp_path / f.name)
    img = cv2.imread(str(files[0]))
    cv2.imwrite(str(tmp_path / "z_blurred.png"), cv2.GaussianBlur(img, (0, 0), 3.0))
    cv2.imwrite(str(tmp_path / "z_copy.png"), img)
    cv2.imwrite(str(tmp_path / "z_blank.png"), np.full_like(img, 128))
    cv2.imwrite(str(tmp_path / "z_small.png"), cv2.resize(img, (320, 240)))
    (tmp_path / "z_broken.jpg").write_bytes(b"not a jpeg")
    out = tmp_path / "cal.yaml"
    code = main(
        camera_cmd(["--images", str(tmp_path)], "chessboard", "7", "7", "0.0195", str(out), "--no-progress")
    )
    stdout = capsys.readouterr().out
    assert code == 0
    rej = _rejected(stdout)
    assert rej["z_blurred.png"].startswith("blurry: edge width")
    assert rej["z_copy.png"].startswith(f"near-duplicate of {files[0].name}")
    assert rej["z_blank.png"].startswith("pattern not found")
    assert rej["z_broken.jpg"].startswith("unreadable")
    assert rej["z_small.png"].startswith("image size 320x240 differs")
    assert [n for n, _ in load_calibration(out).views] == [f.name for f in files]


# ---------------------------------------------------------------- synthetic round trip


def test_synthetic_round_trip_recovers_intrinsics(tmp_path: Path, synthetic_views, capsys) -> None:
    for k, (img, _, _) in enumerate(synthetic_views):
        cv2.imwrite(str(tmp_path / f"view{k:02d}.png"), img)
    out = tmp_path / "sim.yaml"
    code = main(
        camera_cmd(
            ["--images", str(tmp_path)],
            "chessboard",
            "7",
            "7",
            "0.03",
            str(out),
            "--device",
            "sim",
            "--no-progress",
        )
    )
    assert code == 0, capsys.readouterr()
    cal = load_calibration(out)
    truth = SIM.camera_matrix
    for got, want in [
        (cal.fx, truth[0, 0]),
        (cal.fy, truth[1, 1]),
        (cal.cx, truth[0, 2]),
        (cal.cy, truth[1, 2]),
    ]:
        assert abs(got - want) / want < 0.01
    assert abs(cal.dist_coeffs[0] - SIM.dist_coeffs[0]) < 0.01
    assert cal.device == "sim" and cal.rms_px < 0.2
    # the fitted model reprojects the true board corners where the true camera puts them
    img, rvec, tvec = synthetic_views[0]
    obj = BOARD.object_points().astype(float)
    ref, _ = cv2.projectPoints(obj, rvec, tvec, SIM.camera_matrix, SIM.dist_coeffs)
    ok, r2, t2 = cv2.solvePnP(obj, ref, cal.camera_matrix, cal.dist_coeffs)
    got, _ = cv2.projectPoints(obj, r2, t2, cal.camera_matrix, cal.dist_coeffs)
    assert ok and np.abs(got - ref).max() < 0.3


def test_synthetic_video_with_repeated_frames(tmp_path: Path, synthetic_views) -> None:
    """A video (MJPG .avi) holding each view for 3 frames: duplicates skipped, intrinsics within 1 %."""
    path = tmp_path / "board.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, SIZE)
    assert vw.isOpened()
    for img, _, _ in synthetic_views[:8]:
        for _ in range(3):
            vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    vw.release()
    out = tmp_path / "vid.yaml"
    res = run_cli(
        "calibrate", "camera", "--video", str(path), "--pattern", "chessboard", "--cols", "7", "--rows", "7",
        "--square", "0.03", "--out", str(out), "--no-progress", timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    rej = _rejected(res.stdout)
    assert len(rej) == 16 and all(r.startswith("near-duplicate") for r in rej.values())
    cal = load_calibration(out)
    assert len(cal.views) == 8
    assert abs(cal.fx - 700.0) / 700.0 < 0.01 and abs(cal.cx - 480.0) / 480.0 < 0.01


def test_charuco_synthetic() -> None:
    spec = PatternSpec("charuco", 5, 7, 0.04, 0.03)
    rng = np.random.default_rng(3)
    tex = board_texture(spec)
    frames = [
        (f"v{k}", render_view(tex, SIM.camera_matrix, SIM.dist_coeffs, SIZE, r, t, noise_std=1.0, rng=rng))
        for k, (r, t) in enumerate(random_poses(spec, SIM.camera_matrix, SIM.dist_coeffs, SIZE, 8, rng))
    ]
    res = run_camera_wizard(ListSource(frames), spec)
    assert res.exit_code == 0, res.message
    assert abs(res.calibration.fx - 700.0) / 700.0 < 0.01 and abs(res.calibration.cy - 360.0) / 360.0 < 0.01


def test_outlier_view_is_rejected_with_reason() -> None:
    """Views projected with the true camera (0.1 px noise) plus one view whose points were shifted."""
    rng = np.random.default_rng(1)
    obj = BOARD.object_points()
    views = []
    for k, (r, t) in enumerate(random_poses(BOARD, SIM.camera_matrix, SIM.dist_coeffs, SIZE, 10, rng)):
        px, _ = cv2.projectPoints(obj.astype(float), r, t, SIM.camera_matrix, SIM.dist_coeffs)
        px = px.reshape(-1, 2) + rng.normal(0, 0.1, (len(obj), 2))
        if k == 4:
            px[:10] += 3.0  # a mis-detected row
        views.append(View(f"v{k}", px.astype(np.float32), obj))
    res = calibrate_views(views, SIZE, SolveOptions())
    assert [n for n, _ in res.rejected] == ["v4"]
    assert res.rejected[0][1].startswith("outlier: reprojection error")
    assert res.rms_px < 0.15 and abs(res.camera_matrix[0, 0] - 700.0) < 3.0


def test_head_on_views_are_degenerate(tmp_path: Path) -> None:
    """Boards all facing the camera: the focal length is unobservable; refused (exit 1), nothing written."""
    tex = board_texture(BOARD)
    frames = []
    for k, (u, v) in enumerate(
        [(0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7), (0.5, 0.5), (0.4, 0.6), (0.6, 0.4)]
    ):
        z = 0.6
        c = np.array([(u * 960 - 480) / 700 * z, (v * 720 - 360) / 700 * z, z])
        img = render_view(tex, SIM.camera_matrix, SIM.dist_coeffs, SIZE, np.zeros(3), c - [0.09, 0.09, 0.0])
        frames.append((f"v{k}", img))
    res = run_camera_wizard(ListSource(frames), BOARD)
    assert res.exit_code == 1 and res.calibration is None
    assert "degenerate views" in res.message


# ---------------------------------------------------------------- bad input


def test_wrong_pattern_size_writes_nothing(tmp_path: Path, photo_sets: tuple[Path, Path]) -> None:
    out = tmp_path / "cal.yaml"
    argv = camera_cmd(
        ["--images", str(photo_sets[0])], "chessboard", "9", "6", "0.02", str(out), "--no-progress"
    )
    res = run_cli(*argv, timeout=120)
    assert res.returncode == 2
    assert (
        "pattern (chessboard 9x6 inner corners" in res.stderr and "not found in any of the 18" in res.stderr
    )
    assert "no calibration file written" in res.stderr and not out.exists()


def test_unreadable_files_and_missing_folder(tmp_path: Path, capsys) -> None:
    (tmp_path / "a.jpg").write_bytes(b"garbage")
    (tmp_path / "b.png").write_bytes(b"")
    out = tmp_path / "cal.yaml"
    base = [
        "calibrate",
        "camera",
        "--pattern",
        "chessboard",
        "--cols",
        "7",
        "--rows",
        "7",
        "--square",
        "0.02",
    ]
    assert main([*base, "--images", str(tmp_path), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "none of the 2 frame(s) could be read" in err and not out.exists()
    assert main([*base, "--images", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert f"--images {tmp_path / 'nope'}: not a folder" in capsys.readouterr().err
    assert main([*base, "--video", str(tmp_path / "a.jpg"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--video {tmp_path / 'a.jpg'}: " in err and "video" in err.split(":", 2)[2]
    assert not out.exists()


def test_video_with_one_view(tmp_path: Path, synthetic_views, capsys) -> None:
    path = tmp_path / "still.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, SIZE)
    for _ in range(15):
        vw.write(cv2.cvtColor(synthetic_views[0][0], cv2.COLOR_GRAY2BGR))
    vw.release()
    out = tmp_path / "cal.yaml"
    code = main(camera_cmd(["--video", str(path)], "chessboard", "7", "7", "0.03", str(out), "--no-progress"))
    captured = capsys.readouterr()
    assert code == 2 and not out.exists()
    assert "only 1 usable view(s); at least 6" in captured.err
    assert len(_rejected(captured.out)) == 14


def test_non_interactive_missing_options_fail_clearly(tmp_path: Path) -> None:
    res = run_cli("calibrate", "camera", "--images", str(tmp_path), "--out", str(tmp_path / "c.yaml"))
    assert res.returncode == 2
    assert "no image files" in res.stderr
    (tmp_path / "x.png").write_bytes(b"")
    res = run_cli("calibrate", "camera", "--images", str(tmp_path), "--out", str(tmp_path / "c.yaml"))
    assert res.returncode == 2 and "--pattern is required (no terminal to ask on" in res.stderr


def test_interactive_prompts(tmp_path: Path, synthetic_views, monkeypatch, capsys) -> None:
    for k, (img, _, _) in enumerate(synthetic_views[:8]):
        cv2.imwrite(str(tmp_path / f"view{k}.png"), img)
    out = tmp_path / "asked.yaml"
    answers = iter([str(tmp_path), "chessbord", "chessboard", "7", "7", "x", "0.03", str(out)])
    asked: list[str] = []

    def fake_input(question: str) -> str:
        asked.append(question)
        return next(answers)

    monkeypatch.setattr(prompts, "interactive", lambda: True)
    monkeypatch.setattr("builtins.input", fake_input)
    assert main(["calibrate", "camera", "--no-progress"]) == 0
    assert asked[0].startswith("Source") and asked[1].startswith("Pattern") and asked[2].startswith("Pattern")
    assert "one of chessboard, charuco, acircles is required" in capsys.readouterr().err
    assert abs(load_calibration(out).fx - 700.0) < 7.0


# ---------------------------------------------------------------- file format, check


def test_calibration_file_optional_keys_are_validated(tmp_path: Path) -> None:
    d = yaml.safe_load((MISSIONS / "cameras" / "tello_down_sim.yaml").read_text())
    cal = calibration_from_dict(d)
    assert "pattern" not in cal.to_dict() and "views" not in cal.to_dict()  # old files round-trip unchanged
    d2 = {**d, "pattern": {"kind": "acircles", "cols": 4, "rows": 11, "square_m": 0.01}}
    d2["views"] = [{"name": "a.png", "error_px": 0.2}]
    cal2 = calibration_from_dict(d2)
    cal2.save(tmp_path / "c.yaml")
    assert load_calibration(tmp_path / "c.yaml").to_dict() == cal2.to_dict()
    assert [p.name for p in tmp_path.iterdir()] == ["c.yaml"]  # no temporary file left behind
    for bad, key in [
        ({"kind": "dots", "cols": 4, "rows": 11, "square_m": 0.01}, "pattern.kind"),
        ({"kind": "chessboard", "cols": 0, "rows": 7, "square_m": 0.01}, "pattern.cols"),
        ({"kind": "chessboard", "cols": 7, "rows": 7, "square_m": -1}, "pattern.square_m"),
    ]:
        with pytest.raises(CalibrationError, match=key):
            calibration_from_dict({**d, "pattern": bad})
    with pytest.raises(CalibrationError, match=r"views\.0\.error_px"):
        calibration_from_dict({**d, "views": [{"name": "a", "error_px": float("nan")}]})


def test_check_reports_undistortion(tmp_path: Path, capsys, photo_sets: tuple[Path, Path]) -> None:
    CHESS, CIRCLES = photo_sets
    cal_path = tmp_path / "cal.yaml"
    base = ["--pattern", "chessboard", "--cols", "7", "--rows", "7", "--square", "0.0195"]
    assert (
        main(["calibrate", "camera", "--images", str(CHESS), *base, "--out", str(cal_path), "--no-progress"])
        == 0
    )
    capsys.readouterr()
    und = tmp_path / "und.png"
    code = main(
        ["calibrate", "check", str(cal_path), "--image", str(CHESS / "left12.jpg"), "--out", str(und), *base]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "distortion displacement on the image outline: max" in out and "field of view" in out
    m = re.search(r"RMS distance to a straight line: ([0-9.]+) px raw -> ([0-9.]+) px undistorted", out)
    assert m and float(m.group(2)) < float(m.group(1))  # undistortion straightens the board's rows
    assert cv2.imread(str(und)).shape == (480, 640, 3)
    code = main(["calibrate", "check", str(cal_path), "--image", str(CIRCLES / "left01.jpg")])
    assert code == 2 and "the sample is 640x512 but the calibration is for 640x480" in capsys.readouterr().err


def test_capture_stops_at_max_views(synthetic_views) -> None:
    frames = [(f"v{k}", img) for k, (img, _, _) in enumerate(synthetic_views)]
    res = run_camera_wizard(ListSource(frames), BOARD, CaptureOptions(max_views=7), SolveOptions(min_views=6))
    assert res.exit_code == 0 and res.frames_seen == 7 and len(res.used) == 7


def test_too_few_views_is_refused() -> None:
    with pytest.raises(SolveError, match="only 2 usable view"):
        calibrate_views([View("a", np.zeros((4, 2)), np.zeros((4, 3)))] * 2, SIZE, SolveOptions())
