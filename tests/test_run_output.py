"""What `run` and `report` print (flightstack.cli.summary): the same metric lines from one function, each
message with its level, and a figure that can look like a failure explained under it."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from tqdm import tqdm

from flightstack.cli import app as cli
from flightstack.cli.summary import LEVELS, ConsoleFormatter, ConsoleHandler, metric_lines, with_level
from flightstack.config.mission import load_mission
from flightstack.learning.training import minimum_duration, training_shortfall
from tests.conftest import terminal_lines

GAIN_DOC = "docs/paper-comparison.md#gain-analysis"


def _metrics(satisfied: bool, seen: dict[str, float]) -> dict[str, Any]:
    """A made-up metrics.json of one mode (the fields metric_lines reads)."""
    mode = {"ticks": 100, "mean_sq_error": 1e-3, "sq_mean_error": 2e-4, "mean_position_error_m": 0.05}
    mode["visible_fraction"] = seen
    gc = {"evaluated": True, "kappa": 2.0 if satisfied else -21.0, "L_mu": 11.4, "lambda_H": 0.68}
    events = [{"kind": "takeoff"}, {"kind": "fence_soft"}, {"kind": "land"}]
    return {
        "modes": {"none": mode},
        "gain_condition": {**gc, "satisfied": satisfied},
        "safety_events": events,
        "recording": {"complete": True, "reason": None},
    }


def test_a_drone_blind_by_design_gets_a_note_and_a_seeing_one_a_warning() -> None:
    """paper_experiment's drone 2 has `sees_target: false`: its 0 % is expected, derived from the mission
    (not from a drone number); a drone that can see and never did gets a warning."""
    mission = load_mission("paper_experiment")
    blind = [str(d.id) for d in mission.drones if not d.sees_target]
    seeing = [str(d.id) for d in mission.drones if d.sees_target]
    assert blind and seeing
    lines = metric_lines(_metrics(False, {seeing[0]: 1.0, blind[0]: 0.0}), mission)
    assert f"{blind[0]}: 0 %" in lines[0]
    assert lines[1].strip().startswith("note: expected:") and "`sees_target: false`" in lines[1]
    lines = metric_lines(_metrics(False, {seeing[0]: 0.0, blind[0]: 0.0}), mission)
    assert lines[1].strip().startswith(f"warning: drone {seeing[0]} never saw the target")
    assert lines[2].strip().startswith(f"note: expected: drone {blind[0]}")


def test_an_unmet_gain_condition_and_rules_that_acted_say_so_on_the_next_line() -> None:
    lines = metric_lines(_metrics(False, {}), None)
    (k,) = [i for i, ln in enumerate(lines) if "gain condition:" in ln]
    assert "(NOT satisfied)" in lines[k] and lines[k + 1].strip().startswith("note: not a fault")
    assert GAIN_DOC in lines[k + 1]
    (s,) = [i for i, ln in enumerate(lines) if "safety events:" in ln]
    assert lines[s] == "  safety events: 3 (events.jsonl; 1 warning, 2 info)"
    assert lines[s + 1].strip() == (
        "warning: safety rules acted: fence_soft x1 (what each kind means: docs/logs.md#the-run-directory; "
        "the rules: docs/safety.md)"
    )
    lines = metric_lines(_metrics(True, {}), None)
    (k,) = [i for i, ln in enumerate(lines) if "gain condition:" in ln]
    assert "(satisfied)" in lines[k] and "note:" not in lines[k + 1]


def test_a_message_keeps_its_level_or_gets_info() -> None:
    assert with_level("error: boom") == "error: boom"
    assert with_level("emulated lab: 2 Tello emulators") == "info: emulated lab: 2 Tello emulators"
    assert LEVELS == ("info", "note", "warning", "error")


def test_run_and_report_print_the_same_metric_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One run directory: `report` prints exactly the lines `run` printed, up to run's speed and threads
    lines (the command's, not the run's) and report's list of rebuilt files; the rebuilt metrics.json keeps
    the run's thread limits."""
    out = tmp_path / "run"
    argv = ["run", "paper_experiment", "--rig", "ideal", "--duration", "12", "--out", str(out)]
    assert cli.main([*argv, "--no-progress"]) == 0
    ran = capsys.readouterr().out.splitlines()
    threads = json.loads((out / "metrics.json").read_text())["threads"]
    assert cli.main(["report", str(out), "--no-plots"]) == 0
    assert json.loads((out / "metrics.json").read_text())["threads"] == threads  # kept by the rebuild
    reported = capsys.readouterr().out.splitlines()
    assert reported[-1] == "  rebuilt metrics.json"
    shared = reported[:-1]
    assert ran[: len(shared)] == shared
    assert all(ln.lstrip().startswith(("speed ", "threads: ")) for ln in ran[len(shared) :])
    assert any("gain condition: kappa" in ln for ln in shared) and shared[-1] == "  recording complete"


def test_run_help_names_each_experiments_minimum_duration(capsys: pytest.CaptureFixture[str]) -> None:
    """The minimum --duration in `run --help` is computed by the one function the refusal uses."""
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    least = minimum_duration(load_mission("paper_sim"))
    assert least is not None and f"{least:g} s for paper_sim" in text
    short = training_shortfall(load_mission("paper_sim", {"duration_s": least - 1.0}))
    assert short is not None and f"fly at least {least:g} s" in short


def test_an_interrupted_run_ends_on_the_interrupt_not_on_recording_complete() -> None:
    """The recording of an interrupted run is complete with what was flown, and the last line says where
    the signal cut the run and which modes it did not fly."""
    m = _metrics(True, {"1": 1.0})
    m["interrupted"] = True
    m["modes"]["none"] |= {"interrupted": True, "sim_seconds": 3.25}
    mission = load_mission("paper_experiment")
    lines = metric_lines(m, mission)
    assert lines[-2:] == [
        "  recording complete up to the interrupt",
        f"  INTERRUPTED (Ctrl-C or another signal) in mode none after 3.2 s of {mission.duration_s:g} s; "
        "not flown: local, dgp",
    ]
    m["recording"] = {"complete": False, "reason": "disk full"}
    assert metric_lines(m, None)[-2:] == [
        "  recording INCOMPLETE: disk full",
        "  INTERRUPTED (Ctrl-C or another signal) in mode none after 3.2 s",
    ]
    m.update(modes={}, recording={"complete": True, "reason": None})
    assert metric_lines(m, mission)[-1] == (
        "  INTERRUPTED (Ctrl-C or another signal) before any mode flew; not flown: none, local, dgp"
    )
    assert metric_lines(_metrics(True, {}), mission)[-1] == "  recording complete"  # not interrupted


def test_run_interrupted_in_flight_says_so_on_stdout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An interrupt 40 ticks into the first mode (raised where a Ctrl-C lands, in the control loop): exit
    130, and `run`'s metric lines end on the interrupt."""
    from flightstack.cli import run as run_cli

    def interrupting(bars: list[Any]) -> Callable[[str, int], Callable[[int], None]]:
        def make(mode: str, total: int) -> Callable[[int], None]:
            ticks = [0]

            def update(n: int) -> None:
                ticks[0] += n
                if ticks[0] == 40:
                    raise KeyboardInterrupt

            return update

        return make

    monkeypatch.setattr(run_cli, "_progress_factory", interrupting)
    out = tmp_path / "run"
    argv = ["run", "paper_experiment", "--rig", "ideal", "--duration", "12", "--out", str(out), "--progress"]
    assert cli.main(argv) == 130
    lines = capsys.readouterr().out.splitlines()
    assert "  recording complete" not in lines
    (end,) = [i for i, ln in enumerate(lines) if ln.startswith("  INTERRUPTED")]
    assert lines[end - 1] == "  recording complete up to the interrupt"
    none = json.loads((out / "metrics.json").read_text())["modes"]["none"]
    assert none["interrupted"] is True and 0 < none["sim_seconds"] < 12.0
    assert lines[end] == (
        f"  INTERRUPTED (Ctrl-C or another signal) in mode none after {none['sim_seconds']:.1f} s of 12 s; "
        "not flown: local, dgp"
    )


def _console(handler: type[logging.StreamHandler[Any]]) -> list[str]:
    """What a terminal shows when a safety event is logged through `handler` while a progress bar is
    drawn on the same stream."""
    stream = io.StringIO()
    log = logging.getLogger("flightstack.safety.console-test")
    sink = handler(stream)
    sink.setFormatter(ConsoleFormatter())
    log.addHandler(sink)
    log.setLevel(logging.INFO)
    log.propagate = False
    try:
        bar = tqdm(total=100, desc="mode none", file=stream, mininterval=0, ascii=True)
        bar.update(10)
        log.info("t=0.000 drone 1 takeoff: battery 90.0 %")
        bar.update(10)
        bar.close()
    finally:
        log.removeHandler(sink)
    return terminal_lines(stream.getvalue())


def test_a_safety_line_is_printed_above_the_progress_bar() -> None:
    """The console's handler (console_logging) clears the bar, prints the line on its own, draws the bar
    again below it; a plain StreamHandler writes the line into the bar's, as the console did."""
    line = "info: flightstack.safety.console-test: t=0.000 drone 1 takeoff: battery 90.0 %"
    shown = _console(ConsoleHandler)
    assert line in shown and shown.index(line) < len(shown) - 2, shown
    assert shown[-2].startswith("mode none:  20%") and shown[-1] == "", shown
    plain = _console(logging.StreamHandler)
    assert line not in plain and any(row.startswith("mode none") and line in row for row in plain), plain
