"""The result of one fault row of `flightstack faults` (flightstack/faults/__init__.py)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class FaultResult:
    """What the system did under one injected fault.

    name: the row's key (`flightstack faults --only NAME`). expected: the documented reaction
    (docs/faults.md). observed: what the events and the recording show, with mission-clock times (s).
    all_safe: every drone ended landed (or hovering inside the fence) and no drone ever crossed the hard
    fence. recording_complete: every tick flown is recorded, finite, saved and re-read identically, and the
    event log has the end of the run and every drone's landing (for a row where nothing may fly: nothing
    was written). crashed: an exception escaped (the run or the row itself). reaction_ok: the observed
    reaction is the expected one. seconds: wall time of the row. problems: every failed check, readable.
    """

    name: str
    expected: str
    observed: str
    all_safe: bool
    recording_complete: bool
    crashed: bool
    seconds: float
    reaction_ok: bool = True
    problems: list[str] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def handled(self) -> bool:
        """No crash, every drone safe, recording intact and the expected reaction."""
        return not self.crashed and self.all_safe and self.recording_complete and self.reaction_ok

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "handled": self.handled}


FaultRow = Callable[[Path, Path], FaultResult]
"""A row of the fault table: (mission file, work directory for this row's files) -> FaultResult."""


class Checks:
    """Collects named boolean checks of one row; `failed` lists the ones that did not hold."""

    def __init__(self) -> None:
        self.failed: list[str] = []

    def check(self, ok: bool, what: str) -> bool:
        """Record `what` as failed unless ok; returns ok."""
        if not ok:
            self.failed.append(what)
        return bool(ok)

    @property
    def ok(self) -> bool:
        return not self.failed
