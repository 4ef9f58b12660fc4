"""The guardian's rows of `flightstack faults`: the process that flies the emulated lab is killed
(`process_killed`: SIGKILL, as an out-of-memory kill or a crash in native code would) or stopped
(`agent_stopped`: SIGSTOP, a hang, then SIGCONT), mid-pursuit: nothing of that process can react; its
guardian process (drivers/guardian/) must. `guardian_killed` kills the guardian alone: the flight, which
watches the guardian's heartbeat, lands by itself at once. Kills by name and of both processes:
rows_lab_kills.py.

Times are time.monotonic() seconds shared with the emulators, reported in milliseconds in `details`.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

from flightstack.faults.lab_flight import (
    FAULT_AFTER_S,
    PURSUIT_WAIT_S,
    FlyProcess,
    drone_reaction,
    lab_result,
    per_drone,
)
from flightstack.faults.result import Checks, FaultResult
from flightstack.sim_backend.emulated_lab import EmulatedLab, command_times, first, ms, phase_times, rc_times

KILL_HOVER_S = 0.5
"""Parent killed → `rc 0 0 0 0` at every drone within this (s)."""
KILL_LAND_S = 2.0
"""... and `land` within this (s)."""
STALL_S = 0.5
"""The guardian's stall bound (GuardianConfig.stall_s, s): a stopped parent is taken over after it."""
DOWN_WAIT_S = 15.0
"""How long the row waits for the drones to be down after the fault (s; the Tello's own auto-land is 15 s)."""
STOP_S = 0.5
"""`guardian_killed`: `rc 0 0 0 0` or `land` at every drone within this (s)."""
DOWN_S = 8.0
"""... and every drone down within this (s): far below the Tello's own 15 s auto-land."""
GUARDIAN_MARK = "tello-guardian-"
"""In the guardian's command line (drivers/guardian.guardian_argv): how these rows find it."""


def command_line(pid: int) -> str:
    """/proc/PID/cmdline with spaces for NULs ("" once the process is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def descendants(root: int) -> list[int]:
    """Every living descendant of process `root` (not root itself), from /proc/*/stat's parent pids."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        ppid = int(stat[stat.rindex(")") + 2 :].split()[1])  # fields after "(comm)": state, ppid, ...
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], list(children.get(root, []))
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(children.get(pid, []))
    return out


def guardian_pids(root: int) -> list[int]:
    """The guardian processes among root's descendants."""
    return [pid for pid in descendants(root) if GUARDIAN_MARK in command_line(pid)]


def _wait_down(lab: EmulatedLab, timeout_s: float) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end and any(e.flying for e in lab.tellos.values()):
        time.sleep(0.05)


def _after_fault(
    lab: EmulatedLab, t_fault: float, hover_s: float, land_s: float, c: Checks
) -> dict[str, Any]:
    """Per drone: rc 0 0 0 0 within hover_s and land within land_s of t_fault, no non-zero rc after, down
    and not by the Tello's own auto-land. Returns the times in ms."""
    out: dict[str, Any] = {}
    for i, e in lab.tellos.items():
        scratch = Checks()  # drone_reaction's REACT_S bounds are the signal rows'; ours are checked below
        r = drone_reaction(e, t_fault, scratch, f"drone {i}")
        hover, land = r["rc0_ms"], r["land_ms"]
        c.check(hover is not None and hover <= 1e3 * hover_s, f"drone {i}: rc 0 0 0 0 after {hover} ms")
        c.check(land is not None and land <= 1e3 * land_s, f"drone {i}: land after {land} ms")
        moving = rc_times(e, after=t_fault + hover_s, nonzero=True)
        c.check(not moving, f"drone {i}: {len(moving)} non-zero rc after the fault")
        c.check(
            not e.flying and not e.landed_by_timeout, f"drone {i}: {e.phase}, auto-land {e.landed_by_timeout}"
        )
        out[f"drone{i}"] = r
    return out


def _robot(lab: EmulatedLab, c: Checks) -> dict[str, Any]:
    armed = bool(lab.rover.armed)
    speed = max(abs(v) for v in lab.rover.velocity)
    c.check(not armed, "the robot is still armed")
    c.check(speed < 1e-6, f"the robot still moves at {speed:.3f}")
    return {"robot_armed": armed, "robot_speed": speed}


def process_killed(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGKILL to `flightstack fly` on the emulated lab, 1 s into pursuit."""
    wall0 = time.perf_counter()
    root = workdir / "process_killed"
    c, details = Checks(), {}
    with EmulatedLab(root, duration_s=30.0) as lab:
        with FlyProcess(lab, root / "run") as fly:
            started = lab.wait_for_pursuit(PURSUIT_WAIT_S) is not None
            c.check(started, "the pursuit never started")
            t_kill = time.monotonic()
            if started:
                time.sleep(FAULT_AFTER_S)
                t_kill = fly.send(signal.SIGKILL)
            code = fly.wait()
            _wait_down(lab, DOWN_WAIT_S)
            run = fly.result(code)
        time.sleep(0.5)  # the robot's disarm repeats until its heartbeat shows it
        lab.write_log(root / "emulators.json")
        c.check(code == -signal.SIGKILL, f"exit {code}")
        details = _after_fault(lab, t_kill, KILL_HOVER_S, KILL_LAND_S, c) | _robot(lab, c)
        rec_problems = _killed_recording(run.run_dir, t_kill)
    observed = "; ".join(
        f"drone {i}: rc 0 0 0 0 +{d['rc0_ms']} ms, land +{d['land_ms']} ms, down +{d['down_ms']} ms"
        for i, d in per_drone(details)
    )
    observed += f"; robot armed {details.get('robot_armed')}, speed {details.get('robot_speed')}"
    expected = (
        f"the guardian: rc 0 0 0 0 within {KILL_HOVER_S:g} s and land within {KILL_LAND_S:g} s at every "
        "drone, both down (not by the Tello's auto-land), the robot stopped and disarmed; the recording up "
        "to 1 s before the kill readable (`flightstack report`)"
    )
    return lab_result("process_killed", expected, observed, wall0, c, [], rec_problems, details, None)


def _killed_recording(run_dir: Path, t_kill: float) -> list[str]:
    """The row stream of a killed run is readable and ends less than 1 s before the kill."""
    from flightstack.recording.run_dir import load_run

    c = Checks()
    try:
        recs = load_run(run_dir)
    except Exception as exc:  # the finding, not a crash of the row
        return [f"load_run: {type(exc).__name__}: {exc}"]
    rec = recs.get("none")
    if c.check(rec is not None and rec.ticks_done > 0, f"no ticks recovered ({sorted(recs)})"):
        assert rec is not None
        lost = t_kill - float(rec.t[rec.ticks_done - 1])
        c.check(lost < 1.0, f"{lost:.2f} s of flight before the kill not on disk")
    return c.failed


def agent_stopped(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGSTOP to `flightstack fly` 1 s into pursuit, SIGCONT 3 s later."""
    wall0 = time.perf_counter()
    root = workdir / "agent_stopped"
    c = Checks()
    details: dict[str, Any] = {}
    with EmulatedLab(root, duration_s=30.0) as lab:
        with FlyProcess(lab, root / "run") as fly:
            started = lab.wait_for_pursuit(PURSUIT_WAIT_S) is not None
            c.check(started, "the pursuit never started")
            t_stop = time.monotonic()
            if started:
                time.sleep(FAULT_AFTER_S)
                t_stop = fly.send(signal.SIGSTOP)
                _wait_down(lab, DOWN_WAIT_S)
                n_before = {i: len(e.commands) for i, e in lab.tellos.items()}
                fly.send(signal.SIGCONT)
            code = fly.wait()
            run = fly.result(code)
        lab.write_log(root / "emulators.json")
        details = _after_fault(lab, t_stop, STALL_S + 0.3, STALL_S + 2.0, c)
        for i, e in lab.tellos.items():  # after SIGCONT: the resumed process is muted, nothing moves
            resumed = [cmd for _, cmd in list(e.commands)[n_before.get(i, 0) :] if cmd.startswith("rc ")]
            moving = [cmd for cmd in resumed if cmd != "rc 0 0 0 0"]
            c.check(not moving, f"drone {i}: {len(moving)} non-zero rc after SIGCONT ({moving[:3]})")
            details[f"drone{i}"]["rc_after_resume"] = len(resumed)
            t_down = first(phase_times(e, "landed", after=t_stop))
            details[f"drone{i}"]["down_ms"] = ms(None if t_down is None else t_down - t_stop)
        c.check(code not in (0, None), f"exit {code}: the resumed process did not end as taken over")
        c.check(
            "GuardianTakeoverError" in run.output or "guardian" in run.output, "no takeover in the output"
        )
        details["exit_code"] = code
    observed = "; ".join(
        f"drone {i}: rc 0 0 0 0 +{d['rc0_ms']} ms, land +{d['land_ms']} ms, down +{d['down_ms']} ms, "
        f"{d['rc_after_resume']} rc after SIGCONT"
        for i, d in per_drone(details)
    )
    observed += f"; exit {details.get('exit_code')}"
    expected = (
        f"the guardian takes over {STALL_S:g} s after the last heartbeat: rc 0 0 0 0 and land at every "
        "drone, both down; after SIGCONT the process is muted (no non-zero rc reaches a drone), ends non-zero"
    )
    return lab_result("agent_stopped", expected, observed, wall0, c, [], [], details, None)


def _stopped_and_down(lab: EmulatedLab, t_fault: float, c: Checks) -> dict[str, Any]:
    """Per drone: `rc 0 0 0 0` or `land` within STOP_S of t_fault, no non-zero rc after that first stop
    command, down within DOWN_S (not by the Tello's own auto-land). Returns the times in ms."""
    out: dict[str, Any] = {}
    for i, e in lab.tellos.items():
        t_rc0 = first(rc_times(e, after=t_fault, value=(0, 0, 0, 0)))
        t_land = first(command_times(e, "land", after=t_fault))
        stops = [t for t in (t_rc0, t_land) if t is not None]
        t_stop = min(stops) if stops else None
        stop = None if t_stop is None else t_stop - t_fault
        c.check(
            stop is not None and stop <= STOP_S, f"drone {i}: first rc 0 0 0 0 / land after {ms(stop)} ms"
        )
        moving = rc_times(e, after=t_stop, nonzero=True) if t_stop is not None else []
        c.check(not moving, f"drone {i}: {len(moving)} non-zero rc after the first stop command")
        t_down = first(phase_times(e, "landed", after=t_fault))
        down = None if t_down is None else t_down - t_fault
        c.check(
            down is not None and down <= DOWN_S, f"drone {i}: down after {ms(down)} ms (limit {DOWN_S:g} s)"
        )
        c.check(not e.landed_by_timeout, f"drone {i}: landed by the Tello's own auto-land")
        out[f"drone{i}"] = {
            "stop_ms": ms(stop),
            "rc0_ms": ms(None if t_rc0 is None else t_rc0 - t_fault),
            "land_ms": ms(None if t_land is None else t_land - t_fault),
            "down_ms": ms(down),
        }
    return out


def _summary(details: dict[str, Any]) -> str:
    parts = [
        f"drone {i}: rc 0 0 0 0 +{d['rc0_ms']} ms, land +{d['land_ms']} ms, down +{d['down_ms']} ms"
        for i, d in per_drone(details)
    ]
    return (
        "; ".join(parts) + f"; robot armed {details.get('robot_armed')}, speed {details.get('robot_speed')}"
    )


def guardian_killed(mission_path: Path, workdir: Path) -> FaultResult:
    """SIGKILL to the guardian of `flightstack fly` alone, 1 s into pursuit."""
    wall0 = time.perf_counter()
    root = workdir / "guardian_killed"
    c, details = Checks(), {}
    with EmulatedLab(root, duration_s=30.0) as lab:
        with FlyProcess(lab, root / "run") as fly:
            started = lab.wait_for_pursuit(PURSUIT_WAIT_S) is not None
            c.check(started, "the pursuit never started")
            t_kill = time.monotonic()
            guardians = guardian_pids(fly.proc.pid) if fly.proc is not None else []
            c.check(len(guardians) == 1, f"guardians of `fly`: {guardians}")
            if started and guardians:
                time.sleep(FAULT_AFTER_S)
                t_kill = time.monotonic()
                os.kill(guardians[0], signal.SIGKILL)
            code = fly.wait()
            _wait_down(lab, DOWN_WAIT_S)
            run = fly.result(code)
        lab.write_log(root / "emulators.json")
        c.check(code not in (0, None), f"exit {code}: the flight did not end as having lost its guardian")
        c.check(
            "GuardianLostError" in run.output,
            "the output does not say the guardian was lost",
        )
        details = _stopped_and_down(lab, t_kill, c) | _robot(lab, c)
        details["exit_code"] = code
        rec_problems = [] if run.metrics is not None else ["no metrics.json"]
        rec_problems += _killed_recording(run.run_dir, t_kill)
    expected = (
        f"the flight sees its guardian gone and lands: rc 0 0 0 0 or land within {STOP_S:g} s at every "
        f"drone, every drone down within {DOWN_S:g} s, the robot stopped and disarmed, exit non-zero, the "
        "recording and metrics written"
    )
    observed = _summary(details) + f"; exit {details.get('exit_code')}"
    return lab_result("guardian_killed", expected, observed, wall0, c, [], rec_problems, details, run.crashed)


ROWS = {
    "process_killed": process_killed,
    "agent_stopped": agent_stopped,
    "guardian_killed": guardian_killed,
}
