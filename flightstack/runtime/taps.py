"""Observers of a flight that are not part of it: live viewers, live exporters.

A `TickTap` is told after every recorded tick (or chunk of ticks of the compiled loop) and once at the
end of each mode. It must return at once: whatever it does with the data (draw it, encode images, write a
file) happens on its own thread behind a bounded queue that drops when full, so a slow viewer can never
hold the control loop. The runner calls it through `TapSet`, which catches and counts anything a tap
raises: a tap that fails is switched off for the rest of the run, the flight goes on.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from flightstack.recording.timeseries import Recording
    from flightstack.runtime.fleet import Fleet

_log = logging.getLogger(__name__)


class TickTap(Protocol):
    """One observer of a mode's flight. Times are the mission clock's (s), frames as in `Recording`."""

    def start(self, f: Fleet, rec: Recording) -> None:
        """The fleet is assembled and the (empty) recording allocated; nothing has taken off yet."""

    def on_tick(self, f: Fleet, rec: Recording, k_end: int) -> None:
        """Rows [.., k_end) of `rec` are recorded (new since the last call); new events may be in
        rec.events. Must not block."""

    def close(self, rec: Recording) -> None:
        """The mode has ended (landed or failed); `rec` holds every flown tick and the final events."""


class TapSet:
    """The runner's view of its taps: each call guarded, a tap that raises is counted and dropped."""

    def __init__(self, taps: Sequence[TickTap] = ()) -> None:
        self.taps = list(taps)
        self.failures: Counter[str] = Counter()

    def __bool__(self) -> bool:
        return bool(self.taps)

    def _guard(self, tap: TickTap, what: str, *args: object) -> None:
        try:
            getattr(tap, what)(*args)
        except Exception as exc:  # an observer never ends a flight
            name = type(tap).__name__
            self.failures[name] += 1
            _log.warning("tap %s failed in %s (%s: %s); switched off for this run", name, what,
                         type(exc).__name__, exc)  # fmt: skip
            if tap in self.taps:
                self.taps.remove(tap)

    def start(self, f: Fleet, rec: Recording) -> None:
        for tap in list(self.taps):
            self._guard(tap, "start", f, rec)

    def on_tick(self, f: Fleet, rec: Recording, k_end: int) -> None:
        for tap in list(self.taps):
            self._guard(tap, "on_tick", f, rec, k_end)

    def close(self, rec: Recording) -> None:
        for tap in list(self.taps):
            self._guard(tap, "close", rec)
