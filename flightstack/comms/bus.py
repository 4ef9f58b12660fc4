"""The bus agents use to exchange prediction messages (DESIGN §6), and the in-process lock-step bus.

Every bus carries encoded bytes and decodes them on receipt, so the in-process bus exercises exactly the
validation path of the network bus: malformed, foreign or stale messages are dropped and counted.
"""

from __future__ import annotations

from collections import Counter
from typing import Protocol

from flightstack.comms.messages import PredictionMessage, decode, encode


class Bus(Protocol):
    """Publish own predictions; read the newest valid message of each neighbour."""

    @property
    def dropped(self) -> Counter[str]: ...

    def publish(self, msg: PredictionMessage) -> None: ...
    def publish_raw(self, data: bytes) -> None: ...
    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None: ...
    def close(self) -> None: ...


class InProcBus:
    """Shared by all agents of one process; lock-step: a message is readable as soon as it is published.

    `latest` returns the newest message of `sender` whose stamp is within `stale_after` seconds of `now`
    (None otherwise, counted as 'stale'). Out-of-order or duplicate sequence numbers are dropped.
    """

    def __init__(self, mission: str, known_senders: set[int]) -> None:
        self.mission = mission
        self.known = frozenset(known_senders)
        self._latest: dict[int, PredictionMessage] = {}
        self.dropped: Counter[str] = Counter()
        self.delivered = 0

    def publish(self, msg: PredictionMessage) -> None:
        self.publish_raw(encode(msg))

    def publish_raw(self, data: bytes) -> None:
        msg, reason = decode(data, self.mission, self.known)
        if msg is None:
            self.dropped[reason or "unknown"] += 1
            return
        prev = self._latest.get(msg.sender)
        if prev is not None and msg.seq <= prev.seq:
            self.dropped["old or duplicate seq"] += 1
            return
        self._latest[msg.sender] = msg
        self.delivered += 1

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        msg = self._latest.get(sender)
        if msg is None:
            return None
        if now - msg.stamp > stale_after:
            self.dropped["stale"] += 1
            return None
        return msg

    def close(self) -> None:
        self._latest.clear()
