"""Flying the emulated lab (sim_backend/emulated_lab.py) for the fault table's rows, and judging it.

- `fly_inprocess(lab, run_dir, ...)`: the flight (flightstack.runtime.flight) in this process with the
  real hardware backend (drivers/lab/hardware.py, guardian process included) and the streaming recorder,
  like `flightstack fly --yes` without the preflight. Rows that reach into the drivers (socket errors),
  the bus (a stalled tick) or the recorder (ENOSPC) use it; `injector(backend)` runs on a thread of its
  own meanwhile.
- `FlyProcess(lab, run_dir)`: `flightstack fly MISSION --out DIR --yes` as a child process (preflight
  included), for rows that send signals or talk to it from another "terminal" (`flightstack abort`).
- `judge_lab_safety`, `judge_lab_recording`: the all-safe and recording verdicts of a lab row, judged at
  the emulators and on the run directory; `lab_result` builds the FaultResult; `drone_reaction` measures
  rc 0 0 0 0 / land / touchdown after an event at one emulator.

Units: times are time.monotonic() seconds (shared with child processes and the emulators' records);
durations in seconds; reaction times reported in milliseconds.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from flightstack.faults.result import Checks, FaultResult
from flightstack.faults.rows_cli import cli_command, cli_env
from flightstack.sim_backend.emulated_lab import (
    TRUTH_PERIOD_S,
    EmulatedLab,
    command_times,
    first,
    ms,
    phase_times,
    rc_times,
)

PROCESS_TIMEOUT_S = 120.0
"""Bound on any child process of a lab row (s); it is killed after that."""
PURSUIT_WAIT_S = 60.0
"""Longest wait for the pursuit to start (connect, takeoff, and for a child `fly` its preflight) (s)."""
FAULT_AFTER_S = 1.0
"""Faults start this long after the pursuit did (s)."""
REACT_S = 0.5
"""Bound on rc 0 0 0 0 and on land after a signal or an abort, where the drone accepts it (s)."""
ZERO = (0, 0, 0, 0)


# ---- flying: in this process -------------------------------------------------------------------------------
@dataclass
class LabRun:
    """One flight of the emulated lab: where it was written, what the runner returned and when it flew.

    t_start/t_end: time.monotonic() (s) around the flight (backend built → recording closed). rec and
    metrics: in-process flights (metrics.json as written); exit_code and output: `flightstack fly` in a
    child process (None: killed at the timeout). crashed: what escaped (in-process) or a traceback in
    the child's stderr."""

    run_dir: Path
    t_start: float = math.nan
    t_end: float = math.nan
    rec: Any = None
    metrics: dict[str, Any] | None = None
    exit_code: int | None = None
    output: str = ""
    crashed: str | None = None
    injector_error: str | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def events(self) -> list[dict[str, Any]]:
        """events.jsonl of the run (lines that do not parse are skipped; [] when absent)."""
        path = self.run_dir / "events.jsonl"
        out = []
        if path.is_file():
            for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
                try:
                    out.append(json.loads(line))
                except ValueError:
                    continue
        return out

    def safety(self, kind: str | None = None, drone: int | None = None) -> list[dict[str, Any]]:
        """Safety events of the run (of one kind / one drone), in file order."""
        evs = [e for e in self.events() if e.get("event") == "safety"]
        return [
            e for e in evs if (kind is None or e["kind"] == kind) and (drone is None or e["drone"] == drone)
        ]

    def end_reason(self) -> str | None:
        """The `end` event's reason, None if there is none."""
        ends = [e for e in self.events() if e.get("event") == "end"]
        return str(ends[0]["reason"]) if ends else None


def fly_inprocess(
    lab: EmulatedLab,
    run_dir: Path,
    *,
    bus_wrapper: Callable[[Any], Any] | None = None,
    injector: Callable[[Any], object] | None = None,
    injector_timeout_s: float = 60.0,
) -> LabRun:
    """Fly mode `none` of the lab's mission in this process through flightstack.runtime.flight (hardware
    backend, in-process bus with its operator listener, the run directory written as it flies,
    metrics.json), like `flightstack fly --yes` without the preflight. bus_wrapper(bus) may wrap the
    bus; injector(backend) runs on a daemon thread from the moment the backend is built (it must bound
    its own waits; joined for injector_timeout_s s). Never raises for the flight itself: an exception
    is `LabRun.crashed`."""
    from flightstack.runtime.flight import Flight

    run = LabRun(Path(run_dir), t_start=time.monotonic())
    errors: list[str] = []
    threads: list[threading.Thread] = []

    def start_injector(backend: Any) -> Any:
        if injector is not None:

            def inject() -> None:
                try:
                    injector(backend)
                except Exception:
                    errors.append(traceback.format_exc(limit=-3))

            threads.append(threading.Thread(target=inject, name="lab-injector", daemon=True))
            threads[-1].start()
        return backend

    try:
        with Flight(
            lab.mission(), run.run_dir, modes=["none"], wrap_backend=start_injector, wrap_bus=bus_wrapper
        ) as flight:
            res = flight.fly()
        run.rec = res.recordings.get("none")
        run.metrics = res.metrics
    except Exception as exc:
        run.crashed = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=-3)}"
    finally:
        for thread in threads:
            thread.join(injector_timeout_s)
        run.t_end = time.monotonic()
    run.injector_error = errors[0] if errors else None
    return run


# ---- flying: `flightstack fly` in a child process ----------------------------------------------------------
class FlyProcess:
    """`flightstack fly MISSION --out RUN_DIR --yes --no-progress` in a child process (a context manager;
    the child is killed on exit if still running). Its output goes to RUN_DIR.parent/fly.out / fly.err
    (files: a chatty child never blocks on a full pipe)."""

    def __init__(self, lab: EmulatedLab, run_dir: Path, *extra: str, python: str | None = None) -> None:
        """python: the interpreter to run it with (None: this one's, sys.executable)."""
        self.lab = lab
        self.python = python
        self.run_dir = Path(run_dir)
        self.args = (
            "fly",
            str(lab.mission_path),
            "--out",
            str(self.run_dir),
            "--yes",
            "--no-progress",
            *extra,
        )
        self.proc: subprocess.Popen[bytes] | None = None
        self.t_start = math.nan
        self.signals: list[tuple[float, str]] = []
        """(time.monotonic() just before sending, signal name) of every signal sent."""
        self._out = self.run_dir.parent / f"{self.run_dir.name}.fly.out"
        self._err = self.run_dir.parent / f"{self.run_dir.name}.fly.err"

    def __enter__(self) -> FlyProcess:
        self.run_dir.parent.mkdir(parents=True, exist_ok=True)
        with open(self._out, "wb") as out, open(self._err, "wb") as err:
            self.t_start = time.monotonic()
            cmd = cli_command(*self.args)
            cmd[0] = self.python or cmd[0]
            self.proc = subprocess.Popen(cmd, env=cli_env(), stdout=out, stderr=err)
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.kill()

    def alive(self) -> bool:
        """The child runs."""
        return self.proc is not None and self.proc.poll() is None

    def send(self, sig: signal.Signals) -> float:
        """Send `sig` to the child; the time.monotonic() just before (s)."""
        assert self.proc is not None
        t = time.monotonic()
        self.proc.send_signal(sig)
        self.signals.append((t, sig.name))
        return t

    def delivered(self, sig: signal.Signals, timeout_s: float = 2.0) -> bool:
        """Wait (≤ timeout_s s) until `sig` is no longer pending at the child (/proc/PID/status SigPnd and
        ShdPnd: the kernel handed it to the process); True if so, or where that cannot be read. A second
        signal of the same kind sent while the first is pending is merged into it (standard signals do not
        queue): on a loaded machine the child may not run for tens of ms."""
        assert self.proc is not None
        bit = 1 << (int(sig) - 1)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            try:
                status = Path(f"/proc/{self.proc.pid}/status").read_text()
                fields = dict(line.split(":", 1) for line in status.splitlines())
                pending = int(fields["SigPnd"], 16) | int(fields["ShdPnd"], 16)
            except (OSError, KeyError, ValueError):
                return True
            if not pending & bit:
                return True
            time.sleep(0.001)
        return False

    def wait(self, timeout_s: float = PROCESS_TIMEOUT_S) -> int | None:
        """Wait for the child's exit (s); its exit code, or None when it had to be killed."""
        assert self.proc is not None
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            return None

    def kill(self) -> None:
        """SIGKILL the child if it still runs, and reap it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            with suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=10.0)

    def output(self) -> str:
        """The child's stdout and stderr so far."""
        parts = []
        for p in (self._out, self._err):
            try:
                parts.append(p.read_text(encoding="utf-8", errors="replace"))
            except OSError:
                continue
        return "\n".join(parts)

    def result(self, exit_code: int | None) -> LabRun:
        """A LabRun of this child (crashed: a traceback in its output, or killed at the timeout)."""
        text = self.output()
        crashed = None
        if exit_code is None:
            crashed = f"`flightstack fly` did not exit within {PROCESS_TIMEOUT_S:g} s (killed)"
        elif "Traceback" in text:
            crashed = "traceback in `flightstack fly`'s output: " + text[text.index("Traceback") :][-1500:]
        metrics = None
        mpath = self.run_dir / "metrics.json"
        if mpath.is_file():
            try:
                metrics = json.loads(mpath.read_text())
            except ValueError:
                metrics = None
        return LabRun(
            self.run_dir,
            t_start=self.t_start,
            t_end=time.monotonic(),
            metrics=metrics,
            exit_code=exit_code,
            output=text,
            crashed=crashed,
        )


# ---- judging a lab run -------------------------------------------------------------------------------------
def judge_lab_safety(lab: EmulatedLab, run: LabRun) -> list[str]:
    """Problems with the drones' safety (empty: safe), judged at the emulators: every Tello on the ground
    at the end, none landed by its own 15 s auto-land (nothing of ours landed it), no true position (the
    emulator's, without `mocap_offset`) beyond the hard fence (the floor is not checked: landing is below
    it), a `landed` and no `NOT LANDED` event per drone."""
    from flightstack.faults.result import Checks
    from flightstack.runtime.runner import safety_limits
    from flightstack.safety import outside_hard_fence

    c = Checks()
    for i, e in lab.tellos.items():
        c.check(not e.flying, f"drone {i} still {e.phase} at the end (emulator)")
        c.check(not e.landed_by_timeout, f"drone {i} landed by the Tello's own 15 s auto-land")
    limits = safety_limits(lab.mission())
    beyond: dict[int, int] = {}
    for _, i, p in list(lab.truth):
        if outside_hard_fence(np.asarray(p), limits, check_floor=False):
            beyond[i] = beyond.get(i, 0) + 1
    c.check(not beyond, f"beyond the hard fence (true position) on {beyond} samples of {TRUTH_PERIOD_S} s")
    events = list(run.rec.events) if run.rec is not None else run.events()
    for i in lab.tellos:
        fates = [
            e["event"] for e in events if e.get("drone") == i and e.get("event") in ("landed", "NOT LANDED")
        ]
        c.check(fates == ["landed"], f"drone {i}: landed/NOT LANDED events {fates}")
    return c.failed


def judge_lab_recording(run: LabRun, complete: bool = True, min_ticks: int = 1) -> list[str]:
    """Problems with the run directory (empty: as expected): metrics.json with "recording": {"complete":
    `complete`}; timeseries_none.npz with every tick the metrics count (at least `min_ticks`), t/V_cmd/g_wi
    finite; the run's
    events (events.jsonl, or for an incomplete recording the flown Recording's) with one `end`, one
    `landed`/`NOT LANDED` per drone and the `safety tick` summary."""
    from flightstack.faults.result import Checks
    from flightstack.recording.timeseries import Recording

    c = Checks()
    m = run.metrics
    if not c.check(m is not None, "metrics.json not written"):
        return c.failed
    assert m is not None
    status = m.get("recording", {})
    c.check(status.get("complete") is complete, f"metrics recording {status}, expected complete={complete}")
    mode = m.get("modes", {}).get("none", m)
    ticks = int(mode.get("ticks", -1))
    npz = run.run_dir / "timeseries_none.npz"
    if c.check(npz.is_file(), "timeseries_none.npz not written"):
        rec = Recording.load(str(npz))
        k = rec.ticks_done
        c.check(k == ticks and k >= min_ticks, f"{k} ticks saved, metrics say {ticks} (at least {min_ticks})")
        if run.rec is not None:
            c.check(k == run.rec.ticks_done, f"{k} ticks saved, {run.rec.ticks_done} flown")
        for f in ("t", "V_cmd", "g_wi"):
            c.check(bool(np.all(np.isfinite(getattr(rec, f)[:k]))), f"{f} not finite")
    events = run.events() if complete or run.rec is None else list(run.rec.events)
    ends = [e for e in events if e.get("event") == "end"]
    c.check(len(ends) == 1, f"{len(ends)} end events")
    c.check(any(e.get("event") == "safety tick" for e in events), "no `safety tick` event")
    for i in {d for d in (e.get("drone") for e in events if e.get("event") in ("landed", "NOT LANDED"))}:
        n = sum(1 for e in events if e.get("drone") == i and e.get("event") in ("landed", "NOT LANDED"))
        c.check(n == 1, f"drone {i}: {n} landed/NOT LANDED events")
    c.check(
        any(e.get("event") in ("landed", "NOT LANDED") for e in events), "no landed/NOT LANDED event at all"
    )
    return c.failed


@contextmanager
def patched(obj: Any, name: str, value: Any) -> Iterator[None]:
    """Set `obj.name = value` for the block, then restore the previous value (fault injection)."""
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


# ---- building a row's result and common measurements ----------------------------------------------
def lab_result(
    name: str,
    expected: str,
    observed: str,
    wall0: float,
    reaction: Checks,
    safety: list[str],
    recording: list[str],
    details: dict[str, Any],
    crash: str | None,
) -> FaultResult:
    """The FaultResult of a row: the three problem lists (empty: fine) and what crashed, if anything."""
    problems = [f"reaction: {p}" for p in reaction.failed] + [f"safety: {p}" for p in safety]
    problems += [f"recording: {p}" for p in recording]
    if crash:
        problems.insert(0, f"crashed: {crash[-1500:]}")
    return FaultResult(
        name=name,
        expected=expected,
        observed=observed,
        all_safe=not safety,
        recording_complete=not recording,
        crashed=bool(crash),
        seconds=time.perf_counter() - wall0,
        reaction_ok=reaction.ok,
        problems=problems,
        details=details,
    )


def crash_of(run: LabRun) -> str | None:
    """What crashed in a flight: the run or the injector raised, or the child showed a traceback or had
    to be killed (None: nothing)."""
    return run.crashed or run.injector_error


def run_result(
    name: str,
    expected: str,
    observed: str,
    wall0: float,
    lab: EmulatedLab,
    run: LabRun,
    reaction: Checks,
    details: dict[str, Any],
    recording: list[str] | None = None,
) -> FaultResult:
    """lab_result of one flight on `lab`: the lab's safety judgement (judge_lab_safety), the recording's
    (`recording`, by default judge_lab_recording's of a complete run), its run directory in the details,
    its crash as the crash."""
    return lab_result(
        name,
        expected,
        observed,
        wall0,
        reaction,
        judge_lab_safety(lab, run),
        judge_lab_recording(run) if recording is None else recording,
        {"run_dir": str(run.run_dir), **details},
        crash_of(run),
    )


def emulator_errors(
    lab: EmulatedLab,
    c: Checks,
    blind: bool = False,
    unforeseen: Mapping[int, tuple[float, float]] | None = None,
) -> list[tuple[float, str, str, str]]:
    """A failed check per emulator that reported internal errors (the lab itself misbehaved) or, unless the
    row leaves the drivers `blind`, refused a command a real Tello refuses in its phase (`refused`: a land
    on the ground, rc to a drone busy in its takeoff or landing, …): what a driver that sees its drone
    sends must be what the drone accepts. blind: the row takes the drivers' telemetry away (a link loss,
    a guardian that cannot bind the state port); they then re-send `rc 0 0 0 0` and `land` on purpose,
    also to a drone already down (a real one answers `error Motor stop`), and that count is reported.
    unforeseen: per drone, a window (t0, t1) (monotonic s) in which the drone changed its phase by itself
    (a landing of its own) and the driver could not know yet: the rc it ignores then were sent before
    any telemetry said so, and are not counted. Returns those not counted."""
    excused: list[tuple[float, str, str, str]] = []
    for i, e in lab.tellos.items():
        c.check(not e.errors, f"emulator {i} reported errors: {e.errors[:3]}")
        t0, t1 = (unforeseen or {}).get(i, (0.0, -1.0))
        refused: list[tuple[float, str, str, str]] = []
        for r in e.refused:
            unseen = t0 <= r[0] <= t1 and r[2].startswith("rc ") and r[3] == "ignored"
            (excused if unseen else refused).append(r)
        c.check(blind or not refused, f"emulator {i} refused {len(refused)} commands: {refused[:3]}")
    return excused


def wait_then(lab: EmulatedLab, marks: dict[str, float], action: Callable[[], None]) -> bool:
    """Wait for the pursuit, FAULT_AFTER_S more, then mark "fault" and run `action`; False if the
    pursuit never started."""
    t = lab.wait_for_pursuit(PURSUIT_WAIT_S)
    if t is None:
        return False
    marks["pursuit"] = t
    time.sleep(FAULT_AFTER_S)
    marks["fault"] = time.monotonic()
    action()
    return True


def event_t(ev: dict[str, Any] | None) -> float | None:
    """An event's time `t` (s), None without an event."""
    return None if ev is None else float(ev["t"])


def sub(a: float | None, b: float | None) -> float | None:
    """a - b (s), None if either is unknown."""
    return None if a is None or b is None else a - b


def within(x: float | None, hi: float, lo: float = 0.0) -> bool:
    """lo <= x <= hi for a known x (s); False when x is None (the reaction never happened)."""
    return x is not None and lo <= x <= hi


def per_drone(details: dict[str, Any]) -> list[tuple[int, dict[str, Any]]]:
    """(id, its entry) of each drone a row's details hold (key `drone<id>`: DroneIdentity.name), by id."""
    found = [(int(k[5:]), v) for k, v in details.items() if k.startswith("drone") and k[5:].isdigit() and v]
    return sorted(found, key=lambda kv: kv[0])


def drone_reaction(emu: Any, t_cmd: float, c: Checks, who: str, hover_needed: bool = True) -> dict[str, Any]:
    """At one emulator after t_cmd (a signal, an abort, a takeoff completing): rc 0 0 0 0 (unless not
    `hover_needed`: no rc was ever in force) and land within REACT_S, no non-zero rc after the first
    control tick, down. Returns the times in ms."""
    t_hover = first(rc_times(emu, after=t_cmd, value=ZERO))
    t_land = first(command_times(emu, "land", after=t_cmd))
    hover, land = sub(t_hover, t_cmd), sub(t_land, t_cmd)
    if hover_needed:
        c.check(within(hover, REACT_S), f"{who}: rc 0 0 0 0 {hover} s after (limit {REACT_S:g} s)")
    c.check(within(land, REACT_S), f"{who}: land {land} s after (limit {REACT_S:g} s)")
    moving = rc_times(emu, after=t_cmd + 0.06, nonzero=True)
    c.check(not moving, f"{who}: {len(moving)} non-zero rc after")
    t_down = first(phase_times(emu, "landed", after=t_cmd))
    c.check(t_down is not None, f"{who}: never landed")
    return {"rc0_ms": ms(hover), "land_ms": ms(land), "down_ms": ms(sub(t_down, t_cmd))}


__all__ = [
    "FAULT_AFTER_S",
    "PROCESS_TIMEOUT_S",
    "PURSUIT_WAIT_S",
    "REACT_S",
    "ZERO",
    "FlyProcess",
    "LabRun",
    "crash_of",
    "drone_reaction",
    "emulator_errors",
    "event_t",
    "fly_inprocess",
    "judge_lab_recording",
    "judge_lab_safety",
    "lab_result",
    "patched",
    "run_result",
    "sub",
    "wait_then",
    "within",
]
