"""The CLI conventions: `--version`, `python -m flightstack`, shell completion (argcomplete),
`validate` printing a summary (`--json` for the resolved mission), and one meaning per option name
(`--marker-size` for the ChArUco marker side, `--marker` the pixel box of `calibrate markers`)."""

from __future__ import annotations

import argparse
import io
import json
import shutil
import subprocess
import sys
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as dist_version
from pathlib import Path

import argcomplete
import cv2
import numpy as np
import pytest
import yaml

from flightstack.cli import app
from flightstack.cli.app import build_parser, main
from flightstack.cli.validate import id_ranges
from flightstack.config.mission import load_mission, mission_to_dict
from flightstack.config.rig import resolved_document
from tests.conftest import MISSIONS, completion_env


def _subcommands(parser: argparse.ArgumentParser) -> list[str]:
    """The names of the top-level subcommands."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


# ---- --version, python -m flightstack ---------------------------------------------------------------------
def test_version_prints_the_distribution_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out == f"flightstack {dist_version('flightstack')}\n"


def test_version_without_metadata_says_unknown(monkeypatch: pytest.MonkeyPatch) -> None:
    def missing(name: str) -> str:
        raise PackageNotFoundError(name)

    monkeypatch.setattr(app, "version", missing)
    assert app.package_version() == "unknown"


def test_python_m_flightstack_runs_main_and_propagates_its_exit_code(tmp_path: Path) -> None:
    """`python -m flightstack` is the console script: the same output, and main's return code as the exit
    code (2 for a missing file, which main returns rather than raises)."""
    run = [sys.executable, "-m", "flightstack"]
    r = subprocess.run([*run, "--version"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout == f"flightstack {dist_version('flightstack')}\n", r.stderr
    r = subprocess.run(
        [*run, "validate", str(tmp_path / "missing.yaml")], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2 and "missing.yaml" in r.stderr and "Traceback" not in r.stderr


# ---- shell completion --------------------------------------------------------------------------------------
@pytest.mark.parametrize("shell", ["bash", "zsh", "fish"])
def test_completion_prints_the_shell_code(shell: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["completion", shell]) == 0
    code = capsys.readouterr().out
    assert "flightstack" in code and "complete" in code
    assert code == argcomplete.shellcode(["flightstack"], shell=shell).rstrip("\n") + "\n"


def test_completion_rejects_an_unknown_shell(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["completion", "tcsh-like"])
    assert exc.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


class _QuietFinder(argcomplete.CompletionFinder):
    """argcomplete's finder without its debug stream on fd 9 (its documented hook for use under pytest)."""

    def _init_debug_stream(self) -> None:
        pass


def _complete(line: str, monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """What the shell would offer for `line` (cursor at its end), as argcomplete's own tests compute it."""
    monkeypatch.setenv("_ARGCOMPLETE", "1")
    monkeypatch.setenv("COMP_LINE", line)
    monkeypatch.setenv("COMP_POINT", str(len(line)))
    monkeypatch.setenv("_ARGCOMPLETE_IFS", "\n")
    monkeypatch.delenv("_ARGCOMPLETE_SHELL", raising=False)
    out = io.StringIO()
    with pytest.raises(SystemExit) as exc:
        _QuietFinder()(build_parser(), exit_method=sys.exit, output_stream=out)
    assert exc.value.code == 0
    return sorted(c.strip() for c in out.getvalue().split("\n") if c)


def test_completer_offers_the_subcommands(monkeypatch: pytest.MonkeyPatch) -> None:
    names = _subcommands(build_parser())
    expected = sorted(n for n in names if n.startswith("s"))
    assert {"sim", "sweep"} <= set(expected)
    assert _complete("flightstack s", monkeypatch) == expected
    assert _complete("flightstack valid", monkeypatch) == ["validate"]
    assert "completion" in _complete("flightstack ", monkeypatch)


def test_completer_offers_options_and_hides_the_deprecated_alias(monkeypatch: pytest.MonkeyPatch) -> None:
    assert _complete("flightstack validate paper_sim --j", monkeypatch) == ["--json"]
    assert _complete("flightstack calibrate camera --marker", monkeypatch) == ["--marker-size"]
    assert _complete("flightstack calibrate markers --mark", monkeypatch) == ["--marker"]


def test_the_console_script_answers_a_completion_request(tmp_path: Path) -> None:
    """The process the shell code starts: main() answers from argcomplete's environment variables (here
    written to a file instead of fd 8) and exits 0 without running a subcommand."""
    out = tmp_path / "completions"
    env = completion_env("flightstack s", out)
    r = subprocess.run(
        [sys.executable, "-m", "flightstack"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout == ""
    got = sorted(out.read_text().split("\n"))
    assert got == sorted(n for n in _subcommands(build_parser()) if n.startswith("s"))


def test_the_entry_point_modules_carry_the_argcomplete_marker() -> None:
    """Global completion (activate-global-python-argcomplete) completes a console script only when the
    module of its entry point (flightstack.cli, i.e. its __init__.py) has the marker in its first 1024
    bytes; `python -m flightstack` looks in flightstack/__main__.py."""
    import flightstack
    import flightstack.cli

    for path in (Path(flightstack.cli.__file__), Path(flightstack.__file__).with_name("__main__.py")):
        assert "PYTHON_ARGCOMPLETE_OK" in path.read_text()[:1024], path


# ---- validate: a summary; --json the resolved mission ---------------------------------------------------
def test_validate_prints_a_short_summary(capsys: pytest.CaptureFixture[str]) -> None:
    m = load_mission("paper_sim")
    assert main(["validate", "paper_sim"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[-1] == "valid" and len(lines) <= 12
    with pytest.raises(json.JSONDecodeError):
        json.loads(out)
    assert lines[0] == f"mission {m.name}: rig ideal, backend sim_ideal (simulated)"
    assert f"drones: {len(m.drones)} (ids 1-3); complete graph" in out
    assert f"duration {m.duration_s:g} s, dt {m.dt_s:g} s" in out
    assert f"modes {', '.join(m.compare_modes)}" in out
    assert f"k_s {m.gains.k_s:g}" in out and "k_c [" in out and "k_e [" in out
    assert "gp: " in out and f"fusion {m.gp.fusion}" in out and f"noise_var {m.gp.noise_var:g}" in out
    assert "safety: off" in out and "hardware" not in out


def test_validate_summary_names_the_hardware(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", "paper_experiment", "--rig", "lab"]) == 0
    out = capsys.readouterr().out
    assert "backend tello (real hardware)" in out and "safety: on" in out
    assert "hardware (access_point): mocap optitrack; robot at udpout:" in out
    assert "tellos 1 at 192.168.10.1:8889" in out and out.endswith("valid\n")


def test_validate_json_prints_the_resolved_mission(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", "paper_sim", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == mission_to_dict(load_mission("paper_sim"))


def test_validate_a_rig_file_summary_and_json(capsys: pytest.CaptureFixture[str]) -> None:
    lab = MISSIONS / "rigs" / "lab.yaml"
    assert main(["validate", str(lab)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "rig lab: backend tello" and "drones: 2 (ids 1, 2)" in lines and lines[-1] == "valid"
    assert main(["validate", str(lab), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["drones"] == [1, 2]


@pytest.mark.parametrize("as_json", [False, True])
def test_validate_an_invalid_file_exits_2_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], as_json: bool
) -> None:
    doc = resolved_document(MISSIONS / "paper_sim.yaml")
    doc["dt_s"] = -0.05
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    assert main(["validate", str(path), *(["--json"] if as_json else [])]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "dt_s: Input should be greater than or equal to 0.0001" in captured.err


@pytest.mark.parametrize("name", ["", "   ", "\t"], ids=["empty", "blanks", "tab"])
def test_validate_refuses_a_blank_rigid_body_name_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """`hardware.mocap.bodies` maps a drone to the rigid body it flies by: a blank name exits 2 naming the
    key (it validated before)."""
    shutil.copytree(MISSIONS / "cameras", tmp_path / "cameras")  # the rig's calibrations, beside it
    rig = yaml.safe_load((MISSIONS / "rigs" / "lab.yaml").read_text())
    rig["hardware"]["mocap"]["bodies"]["drone1"] = name
    (tmp_path / "rigs").mkdir()
    path = tmp_path / "rigs" / "lab.yaml"
    path.write_text(yaml.safe_dump(rig, sort_keys=False))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "hardware.mocap.bodies.drone1:" in err, err
    assert "not empty or blank" in err, err
    assert main(["validate", "paper_experiment", "--rig", str(path)]) == 2
    assert "hardware.mocap.bodies.drone1:" in capsys.readouterr().err


def test_id_ranges() -> None:
    assert id_ranges([1, 2]) == "1, 2"
    assert id_ranges([0, 2, 3, 4, 10]) == "0, 2-4, 10"
    assert id_ranges(list(range(1, 32))) == "1-31"


# ---- --marker-size (length) vs --marker (pixel box) --------------------------------------------------------
@pytest.mark.parametrize("command", [["camera"], ["check", "cal.yaml", "--image", "x.png"]])
def test_marker_size_is_the_charuco_marker_side(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    args = build_parser().parse_args(["calibrate", *command, "--marker-size", "0.03"])
    assert args.marker_size == 0.03
    assert capsys.readouterr().err == ""


def test_marker_stays_the_pixel_box_of_calibrate_markers(capsys: pytest.CaptureFixture[str]) -> None:
    args = build_parser().parse_args(
        ["calibrate", "markers", "--marker", "red=1,2,3,4", "--marker", "green=5,6,7,8@1"]
    )
    assert args.marker == ["red=1,2,3,4", "green=5,6,7,8@1"]
    assert capsys.readouterr().err == ""


def test_a_bad_marker_size_is_named_by_its_new_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """End to end through `calibrate check`: the pattern's error names --marker-size."""
    image = tmp_path / "sample.png"
    cv2.imwrite(str(image), np.zeros((240, 320, 3), np.uint8))
    cal = str(MISSIONS / "cameras" / "tello_down_sim.yaml")
    pattern = ["--pattern", "charuco", "--cols", "5", "--rows", "7", "--square", "0.04"]
    assert main(["calibrate", "check", cal, "--image", str(image), *pattern, "--marker-size", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "--marker-size: the ArUco marker side (metres) must be in (0, square=0.04)" in err
