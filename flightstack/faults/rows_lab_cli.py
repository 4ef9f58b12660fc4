"""The rows of `flightstack faults` that fly `flightstack fly` on the emulated lab in a child
process: signals (`sighup`, `double_sigint`: the second Ctrl-C 20 ms after the first reached the
process) and an operator abort while the Tellos take off (`abort_during_takeoff`). FaultRows (mission
file, work directory) -> FaultResult, listed in rows_lab.ROWS. Reaction times are measured on the
emulators' records (time.monotonic() s, shared with the child process) and reported in `details` in
milliseconds.
"""

from __future__ import annotations

import io
import re
import signal
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

from flightstack.faults.lab_flight import (
    FAULT_AFTER_S,
    PURSUIT_WAIT_S,
    REACT_S,
    FlyProcess,
    drone_reaction,
    judge_lab_recording,
    run_result,
    sub,
)
from flightstack.faults.result import Checks, FaultResult
from flightstack.sim_backend.emulated_lab import EmulatedLab, command_times, first, ms, phase_times, rc_times

SECOND_SIGNAL_S = 0.02
"""Delay of the second Ctrl-C after the first reached the process (s; FlyProcess.delivered)."""
ACK_LINE = re.compile(r"acknowledged by drones \[([\d, ]+)\] in ([\d.]+) ms")


# ---- sighup, double_sigint ---------------------------------------------------------------------------------
def _signal_row(name: str, workdir: Path, signals: tuple[signal.Signals, ...]) -> FaultResult:
    """Signals to `flightstack fly` on the emulated lab FAULT_AFTER_S into pursuit (the next one
    SECOND_SIGNAL_S after the previous)."""
    wall0 = time.perf_counter()
    root = workdir / name
    sent: list[float] = []
    with EmulatedLab(root, duration_s=30.0) as lab:
        with FlyProcess(lab, root / "run") as fly:
            if lab.wait_for_pursuit(PURSUIT_WAIT_S) is not None:
                time.sleep(FAULT_AFTER_S)
                for k, sig in enumerate(signals):
                    if k:  # after the previous one reached the process: pending, the two would merge
                        fly.delivered(signals[k - 1])
                        time.sleep(SECOND_SIGNAL_S)
                    sent.append(fly.send(sig))
            code = fly.wait()
            run = fly.result(code)
        lab.write_log(root / "emulators.json")
        c = Checks()
        c.check(bool(sent), "the pursuit never started: no signal sent")
        ts = sent[0] if sent else run.t_start
        c.check(code == 130, f"exit code {code}")
        details: dict[str, Any] = {"run_dir": str(run.run_dir), "exit_code": code}
        if len(sent) > 1:
            details["second_signal_after_ms"] = ms(sent[1] - sent[0])
        for i, e in lab.tellos.items():
            details[f"drone{i}"] = drone_reaction(e, ts, c, f"drone {i}")
        first_sig = signals[0].name
        land_all = run.safety("land_all")
        c.check(
            bool(land_all) and f"signal {first_sig}" in str(land_all[0]["detail"]),
            f"land_all {[e['detail'] for e in land_all]}",
        )
        sig_events = [str(e["detail"]) for e in run.safety("signal")]
        if len(signals) > 1:
            ignored = [d for d in sig_events if "ignored" in d]
            c.check(len(ignored) == len(signals) - 1, f"signal events {sig_events}")
        c.check(run.end_reason() == "interrupted", f"run ended: {run.end_reason()}")
        c.check((run.metrics or {}).get("interrupted") is True, "metrics.json: interrupted is not true")
        c.check("interrupted" in run.output, "no 'interrupted' in the output")
        for i, e in lab.tellos.items():
            c.check(not e.errors, f"emulator {i} reported errors: {e.errors[:3]}")
        names = " + ".join(s.name for s in signals)
        reacts = "; ".join(
            f"drone {i}: rc 0 0 0 0 +{details[f'drone{i}']['rc0_ms']} ms, land "
            f"+{details[f'drone{i}']['land_ms']} ms, down +{details[f'drone{i}']['down_ms']} ms"
            for i in lab.tellos
        )
        observed = (
            f"exit {code}; {names} in pursuit: {reacts}; signal events {sig_events}; end: {run.end_reason()}"
        )
        second = (
            f"; the second {signals[1].name} {1e3 * SECOND_SIGNAL_S:g} ms later is logged and ignored"
            if len(signals) > 1
            else ""
        )
        expected = (
            f"land_all (signal {first_sig}): at each emulator rc 0 0 0 0 and land within {REACT_S:g} s, no "
            f"non-zero rc after, every drone down{second}; recording, events and metrics written "
            "(interrupted), exit 130"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
        )


def sighup(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGHUP (the operator's ssh session dropped) to `flightstack fly` in pursuit."""
    return _signal_row("sighup", workdir, (signal.SIGHUP,))


def double_sigint(mission_path: Path, workdir: Path) -> FaultResult:
    """Ctrl-C twice, 20 ms apart, to `flightstack fly` in pursuit."""
    return _signal_row("double_sigint", workdir, (signal.SIGINT, signal.SIGINT))


# ---- abort_during_takeoff ----------------------------------------------------------------------------------
SLOW_TAKEOFF_S = 5.0
"""Drone 2's emulated takeoff answers `ok` after this long (s; it climbs 2 s, then hovers, stabilising)."""


def abort_args(mission: Path, timeout_s: float) -> Any:
    """The parsed arguments of `flightstack abort MISSION --timeout T` (parsed ahead, so that timing the
    abort does not include the command line's imports)."""
    from flightstack.cli.app import build_parser

    return build_parser().parse_args(["abort", str(mission), "--timeout", f"{timeout_s:g}"])


def cli_abort(args: Any) -> tuple[int, str, str]:
    """Run `flightstack abort` (arguments from abort_args) in this process: the command's own code,
    without main()'s process-wide signal setup. (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = int(args.func(args))
    return code, out.getvalue(), err.getvalue()


def acks_in(stdout: str) -> dict[int, float]:
    """drone id -> time to acknowledge (ms) from `flightstack abort`'s output."""
    out: dict[int, float] = {}
    for ids, t_ms in ACK_LINE.findall(stdout):
        for i in ids.split(","):
            out[int(i)] = float(t_ms)
    return out


def _wait(pred: Any, timeout_s: float) -> bool:
    """Poll pred() every 5 ms for at most timeout_s (s); its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return bool(pred())


def abort_during_takeoff(mission_path: Path, workdir: Path) -> FaultResult:
    """`flightstack abort` while drone 1 hovers after its takeoff and drone 2 is still taking off (slow)."""
    wall0 = time.perf_counter()
    name = "abort_during_takeoff"
    root = workdir / name
    t_abort: float | None = None
    abort_code, abort_out, abort_err = -1, "", ""
    with EmulatedLab(root, duration_s=30.0) as lab:
        e1, e2 = lab.tellos[1], lab.tellos[2]
        e2.faults.takeoff_s = SLOW_TAKEOFF_S
        args = abort_args(lab.mission_path, 5.0)
        with FlyProcess(lab, root / "run") as fly:
            ready = _wait(
                lambda: e1.phase == "flying" and len(rc_times(e1)) >= 3 and e2.phase == "takeoff", 60.0
            )
            if ready:
                t_abort = time.monotonic()
                abort_code, abort_out, abort_err = cli_abort(args)
            code = fly.wait()
            run = fly.result(code)
        lab.write_log(root / "emulators.json")
        c = Checks()
        c.check(t_abort is not None, "drone 1 airborne while drone 2 takes off: never reached")
        ta = t_abort if t_abort is not None else run.t_start
        acks = acks_in(abort_out)
        c.check(abort_code == 0, f"`flightstack abort` exit {abort_code}: {abort_err.strip()[-300:]}")
        c.check(sorted(acks) == sorted(lab.tellos), f"acknowledged by {sorted(acks)}")
        d1 = drone_reaction(e1, ta, c, "drone 1 (airborne)")
        t_up2 = first(phase_times(e2, "flying", after=ta))
        c.check(t_up2 is not None, "drone 2's takeoff never completed")
        # `land` goes out at once whatever the phase; a Tello busy taking off refuses it (error), so it goes
        # out again when the takeoff's `ok` comes
        land2 = first(command_times(e2, "land", after=ta))
        c.check(land2 is not None and land2 - ta <= REACT_S, f"drone 2: first land {ms(sub(land2, ta))} ms")
        rc2 = rc_times(e2, after=ta - 60.0, before=t_up2 if t_up2 is not None else ta)
        c.check(not rc2, f"drone 2: {len(rc2)} rc sent before its takeoff completed")
        # it never got an rc since its takeoff began (its sticks are neutral): land, no rc 0 0 0 0 needed
        d2 = drone_reaction(e2, t_up2 if t_up2 is not None else ta, c, "drone 2 (after its takeoff)", False)
        moving2 = rc_times(e2, after=ta, nonzero=True)
        c.check(not moving2, f"drone 2: {len(moving2)} non-zero rc after the abort")
        c.check(code == 1 and "operator abort" in run.output, f"fly exit {code} (expected 1, operator abort)")
        c.check(run.end_reason() == "operator abort", f"run ended: {run.end_reason()}")
        for i, e in lab.tellos.items():
            c.check(not e.errors, f"emulator {i} reported errors: {e.errors[:3]}")
        details = {
            "run_dir": str(run.run_dir),
            "abort_exit_code": abort_code,
            "ack_ms": {str(i): v for i, v in acks.items()},
            "drone1_after_abort": d1,
            "drone2_first_land_after_abort_ms": ms(sub(land2, ta)),
            "drone2_takeoff_done_after_abort_ms": ms(sub(t_up2, ta)),
            "drone2_after_its_takeoff": d2,
            "fly_exit_code": code,
        }
        hover2 = (
            "no rc (none sent since its takeoff)"
            if d2["rc0_ms"] is None
            else f"rc 0 0 0 0 +{d2['rc0_ms']} ms"
        )
        observed = (
            f"abort exit {abort_code}, acks (ms) {acks}; drone 1: rc 0 0 0 0 +{d1['rc0_ms']} ms, land "
            f"+{d1['land_ms']} ms, down +{d1['down_ms']} ms after the abort; drone 2: land "
            f"+{details['drone2_first_land_after_abort_ms']} ms (refused while busy), finished its takeoff "
            f"+{details['drone2_takeoff_done_after_abort_ms']} ms after the abort, then {hover2}, land "
            f"+{d2['land_ms']} ms, down +{d2['down_ms']} ms; fly exit {code}, end: {run.end_reason()}"
        )
        expected = (
            "`flightstack abort` exits 0 with every drone's ack; the airborne drone gets rc 0 0 0 0 and "
            f"land within {REACT_S:g} s; the one taking off gets land within {REACT_S:g} s (a Tello busy "
            f"taking off refuses it) and no rc before its takeoff completes, then land again within "
            f"{REACT_S:g} s; no non-zero rc after the abort; both down; fly ends as an "
            "operator abort (exit 1) with its recording"
        )
        return run_result(
            name,
            expected,
            observed,
            wall0,
            lab,
            run,
            c,
            details,
            recording=judge_lab_recording(run, min_ticks=0),  # aborted before the pursuit: no tick flown
        )
