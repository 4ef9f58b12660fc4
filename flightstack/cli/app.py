# PYTHON_ARGCOMPLETE_OK
"""Operator command line (`flightstack -h`): the commands grouped by what an operator does (COMMANDS).

Only the command being run (or completed) is built with its options, and only its modules are imported:
`flightstack --help` and a completion of a command's name import none of numpy, numba, scipy, matplotlib,
cv2 or zenoh (tests/test_cli_help.py). `build_parser()` without arguments builds every command."""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import argcomplete

from flightstack import threads


def cmd_report(args: argparse.Namespace) -> int:
    """Rebuild metrics.json and the plots of a run directory from its recording (also one cut short by
    a kill, a crash or a full disk: then from the row streams), and finalise a live MCAP its writer left
    torn (`finalise_live_mcap`); exit 2 with one line `error: <file>: <what>` when a file it needs is
    missing or damaged (recording.files.REQUIRED_FILES); a damaged optional file is skipped with a line
    `warning: skipped: <file>: <what>` on stderr. Prints the same metric lines as `run`
    (flightstack.cli.summary.metric_lines)."""
    from flightstack.analysis.report import rebuild_run, run_mission
    from flightstack.cli.summary import metric_lines, say
    from flightstack.config.mission import load_mission
    from flightstack.recording.files import RunDirError

    run = Path(args.run_dir)
    mission = load_mission(args.mission) if args.mission else None
    try:
        m, plots, skipped = rebuild_run(run, mission, plots=not args.no_plots)
        mission = mission or run_mission(run)
    except RunDirError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finalised, problem = finalise_live_mcap(run)
    for line in [*skipped, *([problem] if problem else [])]:
        say("warning", f"skipped: {line}")
    print(f"run directory: {run}")
    for line in metric_lines(m, mission):
        print(line)
    print(f"  rebuilt metrics.json{''.join(f', {p.name}' for p in plots)}")
    if finalised:
        print(f"  {finalised}")
    return 0


def finalise_live_mcap(run: Path) -> tuple[str | None, str | None]:
    """The run's live MCAP finalised when its writer left it torn (flightstack.recording.mcap_finalise):
    (what was done, None), (None, `<file>: <why not>`), or (None, None) when there is no file or it opens
    already."""
    from flightstack.recording.files import LIVE_MCAP_FILE, TORN_MCAP_FILE
    from flightstack.recording.mcap_finalise import finalise_torn

    path = run / LIVE_MCAP_FILE
    if not path.is_file():
        return None, None
    try:
        done = finalise_torn(path, run / TORN_MCAP_FILE)
    except (OSError, ValueError) as exc:
        return None, f"{LIVE_MCAP_FILE}: torn, and not finalised: {exc}"
    if done is None:
        return None, None
    return (
        f"finalised {LIVE_MCAP_FILE}: {done.messages} messages recovered up to its last complete chunk; "
        f"the torn original ({done.torn_bytes} B) kept as {done.torn.name}"
    ), None


def cmd_preflight(args: argparse.Namespace) -> int:
    """Check every device and file of a hardware mission (its rig's preflight); exit 1 on any FAIL."""
    from flightstack.config.mission import load_mission
    from flightstack.runtime.rig import rig_of

    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    try:
        report = rig_of(mission).preflight(mission, args.id or None, args.deadline, not args.no_camera)
    except ValueError as exc:
        print(f"error: {args.mission}: {exc}", file=sys.stderr)
        return 2
    if report is None:
        print(f"error: {args.mission}: backend {mission.backend!r} has no hardware to check", file=sys.stderr)
        return 2
    print(report.table)
    return 0 if report.passed else 1


def cmd_target(args: argparse.Namespace) -> int:
    """Drive the rig's robot on the mission's square law from its motion-capture pose (drivers/target_run);
    the rig is opened first, as for a flight (the emulated lab starts its emulators)."""
    from flightstack.cli.run import confirm
    from flightstack.config.mission import load_mission
    from flightstack.drivers.lab.target_run import drive_target
    from flightstack.runtime.rig import opened

    mission = load_mission(args.mission, check_files=False, rig=args.rig)
    if mission.hardware is None or mission.hardware.target is None:
        print(f"error: {args.mission}: hardware.target: no robot to drive (set its url)", file=sys.stderr)
        return 2
    sq = mission.target.square
    law = mission.target_law()
    duration = args.duration if args.duration is not None else args.laps * law.lap_time
    if not confirm(
        f"The robot will drive {duration:.0f} s on the {sq.side_m:g} m square. Area clear?", args.yes
    ):
        print("aborted", file=sys.stderr)
        return 1
    with opened(mission) as flown:
        return drive_target(flown, duration)


def cmd_train(args: argparse.Namespace) -> int:
    from flightstack.config.mission import load_mission
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
    """Fly rc steps on one Tello; fit rc-unit → m/s gains and time constants (drivers/tello/identify.py)."""
    from flightstack.drivers.guardian.launcher import Guardian, GuardianConfig
    from flightstack.drivers.tello.config import TelloConfig
    from flightstack.drivers.tello.driver import TelloDriver
    from flightstack.drivers.tello.identify import fits_to_rc_gains, identify, save_identification

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


def version(name: str) -> str:
    """importlib.metadata.version, imported when asked (it costs `--help` tens of ms)."""
    from importlib.metadata import version as dist_version

    return dist_version(name)


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or "unknown" when flightstack runs from a
    checkout that was never installed (no distribution metadata)."""
    from importlib.metadata import PackageNotFoundError

    try:
        return version("flightstack")
    except PackageNotFoundError:
        return "unknown"


def _add_run(sub: Any) -> None:
    from flightstack.cli.run import add_run_arguments, cmd_run

    r = sub.add_parser("run")
    add_run_arguments(r, "experiment: a built-in name (paper_sim, paper_experiment) or a YAML file")
    r.add_argument("--yes", action="store_true", help="confirm that real drones may take off")
    r.set_defaults(func=cmd_run)
    s = sub.add_parser("sim")
    add_run_arguments(s, "experiment or mission YAML file (see mission_configs/)")
    s.set_defaults(func=cmd_run)
    f = sub.add_parser("fly")
    add_run_arguments(f, "experiment (with --rig LAB.yaml) or mission YAML file", simulated_links=False)
    f.add_argument("--yes", action="store_true", help="confirm that the drones may take off")
    f.set_defaults(func=cmd_run)


def _add_preflight(sub: Any) -> None:
    pf = sub.add_parser(
        "preflight",
        description="Check every device and file of a hardware mission before anyone flies, each device in "
        "its own thread, all within --deadline: certificates, the computer's compiled math, camera "
        "calibrations, the gain condition, each drone (link, battery, firmware, video), the Wi-Fi topology, "
        "motion capture (transmission, up axis, bodies) and the robot (failsafe, external navigation). "
        "Nothing takes off and nothing moves. Prints a table of PASS, WARN (flyable, but look) and FAIL "
        "rows; exit 0 without a FAIL, 1 with one, 2 on bad input. The checks: docs/real-lab.md.",
    )
    pf.add_argument("mission", help="experiment (with --rig LAB.yaml) or mission YAML file")
    pf.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    pf.add_argument("--deadline", type=float, default=9.0, help="bound on the whole check (s)")
    pf.add_argument("--no-camera", action="store_true", help="skip the video check")
    pf.add_argument(
        "--id", type=int, action="append", help="check only this drone (repeatable; access-point mode)"
    )
    pf.set_defaults(func=cmd_preflight)


MAX_LAPS = 100
"""Bound on `target --laps`: 100 laps of the paper's square (1 m at 0.1 m/s, 40 s a lap) take 67 min; more
is a typo."""


def laps(text: str) -> float:
    """argparse type of `target --laps`: a finite number of laps in (0, MAX_LAPS] (else exit 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of laps") from None
    if not (math.isfinite(value) and 0 < value <= MAX_LAPS):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of laps in (0, {MAX_LAPS}]")
    return value


def _add_target(sub: Any) -> None:
    from flightstack.cli.run import seconds

    tg = sub.add_parser("target")
    tg.add_argument("mission", help="mission YAML file with hardware.mocap and hardware.target")
    tg.add_argument("--rig", default=None, help="the experiment's rig (default: its `rig:`)")
    tg.add_argument(
        "--laps", type=laps, default=1.0, help=f"laps of the square, at most {MAX_LAPS} (default 1)"
    )
    tg.add_argument("--duration", type=seconds, default=None, help="seconds instead of laps")
    tg.add_argument("--yes", action="store_true", help="confirm that the robot may move")
    tg.set_defaults(func=cmd_target)


def _add_train(sub: Any) -> None:
    t = sub.add_parser("train")
    t.add_argument("run_dir", help="run directory written by `flightstack sim`")
    t.add_argument("--out", required=True, help="experts file to write (.npz)")
    t.add_argument("--mission", default=None, help="mission file (default: RUN_DIR/mission_resolved.yaml)")
    t.add_argument("--from-mode", default="none", help="which recorded mode to learn from (default: none)")
    t.set_defaults(func=cmd_train)


def _add_calibrate(sub: Any) -> None:
    from flightstack.calibration.cli import register as register_calibration
    from flightstack.cli.run import seconds

    cal = sub.add_parser("calibrate")
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
    register_calibration(cal_sub)


def _add_report(sub: Any) -> None:
    rp = sub.add_parser("report")
    rp.add_argument("run_dir", help="run directory written by `flightstack sim`/`fly`/`agent`")
    rp.add_argument("--mission", default=None, help="mission file (default: RUN_DIR/mission_resolved.yaml)")
    rp.add_argument("--no-plots", action="store_true", help="metrics.json only")
    rp.set_defaults(func=cmd_report)


class _Version(argparse.Action):
    """`--version`: argparse's version action, with the version read only when asked."""

    def __init__(self, option_strings: list[str], dest: str, help: str | None = None) -> None:
        super().__init__(
            option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, nargs=0, help=help
        )

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        parser._print_message(f"{parser.prog} {package_version()}\n", sys.stdout)
        parser.exit()


@dataclass(frozen=True)
class Command:
    """A top-level command: its group in `flightstack --help`, its one-line help, and what adds it with
    its options (a function of this module, or "module:function" imported only when it is needed; one
    adder may add several commands)."""

    group: str
    name: str
    help: str
    adder: Callable[[Any], object] | str


GROUPS = ("simulate", "analyse", "hardware", "bus", "shell")
START_HERE = (
    "start here: flightstack run paper_sim   (the paper's simulation, a few seconds, into a run directory;\n"
    "            `flightstack COMMAND -h` shows a command's options)"
)
COMMANDS = (
    Command(
        "simulate", "run", "fly an experiment on a rig (ideal, lab-sim, emulated-lab, a lab file)", _add_run
    ),
    Command("simulate", "sim", "run an experiment on a simulated rig (refuses real drones)", _add_run),
    Command(
        "simulate",
        "sweep",
        "run an experiment over seeds x a grid of overrides, with statistics",
        "flightstack.cli.sweep:register",
    ),
    Command(
        "simulate",
        "faults",
        "fly the simulated mission under each fault and print what the system did",
        "flightstack.faults.cli:register",
    ),
    Command(
        "simulate",
        "generate-mission",
        "write the paper's simulation for N drones (scaling experiments)",
        "flightstack.cli.generate:register",
    ),
    Command(
        "simulate",
        "validate",
        "check an experiment (on its rig), a rig or lab file, or a mission",
        "flightstack.cli.validate:register",
    ),
    Command(
        "analyse",
        "report",
        "rebuild metrics.json and the plots of a run directory (also one cut short by a kill); finalise a "
        "torn recording.mcap",
        _add_report,
    ),
    Command(
        "analyse",
        "view",
        "show a run directory in the Rerun 3-D viewer (poses, estimates, cameras, GP, errors, events)",
        "flightstack.cli.view:register",
    ),
    Command(
        "analyse",
        "export",
        "export a run directory as an MCAP file (Foxglove, PlotJuggler)",
        "flightstack.cli.export:register",
    ),
    Command("analyse", "train", "fit GP experts on a recorded run (data collection without GP)", _add_train),
    Command("hardware", "fly", "fly an experiment on real hardware: preflight, confirm, fly", _add_run),
    Command(
        "hardware", "preflight", "check every device of a hardware mission (pass/fail table)", _add_preflight
    ),
    Command(
        "hardware", "target", "drive the real ground robot on the square law (motion capture)", _add_target
    ),
    Command(
        "hardware",
        "calibrate",
        "calibration tools (cameras, markers, a Tello's gains, latency)",
        _add_calibrate,
    ),
    Command(
        "hardware",
        "draw-lab",
        "draw a lab file as SVG: computers, interfaces, processes, drones, networks and ports",
        "flightstack.cli.draw_lab:register",
    ),
    Command(
        "hardware",
        "bench-loop",
        "does this computer keep the mission's dt while decoding every drone's video? (emulated lab)",
        "flightstack.cli.bench_loop:register",
    ),
    Command(
        "bus",
        "world",
        "serve a simulated mission's world to agent processes over Zenoh",
        "flightstack.cli.network:register",
    ),
    Command(
        "bus",
        "agent",
        "run one agent (its drone, camera, pose) talking to the others over Zenoh",
        "flightstack.cli.network:register",
    ),
    Command(
        "bus",
        "abort",
        "make every agent of a mission land at once; exit 1 naming any that did not ack",
        "flightstack.cli.network:register",
    ),
    Command(
        "bus",
        "status",
        "live table of every agent: liveliness, message age, battery, ...",
        "flightstack.cli.network:register",
    ),
    Command(
        "bus",
        "guard",
        "land the Tello of any agent that vanishes from the bus in flight (station topology only)",
        "flightstack.cli.network:register",
    ),
    Command(
        "bus",
        "certs",
        "create the mission CA and a certificate for each participant",
        "flightstack.cli.certs:register",
    ),
    Command(
        "shell",
        "completion",
        'print shell code for tab completion (eval "$(flightstack completion bash)")',
        "flightstack.cli.completion:register",
    ),
)
_BY_NAME = {c.name: c for c in COMMANDS}


class _Subcommands:
    """The subparsers action as the adders see it: `add_parser(name)` gets the command's help from
    COMMANDS (its one place); a name added already (by an adder of several commands) is not added again."""

    def __init__(self, action: argparse._SubParsersAction) -> None:
        self._action = action

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        existing = self._action.choices.get(name)
        if isinstance(existing, argparse.ArgumentParser):
            return existing
        kwargs.setdefault("help", _BY_NAME[name].help)
        return self._action.add_parser(name, **kwargs)


def sentence(text: str) -> str:
    """`text` as a sentence: a capital first letter and a full stop."""
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def shows_default(action: argparse.Action) -> bool:
    """Whether `-h` appends the action's default: an option or optional positional with a value that says
    something (not None, False, empty), whose help does not already name its default."""
    takes_value = (bool(action.option_strings) and action.nargs != 0) or action.nargs in ("?", "*")
    said = "default" in str(action.help or "").lower()
    empty = action.default in (None, False, "", [], ()) or action.default is argparse.SUPPRESS
    return takes_value and not said and not empty and action.help is not argparse.SUPPRESS


class _DefaultsShown(argparse.HelpFormatter):
    """Help that names each option's default (shows_default)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = super()._get_help_string(action)
        if text is None or not shows_default(action):
            return text
        if text.endswith(")"):  # "bound on the whole check (s)" -> "(s; default: 9.0)"
            return f"{text[:-1]}; default: %(default)s)"
        return f"{text} (default: %(default)s)"


class _RawDescriptionDefaultsShown(_DefaultsShown, argparse.RawDescriptionHelpFormatter):
    """_DefaultsShown for a parser whose description keeps its line breaks."""


_SHOWN = {
    argparse.HelpFormatter: _DefaultsShown,
    argparse.RawDescriptionHelpFormatter: _RawDescriptionDefaultsShown,
}


def _complete_help(parser: argparse.ArgumentParser) -> None:
    """Every (sub)command's `-h` names its options' defaults, and has a description: its own, else its
    one-line help as a sentence."""
    for plain, shown in _SHOWN.items():
        if parser.formatter_class is plain:
            parser.formatter_class = shown
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                if sub.description is None and helps.get(name):
                    sub.description = sentence(str(helps[name]))
                _complete_help(sub)


def _adder(adder: Callable[[Any], object] | str) -> Callable[[Any], object]:
    if callable(adder):
        return adder
    module, _, function = adder.partition(":")
    return getattr(importlib.import_module(module), function)


def command_listing() -> str:
    """The commands by group, for `flightstack --help`."""
    width = max(len(c.name) for c in COMMANDS)
    lines = [START_HERE, ""]
    for group in GROUPS:
        lines.append(f"{group}:")
        lines += [f"  {c.name:{width}s}  {c.help}" for c in COMMANDS if c.group == group]
    return "\n".join(lines)


def build_parser(selected: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The parser of `flightstack`: every command with its options (selected None), or only the
    `selected` ones (the others by name, so that `--help`, an unknown name and the completion of a name
    work without importing their modules)."""
    p = argparse.ArgumentParser(
        prog="flightstack",
        usage="flightstack [-h] [--version] COMMAND ...",
        description=command_listing(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action=_Version, help="show the installed version and exit")
    action = p.add_subparsers(
        dest="command", required=True, metavar="COMMAND", help=argparse.SUPPRESS, prog="flightstack"
    )
    sub = _Subcommands(action)
    wanted = set(_BY_NAME) if selected is None else set(selected) & set(_BY_NAME)
    for adder in dict.fromkeys(c.adder for c in COMMANDS if c.name in wanted):  # each adder once, in order
        _adder(adder)(sub)
    for c in COMMANDS:
        sub.add_parser(c.name)  # the rest by name only (skipped where an adder added it)
    _complete_help(p)
    return p


def selected_commands(argv: list[str]) -> set[str]:
    """The commands named in `argv` or, for a completion request, in the shell's line (COMP_LINE)."""
    words = list(argv)
    if "_ARGCOMPLETE" in os.environ:
        line = os.environ.get("COMP_LINE", "")
        point = os.environ.get("COMP_POINT", "")
        words = line[: int(point)].split() if point.isdigit() else line.split()
    return set(words) & set(_BY_NAME)


def _sigterm_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Entry point. SIGTERM is handled like Ctrl-C: drones land, the recording is written, exit 130."""
    argv = sys.argv[1:] if argv is None else argv
    threads.apply(
        threads.limits_for(1)
    )  # before a command's modules load BLAS or numba (flightstack.threads)
    parser = build_parser(selected_commands(argv))
    # a tab-completion request (the shell code of `flightstack completion`) is answered here, then exits
    argcomplete.autocomplete(parser)
    args = parser.parse_args(argv)
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    # Ctrl-C must stop a run even when whoever started us ignored SIGINT (a background job of a script,
    # some launchers): Python then keeps SIG_IGN and `kill -INT` would do nothing
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print("warning: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a device that cannot be reached, a file that cannot be written, ...
        from flightstack.config.mission import MissionError
        from flightstack.config.rig import RigError

        if isinstance(exc, (MissionError, RigError)):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if os.environ.get("FLIGHTSTACK_DEBUG"):
            raise
        hint = "FLIGHTSTACK_DEBUG=1 shows the traceback"
        print(f"error: {type(exc).__name__}: {exc} ({hint})", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
