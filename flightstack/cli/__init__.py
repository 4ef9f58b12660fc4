# PYTHON_ARGCOMPLETE_OK
"""The operator CLI (`flightstack ...`): `main` parses and dispatches; `network` holds the agent and world
processes' subcommands, `certs` the mission CA.

The console script `flightstack` enters here: the `PYTHON_ARGCOMPLETE_OK` marker on the first line lets
argcomplete's global completion (`activate-global-python-argcomplete`) complete it; `flightstack completion
SHELL` prints the per-command shell code instead (flightstack/cli/completion.py)."""

from flightstack.cli.app import main

__all__ = ["main"]
