"""A bus whose messages arrive late or never: the rig's `bus` link between agents that share one clock
(the simulated lab, flightstack/config/links.py).

`DelayedBus` wraps another bus (the in-process one): each published message is sent on the link of its
sender, lost with the link's loss, else handed to the inner bus once the clock (the lab's world time, s)
reaches its send time + the link's delay. Messages of one sender arrive in the order they were sent, as
on Zenoh's TCP links (a message drawn earlier than the one before it waits for it). Only `latest` and
the lock-step waits deliver what is due; the rest of the bus (operator channel, presence) is the inner
bus's, untouched.
"""

from __future__ import annotations

import heapq
from collections import Counter
from collections.abc import Callable
from typing import Any, Protocol

from flightstack.comms.bus import Bus
from flightstack.comms.control import ControlEvent
from flightstack.comms.messages import PredictionMessage, sender_of
from flightstack.events import Event

LOST = "lost on the bus link"
"""The drop counter of the messages the link lost."""
UNNAMED_SENDER = 2**16
"""The link of raw bytes whose header names no sender (sender ids are below it)."""


class LinkDraws(Protocol):
    """One sender's link (e.g. config.links.LinkDelays): whether the next message is lost, and how late
    it arrives (s)."""

    def lost(self) -> bool: ...
    def delay(self) -> float: ...


class DelayedBus:
    """A Bus around `inner` (module). clock: the shared clock (s); link_of: sender id -> its link (asked
    once per sender; raw bytes whose header names no sender go on the link of UNNAMED_SENDER)."""

    def __init__(self, inner: Bus, clock: Callable[[], float], link_of: Callable[[int], LinkDraws]) -> None:
        self.inner = inner
        self.clock = clock
        self._link_of = link_of
        self._links: dict[int, LinkDraws] = {}
        self._last_arrival: dict[int, float] = {}
        self._queue: list[tuple[float, int, PredictionMessage | bytes]] = []  # (arrival, order, message)
        self._order = 0
        self.lost: Counter[int] = Counter()
        """Messages the link lost, by sender."""
        self.delays: list[float] = []
        """Each message's delay (s, arrival - send time on the clock), in the order sent."""

    def _send(self, sender: int, item: PredictionMessage | bytes) -> None:
        link = self._links.get(sender)
        if link is None:
            link = self._links[sender] = self._link_of(sender)
        if link.lost():
            self.lost[sender] += 1
            return
        t = self.clock()
        arrival = max(t + link.delay(), self._last_arrival.get(sender, t))
        self._last_arrival[sender] = arrival
        self.delays.append(arrival - t)
        self._order += 1
        heapq.heappush(self._queue, (arrival, self._order, item))

    def deliver(self) -> None:
        """Hand every message due by now to the inner bus (oldest arrival first)."""
        now = self.clock()
        while self._queue and self._queue[0][0] <= now:
            item = heapq.heappop(self._queue)[2]
            if isinstance(item, PredictionMessage):
                self.inner.publish(item)
            else:
                self.inner.publish_raw(item)

    # ---- PredictionBus ------------------------------------------------------------------------------------
    @property
    def dropped(self) -> Counter[str]:
        out = Counter(self.inner.dropped)
        if self.lost:
            out[LOST] = sum(self.lost.values())
        return out

    def publish(self, msg: PredictionMessage) -> None:
        self._send(msg.sender, msg)

    def publish_raw(self, data: bytes) -> None:
        sender = sender_of(data)
        self._send(UNNAMED_SENDER if sender is None else sender, bytes(data))

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        self.deliver()
        return self.inner.latest(sender, now, stale_after)

    def close(self) -> None:
        self._queue.clear()
        self.inner.close()

    # ---- LockstepBus ------------------------------------------------------------------------------------
    def wait_alive(self, senders: set[int], timeout_s: float) -> set[int]:
        self.deliver()
        return self.inner.wait_alive(senders, timeout_s)

    def wait_for_stamp(self, senders: set[int], stamp: float, timeout_s: float) -> set[int]:
        """The inner bus's wait (messages still on their way are not waited for: they are late)."""
        self.deliver()
        return self.inner.wait_for_stamp(senders, stamp, timeout_s)

    # ---- OperatorChannel --------------------------------------------------------------------------------
    def control_events(self) -> list[ControlEvent]:
        return self.inner.control_events()

    def publish_control(self, kind: str, payload: dict[str, Any]) -> None:
        self.inner.publish_control(kind, payload)

    @property
    def presence_events(self) -> list[Event]:
        return self.inner.presence_events
