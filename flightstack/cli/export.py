"""`flightstack export RUN_DIR --mcap FILE [--modes a,b] [--force]`: a run directory as one MCAP file for
Foxglove and PlotJuggler (flightstack.recording.mcap_export: the live MCAP's topics `/<mode>/...`, typed
protobuf messages, mission-clock time base), for run directories written without the live MCAP.

Exit codes: 0 written (a damaged optional file skipped: a line `skipped: <file>: <what>` on stderr); 2
bad input (no such run directory, no recording in it, a damaged recording, an unknown mode, FILE exists
without --force, FILE is a directory); 1 an error while writing (reported by `cli.app.main`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from flightstack.cli.run import mode_list


def register(sub: Any) -> None:
    """Add the `export` subcommand to the CLI's subparsers."""
    p = sub.add_parser("export")
    p.add_argument("run_dir", help="run directory written by `flightstack run`/`sim`/`fly`/`agent`")
    p.add_argument("--mcap", required=True, metavar="FILE", help="MCAP file to write (e.g. run.mcap)")
    p.add_argument(
        "--modes", type=mode_list, default=None, metavar="A,B", help="only these modes (default: every one)"
    )
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    """Write RUN_DIR's recording to FILE and print a short summary (topics, messages, span)."""
    from flightstack.recording.files import MISSION_FILE, RunDirError
    from flightstack.recording.mcap_export import ExportError, export_mcap
    from flightstack.recording.run_reader import resolved_mission

    run, out = Path(args.run_dir), Path(args.mcap)
    if not run.is_dir():
        print(f"error: {run}: no such run directory", file=sys.stderr)
        return 2
    if out.is_dir():
        print(f"error: {out}: is a directory (give a file name, e.g. {out / 'run.mcap'})", file=sys.stderr)
        return 2
    if out.exists() and not args.force:
        print(f"error: {out} exists (pass --force to overwrite it)", file=sys.stderr)
        return 2
    mission, why = resolved_mission(run)  # lets a run cut short get its e_c and e_e recomputed
    if why is not None and (run / MISSION_FILE).is_file():
        print(f"note: {run}: {why}; exporting the arrays as recorded", file=sys.stderr)
    try:
        s = export_mcap(run, out, args.modes, mission)
    except (ExportError, RunDirError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in s.skipped:
        print(f"skipped: {line}", file=sys.stderr)
    size_mb = out.stat().st_size / 1e6
    print(f"wrote {out} ({size_mb:.1f} MB): {len(s.topics)} topics, {s.messages} messages")
    for mode in s.modes:
        topics = f"/{mode}/..."
        print(f"  {topics:14s} {s.mode_ticks[mode]:7d} ticks   {s.mode_seconds[mode]:8.2f} s mission clock")
    print("  log time: each mode's mission clock from its first wall time (docs/logs.md)")
    return 0
