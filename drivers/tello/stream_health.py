"""What a Tello's state stream says about itself beside the telemetry: implausible values, and runs of
datagrams the parser rejects; each an event once, so that neither a drifted value nor a run of unreadable
lines is ever a silent link (pure: no sockets, threads or clocks; it returns the events' details, which
drivers/tello/status.py records as the phase tracker's; the driver holds a lock).

- **Implausible values** (`accepted`): a parsed line keeps every finite value as sent and flags those
  outside the physical bounds (drivers/tello/state.py `PLAUSIBLE`). The first implausible value of a field
  is the event `state_implausible` naming the field, the value and the bounds; that field's next one is an
  event only after the episode has ended, i.e. once a line carried the field within its bounds again (a
  line without the field ends nothing); the driver also counts every line with an implausible value
  (`counts["state_implausible"]`). The decision: the driver uses the value as sent (any substitute would be
  a guess; the event names the value), and the line keeps the link alive and feeds the phase tracker. A
  drifted `h` then changes no phase decision while `tof` is in range ("near the ground" is `tof`'s; `h`
  is read for its changes), `tof` from 6553 up is out of range, `time` is read only for its changes, a
  `bat` below 0 reads as empty and one above 100 FAILs preflight (drivers/tello/preflight.py); field by
  field: docs/drivers.md, "Implausible values and rejected lines".
- **Rejected runs** (`rejected`): state datagrams from the drone's address that the parser rejects (not
  ASCII, malformed, a value that is no finite number, a field missing: drivers/tello/state.py), with no
  valid line between them and no gap longer than `run_s` (a longer gap is silence: the next rejected
  datagram starts a new run). Once a run has lasted `run_s`, one event `state_rejected_run` gives the
  number of datagrams, the duration and the count of each reason; a valid line ends the run. `run_s` is the
  driver's `link_timeout_s` (1 s by default): the link is lost after that long without a valid line
  (drivers/tello/watchdog.py), so the run's event comes with the `link_lost` it explains, and `rejected_note`
  adds the run to `link_lost`'s detail and to the land's "telemetry silent" re-send reason.

Times: time.monotonic() s of the receive.
"""

from __future__ import annotations

from collections import Counter

from flightstack.drivers.tello.state import PLAUSIBLE, TelloTelemetry


class StreamHealth:
    """Implausible-value episodes and rejected runs of one drone's state stream (module docstring)."""

    def __init__(self, run_s: float) -> None:
        """run_s (s): how long a run of rejected datagrams lasts before it is an event."""
        self.run_s = run_s
        self._implausible: set[str] = set()  # fields in an episode of implausible values
        self._run_first_t: float | None = None  # the first rejected datagram of the current run
        self._run_last_t = 0.0
        self._run_reasons: Counter[str] = Counter()
        self._run_reported = False

    def accepted(self, s: TelloTelemetry) -> list[str]:
        """A parsed line: it ends a run; the details of its `state_implausible` events (a field's first
        implausible value of an episode: "h=-1010 outside [-1000, 3000]")."""
        self._run_first_t = None
        self._implausible -= {k for k in self._implausible if k in s.fields and k not in s.implausible}
        new = [k for k in s.implausible if k not in self._implausible]
        self._implausible.update(new)
        return [f"{k}={s.fields[k]:g} outside [{PLAUSIBLE[k][0]:g}, {PLAUSIBLE[k][1]:g}]" for k in new]

    def rejected(self, t: float, reason: str) -> str | None:
        """A datagram from the drone that the parser rejected for `reason` at `t`; the detail of the
        `state_rejected_run` event when the run has just lasted `run_s`, else None."""
        if self._run_first_t is None or t - self._run_last_t > self.run_s:
            self._run_first_t, self._run_reported = t, False
            self._run_reasons.clear()
        self._run_last_t = t
        self._run_reasons[reason] += 1
        if self._run_reported or t - self._run_first_t < self.run_s:
            return None
        self._run_reported = True
        return self._describe_run()

    def rejected_note(self) -> str:
        """ "" when no datagram was rejected since the last valid line; else "; " and the run."""
        return "" if self._run_first_t is None else f"; {self._describe_run()}"

    def _describe_run(self) -> str:
        assert self._run_first_t is not None
        n = sum(self._run_reasons.values())
        reasons = ", ".join(f"{r} {c}" for r, c in self._run_reasons.most_common())
        span = self._run_last_t - self._run_first_t
        return f"{n} state datagrams from the drone rejected over {span:.2f} s, none valid ({reasons})"
