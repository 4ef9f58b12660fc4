"""Commands for agents in separate processes over Zenoh: `agent`, `world`, `abort`, `status`.

    flightstack world MISSION                       # simulated missions: serve the world (clock master)
    flightstack agent MISSION --id N --out DIR      # one agent: its drone, camera, pose (sim or hardware)
    flightstack abort MISSION [--timeout S]         # every agent lands at once; exit 1 if one did not ack
    flightstack status MISSION [--once]             # live table of every agent

The mission's `bus: {kind: zenoh, zenoh: {endpoints: ...}}` says where each participant listens.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightstack.config.mission import Mission, MissionError, load_mission
from flightstack.config.types import Mode

if TYPE_CHECKING:
    from flightstack.comms.control import StatusReport


MISSION_HELP = "experiment (with --rig) or mission YAML file; its `bus:` names where the agents listen"


def _zenoh_mission(path: str, rig: str | None = None) -> Mission:
    mission = load_mission(path, rig=rig)
    if mission.bus.kind != "zenoh" or mission.bus.zenoh is None:
        raise MissionError(f"{path}: bus.kind: this command needs the zenoh bus (bus.zenoh.endpoints)")
    return mission


def cmd_world(args: argparse.Namespace) -> int:
    from flightstack.sim_backend.served.server import WorldServer

    mission = _zenoh_mission(args.mission, args.rig)
    server = WorldServer(mission, log=lambda s: print(s, flush=True))
    summary = server.run()
    for e in summary.events:
        print(e)
    landed = ", ".join(f"{i}: {'landed' if ok else 'NOT LANDED'}" for i, ok in summary.landed.items())
    print(
        f"world: {summary.ticks} ticks, {summary.sim_seconds:.2f} s simulated in "
        f"{summary.wall_seconds:.1f} s wall; drones {landed}; dropped {summary.dropped or 'none'}",
        flush=True,
    )
    return 0 if all(summary.landed.values()) else 1


def cmd_agent(args: argparse.Namespace) -> int:
    """`agent MISSION --id N`: fly drone N of a mission over its Zenoh bus (one mode), record it in its
    own run directory; the exit code."""
    from flightstack.cli.run import (
        claim_out_dir,
        clear_for_run,
        default_out_dir,
        fly_or_say,
        live_mcap_problem,
        to_stderr,
    )
    from flightstack.cli.view import open_live_viewer, viewer_problem
    from flightstack.runtime.flight import Flight

    mission = _zenoh_mission(args.mission, args.rig)
    mode = args.mode or mission.compare_modes[-1]
    try:  # the drone, the bus and the mode's experts, before anything is opened
        flight_args: dict[str, Any] = {"modes": [mode], "agent_id": args.id, "say": to_stderr}
        Flight(mission, None, **flight_args)
    except MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    problem = viewer_problem(
        args
    )  # rerun-sdk missing (how to install it), a bad --viewer-host: before flying
    if problem is not None:
        print(f"error: {problem}; nothing took off", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out is not None else default_out_dir(f"{mission.name}-agent{args.id}")
    problem = claim_out_dir(out, args.force)  # before anything takes off: empty (or --force), 50 MB free
    if problem is not None:
        print(f"error: --out {out}: {problem}; nothing took off", file=sys.stderr)
        return 2
    if args.out is None:
        print(f"agent {args.id}: run directory {out} (--out DIR chooses another)", file=sys.stderr)
    try:  # --viewer: this agent's drone live in Rerun (flightstack.viewer.live)
        tap = open_live_viewer(args, mission, out, [mode])
    except (OSError, RuntimeError) as exc:
        print(f"error: --viewer: {exc}; nothing took off", file=sys.stderr)
        return 2
    try:
        clear_for_run(out, args.force)
        taps = [tap] if tap is not None else []
        flight = Flight(mission, out, taps=taps, live_mcap=args.live_mcap, **flight_args)
        res = fly_or_say(flight)
    finally:
        if tap is not None:
            tap.finish()
    if res is None:
        return 2
    rec = res.recordings.get(mode)
    for line in flight.session_reports():
        print(f"agent {args.id}: {line}", file=sys.stderr)
    ticks = 0 if rec is None else rec.ticks_done
    print(f"agent {args.id}: {ticks} ticks of mode {mode}; recording in {out}", flush=True)
    status = res.metrics.get("recording", {"complete": False, "reason": "metrics.json not written"})
    if not status["complete"]:
        print(f"agent {args.id}: recording incomplete: {status['reason']}", file=sys.stderr)
    mcap_problem = live_mcap_problem(flight, out)
    if mcap_problem is not None:
        print(f"agent {args.id}: {mcap_problem}", file=sys.stderr)
    if res.interrupted:
        return 130
    if res.error:
        landed = rec is not None and any(
            e.get("event") == "landed" and e.get("drone") == args.id for e in rec.events
        )
        what = "its drone landed" if landed else "landing requested, not confirmed (no telemetry)"
        print(f"agent {args.id}: {res.error}; {what}", file=sys.stderr)
        return 1
    return 0 if status["complete"] and mcap_problem is None else 1


def cmd_abort(args: argparse.Namespace) -> int:
    """Publish the abort at once (Zenoh and/or the loopback listener of an in-process `fly`), then wait
    `--timeout` s for every agent's acknowledgement (flightstack/comms/abort.py). Prints each
    acknowledging process with its drones and time to ack (ms); exit 0 only if every drone of the
    mission acknowledged, else 1 naming the others."""
    from flightstack.comms.abort import send_abort

    mission = load_mission(args.mission, rig=args.rig)
    if not (args.timeout >= 0 and math.isfinite(args.timeout)):
        print(f"error: --timeout {args.timeout}: must be a finite number of seconds >= 0", file=sys.stderr)
        return 2
    rep = send_abort(mission, args.reason, args.timeout)
    print(f"abort {rep.abort_id[:8]} sent to mission {mission.name} via {' and '.join(rep.channels)}")
    for ack, ms in rep.processes():
        who = f"pid {ack.pid} on {ack.host}, {ack.via}"
        print(f"  acknowledged by drones {list(ack.drones)} in {ms:.1f} ms ({who})")
    if rep.present is not None:
        absent = sorted(set(rep.expected) - set(rep.present))
        print(f"abort sent to mission {mission.name}: agents present {rep.present}, absent {absent}")
    if rep.missing:
        print(
            f"error: agents {rep.missing} did not acknowledge the abort within {args.timeout:g} s "
            "(not running, not reachable, or not listening): land them by other means",
            file=sys.stderr,
        )
        return 1
    slowest = max(rep.latency_ms(i) for i in rep.expected)
    print(f"every agent acknowledged: drones {rep.expected}, slowest {slowest:.1f} ms")
    return 0


def status_table(
    statuses: dict[int, tuple[StatusReport, float]],
    alive: set[int],
    ids: list[int],
    now: float,
    msg_age: dict[int, float | None] | None = None,
) -> str:
    """One row per agent. `statuses`: drone → (its last validated status, time.monotonic() at receipt, s);
    `age s`: since its last status report; `msg s`: since its last prediction message (wall seconds, as
    received here). Every value of a StatusReport is typed and bounded (flightstack/comms/control.py), so
    no status can break the table."""
    msg_age = msg_age or {}

    def age(i: int) -> str:
        a = msg_age.get(i)
        return f"{a:6.2f}" if a is not None else f"{'-':>6}"

    head = f"{'drone':>5}  {'alive':5}  {'age s':>6}  {'msg s':>6}  {'mode':6}  {'t s':>8}  "
    head += f"{'batt %':>6}  {'flying':6}  {'seen':5}  {'fused':>5}  {'pose':5}  problems"
    lines = [head]
    for i in ids:
        if i not in statuses:
            lines.append(f"{i:>5}  {'yes' if i in alive else 'no':5}  {'-':>6}  {age(i)}  (no status yet)")
            continue
        s, received = statuses[i]
        problems = [s.rejection] if s.rejection else []
        if not s.link_alive:
            problems.append("link lost")
        if s.dropped:
            problems.append("dropped " + ", ".join(f"{k}: {v}" for k, v in s.dropped))
        if s.restarts:  # each a message its bus took by the restart rule (comms/acceptance.py)
            problems.append("restarts " + ", ".join(f"{k}: {v}" for k, v in s.restarts))
        lines.append(
            f"{i:>5}  {'yes' if i in alive else 'no':5}  {now - received:6.1f}  {age(i)}  {s.mode:6}  "
            f"{s.t:8.2f}  {s.battery_pct:6.0f}  {'yes' if s.flying else 'no':6}  "
            f"{'yes' if s.visible else 'no':5}  {s.n_fused:5d}  {'ok' if s.pose_fresh else 'LOST':5}  "
            f"{'; '.join(problems)}"
        )
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    """Print the table of every agent's last status (live, or `--once`). Statuses come validated from the
    bus (malformed ones are dropped and counted there); only drones of the mission are shown."""
    from flightstack.comms.control import status_report
    from flightstack.comms.factory import make_bus

    mission = _zenoh_mission(args.mission, args.rig)
    ids = [d.id for d in mission.drones]
    bus = make_bus(mission, "operator", set())
    statuses: dict[int, tuple[StatusReport, float]] = {}
    live = sys.stdout.isatty() and not args.once
    t_end = time.monotonic() + (args.wait if args.once else args.duration)
    try:
        while True:
            for ev in bus.control_events():
                report = status_report(ev)
                if report is not None and report.drone in ids:
                    statuses[report.drone] = (report, ev.time)
            now = time.monotonic()
            # --once: every agent's status, a prediction (a live sender is heard after a short run of
            # consecutive messages: acceptance.py's first-seq rule) and its liveliness token (answered by
            # a query of its own, which may come after both), or the wait is over
            alive = bus.alive()  # type: ignore[attr-defined]
            heard = all(
                i in statuses and bus.message_age(i) is not None and i in alive  # type: ignore[attr-defined]
                for i in ids
            )
            done = now >= t_end or (args.once and heard)
            if done or not args.once:
                ages = {i: bus.message_age(i) for i in ids}  # type: ignore[attr-defined]
                table = status_table(statuses, bus.alive(), ids, now, ages)  # type: ignore[attr-defined]
                table += "".join(f"\nWARNING {r}" for r in bus.session_reports)  # type: ignore[attr-defined]
                print(("\x1b[2J\x1b[H" if live else "") + table, flush=True)
            if done:
                break
            time.sleep(0.2 if args.once else 1.0)
    except KeyboardInterrupt:
        pass
    finally:
        bus.close()
    return 0 if statuses else 1


def cmd_guard(args: argparse.Namespace) -> int:
    """Watch every agent's presence; land the Tello of an agent that vanishes in flight from this
    computer (drivers/lab/guard.py). Station topology only: exit 2 naming the topology otherwise. One line
    per event on stdout; ends after `--duration` s (a landing in progress is completed first) or at
    Ctrl-C; exit 0."""
    from flightstack.comms.factory import make_bus
    from flightstack.drivers.guardian.process import Log
    from flightstack.drivers.lab.guard import Guard, guard_refusal

    mission = load_mission(args.mission, rig=args.rig)
    why = guard_refusal(mission)
    if why is not None:
        print(f"error: {why}", file=sys.stderr)
        return 2
    for name in ("duration", "land_resend", "give_up", "status_fresh"):
        v = getattr(args, name)
        if v is not None and not (v > 0 and (math.isfinite(v) or name == "duration")):
            print(f"error: --{name.replace('_', '-')} {v}: must be a number of seconds > 0", file=sys.stderr)
            return 2
    log = Log(None, name="guard", stream=sys.stdout)
    bus = make_bus(mission, "guard", set())
    guard: Any = None
    try:
        guard = Guard(
            mission,
            bus,
            log,
            status_fresh_s=args.status_fresh,
            land_resend_s=args.land_resend,
            give_up_s=args.give_up,
        )
        guard.start_line()
        summary = guard.run(args.duration)
    except KeyboardInterrupt:
        if guard is not None:
            guard.interrupted()
            summary = guard.summary
    finally:
        if guard is not None:
            guard.close()
        bus.close()
    if guard is not None:
        done = ", ".join(f"drone {t.drone}: {t.result}" for t in summary.takeovers) or "none"
        log(f"guard ends: takeovers {done}; departures not in flight {len(summary.ignored)}")
    log.close()
    return 0


def register(sub: Any) -> None:
    w = sub.add_parser("world")
    w.add_argument("mission", help=MISSION_HELP)
    w.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    w.set_defaults(func=cmd_world)
    a = sub.add_parser("agent")
    a.add_argument("mission", help=MISSION_HELP)
    a.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    a.add_argument("--id", type=int, required=True, help="the drone id this process flies")
    agent_modes = [m.value for m in Mode if m is not Mode.ORACLE]
    a.add_argument("--mode", choices=agent_modes, help="default: the last of compare_modes")
    a.add_argument(
        "--out",
        default=None,
        help="directory for this agent's recording (must be empty unless --force; default: "
        "runs/<experiment name>-agent<ID>-<YYYYmmdd-HHMMSS>)",
    )
    a.add_argument(
        "--force",
        action="store_true",
        help="reuse a non-empty --out: first remove the files a run writes there; every other file is kept",
    )
    from flightstack.cli.run import add_live_mcap_argument
    from flightstack.cli.view import add_viewer_argument

    add_live_mcap_argument(a)
    add_viewer_argument(a)
    a.set_defaults(func=cmd_agent)
    ab = sub.add_parser(
        "abort",
        description="Publish an abort to every agent of the mission at once (over Zenoh, and to the loopback "
        "listener of an in-process `fly`), then wait --timeout s for their acknowledgements: each agent "
        "lands its drones. Prints who acknowledged and how fast; exit 0 only if every drone of the mission "
        "acknowledged, else 1 naming the others: land them by other means (docs/bus.md).",
    )
    ab.add_argument("mission", help=MISSION_HELP)
    ab.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    ab.add_argument(
        "--reason",
        default="operator abort",
        help="why, sent with the abort (at most 1024 characters): each agent's run ends with the error "
        "`operator abort: REASON`",
    )
    ab.add_argument(
        "--timeout",
        "--wait",
        dest="timeout",
        type=float,
        default=2.0,
        help="how long to wait for every agent's acknowledgement after sending (s)",
    )
    ab.set_defaults(func=cmd_abort)
    st = sub.add_parser("status")
    st.add_argument("mission", help=MISSION_HELP)
    st.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    st.add_argument("--once", action="store_true", help="print one table when every agent reported, exit")
    st.add_argument("--wait", type=float, default=3.0, help="with --once: longest wait for reports (s)")
    st.add_argument(
        "--duration", type=float, default=math.inf, help="stop after this long (s; default: until Ctrl-C)"
    )
    st.set_defaults(func=cmd_status)
    gd = sub.add_parser(
        "guard",
        description="Follow every agent's liveliness token and status on the bus; when an agent vanishes "
        "while its drone flies, land that Tello from this computer (rc 0 0 0 0 and land, re-sent every "
        "--land-resend s until its telemetry shows it down, for at most --give-up s). Silence alone is "
        "reported, never acted on. Station topology only (exit 2 otherwise); one line per event on stdout; "
        "Ctrl-C or --duration ends it with exit 0 (docs/bus.md#guard).",
    )
    gd.add_argument("mission", help=MISSION_HELP)
    gd.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    gd.add_argument(
        "--duration",
        type=float,
        default=math.inf,
        help="stop watching after this long (s; default: until Ctrl-C)",
    )
    gd.add_argument(
        "--status-fresh",
        type=float,
        default=None,
        help="in flight = last status flying and at most this old when the token vanishes "
        "(s; default max(2, lease + 1))",
    )
    gd.add_argument("--land-resend", type=float, default=1.0, help="re-send rc 0 0 0 0 + land this often (s)")
    gd.add_argument(
        "--give-up",
        type=float,
        default=20.0,
        help="stop re-sending after this long without seeing it down (s)",
    )
    gd.set_defaults(func=cmd_guard)
