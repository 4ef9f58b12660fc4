# PYTHON_ARGCOMPLETE_OK
"""Operator command line (`flightstack -h`): sim, fly, report, preflight, target, world, agent, abort, ..."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import argcomplete

from flightstack.cli.run import (
    _confirm,
    add_run_arguments,
    cmd_run,
    seconds,
)
from flightstack.config.mission import MissionError, load_mission
from flightstack.config.rig import RigError


def cmd_report(args: argparse.Namespace) -> int:
    """Rebuild metrics.json and the plots of a run directory from its recording (also one cut short by
    a kill, a crash or a full disk: then from the row streams); exit 2 with one line `error: <file>:
    <what>` when a file it needs is missing or damaged (recording.files.REQUIRED_FILES); a damaged
    optional file is skipped with a line `warning: skipped: <file>: <what>` on stderr. Prints the same
    metric lines as `run` (flightstack.cli.summary.metric_lines)."""
    from flightstack.analysis.report import rebuild_run, run_mission
    from flightstack.cli.summary import metric_lines, say
    from flightstack.recording.files import RunDirError

    run = Path(args.run_dir)
    mission = load_mission(args.mission) if args.mission else None
    try:
        m, plots, skipped = rebuild_run(run, mission, plots=not args.no_plots)
        mission = mission or run_mission(run)
    except RunDirError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in skipped:
        say("warning", f"skipped: {line}")
    print(f"run directory: {run}")
    for line in metric_lines(m, mission):
        print(line)
    print(f"  rebuilt metrics.json{''.join(f', {p.name}' for p in plots)}")
    return 0


def cmd_preflight(args: argparse.Namespace) -> int:
    """Check every device and file of a hardware mission; exit 1 on any FAIL (drivers/preflight.py)."""
    from flightstack.drivers.preflight import format_table, run_preflight

    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    if mission.simulated:
        print(f"error: {args.mission}: backend {mission.backend!r} has no hardware to check", file=sys.stderr)
        return 2
    try:
        rows = run_preflight(mission, args.deadline, not args.no_camera, drone_ids=args.id or None)
    except ValueError as exc:
        print(f"error: {args.mission}: {exc}", file=sys.stderr)
        return 2
    print(format_table(rows))
    return 1 if any(r.status == "FAIL" for r in rows) else 0


def cmd_target(args: argparse.Namespace) -> int:
    """Drive the real robot on the mission's square law from its motion-capture pose (drivers/target_run)."""
    from flightstack.drivers.guardian import Guardian, GuardianConfig
    from flightstack.drivers.hardware import body_names, mocap_config, scamper_config
    from flightstack.drivers.mocap import MocapPoseSource
    from flightstack.drivers.scamper import ScamperDriver
    from flightstack.drivers.target_run import drive_square, lap_summary
    from flightstack.paper.target_law import SquareLaw

    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    if mission.hardware is None or mission.hardware.target is None:
        print(f"error: {args.mission}: hardware.target: no robot to drive (set its url)", file=sys.stderr)
        return 2
    sq = mission.target.square
    law = SquareLaw(sq.side_m, sq.speed_mps, sq.gain, mission.target.initial_pose.theta)
    duration = args.duration if args.duration is not None else args.laps * law.lap_time
    if not _confirm(
        f"The robot will drive {duration:.0f} s on the {sq.side_m:g} m square. Area clear?", args.yes
    ):
        print("aborted", file=sys.stderr)
        return 1
    sc = scamper_config(mission)
    assert sc is not None
    mocap = MocapPoseSource(mocap_config(mission))
    robot = ScamperDriver(sc)
    body = body_names(mission)["target"]
    # if this process dies or stalls, the guardian stops and disarms the robot (drivers/guardian.py)
    guardian = Guardian.start(GuardianConfig.for_devices([], sc.url))
    robot.set_muted(guardian.taken_over)
    armed = [False]

    def beat(now: float, res: object) -> None:
        if not armed[0]:
            guardian.arm()
            armed[0] = True
        guardian.heartbeat()

    try:
        mocap.start()
        if mocap_wait(mocap, body, 2.0) is None:
            print(f"error: motion capture does not see the robot (body {body!r})", file=sys.stderr)
            return 1
        robot.connect()
        print(f"driving {duration:.1f} s ({duration / law.lap_time:.2f} laps); Ctrl-C stops the robot")
        res = drive_square(
            robot,
            mocap,
            law,
            duration,
            body=body,
            link_alive=robot.link_alive,
            robot_ready=lambda: (
                robot.robot_state().ready and not guardian.taken_over() and guardian.lost() is None
            ),
            on_tick=beat,
        )
        print(lap_summary(res, law))
        if (lost := guardian.lost()) is not None:
            print(f"error: {lost}: the robot was stopped (never driven without it)", file=sys.stderr)
        return 0 if res.ended_by == "duration" else 1
    finally:
        guardian.arm(False)
        robot.close()
        mocap.close()
        guardian.finish()


def mocap_wait(mocap: object, body: str, timeout_s: float) -> object | None:
    """The body's first pose within timeout_s (s), or None."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        sp = mocap.latest(body)  # type: ignore[attr-defined]
        if sp is not None:
            return sp
        time.sleep(0.02)
    return None


def cmd_train(args: argparse.Namespace) -> int:
    from flightstack.learning.training import collect_datasets, save_experts, train_experts
    from flightstack.recording.timeseries import Recording

    run = Path(args.run_dir)
    mission = load_mission(args.mission or run / "mission_resolved.yaml")
    src = run / f"timeseries_{args.from_mode}.npz"
    if not src.is_file():
        print(f"error: {src}: no recording of mode {args.from_mode!r} in {run}", file=sys.stderr)
        return 2
    try:
        rec = Recording.load(str(src))
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
    from flightstack.drivers.guardian import Guardian, GuardianConfig
    from flightstack.drivers.identify import fits_to_rc_gains, identify, save_identification
    from flightstack.drivers.tello import TelloConfig, TelloDriver

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
    cfg = TelloConfig(host=args.ip, control_port=args.port, connect_timeout_s=args.timeout)
    driver = TelloDriver(cfg)
    # if this process dies, its guardian hovers and lands the drone (the stall check stays unarmed: the
    # identification loop does not beat it; the driver's loop watchdog covers a stalled loop)
    guardian = Guardian.start(GuardianConfig.for_devices([cfg]))
    driver.set_muted(guardian.taken_over)
    try:
        driver.connect()
        if (lost := guardian.lost()) is not None:
            print(f"error: {lost}: not taking off without it", file=sys.stderr)
            return 1
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
        guardian.finish()


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or "unknown" when flightstack runs from a
    checkout that was never installed (no distribution metadata)."""
    try:
        return version("flightstack")
    except PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flightstack", description=__doc__)
    p.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="fly an experiment on a rig (ideal, lab-sim, emulated-lab, a lab file)")
    add_run_arguments(r, "experiment: a built-in name (paper_sim, paper_experiment) or a YAML file")
    r.add_argument("--yes", action="store_true", help="confirm that real drones may take off")
    r.set_defaults(func=cmd_run)
    s = sub.add_parser("sim", help="run an experiment on a simulated rig (refuses real drones)")
    add_run_arguments(s, "experiment or mission YAML file (see mission_configs/)")
    s.set_defaults(func=cmd_run)
    f = sub.add_parser("fly", help="fly an experiment on real hardware: preflight, confirm, fly")
    add_run_arguments(f, "experiment (with --rig LAB.yaml) or mission YAML file")
    f.add_argument("--yes", action="store_true", help="confirm that the drones may take off")
    f.set_defaults(func=cmd_run)
    pf = sub.add_parser("preflight", help="check every device of a hardware mission (pass/fail table)")
    pf.add_argument("mission")
    pf.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    pf.add_argument("--deadline", type=float, default=9.0, help="bound on the whole check (s)")
    pf.add_argument("--no-camera", action="store_true", help="skip the video check")
    pf.add_argument(
        "--id", type=int, action="append", help="check only this drone (repeatable; access-point mode)"
    )
    pf.set_defaults(func=cmd_preflight)
    tg = sub.add_parser("target", help="drive the real ground robot on the square law (motion capture)")
    tg.add_argument("mission", help="mission YAML file with hardware.mocap and hardware.target")
    tg.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    tg.add_argument("--laps", type=float, default=1.0, help="laps of the square (default 1)")
    tg.add_argument("--duration", type=seconds, default=None, help="seconds instead of laps")
    tg.add_argument("--yes", action="store_true", help="confirm that the robot may move")
    tg.set_defaults(func=cmd_target)
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
    cd.add_argument("--duration", type=seconds, default=2.0, help="seconds per step")
    cd.add_argument("--timeout", type=float, default=5.0, help="connect timeout (s)")
    cd.add_argument("--out", required=True, help="YAML file to write")
    cd.add_argument("--yes", action="store_true", help="confirm that the drone may take off")
    cd.set_defaults(func=cmd_calibrate_drone)
    from flightstack.calibration.cli import register as register_calibration

    register_calibration(cal_sub)
    from flightstack.cli.certs import register as register_certs
    from flightstack.cli.export import register as register_export
    from flightstack.cli.generate import register as register_generate
    from flightstack.cli.network import register as register_network
    from flightstack.cli.sweep import register as register_sweep
    from flightstack.cli.view import register as register_view
    from flightstack.faults.cli import register as register_faults

    register_network(sub)
    register_faults(sub)
    register_certs(sub)
    register_sweep(sub)
    register_generate(sub)
    register_export(sub)
    register_view(sub)
    rp = sub.add_parser(
        "report", help="rebuild metrics.json and the plots of a run directory (also one cut short by a kill)"
    )
    rp.add_argument("run_dir", help="run directory written by `flightstack sim`/`fly`/`agent`")
    rp.add_argument("--mission", default=None, help="mission file (default: RUN_DIR/mission_resolved.yaml)")
    rp.add_argument("--no-plots", action="store_true", help="metrics.json only")
    rp.set_defaults(func=cmd_report)
    from flightstack.cli.validate import register as register_validate

    register_validate(sub)
    from flightstack.cli.completion import register as register_completion

    register_completion(sub)
    from flightstack.cli.bench_loop import register as register_bench_loop

    register_bench_loop(sub)
    return p


def _sigterm_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Entry point. SIGTERM is handled like Ctrl-C: drones land, the recording is written, exit 130."""
    parser = build_parser()
    # a tab-completion request (the shell code of `flightstack completion`) is answered here, then exits
    argcomplete.autocomplete(parser)
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    # Ctrl-C must stop a run even when whoever started us ignored SIGINT (a background job of a script,
    # some launchers): Python then keeps SIG_IGN and `kill -INT` would do nothing
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return int(args.func(args))
    except (MissionError, RigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a device that cannot be reached, a file that cannot be written, ...
        if os.environ.get("FLIGHTSTACK_DEBUG"):
            raise
        hint = "FLIGHTSTACK_DEBUG=1 shows the traceback"
        print(f"error: {type(exc).__name__}: {exc} ({hint})", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
