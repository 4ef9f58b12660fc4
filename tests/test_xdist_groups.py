"""The system tier's xdist groups reach the scheduler: a module-scoped fixture of one group runs once.

pytest 9.2 keeps a node's id where pytest-xdist 3.8's `--dist loadgroup` does not rename it, so every
group was spread over the workers: each fault table's module fixture flew three times, the tier took 22
minutes instead of 9 and its timing tests ran on an overloaded machine (pyproject.toml pins pytest below
9.2). This test runs a small suite on two workers and counts the fixture's set-ups.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SUITE = """
import os
import pytest

@pytest.hookimpl(tryfirst=True)  # as tests/conftest.py: before xdist reads the groups
def pytest_collection_modifyitems(items):
    for item in items:
        item.add_marker(pytest.mark.xdist_group("one"))
"""

MODULE = """
import os
import pytest

@pytest.fixture(scope="module")
def table():
    with open(os.environ["SETUPS"], "a") as f:
        f.write(os.environ.get("PYTEST_XDIST_WORKER", "-") + "\\n")

@pytest.mark.parametrize("n", range(6))
def test_row(table, n):
    pass
"""


def test_one_group_runs_on_one_worker_and_sets_its_module_fixture_up_once(tmp_path: Path) -> None:
    pytest.importorskip("xdist")
    (tmp_path / "conftest.py").write_text(SUITE)
    (tmp_path / "test_rows.py").write_text(MODULE)
    setups = tmp_path / "setups.txt"
    env = {"SETUPS": str(setups), "PATH": "/usr/bin:/bin", "PYTHONDONTWRITEBYTECODE": "1"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist", "loadgroup"]
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    workers = setups.read_text().split()
    assert len(workers) == 1, f"module fixture set up on {workers}: xdist_group is not honoured"
