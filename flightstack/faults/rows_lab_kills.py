"""The fault table's kill rows: an operator's `pkill -9` by name, and every order in which the flight and
its guardian can both die, on the emulated lab.

- `pkill_*`: the processes that `pkill -9 [-f] PATTERN` would select (the real `pgrep [-f] PATTERN`),
  restricted to the flight's own process tree and its guardian (never this process or anything else on
  the machine), SIGKILLed by pid 1 s into pursuit. The flight runs as `<environment>/bin/python3 -m
  flightstack fly` so that every pattern selects it; the guardian (drivers/guardian/) must be selected
  by none and land everything.
- `both_killed_pursuit`, `both_killed_climb`: the flight and its guardian SIGKILLed by pid (the guardian
  first, then the flight at once: what the out-of-memory killer or a session's end can do) 1 s into
  pursuit, and while the drones climb just after takeoff. Nothing of ours is left: only the Tello's own
  auto-land, so the climb each drone's last `rc` may still carry it is bounded by the safety layer's
  `climb_limited` rule (flightstack/safety/rules.climb_cap); measured: the highest true z before it is
  down against the fence's ceiling plus its hard margin. The robot is left to its own GCS failsafe.
- `killed_guardian_stopped`: the guardian SIGSTOPped, then the flight SIGKILLed before it notices
  (its guardian is silent for GUARDIAN_SILENT_S first): the same bound; the guardian is killed after.

Times are time.monotonic() seconds shared with the emulators, reported in milliseconds in `details`;
heights in m in the world frame Σw (motion capture's truth, without `mocap_offset`).
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from flightstack.faults.lab_flight import FAULT_AFTER_S, PURSUIT_WAIT_S, FlyProcess, lab_result, per_drone
from flightstack.faults.result import Checks, FaultResult, FaultRow
from flightstack.faults.rows_lab_process import command_line, descendants, guardian_pids
from flightstack.sim_backend.emulated_lab import EmulatedLab, command_times, first, ms, phase_times, rc_times

STOP_S = 0.5
"""`pkill_*`: the first `rc 0 0 0 0` or `land` at every drone within this after the kill (s)."""
DOWN_S = 8.0
"""`pkill_*`: every drone down within this (s), far below the Tello's own 15 s auto-land."""
DISARM_S = 2.0
"""`pkill_*`: the robot disarmed within this (s)."""
AUTO_LAND_WAIT_S = 24.0
"""Rows that leave the drones to their own auto-land (15 s after the last command, then the descent)
wait this long for them to be down (s)."""
CLIMB_WAIT_S = 3.0
"""`both_killed_climb`: longest wait after the pursuit started for an upward rc at every drone (s)."""
STOPPED_KILL_S = 0.2
"""`killed_guardian_stopped`: the flight is killed this long after its guardian was stopped (s): before
it sees the guardian silent (drivers/guardian.GUARDIAN_SILENT_S)."""
POLL_S = 0.005
"""How often the rows look at the robot's arming and the drones' phases (s)."""

PATTERNS: dict[str, tuple[str, ...]] = {
    "pkill_python": ("python",),
    "pkill_python3": ("python3",),
    "pkill_f_python": ("-f", "python"),
    "pkill_f_flightstack": ("-f", "flightstack"),
    "pkill_f_venv": ("-f", sys.prefix),
}
"""Each row's `pgrep` arguments: the pattern of `pkill -9 ...` (the last, the environment's path)."""


def python3() -> str:
    """This environment's `python3` (what an operator types; its process name matches "python" and
    "python3"), else this interpreter."""
    exe = os.path.join(os.path.dirname(sys.executable), "python3")
    return exe if os.access(exe, os.X_OK) else sys.executable


def pgrep(args: tuple[str, ...]) -> set[int]:
    """The pids `pgrep ARGS` selects (the real pgrep, so the real matching rules); empty when none."""
    out = subprocess.run(["pgrep", *args], capture_output=True, text=True, timeout=10.0, check=False)
    if out.returncode not in (0, 1):
        raise RuntimeError(f"pgrep {' '.join(args)} exited {out.returncode}: {out.stderr.strip()}")
    return {int(w) for w in out.stdout.split()}


def process_name(pid: int) -> str:
    """/proc/PID/comm ("" once the process is gone)."""
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return ""


def kill_pids(pids: list[int], sig: signal.Signals = signal.SIGKILL) -> float:
    """Send `sig` to each pid in order (a gone one is skipped); time.monotonic() just before the first."""
    t = time.monotonic()
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            continue
    return t


def _watch(lab: EmulatedLab, timeout_s: float) -> float | None:
    """Wait until every drone is down and the robot disarmed (or timeout_s, s), looking every POLL_S;
    when the robot was first seen disarmed (time.monotonic(), None: never)."""
    t_disarmed = None
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if t_disarmed is None and lab.rover is not None and not lab.rover.armed:
            t_disarmed = time.monotonic()
        if t_disarmed is not None and not any(e.flying for e in lab.tellos.values()):
            break
        time.sleep(POLL_S)
    return t_disarmed


def positions(lab: EmulatedLab, i: int, after: float, before: float) -> list[tuple[float, float, float]]:
    """Drone i's true positions (m, Σw) sampled within [after, before] (s)."""
    return [p for t, j, p in list(lab.truth) if j == i and after <= t <= before]


def _rise(lab: EmulatedLab, t_fault: float, c: Checks, ceiling: float) -> dict[str, Any]:
    """Per drone: z at the fault, the highest z before it is down and the largest horizontal distance from
    where it was at the fault (m), when it is down and how (auto-land);
        a failed check when it went above `ceiling` (the hard fence's, m)."""
    out: dict[str, Any] = {}
    for i, e in lab.tellos.items():
        t_down = first(phase_times(e, "landed", after=t_fault))
        c.check(t_down is not None, f"drone {i}: not down")
        before = positions(lab, i, t_fault - 0.2, t_fault)
        p0 = before[-1] if before else None
        z0 = None if p0 is None else p0[2]
        ps = positions(lab, i, t_fault, t_down if t_down is not None else time.monotonic())
        z_max = max(p[2] for p in ps) if ps else None
        drift = max((math.hypot(p[0] - p0[0], p[1] - p0[1]) for p in ps), default=None) if p0 else None
        c.check(
            z_max is not None and z_max <= ceiling,
            f"drone {i}: up to z {z_max} m before it was down (limit {ceiling:g} m)",
        )
        out[f"drone{i}"] = {
            "z_kill_m": None if z0 is None else round(z0, 3),
            "z_max_m": None if z_max is None else round(z_max, 3),
            "rise_m": None if z0 is None or z_max is None else round(z_max - z0, 3),
            "drift_xy_m": None if drift is None else round(drift, 3),
            "down_ms": ms(None if t_down is None else t_down - t_fault),
            "auto_land": bool(e.landed_by_timeout),
        }
    return out


def _ceiling(lab: EmulatedLab) -> float:
    """The hard fence's ceiling of the lab's mission (m, Σw): the fence's plus its hard margin."""
    from flightstack.runtime.fleet import safety_limits

    return float(safety_limits(lab.mission()).hard_hi[2])


def _robot_alone(lab: EmulatedLab, t_fault: float) -> dict[str, Any]:
    """What the robot's own failsafes did once nobody sent it a heartbeat or a pose (ms after the fault).
    The pose feed stops with the flight's process, so the EKF failsafe holds the robot after 1 s; ArduPilot's
    GCS failsafe then does not act in HOLD (`Rover::failsafe_trigger`, FS_OPTIONS bit 0 unset)."""
    rover = lab.rover
    t_fs = rover.failsafe_t
    t_ekf = next((t for t, _, text in rover.statustexts if text == "EKF failsafe" and t >= t_fault), None)
    return {
        "robot_failsafe_ms": ms(None if t_fs is None else t_fs - t_fault),
        "robot_failsafe_action": rover.failsafe_action,
        "robot_ekf_failsafe_ms": ms(None if t_ekf is None else t_ekf - t_fault),
        "robot_mode": rover.mode,
        "robot_armed": bool(rover.armed),
        "robot_speed": max(abs(v) for v in rover.velocity),
    }


def _summary(details: dict[str, Any], keys: tuple[str, ...]) -> str:
    parts = [f"drone {i}: " + ", ".join(f"{k} {d.get(k)}" for k in keys) for i, d in per_drone(details)]
    return "; ".join(parts)


# ---- pkill by pattern ----------------------------------------------------------------------------------
def _pkill(name: str, workdir: Path) -> FaultResult:
    wall0 = time.perf_counter()
    args = PATTERNS[name]
    root = workdir / name
    c = Checks()
    details: dict[str, Any] = {}
    with EmulatedLab(root, duration_s=30.0) as lab:
        with FlyProcess(lab, root / "run", python=python3()) as fly:
            assert fly.proc is not None
            started = lab.wait_for_pursuit(PURSUIT_WAIT_S) is not None
            c.check(started, "the pursuit never started")
            t_kill, killed, guardians = time.monotonic(), [], guardian_pids(fly.proc.pid)
            names = {pid: process_name(pid) for pid in guardians}
            lines = {pid: command_line(pid) for pid in guardians}
            if started:
                time.sleep(FAULT_AFTER_S)
                ours = {fly.proc.pid, *descendants(fly.proc.pid)}
                guardians = guardian_pids(fly.proc.pid)
                names = {pid: process_name(pid) for pid in ours}
                lines = {pid: command_line(pid) for pid in guardians}
                killed = sorted(pgrep(args) & ours)
                t_kill = kill_pids(killed)
            c.check(len(guardians) == 1, f"guardians of `fly`: {guardians}")
            c.check(fly.proc.pid in killed, f"`pgrep {' '.join(args)}` did not select `fly` ({names})")
            c.check(not set(guardians) & set(killed), f"`pgrep {' '.join(args)}` selected the guardian")
            t_disarmed = _watch(lab, DOWN_S + 2.0)
            code = fly.wait()
        time.sleep(0.3)
        lab.write_log(root / "emulators.json")
        c.check(code == -signal.SIGKILL, f"exit {code}")
        for i, e in lab.tellos.items():
            t_rc0 = first(rc_times(e, after=t_kill, value=(0, 0, 0, 0)))
            t_land = first(command_times(e, "land", after=t_kill))
            stops = [t for t in (t_rc0, t_land) if t is not None]
            stop = min(stops) - t_kill if stops else None
            c.check(stop is not None and stop <= STOP_S, f"drone {i}: first stop command after {ms(stop)} ms")
            moving = rc_times(e, after=min(stops), nonzero=True) if stops else []
            c.check(not moving, f"drone {i}: {len(moving)} non-zero rc after the first stop command")
            t_down = first(phase_times(e, "landed", after=t_kill))
            down = None if t_down is None else t_down - t_kill
            c.check(down is not None and down <= DOWN_S, f"drone {i}: down after {ms(down)} ms")
            c.check(not e.landed_by_timeout, f"drone {i}: landed by the Tello's own auto-land")
            details[f"drone{i}"] = {
                "stop_ms": ms(stop),
                "land_ms": ms(None if t_land is None else t_land - t_kill),
                "down_ms": ms(down),
            }
        disarm = None if t_disarmed is None else t_disarmed - t_kill
        c.check(disarm is not None and disarm <= DISARM_S, f"robot disarmed after {ms(disarm)} ms")
        details["disarm_ms"] = ms(disarm)
        details["robot_speed"] = max(abs(v) for v in lab.rover.velocity)
        c.check(details["robot_speed"] < 1e-6, f"the robot still moves at {details['robot_speed']}")
        details["pattern"] = " ".join(args)
        details["killed"] = {str(pid): names.get(pid, "") for pid in killed}
        details["guardian"] = {str(pid): f"{names.get(pid, '')}: {lines.get(pid, '')}" for pid in guardians}
    expected = (
        f"`pkill -9 {' '.join(args)}` takes the flight, never its guardian (process name and command line "
        f"match no such pattern): first `rc 0 0 0 0` or `land` within {STOP_S:g} s at every drone, every "
        f"drone down within {DOWN_S:g} s, the robot disarmed within {DISARM_S:g} s"
    )
    observed = f"killed {sorted(details.get('killed', {}).values())}; "
    observed += _summary(details, ("stop_ms", "land_ms", "down_ms"))
    observed += f"; disarm {details.get('disarm_ms')} ms"
    return lab_result(name, expected, observed, wall0, c, [], [], details, None)


def pkill_python(mission_path: Path, workdir: Path) -> FaultResult:
    """`pkill -9 python` (process names; this row's flight and guardian only) 1 s into pursuit."""
    return _pkill("pkill_python", workdir)


def pkill_python3(mission_path: Path, workdir: Path) -> FaultResult:
    """`pkill -9 python3` (process names; this row's flight and guardian only) 1 s into pursuit."""
    return _pkill("pkill_python3", workdir)


def pkill_f_python(mission_path: Path, workdir: Path) -> FaultResult:
    """`pkill -9 -f python` (command lines; this row's flight and guardian only) 1 s into pursuit."""
    return _pkill("pkill_f_python", workdir)


def pkill_f_flightstack(mission_path: Path, workdir: Path) -> FaultResult:
    """`pkill -9 -f flightstack` (command lines; this row's flight and guardian only) 1 s into pursuit."""
    return _pkill("pkill_f_flightstack", workdir)


def pkill_f_venv(mission_path: Path, workdir: Path) -> FaultResult:
    """`pkill -9 -f <the environment's path>` (this row's flight and guardian only) 1 s into pursuit."""
    return _pkill("pkill_f_venv", workdir)


# ---- nothing of ours left --------------------------------------------------------------------------------
def _wait_upward_rc(lab: EmulatedLab, after: float, timeout_s: float) -> bool:
    """Wait until every drone received an rc with its up/down stick up since `after` (s)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if all(any(t > after and rc[2] > 0 for t, rc in list(e.rc_history)) for e in lab.tellos.values()):
            return True
        time.sleep(0.01)
    return False


def _alone(name: str, workdir: Path, when: str, order: str) -> FaultResult:
    """Both processes gone (`order`: "both" SIGKILLs the guardian then the flight; "stopped" SIGSTOPs the
    guardian, SIGKILLs the flight STOPPED_KILL_S later) `when` ("pursuit": FAULT_AFTER_S into pursuit,
    "climb": at the first upward rc after the pursuit started)."""
    wall0 = time.perf_counter()
    root = workdir / name
    c = Checks()
    details: dict[str, Any] = {}
    with EmulatedLab(root, duration_s=40.0) as lab:
        ceiling = _ceiling(lab)
        with FlyProcess(lab, root / "run") as fly:
            assert fly.proc is not None
            t_pursuit = lab.wait_for_pursuit(PURSUIT_WAIT_S, n_rc=1 if when == "climb" else 10)
            c.check(t_pursuit is not None, "the pursuit never started")
            guardians = guardian_pids(fly.proc.pid)
            c.check(len(guardians) == 1, f"guardians of `fly`: {guardians}")
            t_kill = time.monotonic()
            if t_pursuit is not None and guardians:
                if when == "climb":
                    climbing = _wait_upward_rc(lab, t_pursuit - 1.0, CLIMB_WAIT_S)
                    c.check(climbing, "no upward rc after takeoff")
                else:
                    time.sleep(FAULT_AFTER_S)
                if order == "stopped":
                    t_stop = kill_pids(guardians, signal.SIGSTOP)
                    time.sleep(STOPPED_KILL_S)
                    t_kill = kill_pids([fly.proc.pid])
                    details["stop_to_kill_ms"] = ms(t_kill - t_stop)
                else:
                    t_kill = kill_pids([*guardians, fly.proc.pid])
            code = fly.wait()
            t_end = time.monotonic() + AUTO_LAND_WAIT_S
            while time.monotonic() < t_end and any(e.flying for e in lab.tellos.values()):
                time.sleep(0.05)
            details |= _rise(lab, t_kill, c, ceiling) | _robot_alone(lab, t_kill)
            kill_pids(guardians, signal.SIGKILL)  # a stopped guardian: never resumed (it would land them)
        lab.write_log(root / "emulators.json")
        c.check(code == -signal.SIGKILL, f"exit {code}")
        details["ceiling_m"] = ceiling
        rises = [d["rise_m"] for k, d in details.items() if re.fullmatch(r"drone\d+", k)]
        details["largest_rise_m"] = max((r for r in rises if r is not None), default=None)
    what = "stopped guardian, flight killed" if order == "stopped" else "flight and guardian killed"
    expected = (
        f"{what} ({when}): nothing of ours is left, the drones fly their last rc until their own auto-land; "
        f"no drone above the hard fence's ceiling ({ceiling:g} m) before it is down; the robot's own "
        "failsafes hold it (EKF: its pose feed stopped; else GCS: its heartbeat stopped)"
    )
    observed = _summary(details, ("z_kill_m", "z_max_m", "rise_m", "drift_xy_m", "down_ms"))
    observed += f"; robot EKF failsafe +{details.get('robot_ekf_failsafe_ms')} ms, GCS failsafe "
    observed += f"+{details.get('robot_failsafe_ms')} ms (FS_ACTION {details.get('robot_failsafe_action')}), "
    observed += f"mode {details.get('robot_mode')}, speed {details.get('robot_speed')}"
    return lab_result(name, expected, observed, wall0, c, [], [], details, None)


def both_killed_pursuit(mission_path: Path, workdir: Path) -> FaultResult:
    """The guardian and `flightstack fly` SIGKILLed by pid together, 1 s into pursuit."""
    return _alone("both_killed_pursuit", workdir, "pursuit", "both")


def both_killed_climb(mission_path: Path, workdir: Path) -> FaultResult:
    """The guardian and `flightstack fly` SIGKILLed by pid together at the first upward rc after takeoff."""
    return _alone("both_killed_climb", workdir, "climb", "both")


def killed_guardian_stopped(mission_path: Path, workdir: Path) -> FaultResult:
    """The guardian SIGSTOPped, `flightstack fly` SIGKILLed STOPPED_KILL_S later, 1 s into pursuit."""
    return _alone("killed_guardian_stopped", workdir, "pursuit", "stopped")


ROWS: dict[str, FaultRow] = {
    "pkill_python": pkill_python,
    "pkill_python3": pkill_python3,
    "pkill_f_python": pkill_f_python,
    "pkill_f_flightstack": pkill_f_flightstack,
    "pkill_f_venv": pkill_f_venv,
    "both_killed_pursuit": both_killed_pursuit,
    "both_killed_climb": both_killed_climb,
    "killed_guardian_stopped": killed_guardian_stopped,
}
"""The kill rows, in table order."""
