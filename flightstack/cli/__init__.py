# PYTHON_ARGCOMPLETE_OK
"""The operator CLI (`flightstack ...`): `main` parses and dispatches; `network` holds the agent and world
processes' subcommands, `certs` the mission CA.

The console script `flightstack` enters here: the `PYTHON_ARGCOMPLETE_OK` marker on the first line lets
argcomplete's global completion (`activate-global-python-argcomplete`) complete it; `flightstack completion
SHELL` prints the per-command shell code instead (flightstack/cli/completion.py)."""

from __future__ import annotations

import gc


def main(argv: list[str] | None = None) -> int:
    """The console script and `python -m flightstack`: app.main, then, the process being about to exit,
    every object left is frozen (gc.freeze): CPython's finalisation would otherwise run full collections
    over the ~200 000 objects of the ~1400 modules a run imports (measured: 1.1-1.8 s of a run's process
    on loaded cores, docs/performance.md). Objects are still freed; the files are closed by then."""
    from flightstack.cli import app  # here, so `python -m flightstack.cli.app` imports app only once

    code = app.main(argv)
    if argv is None:  # a process of its own (a caller passing argv, e.g. a test, goes on living)
        gc.freeze()
    return code


__all__ = ["main"]
