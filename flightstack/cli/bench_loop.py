"""`flightstack bench-loop [EXPERIMENT] [--rig emulated-lab] [--seconds S] [--network PROFILE]`: does
this computer keep the mission's control period while decoding every drone's video? (loop health)

It flies the experiment's `none` mode for S seconds on the emulated lab: one Tello emulator per drone
streaming H.264 video on loopback, the NatNet motion-capture emulator, the MAVLink rover, the real
drivers, decoders, marker extraction and safety layer, on the wall clock. That is the flight's own
loop, so its loop health (flightstack.analysis.loop_health) is the answer. The emulators encode the
video on this computer too, which real Tellos do on board: the benchmark is pessimistic by that load.

With --network PROFILE every emulated device's packets pass a seeded lossy-network model (docs/links.md):
the same question on a Wi-Fi that loses, delays, reorders and blacks out.

Exit 0 when the loop kept dt (at most 1 % of the ticks overran and the p99 compute time < dt), 1 when
it did not or the run failed, 2 for bad arguments. Real drones are never flown: any rig whose devices
are not the emulated lab's is refused."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flightstack.analysis.loop_health import loop_health_line
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import RigError

DEFAULT_EXPERIMENT = "paper_experiment"


def cmd_bench_loop(args: argparse.Namespace) -> int:
    """Fly `none` on the emulated lab for args.seconds and judge its loop health (module docstring)."""
    try:
        overrides: dict[str, object] = {"compare_modes": ["none"], "duration_s": args.seconds}
        if args.network is not None:
            overrides["links.network"] = args.network
        mission = load_mission(args.experiment, overrides, rig=args.rig)
    except (MissionError, RigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not mission.start_emulators:
        print(
            f"error: bench-loop runs on the emulated lab only (rig {args.rig!r} is "
            f"{'simulated' if mission.simulated else 'real hardware'}); it never flies real drones "
            "and a simulated clock does not measure the wall-clock loop",
            file=sys.stderr,
        )
        return 2
    from flightstack.cli.run import claim_out_dir, clear_for_run, default_out_dir, fly_or_say, to_stderr
    from flightstack.runtime.flight import Flight

    out = Path(args.out) if args.out else default_out_dir(mission.name)
    problem = claim_out_dir(out, force=bool(args.out))  # a directory named on purpose is reused
    if problem is not None:
        print(f"error: --out {out}: {problem}; nothing took off", file=sys.stderr)
        return 2
    clear_for_run(out, force=bool(args.out))
    res = fly_or_say(Flight(mission, out, modes=["none"], plots=True, say=to_stderr))
    if res is None:
        return 2
    health = (res.metrics.get("modes", {}).get("none") or {}).get("loop_health")
    if not health:
        print(f"bench-loop: no loop health recorded ({res.error or 'no tick flown'}); run directory {out}")
        return 1
    n = len(mission.drones)
    verdict = "KEEPS" if health["keeps_dt"] else "DOES NOT keep"
    print(
        f"bench-loop: this computer {verdict} dt = {1e3 * mission.dt_s:.0f} ms with {n} drones' video "
        f"(network {mission.links.network})"
    )
    print(f"  {loop_health_line(health)}")
    print(f"  plot: {out / 'loop_health.png'}")
    complete = res.metrics.get("recording", {}).get("complete", False)
    return 0 if complete and not res.error and not res.interrupted and health["keeps_dt"] else 1


def register(sub: argparse._SubParsersAction) -> None:
    """Add `bench-loop` to the top-level subcommands."""
    from flightstack.cli.run import add_network_argument, seconds

    b = sub.add_parser(
        "bench-loop",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    b.add_argument(
        "experiment", nargs="?", default=DEFAULT_EXPERIMENT, help=f"experiment (default {DEFAULT_EXPERIMENT})"
    )
    b.add_argument("--rig", default="emulated-lab", help="an emulated-lab rig (default emulated-lab)")
    b.add_argument("--seconds", type=seconds, default=10.0, help="pursuit seconds to measure (default 10)")
    b.add_argument("--out", default=None, help="run directory (default runs/<experiment>-<stamp>)")
    add_network_argument(b)
    b.set_defaults(func=cmd_bench_loop)
