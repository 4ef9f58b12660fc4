"""flightstack.events: every kind is declared once with its severity and meaning, an Event of an undeclared
kind is refused, the recorded form reads back to its kind, and a short simulated run records only declared
kinds."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import get_args

import pytest

from flightstack.cli import app as cli
from flightstack.events import (
    END_KINDS,
    KINDS,
    BusKind,
    Event,
    EventKind,
    RunKind,
    SafetyKind,
    Severity,
    end_kind,
    kind_of,
    severity,
)
from flightstack.recording.run_reader import load_run


def test_every_kind_is_declared_once_with_a_severity_and_a_meaning() -> None:
    assert set(get_args(EventKind)) == set(KINDS)
    for kind, info in KINDS.items():
        assert info.severity in get_args(Severity), kind
        assert info.meaning and "\n" not in info.meaning, kind


def test_an_undeclared_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="undeclared event kind 'stale_pose'"):
        Event(0.0, 1, "stale_pose")  # type: ignore[arg-type]


@pytest.mark.parametrize("kind", get_args(SafetyKind))
def test_a_safety_event_is_recorded_with_its_fields_and_read_back(kind: SafetyKind) -> None:
    ev = Event(1.5, 2, kind, "why", source="safety")
    rec = ev.record("dgp")
    assert rec == {"event": "safety", "mode": "dgp", **ev.to_dict()}
    assert list(rec)[:2] == ["event", "mode"]
    assert kind_of(rec) == kind and severity(rec) == KINDS[kind].severity


@pytest.mark.parametrize("kind", get_args(BusKind))
def test_a_bus_event_is_recorded_as_bus_presence(kind: BusKind) -> None:
    rec = Event(123.0, 3, kind, source="bus", clock="monotonic").record("none")
    assert rec == {"event": "bus presence", "mode": "none", "sender": 3, "what": kind, "monotonic": 123.0}
    assert kind_of(rec) == kind


@pytest.mark.parametrize("kind", [k for k in get_args(RunKind) if k not in END_KINDS])
def test_a_runner_event_is_recorded_flat_with_its_facts(kind: RunKind) -> None:
    rec = Event(2.0, 1, kind, facts={"height_m": 0.0}).record("local")
    assert rec == {"t": 2.0, "event": kind, "drone": 1, "height_m": 0.0, "mode": "local"}
    assert kind_of(rec) == kind


@pytest.mark.parametrize(
    ("reason", "kind", "level"),
    [
        ("mission complete", "end", "INFO"),
        ("every drone landed", "end_early", "WARNING"),
        ("operator abort", "end_early", "WARNING"),
        ("exception: RuntimeError: boom", "end_exception", "ERROR"),
    ],
)
def test_every_end_is_recorded_as_end_and_its_severity_follows_its_reason(
    reason: str, kind: str, level: str
) -> None:
    assert end_kind(reason) == kind
    rec = Event(3.0, None, end_kind(reason), facts={"reason": reason}).record("dgp")
    assert rec == {"t": 3.0, "event": "end", "reason": reason, "mode": "dgp"}
    assert kind_of(rec) == kind and severity(rec) == level


def test_a_runner_event_without_a_time_is_recorded_with_t_null() -> None:
    rec = Event(math.nan, None, "recording_stopped", facts={"reason": "disk full"}).record("none")
    assert rec["t"] is None and severity(rec) == "ERROR"


def test_an_event_of_another_version_is_shown_as_a_warning() -> None:
    assert kind_of({"event": "safety", "kind": "stale_pose"}) is None
    assert severity({"event": "something new"}) == "WARNING"


def test_a_short_simulated_run_records_only_declared_kinds(tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = ["run", "paper_experiment", "--rig", "lab-sim", "--modes", "none", "--duration", "0.5"]
    argv += ["--no-progress", "--out", str(out)]
    assert cli.main(argv) == 0
    lines = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    recorded = load_run(out)["none"].events
    assert lines and recorded
    kinds = {kind_of(ev) for ev in [*lines, *recorded]}
    assert None not in kinds, [ev for ev in lines if kind_of(ev) is None]
    assert {"end", "safety tick", "landed", "takeoff", "land"} <= kinds
