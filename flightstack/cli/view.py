"""`flightstack view RUN_DIR [--mode M] [--save FILE.rrd | --connect [ADDR] | --spawn]`: a run directory in
the Rerun 3-D viewer (flightstack.viewer; the optional extra `viewer`), and the `--viewer` option of
run/sim/fly/agent (`add_viewer_argument`, `open_live_viewer`)."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightstack.recording.files import LIVE_FILE, REPLAY_FILE

if TYPE_CHECKING:
    from flightstack.config.mission import Mission
    from flightstack.viewer.foxglove_live import FoxgloveTap
    from flightstack.viewer.live import RerunTap


def cmd_view(args: argparse.Namespace) -> int:
    """Rebuild a Rerun recording from a run directory and show it (spawn/connect) or save it; exit 2
    without rerun-sdk (naming the extra), without a recording or with a damaged one (one line naming
    the file)."""
    from flightstack.viewer.rerun_import import ViewerUnavailable, load_rerun

    try:
        rr = load_rerun()
    except ViewerUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from flightstack.recording.files import RunDirError
    from flightstack.viewer import blueprint, layout
    from flightstack.viewer.replay import Replay
    from flightstack.viewer.sinks import AUTO, Sink, close_stream, connect_url, open_stream, resolve

    run = Path(args.run_dir)
    try:
        replay = Replay.load(run, args.mode)
    except (FileNotFoundError, RunDirError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in replay.skipped:
        print(f"skipped: {line}", file=sys.stderr)
    if args.save is not None:
        sink = Sink("save", str(args.save))
    elif args.connect is not None:
        sink = Sink("connect", connect_url(args.connect or None))
    else:
        sink = resolve("spawn" if args.spawn else AUTO, run / REPLAY_FILE)
    t0 = time.perf_counter()
    name = f"{replay.mission.name if replay.mission else 'run'} ({run.name})"
    try:
        stream = open_stream(rr, sink, name, blueprint.build(rr, list(replay.recordings)))
    except OSError as exc:
        print(f"error: {sink.describe()}: {exc}", file=sys.stderr)
        return 1
    try:
        replay.log(rr, stream)
    except BaseException:
        with contextlib.suppress(Exception):
            close_stream(stream)
        raise
    try:
        close_stream(stream)
    except RuntimeError as exc:  # a viewer that went away while we sent
        print(f"error: {sink.describe()}: {exc}", file=sys.stderr)
        return 1
    print(f"run directory: {run}")
    for mode in replay.recordings:
        r = replay.rates(mode)
        print(
            f"  {mode:7s} {r.ticks:7d} ticks: 3-D every {r.pose_stride} ticks ({r.pose_rows} poses per body, "
            f"<= {layout.REPLAY_3D_HZ:g} Hz), scalars every {r.scalar_stride} ({r.scalar_rows} rows), "
            f"{r.events} events"
        )
    print(f"  logged in {time.perf_counter() - t0:.1f} s to {sink.describe()}")
    return 0


def add_viewer_argument(p: argparse.ArgumentParser) -> None:
    """`--viewer [spawn|connect[:ADDR]|save:FILE.rrd]` (run, sim, fly, agent)."""
    from flightstack.viewer.sinks import AUTO, viewer_spec

    p.add_argument(
        "--viewer",
        nargs="?",
        const=AUTO,
        default=None,
        type=viewer_spec,
        metavar="spawn|connect[:ADDR]|save:FILE.rrd|foxglove[:PORT]",
        help="watch the flight live in the Rerun 3-D viewer (needs `pip install 'flightstack[viewer]'`): "
        "spawn a viewer, connect to one (default 127.0.0.1:9876) or save an .rrd; without a value, spawn "
        f"when there is a display, else save RUN_DIR/{LIVE_FILE} (then put --viewer last, or write "
        "--viewer=auto); foxglove[:PORT]: serve it to Foxglove or Lichtblick over WebSocket on 127.0.0.1 "
        "(default port 8765; docs/logs.md)",
    )
    p.add_argument(
        "--viewer-host",
        default=None,
        metavar="ADDR",
        help="with --viewer foxglove: serve the live view on this IP address of the machine instead of "
        "127.0.0.1, for a second screen on the lab's network (or :: / 0.0.0.0 for every address). Anyone "
        "on that network can connect and subscribe, without a password (docs/security.md); the server's "
        "caps on clients, subscriptions and message sizes apply",
    )


def viewer_problem(args: argparse.Namespace) -> str | None:
    """Why `--viewer` (and `--viewer-host`) cannot work here (rerun-sdk missing, with the install hint; a
    host that is not an address of this machine, or without a Foxglove view), checked before anything
    takes off; None when it can (or was not asked for)."""
    from flightstack.viewer.foxglove_live import foxglove_port, host_problem

    spec, host = getattr(args, "viewer", None), getattr(args, "viewer_host", None)
    if host is not None:
        if spec is None or foxglove_port(spec) is None:
            return "--viewer-host: it serves the Foxglove view; add --viewer foxglove[:PORT]"
        problem = host_problem(host)
        return None if problem is None else f"--viewer-host: {problem}"
    if spec is None or spec.startswith("foxglove"):
        return None  # foxglove-sdk is a dependency
    from flightstack.viewer.rerun_import import ViewerUnavailable, load_rerun

    try:
        load_rerun()
    except ViewerUnavailable as exc:
        return f"--viewer: {exc}"
    return None


def open_live_viewer(
    args: argparse.Namespace, mission: Mission, out: Path, modes: list[str]
) -> RerunTap | FoxgloveTap | None:
    """The live tap of `--viewer` (None without it), its recording named after the mission and `out`;
    prints where it goes (and, off loopback, who can see it). The caller passes it to the runner and
    calls `finish()` at the end. OSError when a Foxglove port cannot be served."""
    spec = getattr(args, "viewer", None)
    if spec is None:
        return None
    from flightstack.viewer.foxglove_live import LOOPBACK, FoxgloveTap, foxglove_port, is_loopback

    port = foxglove_port(spec)
    if port is not None:
        host = getattr(args, "viewer_host", None) or LOOPBACK
        try:
            fox = FoxgloveTap(port, host, name=f"{mission.name} ({out.name}, live)", mission=mission)
        except OSError as exc:  # the port is taken, ...
            raise OSError(f"foxglove on {host} port {port}: {exc}") from None
        print(f"viewer: live at {fox.describe()}", file=sys.stderr)
        if not is_loopback(host):
            from flightstack.viewer.foxglove_server import MAX_CLIENTS, MAX_SUBSCRIPTIONS

            print(
                f"warning: viewer: anyone on the networks of {host} can connect to port {fox.port} and "
                f"subscribe to the flight, without a password (at most {MAX_CLIENTS} clients, "
                f"{MAX_SUBSCRIPTIONS} subscriptions each; docs/security.md)",
                file=sys.stderr,
            )
        return fox
    from flightstack.viewer.live import RerunTap
    from flightstack.viewer.sinks import resolve

    sink = resolve(spec, out / LIVE_FILE)
    tap = RerunTap.open(sink, mission, modes, name=f"{mission.name} ({out.name}, live)")
    print(f"viewer: live to {sink.describe()}", file=sys.stderr)
    return tap


def register(sub: Any) -> None:
    v = sub.add_parser(
        "view",
        description="Rebuild a Rerun recording from RUN_DIR (every mode on one `mission_time` timeline, "
        "under /<mode>/) and spawn a viewer, connect to one, or save an .rrd. Without a choice: spawn "
        f"when there is a display, else write RUN_DIR/{REPLAY_FILE}. "
        "Needs `pip install 'flightstack[viewer]'`.",
    )
    v.add_argument("run_dir", help="run directory written by `flightstack run`/`sim`/`fly`/`agent`")
    v.add_argument("--mode", default=None, help="only this mode (default: every recorded mode)")
    where = v.add_mutually_exclusive_group()
    where.add_argument("--save", default=None, metavar="FILE.rrd", help="write the recording to FILE.rrd")
    where.add_argument(
        "--connect",
        nargs="?",
        const="",
        default=None,
        metavar="ADDR",
        help="send it to a running viewer (HOST:PORT or a rerun+http:// URL; default 127.0.0.1:9876)",
    )
    where.add_argument("--spawn", action="store_true", help="start a viewer and send it there")
    v.set_defaults(func=cmd_view)
