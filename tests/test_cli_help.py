"""`flightstack --help` and the completion of a command's name import only what they need (no numpy,
numba, scipy, matplotlib, cv2 or zenoh: measured with `python -X importtime`, no timing asserted), and the
help lists every command once, grouped by what an operator does, under a "start here" line."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from flightstack.cli.app import COMMANDS, GROUPS, build_parser, selected_commands
from tests.conftest import completion_env

HEAVY = ("numpy", "numba", "scipy", "matplotlib", "cv2", "zenoh")


def _imported(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> tuple[set[str], str]:
    """The top-level packages `python -X importtime -m flightstack ARGV` imported, and its stdout."""
    r = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "flightstack", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    names = {
        line.split("|")[-1].strip().split(".")[0]
        for line in r.stderr.splitlines()
        if line.startswith("import time:")
    }
    assert "flightstack" in names  # the output is what we think it is
    return names, r.stdout


def test_help_imports_none_of_the_heavy_packages(tmp_path: Path) -> None:
    names, out = _imported(["--help"], tmp_path)
    assert not names & set(HEAVY), sorted(names & set(HEAVY))
    assert out.splitlines()[2].startswith("start here: flightstack run paper_sim")


def test_completing_a_command_name_imports_none_of_the_heavy_packages(tmp_path: Path) -> None:
    out = tmp_path / "completions"
    env = completion_env("flightstack s", out)
    names, _ = _imported([], tmp_path, env)
    assert not names & set(HEAVY), sorted(names & set(HEAVY))
    assert sorted(out.read_text().split("\n")) == ["sim", "status", "sweep"]


def test_the_help_lists_every_command_once_by_group(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert sorted(sub.choices) == sorted(c.name for c in COMMANDS)  # every command is in the table
    assert {c.group for c in COMMANDS} == set(GROUPS)
    with pytest.raises(SystemExit):
        build_parser(set()).parse_args(["--help"])
    text = capsys.readouterr().out
    groups = [line[:-1] for line in text.splitlines() if line.endswith(":") and line[:-1] in GROUPS]
    assert groups == list(GROUPS)
    listed = [
        line.split()[0] for line in text.splitlines() if line.startswith("  ") and not line.startswith("   ")
    ]
    assert sorted(n for n in listed if not n.startswith("-")) == sorted(c.name for c in COMMANDS)


def test_only_the_named_command_is_built_with_its_options() -> None:
    assert selected_commands(["run", "paper_sim", "--out", "x"]) == {"run"}
    assert selected_commands(["--help"]) == set()
    parser = build_parser({"validate"})
    assert parser.parse_args(["validate", "paper_sim", "--json"]).json is True
    with pytest.raises(SystemExit):  # a command built by name only takes no options
        parser.parse_args(["run", "paper_sim", "--out", "x"])
