"""The process's thread pools (flightstack.threads): one rule, applied before or after BLAS and numba are
loaded, exported to child processes, and what a run reports."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flightstack import threads


def _in_child(code: str, env: dict[str, str] | None = None) -> dict[str, object]:
    """Run `code` in a fresh interpreter (the pools are process-wide); its last stdout line as JSON."""
    base = {k: v for k, v in os.environ.items() if k not in (*threads.BLAS_ENV, threads.NUMBA_ENV)}
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env={**base, **(env or {})}
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def test_the_rule_gives_each_flight_one_blas_and_one_numba_thread() -> None:
    lim = threads.limits_for(3)
    assert (lim.workers, lim.blas, lim.numba) == (3, 1, 1)
    assert lim.cpus == len(os.sched_getaffinity(0))
    assert "BLAS 1, numba 1 per flight; 3 flights at once" in lim.line()
    with pytest.raises(ValueError, match="at least 1"):
        threads.limits_for(0)


@pytest.mark.parametrize("first", ["apply", "import"])
def test_apply_limits_blas_and_numba_loaded_before_or_after(first: str) -> None:
    """Whether numpy, scipy and numba are loaded before `apply` (threadpoolctl, set_num_threads) or after
    (the environment variables), BLAS runs one thread; a child process inherits the limits."""
    load = "import numpy, scipy.linalg, numba"
    steps = [load, "threads.apply(threads.limits_for(1))"]
    code = "\n".join(
        [
            "import json, subprocess, sys",
            "from flightstack import threads",
            *(steps if first == "import" else steps[::-1]),
            "import numba",
            "ask = 'import os; print(os.environ[\"OPENBLAS_NUM_THREADS\"])'",
            "child = subprocess.run([sys.executable, '-c', ask], capture_output=True, text=True)",
            "child = child.stdout.strip()",
            "now = {'numba_now': numba.get_num_threads(), 'child': child}",
            "print(json.dumps({**threads.in_effect().as_dict(), **now}))",
        ]
    )
    got = _in_child(code)
    assert got["blas"] == 1 and got["numba_now"] == 1 and got["child"] == "1", got


def test_the_cli_applies_the_rule_before_a_command_loads_numba(tmp_path: Path) -> None:
    """`flightstack validate` (a command that loads numpy and numba) runs with the rule's pools: the
    environment is set before its modules load, so numba's pool itself is one thread."""
    code = (
        "import json, sys\n"
        "from flightstack.cli.app import main\n"
        "code = main(['validate', 'paper_sim'])\n"
        "import numba\n"
        "from flightstack import threads\n"
        "print(json.dumps({**threads.in_effect().as_dict(), 'code': code,"
        " 'numba_pool': numba.config.NUMBA_NUM_THREADS}))"
    )
    got = _in_child(code)
    assert got["code"] == 0 and got["blas"] == 1 and got["numba_pool"] == 1, got
