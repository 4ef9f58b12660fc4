"""The operator CLI (`flightstack ...`): `main` parses and dispatches; `network` holds the agent and world
processes' subcommands, `certs` the mission CA."""

from flightstack.cli.app import main

__all__ = ["main"]
