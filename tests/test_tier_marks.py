"""The suite's marks as .ci/run uses them (tests/conftest.py): a test is `timing` exactly when it bounds a
safety reaction's time (it requests `safety_bound`), is a row of a fault table flown on the emulated lab
or is one of conftest's CPU_TIMED_TESTS (each listed with why);
`fault_table` marks those tables only; every test is in exactly one of `unit` and `system`; and no test
that bounds a reaction is lost (37 test functions on 2026-12-06: 36 system, 1 unit).

The whole suite is collected in a child pytest (about 8 s) with a plugin that writes each test's marks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.conftest import CPU_TIMED_TESTS, FAULT_FLIGHT_MODULES, REPO, SAFETY_BOUND_FIXTURE

SAFETY_BOUND_FUNCTIONS_AT_LEAST = 37
"""Test functions that assert a safety_bound when the mark became per test (2026-12-06)."""

PLUGIN = """
import json, os
import pytest

@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    rows = [
        {
            "id": item.nodeid,
            "function": item.nodeid.split("[")[0],
            "module": item.path.stem,
            "bounds": "SAFETY_BOUND" in getattr(item, "fixturenames", ()),
            "marks": sorted({m.name for m in item.iter_markers()}),
        }
        for item in items
    ]
    with open(os.environ["MARKS_OUT"], "w") as f:
        json.dump(rows, f)
"""


def test_timing_is_per_test_and_nothing_bounded_is_lost(tmp_path: Path) -> None:
    (tmp_path / "marks_plugin.py").write_text(PLUGIN.replace("SAFETY_BOUND", SAFETY_BOUND_FIXTURE))
    out = tmp_path / "marks.json"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}  # not this run's worker
    env.update(MARKS_OUT=str(out), PYTHONPATH=str(tmp_path))
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        "--collect-only",
        "-q",
        "-p",
        "no:cacheprovider",
        "-p",
        "marks_plugin",
    ]
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    rows = json.loads(out.read_text())
    assert len(rows) > 1000

    for r in rows:
        marks = set(r["marks"])
        fault = r["module"] in FAULT_FLIGHT_MODULES
        assert ("timing" in marks) == (r["bounds"] or fault or r["function"] in CPU_TIMED_TESTS), r
        assert ("fault_table" in marks) == fault, r
        assert len(marks & {"unit", "system"}) == 1, r

    listed = {r["function"] for r in rows} & CPU_TIMED_TESTS
    assert listed == CPU_TIMED_TESTS, CPU_TIMED_TESTS - listed  # each name still names a test
    bounded = {r["function"] for r in rows if r["bounds"]}
    bounded_system = {r["function"] for r in rows if r["bounds"] and "system" in r["marks"]}
    print(f"\n{len(bounded)} test functions bound a safety reaction ({len(bounded_system)} system)")
    assert len(bounded) >= SAFETY_BOUND_FUNCTIONS_AT_LEAST
    # the mark is per test: a module with a bounded test keeps its other tests off the serial run
    split = {r["module"] for r in rows if r["bounds"]} - FAULT_FLIGHT_MODULES
    assert any(r["module"] in split and "timing" not in r["marks"] for r in rows)
