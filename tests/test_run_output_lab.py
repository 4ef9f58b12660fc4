"""The run output of `paper_experiment` on the simulated lab explains itself (system tier: a real run of
about 40 s of CPU): the three figures a newcomer read as failures carry their explanation on the next line,
and every line on stderr carries a level, a safety line its kind's severity (a takeoff is `info`)."""

from __future__ import annotations

import pytest

from flightstack.cli.summary import LEVELS
from flightstack.events import KINDS
from tests.conftest import run_cli

pytestmark = pytest.mark.system


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[str], list[str]]:
    out = tmp_path_factory.mktemp("lab") / "run"
    r = run_cli("run", "paper_experiment", "--rig", "lab-sim", "--duration", "12", "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout.splitlines(), r.stderr.splitlines()


def _next(lines: list[str], phrase: str) -> str:
    """The line after the first line holding `phrase`."""
    k = next(i for i, ln in enumerate(lines) if phrase in ln)
    return lines[k + 1].strip()


def test_kappa_not_satisfied_is_explained(lab_run: tuple[list[str], list[str]]) -> None:
    out, _ = lab_run
    note = _next(out, "(NOT satisfied)")
    assert (
        note.startswith("note: not a fault of the run") and "docs/paper-comparison.md#gain-analysis" in note
    )


def test_a_target_never_seen_by_design_is_explained(lab_run: tuple[list[str], list[str]]) -> None:
    out, _ = lab_run
    note = _next(out, "2: 0 %")
    assert note.startswith("note: expected: drone 2 never sees the target by design (`sees_target: false`")


def test_safety_lines_carry_a_level_and_the_takeoff_climb_is_no_timeout(
    lab_run: tuple[list[str], list[str]],
) -> None:
    _, err = lab_run
    safety = [ln for ln in err if "flightstack.safety:" in ln]
    assert any(ln.startswith("info: flightstack.safety: t=0.000 drone 1 takeoff") for ln in safety), err
    assert all(ln.split(":")[0] in LEVELS for ln in err), err  # every stderr line, not only the safety ones
    for ln in safety:  # "<level>: flightstack.safety: t=<t> <drone i | mission> <kind>: <detail>"
        level, _, rest = ln.partition(": flightstack.safety: ")
        kind = rest.split(":")[0].split()[-1]
        assert level == KINDS[kind].severity.lower(), ln
    assert not any("command_timeout" in ln for ln in err), err
