"""What `run` and `report` print about a run: its metrics from metrics.json, by one function for both, and
the console's levels.

Every message line on the console starts with its level (LEVELS): `info:` a fact, `note:` something that
can look like a failure but is expected (why, and where to read more), `warning:` something unexpected
that did not stop the run, `error:` a failure (the exit code is not 0). The result lines (`metric_lines`,
on stdout) are data; under a figure that can look like a failure comes an indented `note:` or `warning:`
line. docs/logs.md ("What a run prints") shows an annotated example.
"""

from __future__ import annotations

import logging
import sys
from collections import Counter
from collections.abc import Mapping
from typing import Any, Literal, TextIO

from tqdm import tqdm

from flightstack.analysis.loop_health import loop_health_line
from flightstack.config.mission import Mission
from flightstack.events import KINDS

Level = Literal["info", "note", "warning", "error"]
LEVELS: tuple[Level, ...] = ("info", "note", "warning", "error")
"""The console's levels, lowest first (docs/logs.md, "What a run prints")."""

_NOTE = "      note: "  # under a result line: indented past the mode's name
_WARNING = "      warning: "


def console_print(line: str, stream: TextIO | None = None) -> None:
    """One line on `stream` (default sys.stderr) above the progress bars drawn there: tqdm clears them,
    the line is printed on a line of its own, and they are drawn again below it."""
    tqdm.write(line, file=sys.stderr if stream is None else stream)


def say(level: Level, text: str, stream: TextIO | None = None) -> None:
    """One message line `<level>: <text>` on `stream` (default sys.stderr), above any progress bar."""
    console_print(f"{level}: {text}", stream)


def with_level(line: str, default: Level = "info") -> str:
    """`line` as a console message: unchanged when it already starts with a level, else `<default>: line`."""
    if any(line.startswith(f"{lv}: ") for lv in LEVELS):
        return line
    return f"{default}: {line}"


class ConsoleFormatter(logging.Formatter):
    """A log record as `<level>: <logger>: <message>`, the level in the console's words (LEVELS): DEBUG and
    INFO are `info`, WARNING `warning`, ERROR and CRITICAL `error`."""

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno >= logging.ERROR:
            level = "error"
        elif record.levelno >= logging.WARNING:
            level = "warning"
        else:
            level = "info"
        return f"{level}: {record.name}: {record.getMessage()}"


class ConsoleHandler(logging.StreamHandler):
    """A log record as one line above the progress bars (console_print), never inside a bar's line."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            console_print(self.format(record), self.stream)
            self.flush()
        except Exception:
            self.handleError(record)


def console_logging() -> None:
    """Log records on stderr through ConsoleFormatter, above the progress bars (ConsoleHandler): warnings
    and errors of any logger, and every safety event as it happens (`flightstack.safety`, each at its
    kind's severity: flightstack.events.KINDS, so a takeoff is `info` and a fence `warning`). Once per
    process: nothing changes when the root logger already has a handler."""
    handler = ConsoleHandler(sys.stderr)
    handler.setFormatter(ConsoleFormatter())
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    logging.getLogger("flightstack.safety").setLevel(logging.INFO)


def metric_lines(m: Mapping[str, Any], mission: Mission | None) -> list[str]:
    """The run's metrics as `run` and `report` print them (same names, numbers and order): per mode its
    ticks, both error metrics, the position error and how often each drone saw the target, the fence and
    the loop's health; the paper's comparison, the gain condition, the safety events, whether the
    recording is complete and, last, whether a signal ended the run. A figure that can look like a failure
    gets a `note:` (expected: why, where to read more) or `warning:` line under it. `mission` (the run's,
    for what its drones can see) may be None."""
    lines: list[str] = []
    blind_noted = False
    for mode, mm in (m.get("modes") or {}).items():
        line = f"  {mode:7s} {int(mm.get('ticks', 0)):7d} ticks   mean_sq_error = {_e(mm, 'mean_sq_error')}"
        line += f"   sq_mean_error = {_e(mm, 'sq_mean_error')}"
        seen = mm.get("visible_fraction") or {}
        if "mean_position_error_m" in mm and seen:
            shown = ", ".join(f"{i}: {100 * f:.0f} %" for i, f in seen.items())
            line += f"   mean position error {mm['mean_position_error_m']:.3f} m   target seen {shown}"
        fence = mm.get("max_fence_excursion_m")
        if fence:
            line += f"   OUTSIDE FENCE by {fence:.3f} m"
        lines.append(line)
        if mm.get("error"):
            lines.append(f"{_WARNING}mode {mode} ended early: {mm['error']}")
        if fence:
            lines.append(
                f"{_WARNING}a drone flew beyond the soft fence; the safety layer clipped its outward "
                "velocity (fence_soft in events.jsonl; docs/safety.md)"
            )
        if not blind_noted and seen and mission is not None:
            notes = _seen_notes(seen, mission)
            lines += notes
            blind_noted = bool(notes)
        gate = {i: c for i, c in (mm.get("vision_gate") or {}).items() if c.get("rejected")}
        if gate:  # detections off their prediction: the observer coasted (docs/equations.md §12)
            shown = ", ".join(f"{i}: {c['rejected']} of {c.get('detections', 0)}" for i, c in gate.items())
            lines.append(f"          detections off their prediction (the observer coasted): {shown}")
        health = mm.get("loop_health")
        if health and health.get("real_time"):  # a simulated clock's wall period only says how fast it ran
            verdict = "kept dt" if health["keeps_dt"] else "DID NOT keep dt"
            lines.append(f"          loop {verdict}: {loop_health_line(health)}")
            if not health["keeps_dt"]:
                lines.append(_late_loop_note(mission))
    if "paper" in m:  # the paper's "squared mean of e" beside the same quantity here (docs: paper comparison)
        lines.append("  the paper's squared mean of e (Sec. 5) beside ours (sq_mean_error):")
        for mode, v in m["paper"]["modes"].items():
            lines.append(f"    {mode:10s} ours {v['ours']:9.2e}   paper {v['paper']:9.2e}")
        for name, v in m["paper"]["ratios"].items():
            lines.append(f"    {name:10s} ours {v['ours']:9.2f}   paper {v['paper']:9.2f}")
        lines.append(
            f"{_NOTE}expected: the absolute values cannot match the paper's; compare the ratios, over seeds "
            "(docs/paper-comparison.md#why-the-absolute-values-cannot-match)"
        )
    if "mean_sq_error" in m.get("ratios", {}):
        cols = "   ".join(f"{k} {v:.2f}" for k, v in m["ratios"]["mean_sq_error"].items())
        lines.append(f"  ratios of mean_sq_error (the paper reports none): {cols}")
    lines += _gain_lines(m.get("gain_condition") or {"evaluated": False})
    lines += _safety_lines(m.get("safety_events") or [])
    rs = m.get("recording") or {}
    if rs:
        state = "complete" if rs.get("complete") else f"INCOMPLETE: {rs.get('reason')}"
        if rs.get("complete") and m.get("interrupted"):
            state += " up to the interrupt"
        lines.append(f"  recording {state}")
    if m.get("interrupted"):
        lines.append(_interrupted_line(m.get("modes") or {}, mission))
    return lines


def _interrupted_line(modes: Mapping[str, Mapping[str, Any]], mission: Mission | None) -> str:
    """The last metric line of a run a signal ended: in which mode, how far, and the modes not flown."""
    cut = [(mode, mm) for mode, mm in modes.items() if mm.get("interrupted")]
    if cut:
        mode, mm = cut[0]
        where = f"in mode {mode} after {float(mm.get('sim_seconds', 0.0)):.1f} s"
        where += f" of {mission.duration_s:g} s" if mission is not None else ""
    else:  # between modes, in training, or while a mode's fleet was assembled
        where = f"after mode {list(modes)[-1]}" if modes else "before any mode flew"
    line = f"  INTERRUPTED (Ctrl-C or another signal) {where}"
    unflown = [mode for mode in (mission.compare_modes if mission else []) if mode not in modes]
    return line + (f"; not flown: {', '.join(unflown)}" if unflown else "")


def _e(mm: Mapping[str, Any], key: str) -> str:
    v = mm.get(key)
    return f"{float('nan') if v is None else v:.3e}"


def _seen_notes(seen: Mapping[str, float], mission: Mission) -> list[str]:
    """Under the first `target seen`: why a drone saw the target 0 % of the time, from the mission: by
    design (`sees_target: false`: a note) or not (a warning)."""
    can = {str(d.id): d.sees_target for d in mission.drones}
    out = []
    for i, f in seen.items():
        if f > 0.0 or i not in can:
            continue
        if not can[i]:
            out.append(
                f"{_NOTE}expected: drone {i} never sees the target by design (`sees_target: false` in "
                f"{mission.name}): it follows the target through its neighbours' estimates "
                "(docs/experiments.md#the-simulated-lab-paper-sec-6)"
            )
        else:
            out.append(
                f"{_WARNING}drone {i} never saw the target, although its experiment says it can: check its "
                "camera mount, its desired pose and vision_rejections in metrics.json"
            )
    return out


def _late_loop_note(mission: Mission | None) -> str:
    """Under `loop DID NOT keep dt`: on the emulated lab (the emulators share this computer) a note, on real
    drones a warning (every command was late)."""
    where = "docs/real-lab.md#loop-health"
    if mission is not None and mission.start_emulators:
        return (
            f"{_NOTE}the emulated lab's emulators share this computer: a busy machine makes the loop late, "
            f"which on real drones would delay every command ({where})"
        )
    return f"{_WARNING}the control loop ran late: every command reached the drones late ({where})"


def _gain_lines(gc: Mapping[str, Any]) -> list[str]:
    where = "docs/paper-comparison.md#gain-analysis"
    if not gc.get("evaluated", True):
        return [
            f"  gain condition: not evaluated ({gc.get('reason') or 'no GP expert'})",
            f"{_NOTE}expected without GP experts (no GP mode, or none trained): kappa needs them ({where})",
        ]
    verdict = "satisfied" if gc["satisfied"] else "NOT satisfied"
    lines = [
        f"  gain condition: kappa = {gc['kappa']:.3f} ({verdict}), L_mu = {gc['L_mu']:.3f}, "
        f"lambda_H = {gc['lambda_H']:.3f}"
    ]
    if not gc["satisfied"]:
        lines.append(
            f"{_NOTE}not a fault of the run: Theorem 1's condition is sufficient, not necessary, and the "
            f"paper's own experiment gains do not meet it either ({where}; docs/architecture.md decision 18)"
        )
    return lines


def _safety_lines(events: list[Mapping[str, Any]]) -> list[str]:
    """The count of safety events by severity (flightstack.events.KINDS; a kind this version does not
    declare counts as a warning), and a warning naming the kinds above INFO (each was printed on stderr as
    it happened)."""
    level = {
        e.get("kind"): KINDS[e["kind"]].severity if e.get("kind") in KINDS else "WARNING" for e in events
    }
    by = Counter(level[e.get("kind")] for e in events)
    parts = [f"{by[s]} {s.lower()}" for s in ("ERROR", "WARNING", "INFO") if by[s]]
    lines = [f"  safety events: {len(events)} (events.jsonl{'; ' + ', '.join(parts) if parts else ''})"]
    acted = Counter(str(e.get("kind")) for e in events if level[e.get("kind")] != "INFO")
    if acted:
        shown = ", ".join(f"{k} x{n}" for k, n in sorted(acted.items()))
        lines.append(
            f"{_WARNING}safety rules acted: {shown} (what each kind means: docs/logs.md#the-run-directory; "
            "the rules: docs/safety.md)"
        )
    return lines
