"""Operator command line: `flightstack sim MISSION --out RUN_DIR` (more subcommands in later issues)."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from collections.abc import Callable
from pathlib import Path

from tqdm import tqdm

from flightstack.mission import MissionError, load_mission


def _progress_factory(bars: list[tqdm]) -> Callable[[str, int], Callable[[int], None]]:
    def make(mode: str, total: int) -> Callable[[int], None]:
        bar = tqdm(
            total=total,
            desc=f"mode {mode:6s}",
            unit="tick",
            unit_scale=True,
            file=sys.stderr,
            mininterval=0.5,
            leave=True,
        )
        bars.append(bar)
        pending = [0]

        def update(n: int) -> None:
            pending[0] += n  # tqdm per tick would cost more than a control tick: batch 500
            if pending[0] >= 500 or bar.n + pending[0] >= total:
                bar.update(pending[0])
                pending[0] = 0

        return update

    return make


def cmd_sim(args: argparse.Namespace) -> int:
    from flightstack.experiment import run_experiment, write_run_dir
    from flightstack.report import write_plots

    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")  # safety events, live
    overrides = {"duration_s": args.duration} if args.duration else None
    mission = load_mission(args.mission, overrides)
    out = Path(args.out)
    bars: list[tqdm] = []
    res = run_experiment(mission, None if args.no_progress else _progress_factory(bars))
    for b in bars:
        b.close()
    write_run_dir(out, mission, res)
    if res.recordings:
        write_plots(out, mission, res.recordings, res.datasets)
    m = res.metrics
    print(f"run directory: {out}")
    for mode, mm in m["modes"].items():
        line = f"  {mode:7s} mean_sq_error = {mm.get('mean_sq_error', float('nan')):.3e}"
        if "mean_position_error_m" in mm:
            seen = ", ".join(f"{i}: {100 * f:.0f} %" for i, f in mm["visible_fraction"].items())
            line += f"   mean position error {mm['mean_position_error_m']:.3f} m   target seen {seen}"
        if mm.get("max_fence_excursion_m"):
            line += f"   OUTSIDE FENCE by {mm['max_fence_excursion_m']:.3f} m"
        print(line)
    if "ratios" in m:
        ours, paper = m["ratios"]["ours"], m["ratios"]["paper"]
        for key in ours:
            print(f"  {key:10s} ours {ours[key]:8.2f}   paper {paper[key]:8.2f}")
    gc = m["gain_condition"]
    verdict = "satisfied" if gc["satisfied"] else "NOT satisfied"
    print(
        f"  gain condition: kappa = {gc['kappa']:.3f} ({verdict}), L_mu = {gc['L_mu']:.3f}, "
        f"lambda_H = {gc['lambda_H']:.3f}"
    )
    print(f"  safety events: {len(m['safety_events'])} (events.jsonl)")
    print(f"  sim {m['sim_seconds']:.1f} s in {m['wall_seconds']:.1f} s wall")
    if res.interrupted:
        print("interrupted: every drone landed, partial recording written", file=sys.stderr)
        return 130
    if res.error:
        print(f"error: {res.error}; every drone landed, partial recording written", file=sys.stderr)
        return 1
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from flightstack.recording import Recording
    from flightstack.training import collect_datasets, save_experts, train_experts

    run = Path(args.run_dir)
    mission = load_mission(args.mission or run / "mission_resolved.yaml")
    src = run / f"timeseries_{args.from_mode}.npz"
    if not src.is_file():
        print(f"error: {src}: no recording of mode {args.from_mode!r} in {run}", file=sys.stderr)
        return 2
    rec = Recording.load(str(src))
    try:
        data = collect_datasets(mission, rec, mission.seed)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    experts = train_experts(mission, data, mission.seed)
    save_experts(args.out, experts)
    for d in data:
        ex = experts[d.drone_id]
        print(
            f"drone {d.drone_id}: {len(d.X)} samples in band {d.band}, "
            f"log marginal likelihood {ex.log_marginal_likelihood().round(2).tolist()}"
        )
    print(f"experts written to {args.out}; reference it as gp.experts_file in a mission")
    return 0


def cmd_calibrate_drone(args: argparse.Namespace) -> int:
    """Fly rc steps on one Tello and fit rc-unit → m/s gains and time constants (drivers/identify.py)."""
    from drivers.identify import fits_to_rc_gains, identify, save_identification
    from drivers.tello import TelloConfig, TelloDriver

    if not args.yes:
        if not sys.stdin.isatty():
            print("error: this takes off and flies the drone; pass --yes to confirm", file=sys.stderr)
            return 2
        answer = input(f"Drone {args.ip} will take off and fly short steps (~1 m). Clear area? [y/N] ")
        if answer.strip().lower() not in ("y", "yes"):
            print("aborted", file=sys.stderr)
            return 1
    print(
        "note: velocities are differenced from the state stream's x/y/z, which a real Tello reports only "
        "over mission pads (enable them, or use motion capture once that backend exists)",
        file=sys.stderr,
    )
    driver = TelloDriver(TelloConfig(host=args.ip, control_port=args.port, connect_timeout_s=args.timeout))
    try:
        driver.connect()
        failed = [c for c in driver.preflight() if not c.ok]
        if failed:
            for c in failed:
                print(f"preflight failed: {c.name}: {c.detail}", file=sys.stderr)
            return 1
        driver.takeoff()
        try:
            fits = identify(driver, rc_amplitude=args.amplitude, duration_s=args.duration)
        finally:
            driver.land()
        save_identification(args.out, fits, args.ip)
        gains = fits_to_rc_gains(fits)
        for axis, f in fits.items():
            print(f"{axis:4s} gain {f.gain:.5f} per rc unit   tau {f.tau_s:.3f} s   delay {f.delay_s:.3f} s")
        print(f"rc_gains for the mission: xy {gains.xy:.5f}, z {gains.z:.5f}, yaw {gains.yaw:.5f}")
        print(f"written to {args.out}")
        return 0
    finally:
        driver.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flightstack", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("sim", help="run a mission on the simulated backend")
    s.add_argument("mission", help="mission YAML file (see mission_configs/)")
    s.add_argument("--out", required=True, help="run directory to write (created if missing)")
    s.add_argument("--duration", type=float, default=None, help="override duration_s (seconds)")
    s.add_argument("--no-progress", action="store_true", help="no progress bars")
    s.set_defaults(func=cmd_sim)
    t = sub.add_parser("train", help="fit GP experts on a recorded run (data collection without GP)")
    t.add_argument("run_dir", help="run directory written by `flightstack sim`")
    t.add_argument("--out", required=True, help="experts file to write (.npz)")
    t.add_argument("--mission", default=None, help="mission file (default: RUN_DIR/mission_resolved.yaml)")
    t.add_argument("--from-mode", default="none", help="which recorded mode to learn from (default: none)")
    t.set_defaults(func=cmd_train)
    cal = sub.add_parser("calibrate", help="calibration tools")
    cal_sub = cal.add_subparsers(dest="what", required=True)
    cd = cal_sub.add_parser("drone", help="identify a Tello's rc-unit -> velocity gains and time constants")
    cd.add_argument("--ip", required=True, help="the drone's IP address (station mode)")
    cd.add_argument("--port", type=int, default=8889, help="its command port (8889 on a real Tello)")
    cd.add_argument("--amplitude", type=int, default=40, help="rc step amplitude (units of -100..100)")
    cd.add_argument("--duration", type=float, default=2.0, help="seconds per step")
    cd.add_argument("--timeout", type=float, default=5.0, help="connect timeout (s)")
    cd.add_argument("--out", required=True, help="YAML file to write")
    cd.add_argument("--yes", action="store_true", help="confirm that the drone may take off")
    cd.set_defaults(func=cmd_calibrate_drone)
    v = sub.add_parser("validate", help="check a mission file and print the resolved mission")
    v.add_argument("mission")
    v.set_defaults(func=cmd_validate)
    return p


def cmd_validate(args: argparse.Namespace) -> int:
    from flightstack.mission import mission_to_dict

    m = load_mission(args.mission)
    print(json.dumps(mission_to_dict(m), indent=2))
    return 0


def _sigterm_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Entry point. SIGTERM is handled like Ctrl-C: drones land, the recording is written, exit 130."""
    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        return int(args.func(args))
    except MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
