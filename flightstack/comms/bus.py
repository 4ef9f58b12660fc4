"""The bus agents use to exchange prediction messages (DESIGN §6), and the in-process lock-step bus.

Every bus carries encoded bytes and decodes them on receipt, so the in-process bus exercises exactly the
validation path of the network bus: malformed, foreign or stale messages are dropped and counted. The
receive side (decode → sequence → staleness) is `flightstack.comms.freshness.Freshness`, shared with the
Zenoh bus.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Protocol

from flightstack.comms.acceptance import AcceptanceBounds
from flightstack.comms.control import ControlEvent
from flightstack.comms.freshness import Freshness, OffsetPolicy, TimeBase
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.events import Event

if TYPE_CHECKING:
    from flightstack.comms.operator_link import LoopbackOperatorListener


class PredictionBus(Protocol):
    """Publish own predictions; read the newest valid message of each neighbour."""

    @property
    def dropped(self) -> Counter[str]: ...

    def publish(self, msg: PredictionMessage) -> None: ...
    def publish_raw(self, data: bytes) -> None: ...
    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None: ...
    def close(self) -> None: ...


class LockstepBus(Protocol):
    """Waiting for neighbours (agents in other processes on a virtual clock).

    Both return the senders still missing after at most `timeout_s` seconds (wall clock); an in-process
    bus returns an empty set at once (every agent is in this process; a message is readable as soon as it
    is published)."""

    def wait_alive(self, senders: set[int], timeout_s: float) -> set[int]: ...
    def wait_for_stamp(self, senders: set[int], stamp: float, timeout_s: float) -> set[int]: ...


class OperatorChannel(Protocol):
    """The operator's side of a mission (flightstack/comms/control.py): aborts in, status out.

    control_events: the operator commands received since the last call, oldest first (drained).
    publish_control: a status report for `flightstack status` / `guard` (no-op where nobody can read it).
    presence_events: `Event`s (kind "joined" | "left", drone = the sender, time.monotonic() s) of the
    agents seen on the network, "second session" (detail: the report) when a second process speaks
    for one of them (identity.py), and "restart" for each message taken by the restart rule (detail:
    the sender and the seqs; acceptance.py).
    """

    def control_events(self) -> list[ControlEvent]: ...
    def publish_control(self, kind: str, payload: dict[str, Any]) -> None: ...

    @property
    def presence_events(self) -> list[Event]: ...


def restart_counts(events: Iterable[Event]) -> dict[str, int]:
    """Messages taken by the restart rule per sender's participant name (certs.agent_name), from a bus's
    presence_events: what a status reports (control.StatusReport.restarts)."""
    from flightstack.comms.certs import agent_name  # not cryptography on every bus's import

    counts = Counter(e.drone for e in events if e.kind == "restart" and e.drone is not None)
    return {agent_name(i): n for i, n in sorted(counts.items())}


class Bus(PredictionBus, LockstepBus, OperatorChannel, Protocol):
    """Everything the runner uses of a bus; InProcBus and flightstack.comms.zenoh_bus.ZenohBus are two."""


class InProcBus:
    """Shared by all agents of one process; lock-step: a message is readable as soon as it is published.

    `latest` returns the newest message of `sender` whose stamp is within `stale_after` seconds of `now`
    (None otherwise, counted as 'stale'). Out-of-order or duplicate sequence numbers are dropped.
    All agents share one clock, so the time base is "stamps" by default (freshness.py).

    operator: the loopback operator listener of an in-process mission (operator_link.py, built by
    `factory.make_bus` on hardware): `control_events()` yields its aborts (already acknowledged to the
    sender by the listener) and `close()` closes it. Without one, `control_events()` is always empty.
    """

    def __init__(
        self,
        mission: str,
        known_senders: set[int],
        *,
        time_base: TimeBase = "stamps",
        clock: Callable[[], float] | None = None,
        policy: OffsetPolicy | None = None,
        operator: LoopbackOperatorListener | None = None,
        bounds: AcceptanceBounds | None = None,
    ) -> None:
        """bounds: what a received prediction may claim (acceptance.py; default AcceptanceBounds())."""
        self.mission = mission
        self.known = frozenset(known_senders)
        self._book = Freshness(mission, self.known, time_base, clock, policy, bounds)
        self.operator = operator

    @property
    def dropped(self) -> Counter[str]:
        """Drop counts by reason: the live counter, plus the operator listener's when there is one."""
        if self.operator is None:
            return self._book.dropped
        return self._book.dropped + self.operator.dropped

    @property
    def delivered(self) -> int:
        return self._book.delivered

    @property
    def freshness(self) -> Freshness:
        """The receive-side book (newest messages, sender clock offsets)."""
        return self._book

    def publish(self, msg: PredictionMessage) -> None:
        self._book.accept(encode(msg))

    def publish_raw(self, data: bytes) -> None:
        self._book.accept(data)

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        return self._book.latest(sender, now, stale_after)

    def control_events(self) -> list[ControlEvent]:
        """Operator commands (aborts) received since the last call, oldest first (drained)."""
        return [] if self.operator is None else self.operator.control_events()

    def publish_control(self, kind: str, payload: dict[str, Any]) -> None:
        """No-op: the loopback operator listener only receives (nobody reads an in-process status)."""

    @property
    def presence_events(self) -> list[Event]:
        """Every agent is in this process: only "restart" events (acceptance.py; mission clock), if any."""
        return list(self._book.restart_events)

    def wait_alive(self, senders: set[int], timeout_s: float) -> set[int]:
        """Every agent is in this process: none missing."""
        return set()

    def wait_for_stamp(self, senders: set[int], stamp: float, timeout_s: float) -> set[int]:
        """Lock-step already: a message is readable as soon as it is published."""
        return set()

    def close(self) -> None:
        self._book.newest.clear()
        if self.operator is not None:
            self.operator.close()
