"""`flightstack run EXPERIMENT --rig RIG` (and its older spellings `sim` and `fly`): one experiment, any
rig (flightstack.config.rig). A simulated rig flies at once; the emulated-lab rig starts its loopback
emulators first; a real lab is preflighted and confirmed. (`validate`: flightstack.cli.validate.)"""

from __future__ import annotations

import argparse
import datetime
import math
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import yaml
from tqdm import tqdm

from flightstack.cli.summary import console_logging, console_print, metric_lines, say, with_level
from flightstack.config.links import PROFILES
from flightstack.config.mission import Mission, MissionError, load_mission
from flightstack.threads import ThreadLimits

if TYPE_CHECKING:
    from flightstack.runtime.flight import Flight, FlightResult

RUNS_ROOT = Path("runs")
"""Where a run without --out goes: runs/<experiment name>-<YYYYmmdd-HHMMSS> (relative to the current
directory)."""


def want_progress(flag: bool | None, stream: TextIO | None = None) -> bool:
    """Progress bars or not: --progress (True) and --no-progress (False) decide; without either, only
    when `stream` (default sys.stderr, where the bars go) is a terminal."""
    if flag is not None:
        return flag
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def default_out_dir(name: str, now: datetime.datetime | None = None, root: Path = RUNS_ROOT) -> Path:
    """root/<name>-<YYYYmmdd-HHMMSS> (local time `now`, default the present), with -2, -3, … appended
    when that already exists (two runs started in the same second); `name` reduced to file-name-safe
    characters."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "run"
    stamp = (now or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    out = root / f"{safe}-{stamp}"
    k = 2
    while out.exists():
        out, k = root / f"{safe}-{stamp}-{k}", k + 1
    return out


def claim_out_dir(out: Path, force: bool) -> str | None:
    """None when `out` may take a run: missing or empty (or, with `force`, holding anything), writable,
    with MIN_FREE_BYTES free (flightstack.recording.files.check_out_dir); else why not. Nothing is
    removed here (`clear_for_run` does that once nothing else can refuse the run)."""
    from flightstack.recording.files import check_out_dir, out_dir_entries, run_files

    entries = out_dir_entries(out)
    if entries and not force:
        ours = run_files(out)
        names = ", ".join(p.name for p in entries[:4]) + (", ..." if len(entries) > 4 else "")
        return (
            f"not empty ({len(entries)} entries: {names}); pass --force to remove the {len(ours)} files "
            "a run writes there (recordings, metrics, plots; every other file is kept), or choose "
            "another directory"
        )
    return check_out_dir(out)


def clear_for_run(out: Path, force: bool) -> None:
    """With --force: remove the files an earlier run wrote in `out` (flightstack.recording.files.RUN_FILES,
    nothing else), so that none of them passes for this run's; says how many on stderr."""
    if not force:
        return
    from flightstack.recording.files import clear_run_files

    removed = clear_run_files(out)
    if removed:
        say("info", f"--force: removed {len(removed)} files of an earlier run from {out}")


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


def with_sets(mission: Mission, sets: list[str]) -> Mission:
    """The mission with each `--set KEY=VALUE` applied (a dotted key and one YAML value, the sweep's
    syntax, parsed by the hardened loader), validated again, and held to what its rig allows
    (flightstack.config.rig_rules: the rig's safety tightened, never loosened); MissionError naming the
    key and the reason."""
    from flightstack.config.mission import parse_mission
    from flightstack.config.rig_rules import beyond_rig
    from flightstack.runtime.flight import resolved_mission_yaml
    from flightstack.sweep.plan import SweepError, parse_set, set_path

    doc = yaml.safe_load(resolved_mission_yaml(mission))  # file paths absolute: loads from anywhere
    for text in sets:
        try:
            key, values = parse_set(text)
            if len(values) != 1:
                raise SweepError(f"--set {key}: one value per key here (a sweep takes several)")
            set_path(doc, key, values[0])
        except SweepError as exc:
            raise MissionError(str(exc)) from None
    label = f"{mission.name} with --set {' '.join(sets)}"
    changed = parse_mission(doc, label)
    why = beyond_rig(mission, changed)
    if why is not None:
        raise MissionError(f"{label}: {why}")
    return changed


def cmd_run(args: argparse.Namespace) -> int:
    """`run EXPERIMENT --rig RIG`, `sim MISSION` (simulated rigs only) and `fly MISSION`: load, check the
    run directory, start an emulated lab or preflight and confirm real drones, fly, report."""
    console_logging()  # the safety events as they happen, each with its level
    overrides: dict[str, object] = {}
    if args.duration is not None:
        overrides["duration_s"] = args.duration
    if args.modes is not None:
        overrides["compare_modes"] = args.modes
    if getattr(args, "links", None) is not None:
        overrides["links"] = {"profile": args.links}
    if getattr(args, "network", None) is not None:
        overrides["links.network"] = args.network
    mission = load_mission(args.mission, overrides, rig=args.rig)
    if args.bus is not None and args.bus != mission.bus.kind:
        bus = _bus_override(mission, args.bus)
        mission = load_mission(args.mission, {**overrides, "bus": bus}, rig=args.rig)
    if getattr(args, "set", None):
        mission = with_sets(mission, args.set)
    problem = network_problem(mission)
    if problem is not None:
        print(f"error: {problem}; nothing took off", file=sys.stderr)
        return 2
    from flightstack.runtime.resources import check_recording_fits

    check_recording_fits(mission)  # MissionError (exit 2) before anything is created or flies
    if args.command == "sim" and mission.rig_type.flies_real_drones:
        print(
            f"error: {args.mission}: backend {mission.backend!r} flies real drones; "
            "use `flightstack preflight` then `flightstack fly`",
            file=sys.stderr,
        )
        return 2
    from flightstack.learning.training import training_shortfall

    short = training_shortfall(mission)  # a data run too short to train the experts: say so now
    if short is not None:
        print(f"error: {mission.name}: {short}; nothing took off", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out is not None else default_out_dir(mission.name)
    problem = claim_out_dir(out, args.force)  # before the preflight and the operator's confirmation
    if problem is not None:
        print(f"error: --out {out}: {problem}; nothing took off", file=sys.stderr)
        return 2
    mcap = getattr(args, "mcap", None)
    if mcap is not None and Path(mcap).exists() and not args.force:
        print(f"error: --mcap {mcap} exists (--force replaces it); nothing took off", file=sys.stderr)
        return 2
    from flightstack.cli.view import viewer_problem

    problem = viewer_problem(args)  # no rerun-sdk (how to install it), a bad --viewer-host: before flying
    if problem is not None:
        print(f"error: {problem}; nothing took off", file=sys.stderr)
        return 2
    if args.out is None:
        say("info", f"run directory: {out} (--out DIR chooses another)")
    if mission.rig_type.flies_real_drones:
        code = _confirm_and_preflight(args, mission)
        if code:
            return code
    clear_for_run(out, args.force)  # on real drones only once the operator confirmed
    return _fly_and_report(args, mission, out)


def fly_or_say(flight: Flight) -> FlightResult | None:
    """Enter `flight` and fly it; None, said on stderr, when it could not start (nothing took off)."""
    from flightstack.runtime.flight import NotFlownError

    try:
        with flight:
            return flight.fly()
    except NotFlownError as exc:
        print(f"error: {exc}; nothing took off", file=sys.stderr)
        return None


def _fly_and_report(args: argparse.Namespace, mission: Mission, out: Path) -> int:
    """Fly every mode of `mission` into the run directory `out` (flightstack.runtime.flight) and print
    the summary; the exit code."""
    from flightstack.cli.view import open_live_viewer
    from flightstack.runtime.flight import Flight

    t_cmd0 = time.perf_counter()
    try:  # --viewer: the live Rerun view (a tap of every mode; flightstack.viewer.live)
        tap = open_live_viewer(args, mission, out, mission.flown_modes())
    except (OSError, RuntimeError) as exc:
        print(f"error: --viewer: {exc}; nothing took off", file=sys.stderr)
        return 2
    bars: list[tqdm] = []
    flight = Flight(
        mission,
        out,
        taps=[tap] if tap is not None else (),
        progress=_progress_factory(bars) if want_progress(args.progress) else None,
        plots=True,
        live_mcap=args.live_mcap,
        say=to_stderr,
    )
    try:
        res = fly_or_say(flight)
    finally:
        for b in bars:
            b.close()
        if tap is not None:
            tap.finish()
    if res is None:
        return 2
    m = res.metrics
    print(f"run directory: {out}")
    for line in metric_lines(m, flight.mission):
        print(line)
    for line in speed_lines(m, time.perf_counter() - t_cmd0):
        print(line)
    if m.get("threads"):  # what the flight ran with (flightstack.threads), as metrics.json has it
        print(f"  {ThreadLimits(**m['threads']).line()}")
    rec_status = m["recording"]
    if not rec_status["complete"]:
        say("error", f"recording incomplete: {rec_status['reason']}")
    mcap_problem = live_mcap_problem(flight, out)
    if mcap_problem is not None:
        say("error", mcap_problem)
    exported = _export_mcap(args, flight.mission, out)
    if res.interrupted:
        say("warning", "interrupted: every drone landed, partial recording written")
        return 130
    if res.error:
        print(f"error: {res.error}; every drone landed, partial recording written", file=sys.stderr)
        return 1
    return 0 if rec_status["complete"] and exported and mcap_problem is None else 1


def live_mcap_problem(flight: Flight, out: Path) -> str | None:
    """One line saying that the live MCAP was not finished, why, and how to finalise it (None: it was
    finished, or none was written). The flight is not affected: the run directory has every tick."""
    from flightstack.recording.files import LIVE_MCAP_FILE

    error = None if flight.writer is None else flight.writer.live_mcap_error
    if error is None:
        return None
    path = out / LIVE_MCAP_FILE
    return f"the live MCAP {path} is incomplete: {error} (`flightstack report {out}` finalises it)"


def _export_mcap(args: argparse.Namespace, mission: Mission, out: Path) -> bool:
    """--mcap FILE: the run directory as MCAP, written after the landing from the recording (so the
    control loop never waits on it; `flightstack export` writes the same file later). False on failure,
    which is reported; the run directory is complete either way."""
    target = getattr(args, "mcap", None)
    if target is None:
        return True
    from flightstack.recording.mcap_export import export_mcap

    try:
        s = export_mcap(out, Path(target), None, mission)
    except Exception as exc:  # the flight is over and recorded: say so, and how to export it again
        print(
            f"error: --mcap {target}: {type(exc).__name__}: {exc}; the run directory is intact "
            f"(flightstack export {out} --mcap FILE)",
            file=sys.stderr,
        )
        return False
    print(f"  MCAP: {target} ({len(s.topics)} topics, {s.messages} messages; Foxglove, PlotJuggler)")
    return True


def speed_lines(m: dict[str, Any], command_s: float) -> list[str]:
    """Sim-time / wall-time of each flown mode's loop (takeoff to landing, kernels already warm), of the
    flown modes together, and of the whole command (warm-up, training, gain analysis, files and plots).
    Modes flown on the wall clock (hardware, the emulated lab) are left out: they run at 1x by design and
    their loop-health line says whether they kept dt."""
    lines, sim, wall = [], 0.0, 0.0
    for mode, mm in m["modes"].items():
        if (mm.get("loop_health") or {}).get("real_time"):
            continue
        s, w = float(mm.get("sim_seconds", 0.0)), float(mm.get("wall_seconds", 0.0))
        if s > 0 and w > 0:
            lines.append(f"  speed {mode:7s} {s:8.1f} s simulated in {w:7.2f} s: {s / w:8.1f}x real time")
            sim, wall = sim + s, wall + w
    if wall > 0:
        train = float(m.get("gp", {}).get("train_seconds", 0.0))
        lines.append(
            f"  speed flown modes {sim:.1f} s in {wall:.2f} s ({sim / wall:.1f}x real time); whole command "
            f"{command_s:.1f} s ({sim / command_s:.1f}x; GP training {train:.1f} s)"
        )
    return lines


def to_stderr(line: str) -> None:
    """A status line of the flight (Flight's `say`), on stderr with its level (`info` unless it has one),
    above the progress bars."""
    console_print(with_level(line))


def _bus_override(mission: Mission, kind: str) -> dict[str, object]:
    """The mission's bus section switched to `kind`; for zenoh without endpoints, all agents of this
    process listen on a free loopback port (nothing leaves the machine)."""
    bus = mission.bus.model_dump(mode="json")
    bus["kind"] = kind
    if kind == "zenoh" and bus.get("zenoh") is None:
        from flightstack.comms.factory import free_loopback_endpoints

        # plaintext on loopback is allowed for simulations only; real drones need the mission's certificates
        security = "plaintext" if mission.simulated else "mtls"
        endpoint = free_loopback_endpoints()[0].replace("tcp/", "tls/" if security == "mtls" else "tcp/")
        bus["zenoh"] = {"endpoints": {"agents": endpoint}, "security": security}
    return bus


def confirm(question: str, yes: bool) -> bool:
    """True when the operator confirmed (--yes, or 'y' at an interactive prompt)."""
    if yes:
        return True
    if not sys.stdin.isatty():
        print("error: this moves real hardware; pass --yes to confirm", file=sys.stderr)
        return False
    return input(f"{question} [y/N] ").strip().lower() in ("y", "yes")


def _confirm_and_preflight(args: argparse.Namespace, mission: Mission) -> int:
    """Preflight every device (the rig's), then ask; 0 to go on, else the exit code."""
    from flightstack.runtime.rig import rig_of

    report = rig_of(mission).preflight(mission)
    if report is not None:
        print(report.table)
    if report is not None and not report.passed:
        print("error: preflight failed; nothing took off", file=sys.stderr)
        return 1
    ids = ", ".join(str(d.id) for d in mission.drones)
    if not confirm(
        f"Drones {ids} will take off and fly {mission.duration_s:g} s per mode. Area clear?", args.yes
    ):
        print("aborted", file=sys.stderr)
        return 1
    return 0


def add_run_arguments(p: argparse.ArgumentParser, mission_help: str, simulated_links: bool = True) -> None:
    """The arguments `run`, `sim` and `fly` share; `simulated_links`: also --network and --links, which
    only the simulated and the emulated lab apply (not `fly`'s real drones)."""
    p.add_argument("mission", help=mission_help)
    p.add_argument(
        "--rig",
        default=None,
        help="rig to fly the experiment on: ideal, lab-sim, emulated-lab, lab or a rig file "
        "(default: the experiment's own `rig:`)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="run directory (created if missing; it must be empty unless --force; default: "
        "runs/<experiment name>-<YYYYmmdd-HHMMSS>)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="reuse a non-empty --out: first remove the files a run writes there (recordings, metrics, "
        "plots of an earlier run); every other file is kept",
    )
    duration = p.add_argument("--duration", type=seconds, default=None)
    duration.help = DurationHelp(  # set after add_argument: argparse would format (compute) it there
        "override duration_s (seconds, > 0); a run with a GP mode must be long enough to train the experts: "
        f"at least {DurationHelp.MINIMUM}, predicted from the target's path (the estimates' transient may "
        "need more; a shorter one is refused before takeoff, naming its minimum)"
    )
    p.add_argument(
        "--modes",
        type=mode_list,
        default=None,
        help="override compare_modes, e.g. none,dgp (comma-separated)",
    )
    bars = p.add_mutually_exclusive_group()
    bars.add_argument(
        "--progress",
        dest="progress",
        action="store_true",
        default=None,
        help="progress bars on stderr even when it is not a terminal (default: only on a terminal)",
    )
    bars.add_argument(
        "--no-progress", dest="progress", action="store_false", default=None, help="no progress bars"
    )
    p.add_argument("--bus", choices=["inproc", "zenoh"], help="override bus.kind (zenoh: on loopback)")
    if simulated_links:
        add_network_argument(p)
        p.add_argument(
            "--links",
            choices=sorted(PROFILES),
            default=None,
            help="replace the rig's links with a profile: how late and lossy video, state, rc, motion "
            "capture and the robot are (docs/links.md; applied by the simulated and the emulated lab)",
        )
    p.add_argument(
        "--set",
        action="append",
        default=None,
        metavar="KEY=VALUE",
        help="set a dotted mission key to a YAML value after the rig is composed, e.g. "
        "compensation.enabled=true or gains.k_s=4 (repeatable; validated like the file)",
    )
    p.add_argument(
        "--mcap",
        default=None,
        metavar="FILE",
        help="also write the run as MCAP (Foxglove, PlotJuggler) after the landing, from the recording; "
        "the same file as `flightstack export RUN_DIR --mcap FILE`",
    )
    add_live_mcap_argument(p)
    from flightstack.cli.view import add_viewer_argument

    add_viewer_argument(p)


def add_live_mcap_argument(p: argparse.ArgumentParser) -> None:
    """--live-mcap / --no-live-mcap (default on): recording.mcap in the run directory, written as the run
    goes by a companion process (flightstack.recording.mcap_live)."""
    p.add_argument(
        "--live-mcap",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="write recording.mcap (Foxglove, PlotJuggler) into the run directory as the run goes, from a "
        "companion process (default: on; docs/logs.md)",
    )


class DurationHelp(str):
    """--duration's help text, which names the shortest duration that trains the GP experts of each built-in
    experiment (flightstack.learning.training.minimum_duration; about 1 s to compute). It is computed only
    when argparse formats the help (`help % params`); shell completion, which shows a help text without a
    `%` as it is, never waits for it."""

    MINIMUM = "the minimum of its experiment"

    def __mod__(self, params: object) -> str:
        from flightstack.config.rig import builtin_names
        from flightstack.learning.training import minimum_duration

        parts = []
        for name in builtin_names("experiment"):
            least = minimum_duration(load_mission(name))
            parts.append(f"{least:g} s for {name}" if least is not None else f"none for {name}")
        return str(self).replace(self.MINIMUM, ", ".join(parts))


def add_network_argument(p: argparse.ArgumentParser) -> None:
    """--network PROFILE: the emulated lab's radio (the mission's `links.network`)."""
    from flightstack.netem import PROFILES

    p.add_argument(
        "--network",
        choices=list(PROFILES),
        default=None,
        help="emulated lab only: every packet of every emulated device passes this seeded radio profile "
        "(default: the rig's `links.network`, clean); see docs/links.md",
    )


def network_problem(mission: Mission) -> str | None:
    """Why the mission's network profile cannot be applied (None: it can): only the emulated lab's
    emulators apply one; a real network is impaired with tc netem (docs/links.md)."""
    if mission.links.network == "clean" or mission.start_emulators:
        return None
    return (
        f"links.network: profile {mission.links.network!r} is applied by the emulated lab's emulators only; "
        "to impair a real lab's network use `tc netem` (docs/links.md)"
    )


def seconds(text: str) -> float:
    """argparse type of a duration: a finite number of seconds > 0 (else exit 2 naming the value)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds > 0")
    return value


def mode_list(text: str) -> list[str]:
    """argparse type of --modes: comma-separated mode names (the schema checks each name)."""
    modes = [m.strip() for m in text.split(",") if m.strip()]
    if not modes:
        raise argparse.ArgumentTypeError(f"{text!r}: give at least one mode, e.g. none,dgp")
    return modes
