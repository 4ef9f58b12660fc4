"""The `faults` subcommand: `flightstack faults [--only NAME ...] [--out DIR] [--mission FILE]`.

Runs the rows of flightstack.faults, prints the table, writes DIR/faults.json, the summary figure
DIR/faults.png (flightstack.faults.figure) and each row's run files under DIR, and exits 0 iff every
row was handled (1 otherwise). `flightstack.cli.app` adds it with `faults_cli.register(sub)`;
`python -m flightstack.faults.cli ...` runs it alone.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the `faults` subcommand to a subparsers object (of `flightstack`'s parser)."""
    from flightstack.faults import DEFAULT_MISSION, FAULTS

    p = sub.add_parser(
        "faults",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--only",
        action="append",
        choices=list(FAULTS),
        metavar="NAME",
        help=f"run only this row (repeatable); rows: {', '.join(FAULTS)}",
    )
    p.add_argument("--out", default="runs/faults", help="directory for faults.json and each row's files")
    p.add_argument("--mission", default=str(DEFAULT_MISSION), help="mission to fly (default: the lab sim)")
    p.add_argument("--expected", action="store_true", help="also print each row's expected reaction")
    p.add_argument("--verbose", action="store_true", help="show the safety events live (logging)")
    p.set_defaults(func=cmd_faults)
    return p


def cmd_faults(args: argparse.Namespace) -> int:
    from flightstack.config.mission import load_mission
    from flightstack.faults import format_table, run_faults, write_json

    load_mission(Path(args.mission))  # a bad mission: exit 2 naming it (MissionError), before any row flies
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    if not args.verbose:  # hundreds of injected-fault safety events would bury the table
        logging.getLogger("flightstack.safety").setLevel(logging.ERROR)
    out = Path(args.out)
    results = run_faults(args.only, out, Path(args.mission))
    print(format_table(results, expected=args.expected))
    write_json(results, out / "faults.json")
    print(f"written: {out / 'faults.json'}")
    try:  # the picture is a convenience: a failure to draw it never changes the verdict
        from flightstack.faults.figure import plot_fault_summary

        fig = plot_fault_summary([r.to_dict() for r in results], out / "faults.png")
        print(f"written: {fig}")
    except Exception as exc:
        print(f"faults.png not written: {type(exc).__name__}: {exc}", file=sys.stderr)
    return 0 if all(r.handled for r in results) else 1


def main(argv: list[str] | None = None) -> int:
    """`flightstack faults ARGS` without the rest of the command line (for tests and `python -m`)."""
    parser = argparse.ArgumentParser(prog="flightstack")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["faults", *(argv or [])])
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
