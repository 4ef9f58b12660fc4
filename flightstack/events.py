"""One event type for everything that happens in a run (issue 17).

An `Event` is what a safety rule, a device driver, the bus, the simulated world or the runner reports:
its time, the drone it concerns, a kind (a short snake_case or plain word), a human-readable detail, the
component it comes from and the clock its time is on. Device drivers and the bus stamp with
`time.monotonic()` of their process (`clock="monotonic"`); the safety layer and the runner with the
mission clock (`clock="mission"`, s since the mission's start; virtual on simulated rigs).

A recording stores events in their serialised form: `Event.to_dict()` (JSON), extended by the runner
with the mode and the record's name under "event" (e.g. {"event": "safety", "mode": "dgp", ...}).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

Clock = Literal["mission", "monotonic"]


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
