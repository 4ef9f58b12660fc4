"""`flightstack --help` and the completion of a command's name import only what they need (no numpy,
numba, scipy, matplotlib, cv2 or zenoh: measured with `python -X importtime`, no timing asserted), and the
help lists every command once, grouped by what an operator does, under a "start here" line."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

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


def _subcommands(parser: argparse.ArgumentParser, path: str = "flightstack") -> list[tuple[str, Any]]:
    """(its command line, parser) of every command and subcommand under `parser`."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += [(f"{path} {name}", sub), *_subcommands(sub, f"{path} {name}")]
    return out


def _help(capsys: pytest.CaptureFixture[str], *command: str) -> str:
    """`flightstack COMMAND -h` as printed, its lines joined (argparse wraps them to the terminal)."""
    with pytest.raises(SystemExit):
        build_parser({command[0]}).parse_args([*command, "-h"])
    return " ".join(capsys.readouterr().out.split())


def test_every_command_has_a_description_and_every_argument_a_help() -> None:
    missing = []
    for path, sub in _subcommands(build_parser()):
        if not sub.description:
            missing.append(f"{path}: no description")
        for action in sub._actions:
            if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)) and not action.help:
                missing.append(f"{path}: {action.dest} has no help")
    assert not missing, missing


def test_every_default_worth_saying_is_said() -> None:
    """An option with a default (not None, False or empty) names it in its help: argparse's own text where
    the help said it, else `(default: X)` appended (into the parentheses of a unit); none says a default
    that tells the operator nothing."""
    unsaid, empty = [], []
    for path, sub in _subcommands(build_parser()):
        fmt = sub._get_formatter()
        for action in sub._actions:
            if not action.help or action.help is argparse.SUPPRESS:
                continue
            text = " ".join(fmt._expand_help(action).split())
            worth = action.option_strings and action.nargs != 0 and action.default not in (None, False, [])
            if worth and "default" not in text.lower():
                unsaid.append(f"{path} {action.option_strings[0]}")
            if any(f"default: {v})" in text for v in ("None", "False", "inf", "[]")):
                empty.append(f"{path} {action.option_strings}: {text}")
    assert not unsaid, unsaid
    assert not empty, empty


def test_preflight_abort_and_guard_say_what_they_do(capsys: pytest.CaptureFixture[str]) -> None:
    preflight = _help(capsys, "preflight")
    assert "Nothing takes off and nothing moves" in preflight and "exit 0 without a FAIL" in preflight
    assert "mission experiment (with --rig LAB.yaml) or mission YAML file" in preflight
    assert "--deadline DEADLINE bound on the whole check (s; default: 9.0)" in preflight
    abort = _help(capsys, "abort")
    assert "each agent lands its drones" in abort and "else 1 naming the others" in abort
    assert "--reason REASON why, sent with the abort" in abort and "(default: operator abort)" in abort
    guard = _help(capsys, "guard")
    assert "land that Tello from this computer" in guard and "Station topology only" in guard
    assert (
        "--give-up GIVE_UP stop re-sending after this long without seeing it down (s; default: 20.0)" in guard
    )


def test_fly_offers_none_of_the_options_only_simulated_rigs_apply(capsys: pytest.CaptureFixture[str]) -> None:
    """--network and --links change what the simulated and the emulated lab apply: `run` and `sim` take
    them, `fly` (real drones) does not list them and refuses them."""
    run, fly = _help(capsys, "run"), _help(capsys, "fly")
    for option in ("--network", "--links"):
        assert option in run and option not in fly, option
    with pytest.raises(SystemExit):
        build_parser({"fly"}).parse_args(["fly", "lab.yaml", "--network", "outage"])
    assert "unrecognized arguments: --network" in capsys.readouterr().err
