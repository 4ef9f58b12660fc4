"""docs/troubleshooting.md quotes the common exit-2 lines; each quote is what the command prints now (a
`…` in a quote stands for a shortened path), so the page cannot drift from the code. Every case stops
before anything flies (exit 2)."""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import pytest

from flightstack import cli

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "troubleshooting.md"
SPAN = re.compile(r"``\s(.+?)\s``|`([^`]+)`")

CASES: dict[str, list[str]] = {
    "out-not-empty": ["run", "paper_sim", "--out", "runs/paper", "--duration", "12"],
    "too-short": ["run", "paper_sim", "--duration", "5", "--out", "o1"],
    "no-rig": ["run", "paper_sim", "--rig", "nosuch", "--out", "o2"],
    "unknown-key": ["run", "paper_sim", "--set", "gp.nosuch=1", "--out", "o3", "--duration", "2"],
    "rig-missing": ["validate", "bad.yaml"],
    "invalid": ["validate", "bad.yaml", "--rig", "ideal"],
    "network-on-sim": ["run", "paper_sim", "--network", "lab-wifi", "--out", "o4", "--duration", "2"],
    "needs-zenoh": ["agent", "paper_experiment", "--rig", "lab", "--id", "1"],
}
"""The commands that print the quoted lines, run in a directory holding `runs/paper/x` and `bad.yaml`."""


def quoted_lines() -> list[list[str]]:
    """The code spans of the first cell of each row of the page's exit-2 table."""
    section = PAGE.read_text(encoding="utf-8").split("## The common exit-2 lines", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `")]
    return [[a or b for a, b in SPAN.findall(row.split(" | ", 1)[0])] for row in rows]


def _pattern(quote: str) -> re.Pattern[str]:
    return re.compile(".*?".join(re.escape(part) for part in quote.split("…")))


@pytest.fixture(scope="module")
def printed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[int, str]]:
    """Each case's exit code and stderr."""
    work = tmp_path_factory.mktemp("troubleshooting")
    (work / "runs" / "paper").mkdir(parents=True)
    (work / "runs" / "paper" / "x").write_text("")
    (work / "bad.yaml").write_text("name: x\nduration_s: -1\n")
    out: dict[str, tuple[int, str]] = {}
    here = os.getcwd()
    os.chdir(work)
    try:
        for name, argv in CASES.items():
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = cli.main(argv)
            out[name] = (code, err.getvalue())
    finally:
        os.chdir(here)
    return out


def test_every_case_exits_2(printed: dict[str, tuple[int, str]]) -> None:
    assert {name: code for name, (code, _) in printed.items()} == dict.fromkeys(CASES, 2), printed


def test_every_quoted_line_is_printed_by_a_case(printed: dict[str, tuple[int, str]]) -> None:
    quotes = quoted_lines()
    assert len(quotes) == len(CASES), f"{len(quotes)} rows in the page's table, {len(CASES)} cases here"
    for spans in quotes:
        hits = [n for n, (_, err) in printed.items() if all(_pattern(s).search(err) for s in spans)]
        assert hits, f"docs/troubleshooting.md quotes {spans!r}, which no case prints now: {printed}"


def test_the_quote_matcher_is_not_vacuous() -> None:
    assert _pattern("error: a … b").search("error: a /long/path b")
    assert not _pattern("error: a … b").search("error: a c")
    assert all(spans and all(spans) for spans in quoted_lines())
