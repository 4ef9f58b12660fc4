"""Damaged and absurd input to every entry point of the command line (`flightstack.cli.app.build_parser`):
each exits with its documented code (docs/getting-started.md, "Exit codes": 2 bad input, 1 a failure),
with one `error:` line naming the file, key or option and the reason; never a traceback, never a bare
exception name. In-process (`main`), so nothing here flies or opens a device: every case is refused
before that. The same inputs are listed in docs/security.md, "Inputs tried"."""

from __future__ import annotations

import io
import re
import zipfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from flightstack.calibration.latency_session import MAX_SESSION_BYTES, RcRecord, VideoRecord, save_session
from flightstack.cli.app import build_parser, main
from flightstack.config.mission import CAMERA_MOUNTS
from tests.conftest import MISSIONS

CONTRACT = {0, 1, 2, 130}
"""The documented exit codes (docs/getting-started.md)."""
BARE = re.compile(r"\b[A-Z]\w*(Error|Exception|Interrupt|Exit)\b|\bBadZipFile\b|\bStopIteration\b")
"""A Python exception's name where a reason belongs."""


def _rc_session() -> RcRecord:
    """A yaw-rate session that estimates: 20 Hz commands changing every 0.6 s, the yaw following them
    0.15 s late at 1 deg/s per rc unit, sampled at 100 Hz."""
    rng = np.random.default_rng(0)
    t_cmd = np.arange(0.0, 14.4, 0.05)
    level, levels = 0, []
    for k in range(len(t_cmd)):
        if k % 12 == 0:
            level = int(rng.choice([v for v in (-40, -20, 0, 20, 40) if v != level]))
        levels.append(level)
    cmd = np.array(levels, float)
    t_yaw = np.arange(0.0, 14.6, 0.01)
    u = cmd[np.clip(np.searchsorted(t_cmd, t_yaw - 0.15, side="right") - 1, 0, len(cmd) - 1)]
    u[t_yaw < 0.15] = 0.0
    return RcRecord(t_cmd, cmd, t_yaw, np.cumsum(u) * 0.01)


def _npy_header(shape: tuple[int, ...]) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _video(**change: object) -> VideoRecord:
    kw: dict[str, object] = {
        "t_pose": np.arange(3.0),
        "g_wi": np.zeros((3, 4)),
        "g_w0": np.zeros((3, 4)),
        "t_frames": np.arange(2.0),
        "pixels": np.zeros((2, 4, 2)),
        "calibration": "camera.yaml",
        "R_ic": np.eye(3),
        "t_ic": np.zeros(3),
        "P0": np.zeros((4, 3)),
    }
    kw.update(change)
    return VideoRecord(**kw)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The damaged inputs, one file or directory each."""
    d = tmp_path_factory.mktemp("damaged")
    rng = np.random.default_rng(36)
    (d / "garbage.yaml").write_bytes(rng.bytes(4096))
    (d / "empty.yaml").write_bytes(b"")
    (d / "adir.yaml").mkdir()
    (d / "images").mkdir()
    cv2.imwrite(str(d / "images" / "view.png"), np.zeros((48, 64), np.uint8))
    (d / "full.yaml").symlink_to("/dev/full")  # every write: ENOSPC, a full disk
    mission = (MISSIONS / "paper_sim.yaml").read_text()  # its drones' list (up to the next key) -> 3.0
    (d / "drones_float.yaml").write_text(
        re.sub(r"^drones:.*?(?=^\S)", "drones: 3.0\n", mission, flags=re.S | re.M)
    )
    # sessions for `calibrate latency`
    rc = _rc_session()
    save_session(d / "good.npz", rc=rc)
    (d / "empty.npz").write_bytes(b"")
    good = (d / "good.npz").read_bytes()
    (d / "truncated.npz").write_bytes(good[: len(good) // 2])
    with zipfile.ZipFile(d / "huge_header.npz", "w") as z:  # 2**40 elements declared, 64 B held
        z.writestr("t_cmd.npy", _npy_header((2**40,)) + bytes(64))
        for name in ("cmd", "t_yaw", "yaw"):
            buf = io.BytesIO()
            np.save(buf, np.zeros(3))
            z.writestr(f"{name}.npy", buf.getvalue())
    n = (MAX_SESSION_BYTES + 2**24) // 8  # a zip bomb: more zeros than a session may hold, deflated
    with zipfile.ZipFile(d / "bomb.npz", "w", zipfile.ZIP_DEFLATED) as z, z.open("t_cmd.npy", "w") as f:
        f.write(_npy_header((n,)))
        chunk = bytes(2**24)
        for _ in range(8 * n // len(chunk)):
            f.write(chunk)
        f.write(bytes(8 * n % len(chunk)))
    np.savez(d / "pickled.npz", t_cmd=np.array([{}], dtype=object), cmd=rc.cmd, t_yaw=rc.t_yaw, yaw=rc.yaw)
    save_session(d / "empty_P0.npz", video=_video(P0=np.zeros((0, 3)), pixels=np.zeros((2, 0, 2))))
    save_session(d / "P0_flat.npz", video=_video(P0=np.zeros(0)))
    save_session(d / "pixels_short.npz", video=_video(pixels=np.zeros((1, 4, 2))))
    save_session(d / "g_wi_3_columns.npz", video=_video(g_wi=np.zeros((3, 3))))
    save_session(d / "yaw_one_sample.npz", rc=RcRecord(rc.t_cmd, rc.cmd, rc.t_yaw[:1], rc.yaw[:1]))
    save_session(d / "cmd_short.npz", rc=RcRecord(rc.t_cmd, rc.cmd[:5], rc.t_yaw, rc.yaw))
    save_session(d / "t_cmd_empty.npz", rc=RcRecord(rc.t_cmd[:0], rc.cmd[:0], rc.t_yaw, rc.yaw))
    save_session(d / "nan_times.npz", rc=RcRecord(rc.t_cmd * np.nan, rc.cmd, rc.t_yaw, rc.yaw))
    save_session(d / "span_1e9.npz", rc=RcRecord(rc.t_cmd + 1e9 * (rc.t_cmd > 7), rc.cmd, rc.t_yaw, rc.yaw))
    save_session(d / "video_no_calibration.npz", video=_video(calibration="no-such-camera.yaml"))
    save_session(d / "R_ic_singular.npz", video=_video(R_ic=np.zeros((3, 3))))
    save_session(d / "R_ic_reflection.npz", video=_video(R_ic=np.diag([1.0, 1.0, -1.0])))
    save_session(d / "R_ic_scaled.npz", video=_video(R_ic=2.0 * np.eye(3)))
    down = {"calibration": str(MISSIONS / "cameras" / "tello_down_sim.yaml"), "R_ic": CAMERA_MOUNTS["down"]}
    save_session(d / "markers_behind.npz", video=_video(**down))  # the camera at the markers' centre
    # a run directory whose row stream is random bytes behind a valid header
    from tests.test_run_dir_damage import ROWS, _make_run, _rows_header, _write_rows_header

    _make_run(d / "run_random_rows")
    doc, rows = _rows_header(d / "run_random_rows" / ROWS)
    _write_rows_header(d / "run_random_rows" / ROWS, doc, rng.bytes(len(rows)))
    return d


BIG = "9" * 5000
DEEP = "[" * 5000 + "]" * 5000

Case = tuple[str, Callable[[Path], list[str]], int, str]
"""(id, argv from the inputs' directory, exit code, what the error line names)."""


def _s(d: Path, name: str) -> list[str]:
    return ["calibrate", "latency", "--session", str(d / name)]


CASES: list[object] = [
    # run / sim / fly (flightstack/cli/run.py)
    (
        "run: missing mission",
        lambda d: ["run", str(d / "missing.yaml"), "--out", str(d / "o")],
        2,
        "missing.yaml",
    ),
    (
        "run: random bytes",
        lambda d: ["run", str(d / "garbage.yaml"), "--out", str(d / "o")],
        2,
        "garbage.yaml",
    ),
    ("run: empty file", lambda d: ["run", str(d / "empty.yaml"), "--out", str(d / "o")], 2, "empty.yaml"),
    ("run: a directory", lambda d: ["run", str(d / "adir.yaml"), "--out", str(d / "o")], 2, "adir.yaml"),
    ("run: --duration nan", lambda d: ["run", "paper_sim", "--duration", "nan"], 2, "--duration"),
    ("run: --duration 1e309", lambda d: ["run", "paper_sim", "--duration", "1e309"], 2, "--duration"),
    ("run: --duration -1", lambda d: ["run", "paper_sim", "--duration", "-1"], 2, "--duration"),
    ("run: --set without =", lambda d: ["run", "paper_sim", "--set", "duration_s"], 2, "duration_s"),
    ("run: --set dt_s=1e-300", lambda d: ["run", "paper_sim", "--set", "dt_s=1e-300"], 2, "dt_s"),
    ("run: --set seed=", lambda d: ["run", "paper_sim", "--set", "seed="], 2, "--set seed: empty value"),
    ("run: --set seed=-1", lambda d: ["run", "paper_sim", "--set", "seed=-1"], 2, "seed"),
    ("run: --set unknown key", lambda d: ["run", "paper_sim", "--set", "no.such.key=1"], 2, "no"),
    (
        "run: --rig random bytes",
        lambda d: ["run", "paper_sim", "--rig", str(d / "garbage.yaml")],
        2,
        "garbage",
    ),
    ("run: --modes empty", lambda d: ["run", "paper_sim", "--modes", ","], 2, "--modes"),
    ("run: --network unknown", lambda d: ["run", "paper_sim", "--network", "x" * 300], 2, "network"),
    (
        "sim: a real lab",
        lambda d: ["sim", "paper_experiment", "--rig", "lab", "--out", str(d / "o")],
        2,
        "real drones",
    ),
    (
        "fly: random bytes",
        lambda d: ["fly", str(d / "garbage.yaml"), "--out", str(d / "o")],
        2,
        "garbage.yaml",
    ),
    (
        "run: drones: 3.0 on lab-sim",
        lambda d: ["run", str(d / "drones_float.yaml"), "--rig", "lab-sim", "--out", str(d / "o")],
        2,
        "drones",
    ),
    (
        "run: --set a 5,000-digit integer",
        lambda d: ["run", "paper_sim", "--set", f"target.substeps={BIG}", "--out", str(d / "o")],
        2,
        "substeps",
    ),
    (
        "run: --set 5,000-deep nesting",
        lambda d: ["run", "paper_sim", "--set", f"target.substeps={DEEP}", "--out", str(d / "o")],
        2,
        "substeps",
    ),
    # preflight, target, train
    ("preflight: random bytes", lambda d: ["preflight", str(d / "garbage.yaml")], 2, "garbage.yaml"),
    ("preflight: no hardware", lambda d: ["preflight", "paper_sim", "--deadline", "nan"], 2, "paper_sim"),
    ("target: random bytes", lambda d: ["target", str(d / "garbage.yaml")], 2, "garbage.yaml"),
    ("target: --duration nan", lambda d: ["target", "paper_sim", "--duration", "nan"], 2, "--duration"),
    ("target: --laps nan", lambda d: ["target", "paper_sim", "--laps", "nan"], 2, "--laps"),
    ("target: --laps inf", lambda d: ["target", "paper_sim", "--laps", "inf"], 2, "--laps"),
    ("target: --laps -1", lambda d: ["target", "paper_sim", "--laps", "-1"], 2, "--laps"),
    ("target: --laps 0", lambda d: ["target", "paper_sim", "--laps", "0"], 2, "--laps"),
    ("target: --laps 1e9", lambda d: ["target", "paper_sim", "--laps", "1e9"], 2, "--laps"),
    ("target: --laps x", lambda d: ["target", "paper_sim", "--laps", "x"], 2, "--laps"),
    ("target: no robot", lambda d: ["target", "paper_sim", "--yes"], 2, "hardware.target"),
    ("train: missing run", lambda d: ["train", str(d / "missing"), "--out", str(d / "x.npz")], 2, "missing"),
    (
        "train: no such mode",
        lambda d: ["train", str(d / "run_random_rows"), "--out", str(d / "x.npz"), "--from-mode", "dgp"],
        2,
        "timeseries_dgp.npz",
    ),
    # calibrate drone / camera / markers / check (nothing takes off: refused by the parser)
    (
        "calibrate drone: --duration nan",
        lambda d: ["calibrate", "drone", "--ip", "127.0.0.1", "--out", "x.yaml", "--duration", "nan"],
        2,
        "--duration",
    ),
    (
        "calibrate drone: --amplitude 1e9",
        lambda d: ["calibrate", "drone", "--ip", "127.0.0.1", "--out", "x.yaml", "--amplitude", "1e9"],
        2,
        "--amplitude",
    ),
    (
        "calibrate camera: missing folder",
        lambda d: [
            "calibrate",
            "camera",
            "--images",
            str(d / "missing"),
            "--pattern",
            "chessboard",
            "--cols",
            "9",
            "--rows",
            "6",
            "--square",
            "0.025",
            "--out",
            str(d / "cam.yaml"),
        ],
        2,
        "missing",
    ),
    (
        "calibrate camera: --square inf",
        lambda d: [
            "calibrate",
            "camera",
            "--images",
            str(d / "images"),
            "--pattern",
            "chessboard",
            "--cols",
            "9",
            "--rows",
            "6",
            "--square",
            "inf",
            "--out",
            str(d / "cam.yaml"),
        ],
        2,
        "square",
    ),
    (
        "calibrate markers: random bytes calibration",
        lambda d: [
            "calibrate",
            "markers",
            "--images",
            str(d / "adir.yaml"),
            "--calibration",
            str(d / "garbage.yaml"),
            "--out",
            str(d / "m.yaml"),
        ],
        2,
        "garbage.yaml",
    ),
    (
        "calibrate check: random bytes",
        lambda d: ["calibrate", "check", str(d / "garbage.yaml"), "--image", str(d / "missing.png")],
        2,
        "garbage.yaml",
    ),
    # calibrate latency --session: every damaged session exits 2 naming it
    ("latency: the good session", lambda d: _s(d, "good.npz"), 0, ""),
    ("latency: empty file", lambda d: _s(d, "empty.npz"), 2, "empty.npz"),
    ("latency: truncated zip", lambda d: _s(d, "truncated.npz"), 2, "truncated.npz"),
    ("latency: 2**40-element header", lambda d: _s(d, "huge_header.npz"), 2, "huge_header.npz"),
    ("latency: zip bomb", lambda d: _s(d, "bomb.npz"), 2, "bomb.npz"),
    ("latency: a pickled object", lambda d: _s(d, "pickled.npz"), 2, "pickled.npz"),
    ("latency: empty P0", lambda d: _s(d, "empty_P0.npz"), 2, "P0"),
    ("latency: P0 flat", lambda d: _s(d, "P0_flat.npz"), 2, "P0"),
    ("latency: pixels of another length", lambda d: _s(d, "pixels_short.npz"), 2, "pixels"),
    ("latency: g_wi of 3 columns", lambda d: _s(d, "g_wi_3_columns.npz"), 2, "g_wi"),
    ("latency: one yaw sample", lambda d: _s(d, "yaw_one_sample.npz"), 2, "t_yaw"),
    ("latency: cmd shorter than t_cmd", lambda d: _s(d, "cmd_short.npz"), 2, "cmd"),
    ("latency: no command", lambda d: _s(d, "t_cmd_empty.npz"), 2, "t_cmd"),
    ("latency: NaN times", lambda d: _s(d, "nan_times.npz"), 2, "t_cmd"),
    ("latency: times 1e9 s apart", lambda d: _s(d, "span_1e9.npz"), 2, "span"),
    ("latency: R_ic singular", lambda d: _s(d, "R_ic_singular.npz"), 2, "R_ic: not a rotation"),
    ("latency: R_ic a reflection", lambda d: _s(d, "R_ic_reflection.npz"), 2, "R_ic: not a rotation"),
    ("latency: R_ic scaled", lambda d: _s(d, "R_ic_scaled.npz"), 2, "R_ic: not a rotation"),
    ("latency: markers behind the camera", lambda d: _s(d, "markers_behind.npz"), 1, "behind the camera"),
    ("latency: no calibration file", lambda d: _s(d, "video_no_calibration.npz"), 2, "no-such-camera.yaml"),
    ("latency: a directory", lambda d: _s(d, "adir.yaml"), 2, "adir.yaml"),
    ("latency: a missing file", lambda d: _s(d, "missing.npz"), 2, "missing.npz"),
    ("latency: --max-rc-lag 1e9", lambda d: [*_s(d, "good.npz"), "--max-rc-lag", "1e9"], 2, "--max-rc-lag"),
    ("latency: --max-lag nan", lambda d: [*_s(d, "good.npz"), "--max-lag", "nan"], 2, "--max-lag"),
    ("latency: --window -1", lambda d: [*_s(d, "good.npz"), "--window", "-1"], 2, "--window"),
    (
        "latency: --out a full disk",
        lambda d: [*_s(d, "good.npz"), "--out", str(d / "full.yaml")],
        1,
        "full.yaml",
    ),
    ("latency: --out not yaml", lambda d: [*_s(d, "good.npz"), "--out", str(d / "x.txt")], 2, "x.txt"),
    (
        "latency: --out in a missing folder",
        lambda d: [*_s(d, "good.npz"), "--out", str(d / "missing" / "x.yaml")],
        2,
        "missing",
    ),
    # the multi-process tools (flightstack/cli/network.py) and certs
    ("world: random bytes", lambda d: ["world", str(d / "garbage.yaml")], 2, "garbage.yaml"),
    ("agent: random bytes", lambda d: ["agent", str(d / "garbage.yaml"), "--id", "1"], 2, "garbage.yaml"),
    ("agent: --id 1e9", lambda d: ["agent", "paper_sim", "--id", "1e9"], 2, "--id"),
    ("abort: missing", lambda d: ["abort", str(d / "missing.yaml")], 2, "missing.yaml"),
    ("status: a directory", lambda d: ["status", str(d / "adir.yaml"), "--once"], 2, "adir.yaml"),
    ("guard: empty file", lambda d: ["guard", str(d / "empty.yaml")], 2, "empty.yaml"),
    (
        "certs: random bytes",
        lambda d: ["certs", str(d / "garbage.yaml"), "--out", str(d / "c")],
        2,
        "garbage.yaml",
    ),
    (
        "certs: --days 1e9",
        lambda d: ["certs", "paper_sim", "--out", str(d / "c"), "--days", "1e9"],
        2,
        "--days",
    ),
    # faults, sweep, generate-mission
    (
        "faults: random bytes mission",
        lambda d: ["faults", "--mission", str(d / "garbage.yaml"), "--out", str(d / "f")],
        2,
        "garbage.yaml",
    ),
    (
        "sweep: random bytes",
        lambda d: ["sweep", str(d / "garbage.yaml"), "--seeds", "2", "--out", str(d / "s")],
        2,
        "garbage.yaml",
    ),
    (
        "sweep: --seeds 1e9",
        lambda d: ["sweep", "paper_sim", "--seeds", "1e9", "--out", str(d / "s")],
        2,
        "--seeds",
    ),
    ("generate-mission: --drones 1e9", lambda d: ["generate-mission", "--drones", "1e9"], 2, "--drones"),
    (
        "generate-mission: random bytes base",
        lambda d: ["generate-mission", "--drones", "3", "--base", str(d / "garbage.yaml")],
        2,
        "garbage.yaml",
    ),
    # the readers of a run directory: random bytes behind a valid row-stream header
    ("report: random rows", lambda d: ["report", str(d / "run_random_rows"), "--no-plots"], 2, ".rows"),
    (
        "export: random rows",
        lambda d: ["export", str(d / "run_random_rows"), "--mcap", str(d / "x.mcap")],
        2,
        ".rows",
    ),
    (
        "view: random rows",
        lambda d: ["view", str(d / "run_random_rows"), "--save", str(d / "x.rrd")],
        2,
        ".rows",
    ),
    ("report: missing", lambda d: ["report", str(d / "missing")], 2, "missing"),
    ("export: missing", lambda d: ["export", str(d / "missing"), "--mcap", str(d / "x.mcap")], 2, "missing"),
    ("view: missing", lambda d: ["view", str(d / "missing"), "--save", str(d / "x.rrd")], 2, "missing"),
    (
        "report: random bytes --mission",
        lambda d: ["report", str(d / "run_random_rows"), "--mission", str(d / "garbage.yaml")],
        2,
        "garbage.yaml",
    ),
    # validate, completion, bench-loop
    ("draw-lab: random bytes", lambda d: ["draw-lab", str(d / "garbage.yaml")], 2, "garbage.yaml"),
    ("draw-lab: empty file", lambda d: ["draw-lab", str(d / "empty.yaml")], 2, "empty.yaml"),
    ("draw-lab: /dev/zero", lambda d: ["draw-lab", "/dev/zero"], 2, "/dev/zero"),
    ("draw-lab: --out a directory", lambda d: ["draw-lab", "lab", "--out", str(d)], 2, "is a directory"),
    ("draw-lab: --out a device", lambda d: ["draw-lab", "lab", "--out", "/dev/null"], 2, "/dev/null"),
    ("validate: random bytes", lambda d: ["validate", str(d / "garbage.yaml")], 2, "garbage.yaml"),
    ("validate: empty file", lambda d: ["validate", str(d / "empty.yaml")], 2, "empty.yaml"),
    ("validate: /dev/zero", lambda d: ["validate", "/dev/zero"], 2, "/dev/zero"),
    ("completion: unknown shell", lambda d: ["completion", "tcsh"], 2, "tcsh"),
    ("bench-loop: --seconds nan", lambda d: ["bench-loop", "--seconds", "nan"], 2, "--seconds"),
    (
        "bench-loop: random bytes rig",
        lambda d: ["bench-loop", "--rig", str(d / "garbage.yaml")],
        2,
        "garbage",
    ),
]


def _id(case: object) -> str:
    values = getattr(case, "values", None)
    return str((values[0] if values else case)[0])  # type: ignore[index]


def test_every_entry_point_is_fed() -> None:
    """Every subcommand of the parser (calibrate's included) has at least one case here."""
    import argparse

    def leaves(p: argparse.ArgumentParser, pre: str) -> list[str]:
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                return [x for n, sp in a.choices.items() for x in leaves(sp, f"{pre} {n}".strip())]
        return [pre]

    commands = leaves(build_parser(), "")
    fed = {_id(c).split(":")[0] for c in CASES}
    fed |= {f"calibrate {c}" for c in ("latency",)}
    missing = [c for c in commands if c not in fed]
    assert not missing, f"no damaged input for: {', '.join(missing)}"


@pytest.mark.parametrize("case", CASES, ids=_id)
def test_damaged_input_exits_with_its_code_and_one_line(
    d: Path, case: Case, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _, argv_of, expected, names = case
    monkeypatch.chdir(d)  # anything a case would write by default lands here
    argv = argv_of(d)
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code if isinstance(exc.code, int) else 2
    _, err = capsys.readouterr()
    shown = err if len(err) < 3000 else err[:1500] + " ... " + err[-1500:]
    assert code in CONTRACT, (code, shown)
    assert "Traceback" not in err, shown
    assert not BARE.search(err), shown
    assert code == expected, (code, shown)
    if expected != 0:
        errors = [line for line in err.splitlines() if "error:" in line]
        assert len(errors) == 1, shown
        assert names in errors[0], (names, errors[0])
