"""`flightstack export RUN_DIR [--mcap FILE] [--csv FILE] [--modes a,b] [--force]`: a run directory as one
MCAP file for Foxglove and PlotJuggler (flightstack.recording.mcap_export: the live MCAP's topics
`/<mode>/...`, typed protobuf messages, mission-clock time base; for run directories written without the
live MCAP) and/or one CSV of its main time series for pandas or a spreadsheet
(flightstack.recording.csv_table; the columns of the run's own timeseries_<mode>.csv).

Exit codes: 0 written (a damaged optional file skipped: a line `skipped: <file>: <what>` on stderr); 2
bad input (no such run directory, no recording in it, a damaged recording, an unknown mode, FILE exists
without --force, FILE is a directory or anything but a regular file (a device node, a FIFO, a socket:
refused even with --force, which replaces a file by rename and would turn a device into a file), FILE is
a file of the run directory itself (its recording), neither --mcap nor --csv); 1 an error while writing
(reported by `cli.app.main`). Files are written to a temporary file beside FILE and renamed over it."""

from __future__ import annotations

import argparse
import stat
import sys
from pathlib import Path
from typing import Any

from flightstack.cli.run import mode_list


def register(sub: Any) -> None:
    """Add the `export` subcommand to the CLI's subparsers."""
    p = sub.add_parser("export")
    p.add_argument("run_dir", help="run directory written by `flightstack run`/`sim`/`fly`/`agent`")
    p.add_argument("--mcap", metavar="FILE", help="MCAP file to write (e.g. run.mcap)")
    p.add_argument("--csv", metavar="FILE", help="CSV file of the main time series to write (e.g. run.csv)")
    p.add_argument(
        "--modes", type=mode_list, default=None, metavar="A,B", help="only these modes (default: every one)"
    )
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    p.set_defaults(func=cmd_export)


def _refused_out(out: Path, example: str, force: bool, run: Path) -> str | None:
    """Why `out` may not be written (a directory, anything but a regular file, a file of the run directory
    `run`, an existing file without --force), or None."""
    if out.is_dir():
        return f"{out}: is a directory (give a file name, e.g. {out / example})"
    if not out.exists():
        return None
    if not stat.S_ISREG(out.stat().st_mode):
        return f"{out}: not a regular file (a device, FIFO or socket): export writes only regular files"
    if out.resolve().is_relative_to(run.resolve()):
        return f"{out}: a file of the run directory {run} (its recording): export writes elsewhere"
    if not force:
        return f"{out} exists (pass --force to overwrite it)"
    return None


def cmd_export(args: argparse.Namespace) -> int:
    """Write RUN_DIR's recording to the files asked for and print a short summary of each."""
    from flightstack.recording.files import MISSION_FILE
    from flightstack.recording.run_reader import resolved_mission

    run = Path(args.run_dir)
    if not run.is_dir():
        print(f"error: {run}: no such run directory", file=sys.stderr)
        return 2
    if args.mcap is None and args.csv is None:
        print("error: nothing to write: give --mcap FILE and/or --csv FILE", file=sys.stderr)
        return 2
    for given, example in ((args.mcap, "run.mcap"), (args.csv, "run.csv")):
        why_not = None if given is None else _refused_out(Path(given), example, args.force, run)
        if why_not is not None:
            print(f"error: {why_not}", file=sys.stderr)
            return 2
    mission, why = resolved_mission(run)  # lets a run cut short get its e_c and e_e recomputed
    if why is not None and (run / MISSION_FILE).is_file():
        print(f"note: {run}: {why}; exporting the arrays as recorded", file=sys.stderr)
    if args.csv is not None:
        code = _export_csv(run, Path(args.csv), args.modes, mission)
        if code or args.mcap is None:
            return code
    return _export_mcap(run, Path(args.mcap), args.modes, mission)


def _export_csv(run: Path, out: Path, modes: list[str] | None, mission: Any) -> int:
    from flightstack.recording.csv_table import export_csv, ticks_written
    from flightstack.recording.files import RunDirError

    try:
        recs, skipped = export_csv(run, out, modes, mission)
    except RunDirError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in skipped:
        print(f"skipped: {line}", file=sys.stderr)
    rows = sum(len(ticks_written(r)) * len(r.drone_ids) for r in recs)
    modes_written = ", ".join(r.mode for r in recs)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB): {rows} rows of modes {modes_written}")
    return 0


def _export_mcap(run: Path, out: Path, modes: list[str] | None, mission: Any) -> int:
    from flightstack.recording.files import RunDirError
    from flightstack.recording.mcap_export import ExportError, export_mcap

    try:
        s = export_mcap(run, out, modes, mission)
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
