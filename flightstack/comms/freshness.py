"""Receive side of every bus, in one place: decode → sequence → sender clock → staleness.

`Freshness` holds what a receiver knows about each sender: its newest valid prediction message, the
receipt time of that message and, in real time, the offset between the sender's clock and the
receiver's. `InProcBus` and `ZenohBus` feed it the bytes they receive (`accept`) and read through it
(`latest`); drop reasons are counted in `dropped` ("old or duplicate seq", "stale", "key sender mismatch",
the reasons of `messages.decode`, plus "stamp ahead" in real time). What the old seqs say about a second
stream under one sender's id is kept in `streams` (streams.py); the bus acts on it (zenoh_bus.py).

Time bases
----------
"stamps" (lock-step runs, simulated clock; the in-process bus): a message's age is `now − stamp`, both
    on the one mission clock. No clock is read, so lock-step runs stay bit-identical.

"receiver" (real-time runs, agents on different computers): sender j's stamps are on j's monotonic
    clock. The receiver learns, per sender,

        offset_j = min over the join window of (t_recv − stamp_j)          (receiver clock − sender clock)

    (t_recv: the receiver's `clock()` at receipt), i.e. the true offset plus the smallest one-way delay
    seen, over the first `join_messages` messages or `join_window_s` s, whichever ends first. Then

        age = clock() − (stamp_j + offset_j)          (`now` passed to `latest` is not used)

    which is never less than the time since the message arrived; a sender minutes ahead or behind fuses
    and goes stale like one on the same clock (tests/test_clock_offset.py: ±10 min). After the window, a
    message implying an age below −(`ahead_tolerance_s` + `drift_ppm`·1e-6 · seconds since the window) is
    dropped ("stamp ahead"); one within that bound lowers offset_j, which therefore never rises. A sender
    that jumps its clock mid-run fails closed (ahead: "stamp ahead"; behind: "stale") until it rejoins:
    silent for `rejoin_after_s`, or `forget` when it leaves the bus, opens a new join window. A slow
    sender clock (20 ppm: 72 ms per hour) ages its messages, towards stale, never towards fresh.

Units: stamps, `now`, `stale_after`, clock readings: seconds; `drift_ppm`: parts per million.
Thread safety: none here; `ZenohBus` calls every method with its lock held.
"""

from __future__ import annotations

import statistics
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from flightstack.comms.acceptance import AcceptanceBounds, SeqState, in_gap, restart_run, seq_verdict
from flightstack.comms.messages import PredictionMessage, decode_checked
from flightstack.comms.streams import DUPLICATE, StreamWatch, digest
from flightstack.events import BusKind, Event

TimeBase = Literal["stamps", "receiver"]
TIME_BASES: tuple[str, ...] = ("stamps", "receiver")


def _offset_event(t_recv: float, sender: int, what: BusKind, offset_s: float) -> Event:
    """A change of what this receiver knows about sender's clock offset (receiver − sender, s)."""
    return Event(t_recv, sender, what, source="bus", clock="monotonic", value=float(offset_s))


@dataclass(frozen=True)
class OffsetPolicy:
    """How a receiver learns and bounds each sender's clock offset (time base "receiver")."""

    join_messages: int = 20  # the join window ends after this many messages ...
    join_window_s: float = 1.0  # ... or this long (s) after its first message, whichever comes first
    rejoin_after_s: float = 2.0  # a sender silent this long (s) re-learns its offset at its next message
    ahead_tolerance_s: float = 0.1  # a message may imply an age down to −this (s) before "stamp ahead"
    drift_ppm: float = 100.0  # plus this clock drift (ppm) times the time since the offset was frozen
    outlier_s: float = 5.0  # a stamp this far (s) from the sender's others is refused ("stamp outlier")

    def __post_init__(self) -> None:
        if self.join_messages < 1:
            raise ValueError("join_messages must be >= 1")
        for name in ("join_window_s", "rejoin_after_s", "ahead_tolerance_s", "drift_ppm", "outlier_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0")


@dataclass
class SenderClock:
    """What a receiver knows of one sender's clock (receiver-clock seconds)."""

    offset: float  # receiver clock − sender clock, incl. the smallest one-way delay seen (s)
    n: int  # messages seen in the current join window
    t_first: float  # receipt time of the window's first message (s)
    last_heard: float  # receipt time of the newest decodable message, accepted or not (s)
    frozen_at: float | None = None  # receipt time at which the window ended (s); None while learning
    frozen_offset: float = 0.0  # offset when the window ended (s)
    raws: list[float] = field(default_factory=list)  # t_recv − stamp of the window's messages (s)


class Freshness:
    """Newest valid message per sender, sequence and staleness checks; see the module docstring.

    `clock`: the receiver's clock (s), read at receipt and in `latest` in time base "receiver" (default
    time.monotonic); never read in time base "stamps" unless a receipt time is passed to `accept`."""

    def __init__(
        self,
        mission: str,
        known_senders: set[int] | frozenset[int],
        time_base: TimeBase = "stamps",
        clock: Callable[[], float] | None = None,
        policy: OffsetPolicy | None = None,
        bounds: AcceptanceBounds | None = None,
    ) -> None:
        if time_base not in TIME_BASES:
            raise ValueError(f"time_base must be one of {TIME_BASES}, not {time_base!r}")
        if clock is None:
            clock = time.monotonic
        self.mission = mission
        self.known = frozenset(known_senders)
        self.time_base: TimeBase = time_base
        self.clock = clock
        self.policy = policy or OffsetPolicy()
        self.newest: dict[int, PredictionMessage] = {}
        self.received: dict[int, float] = {}  # receipt time of each sender's newest accepted message (s)
        self.clocks: dict[int, SenderClock] = {}
        self.offset_events: list[Event] = []  # drone = sender, kind = what, value = offset (s), t = t_recv
        self.dropped: Counter[str] = Counter()
        self.delivered = 0
        self.bounds = bounds or AcceptanceBounds()
        self.seqs: dict[int, SeqState] = {}  # per sender: its rejected run and its newest skip's gap
        self.restarts: Counter[int] = Counter()  # per sender: messages taken by the restart rule
        self.restart_events: list[Event] = []  # one per restart, kind "restart", naming the sender
        # a second stream under a sender's id (streams.py): watched here, acted on by the bus
        b = self.bounds
        self.streams = StreamWatch(b.max_seq_jump, b.max_reorder, b.quarantine_after)

    def accept(
        self, data: bytes, key_sender: str | None = None, t_recv: float | None = None
    ) -> PredictionMessage | None:
        """Decode and check one received message; keep it as the sender's newest, or count the drop.

        key_sender: the sender named by the transport (Zenoh key), checked against the payload's.
        t_recv: receipt time on the receiver's clock (s); read from `clock` when None in time base
        "receiver" (and left unread in "stamps")."""
        msg, reason, bad = decode_checked(data, self.mission, self.known, self.bounds.packed)
        if msg is None:
            self.dropped[reason or "unknown"] += 1
            return None
        if key_sender is not None and key_sender != str(msg.sender):
            self.dropped["key sender mismatch"] += 1
            return None
        if bad:  # AcceptanceBounds.violation, decided by decode's compiled pass
            self.dropped[bad] += 1
            return None
        sender, seq = msg.sender, msg.seq
        prev = self.newest.get(sender)
        prev_seq = None if prev is None else prev.seq
        why = seq_verdict(prev_seq, seq, self.bounds)
        dig = digest(data)
        state = self.seqs.setdefault(sender, SeqState())
        rule: Literal["gap", "restart"] | None = None
        if prev_seq is not None and seq <= prev_seq:  # old: a duplicate, late, another stream's, or a gap's
            unseen = not self.streams.seen(sender, seq)
            if self.streams.refused_old(sender, seq, dig, prev_seq) == DUPLICATE:
                self.dropped[why or "old or duplicate seq"] += 1  # the network repeated it: never a run
                return None
            if (unseen and in_gap(state, seq, prev_seq, self.bounds)) or seq == prev_seq:
                why, rule = None, "gap"  # the stream from before the newest skip goes on (acceptance.py)
        elif prev_seq is not None and why is None and self.streams.resumed(sender, seq, prev_seq):
            rule = "gap"  # the count a restart left goes on: it never stopped, the restart is undone
        if why:  # before the clock: a message refused here must not move the sender's offset
            if not restart_run(state, seq, self.bounds):
                self.dropped[why] += 1
                return None
            rule = "restart"
        if self.time_base == "receiver":
            if t_recv is None:
                t_recv = self.clock()
            why = self._learn(msg, t_recv)
            if why:
                self.dropped[why] += 1
                return None
        if rule == "restart":
            self._restarted(msg, prev_seq, t_recv)
        below = rule == "restart" and prev_seq is not None and seq < prev_seq
        self.streams.accepted(sender, seq, dig, restart=rule == "restart", left=prev_seq if below else None)
        state.taken(prev_seq, seq, by_rule=rule is not None)
        self.newest[sender] = msg
        if t_recv is not None:
            self.received[sender] = t_recv
        self.delivered += 1
        return msg

    def _restarted(self, msg: PredictionMessage, prev_seq: int | None, t_recv: float | None) -> None:
        """Count and report a message taken by the restart rule (acceptance.py): the sender counted again,
        a receiver joined it late, or a stream took the id while the one before it stopped."""
        from flightstack.comms.certs import agent_name  # rare: not cryptography on every bus's import

        self.restarts[msg.sender] += 1
        before = "nothing heard before" if prev_seq is None else f"its newest was seq {prev_seq}"
        detail = (
            f"{agent_name(msg.sender)}: taken again at seq {msg.seq} after {self.bounds.restart_after} "
            f"consecutive messages outside the sequence rules ({before}); restart {self.restarts[msg.sender]}"
        )
        t = t_recv if t_recv is not None else msg.stamp
        clock: Literal["monotonic", "mission"] = "monotonic" if t_recv is not None else "mission"
        self.restart_events.append(Event(t, msg.sender, "restart", detail, source="bus", clock=clock))

    def age(self, sender: int, now: float) -> float | None:
        """Age (s) of `sender`'s newest message: `now − stamp` ("stamps"), or clock() − (stamp + offset)
        ("receiver"); None when there is none."""
        msg = self.newest.get(sender)
        if msg is None:
            return None
        if self.time_base == "stamps":
            return now - msg.stamp
        return self.clock() - (msg.stamp + self.clocks[sender].offset)

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        """Newest message of `sender` if its age is at most `stale_after` (s); None if none, or stale
        (counted "stale"). `now`: the mission clock (s), used in time base "stamps" only."""
        msg = self.newest.get(sender)
        if msg is None:
            return None
        if self.time_base == "stamps":
            if msg.stamp - now > self.bounds.stamp_ahead_s:  # from the future of the mission clock
                self.dropped["stamp ahead"] += 1
                return None
            stale = now - msg.stamp > stale_after
        else:
            age = self.clock() - (msg.stamp + self.clocks[sender].offset)
            if age < -self.policy.ahead_tolerance_s:  # kept before the offset moved past it
                self.dropped["stamp ahead"] += 1
                return None
            stale = age > stale_after
        if stale:
            self.dropped["stale"] += 1
            return None
        return msg

    def forget(self, sender: int) -> None:
        """The sender left: drop its newest message, sequence number and clock offset (a restarted
        agent counts seq from 0 again and re-learns its offset)."""
        self.newest.pop(sender, None)
        self.clocks.pop(sender, None)
        self.seqs.pop(sender, None)
        self.streams.forget(sender)

    def offset(self, sender: int) -> float | None:
        """The learned offset (receiver clock − sender clock, s) of `sender`, None if none yet."""
        c = self.clocks.get(sender)
        return None if c is None else c.offset

    def _learn(self, msg: PredictionMessage, t_recv: float) -> str | None:
        """Update the sender's clock offset with one message received at t_recv; the drop reason
        ("stamp ahead" | "stamp outlier") or None."""
        p = self.policy
        raw = t_recv - msg.stamp
        c = self.clocks.get(msg.sender)
        if c is None or t_recv - c.last_heard > p.rejoin_after_s:  # joins, or rejoins after silence
            what: BusKind = "offset learning" if c is None else "offset re-learning after silence"
            c = SenderClock(offset=raw, n=1, t_first=t_recv, last_heard=t_recv, raws=[raw])
            self.clocks[msg.sender] = c
            self.offset_events.append(_offset_event(t_recv, msg.sender, what, raw))
            self._maybe_freeze(c, msg.sender, t_recv)
            return None
        c.last_heard = t_recv
        if c.frozen_at is None:
            if len(c.raws) >= 2 and abs(raw - statistics.median([*c.raws, raw])) > p.outlier_s:
                return "stamp outlier"  # one forged stamp (1e300) must not become the offset
            c.raws.append(raw)
            med = statistics.median(c.raws)
            near = [r for r in c.raws if abs(r - med) <= p.outlier_s]
            c.offset = min(near) if near else raw  # two far apart: trust the newer until a third decides
            c.n += 1
            self._maybe_freeze(c, msg.sender, t_recv)
            return None
        floor = c.frozen_offset - p.ahead_tolerance_s - p.drift_ppm * 1e-6 * (t_recv - c.frozen_at)
        if raw < floor:
            return "stamp ahead"
        if raw - c.frozen_offset > p.outlier_s + p.drift_ppm * 1e-6 * (t_recv - c.frozen_at):
            return "stamp outlier"  # seconds older than any message of the window on arrival
        c.offset = min(c.offset, raw)
        return None

    def _maybe_freeze(self, c: SenderClock, sender: int, t_recv: float) -> None:
        if c.n >= self.policy.join_messages or t_recv - c.t_first >= self.policy.join_window_s:
            c.frozen_at = t_recv
            c.frozen_offset = c.offset
            self.offset_events.append(_offset_event(t_recv, sender, "offset frozen", c.offset))


__all__ = ["TIME_BASES", "Freshness", "OffsetPolicy", "SenderClock", "TimeBase"]
