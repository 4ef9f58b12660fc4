"""One event type for everything that happens in a run.

An `Event` is what a safety rule, a device driver, the bus, the simulated world or the runner reports:
its time, the drone it concerns, a kind (a short snake_case or plain word), a human-readable detail, the
component it comes from and the clock its time is on. Device drivers and the bus stamp with
`time.monotonic()` of their process (`clock="monotonic"`); the safety layer and the runner with the
mission clock (`clock="mission"`, s since the mission's start; virtual on simulated rigs).

A recording stores events in their serialised form: `Event.to_dict()` (JSON), extended by the runner
with the mode and the record's name under "event" (e.g. {"event": "safety", "mode": "dgp", ...}).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any, Literal

Clock = Literal["mission", "monotonic"]
Severity = Literal["ERROR", "WARNING", "INFO"]

ERROR_EVENTS = frozenset({"NOT LANDED", "recording_stopped"})
WARNING_EVENTS = frozenset({"safety", "lock-step wait timed out"})


@dataclass(frozen=True)
class Event:
    """t: time (s) on `clock`; drone: the drone's id (None: mission-wide or not about one drone); kind;
    detail: free text (a body name, a reason); source: "safety", "bus", "tello", "mocap", "scamper",
    "lab" (the simulated lab's drone model), "world" (the served world) or "run"; value: a number that
    belongs to the event (e.g. a clock offset in s), None if none."""

    t: float
    drone: int | None
    kind: str
    detail: str = ""
    source: str = "run"
    clock: Clock = "mission"
    value: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (every field)."""
        return asdict(self)

    def __str__(self) -> str:
        who = "" if self.drone is None else f" drone {self.drone}"
        tail = f": {self.detail}" if self.detail else ""
        return f"t = {self.t:.3f} s ({self.source}{who}) {self.kind}{tail}"


def mission_time(ev: Mapping[str, Any]) -> float | None:
    """The recorded event's time on the mission clock (s), or None when it has none: no finite `t`, or
    a `t` on another clock (a device's or the bus's monotonic stamp)."""
    t = ev.get("t")
    if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
        return float(t) if ev.get("clock", "mission") == "mission" else None
    return None


def severity(ev: Mapping[str, Any]) -> Severity:
    """How a viewer should show a recorded event (the MCAP export's Log level, the Rerun text log's).

    ERROR: a failure (a drone NOT LANDED, the recording stopped, an `error` field, an event or kind naming
    an error or a failure, a run ended by an exception). WARNING: safety events, a lock-step timeout, a
    run not ended by "mission complete". INFO: the rest."""
    name = str(ev.get("event", ""))
    words = f"{name} {ev.get('kind', '')}".lower()
    reason = str(ev.get("reason") or "")
    if name in ERROR_EVENTS or ev.get("error") or "error" in words or "fail" in words:
        return "ERROR"
    if name == "end" and reason.startswith("exception"):
        return "ERROR"
    if name in WARNING_EVENTS or (name == "end" and reason and reason != "mission complete"):
        return "WARNING"
    return "INFO"
