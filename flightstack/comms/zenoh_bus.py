"""Prediction messages over Zenoh (DESIGN §6): the network implementation of the `Bus` protocol.

Key layout (one mission = one key space; `prefix` defaults to "flightstack"):
    {prefix}/{mission}/pred/{sender}     PredictionMessage bytes (messages.encode), one key per sender
    {prefix}/{mission}/alive/{sender}    liveliness token, one per agent hosted by a process
    {prefix}/{mission}/control/...       operator channel, UTF-8 JSON (flightstack/comms/control.py)
Every key, its payload and the Zenoh encoding its publisher declares: flightstack/comms/wire.py
(docs/wire-format.md). Receivers ignore the encoding (an older peer sends none).

Receiving. One callback subscriber on `pred/*` hands the bytes to `freshness.Freshness.accept` (decode,
sequence, sender clock; no zenoh call, only a short lock), which keeps the newest valid message per sender.
Not a `RingChannel(1)`: on a wildcard it keeps the newest sample of *any* sender and loses the others; the
FIFO handler blocks the session when Python is slow. Bad messages are dropped and counted by reason in
`dropped`, as in `InProcBus`. Messages of a second session publishing as an owned sender are dropped first
("second session", identity.py) and reported once in `presence_events`; so are the messages of a sender
under whose label two streams publish (streams.py: quarantined for the run, "two sessions under one
label"). Every message taken by the restart rule (acceptance.py) is a "restart" event there too, naming
the sender. Own agents' messages take the same encode → Zenoh → decode path as remote ones.

QoS: predictions reliable, congestion control DROP in real time and BLOCK when `reliable` (lock-step),
batched, not express (why and the latency measured: docs/lab_notes.md); control messages express, BLOCK,
priority INTERACTIVE_HIGH.

Lock-step: `wait_for({sender: seq})` blocks (Condition, no polling) until each sender's newest seq reaches
the expected one, the sender left, or the timeout; publish, wait, read gives bit-identical results to the
in-process bus. Presence: liveliness tokens are declared after the subscribers, so a peer that sees a token
also reaches its subscribers; a sender that left reads as None and its seq is forgotten (a restarted agent
counts from 0 again). Time base "stamps" or "receiver": freshness.py. A process hosting agents answers
every valid abort with an "abort_ack" from its ack thread (callbacks never call zenoh); close() ends the
thread and the session (the class is a context manager). More: docs/bus.md ("How it works").

Units: message stamps and `latest(now, stale_after)` are mission-clock seconds; `presence_events` and
`ControlEvent.time` are `time.monotonic()` seconds; `lease_ms` is milliseconds; `timeout_s` seconds.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, Literal

import zenoh

from flightstack.comms import acl as keys
from flightstack.comms.control import (
    ABORT,
    ABORT_ACK,
    CONTROL_KINDS,
    MAX_CONTROL_BYTES,
    ControlEvent,
    ack_payload,
    encode_control,
    parse_control,
)
from flightstack.comms.freshness import Freshness, OffsetPolicy
from flightstack.comms.identity import (
    SECOND_SESSION,
    TWO_STREAMS,
    SessionBook,
    SessionEvent,
    sample_label,
    session_label,
)
from flightstack.comms.messages import MAGIC, PredictionMessage, encode
from flightstack.comms.wire import CONTROL_ENCODING, PRED_ENCODING
from flightstack.comms.zenoh_config import ZenohBusConfig, zenoh_config
from flightstack.events import Event


def _header_sender(data: bytes) -> str:
    """The sender field of a message header, as a key chunk ("raw" when there is no readable header)."""
    if len(data) >= 8 and data[:4] == MAGIC:
        return str(int.from_bytes(data[6:8], "little"))
    return "raw"


def _presence(t: float, sender: int, what: Literal["joined", "left"]) -> Event:
    """A presence change: `what` ("joined" | "left") of agent `sender` at time.monotonic() t (s)."""
    return Event(t, sender, what, source="bus", clock="monotonic")


def _session_event(e: SessionEvent) -> Event:
    """A second session speaking for sender e.sender (kind "second session", detail: the report)."""
    return Event(e.t, e.sender, SECOND_SESSION, e.text, source="bus", clock="monotonic")


class ZenohBus:
    """`Bus` over Zenoh for the agents `cfg.self_ids` of this process; see the module docstring.

    clock: this receiver's clock (s, default time.monotonic), for receipt times and, in time base
    "receiver", message ages; policy: how sender clock offsets are learned (freshness.OffsetPolicy)."""

    def __init__(
        self,
        cfg: ZenohBusConfig,
        *,
        clock: Callable[[], float] | None = None,
        policy: OffsetPolicy | None = None,
    ) -> None:
        conf = zenoh_config(cfg)
        self.cfg = cfg
        self.mission = cfg.mission
        self.self_ids = frozenset(cfg.self_ids)
        self.known = frozenset(cfg.known_senders)
        self._clock = clock or time.monotonic
        self._cond = threading.Condition(threading.Lock())
        self._book = Freshness(cfg.mission, self.known, cfg.time_base, self._clock, policy, cfg.bounds)
        self._latest = self._book.newest  # the same dict: newest valid message per sender
        self._dropped: Counter[str] = self._book.dropped  # the same counter: every drop reason
        self._acks: list[ControlEvent] = []  # aborts to acknowledge (the ack thread publishes)
        self._ack_thread: threading.Thread | None = None
        self.acks_sent = 0
        self._alive: set[int] = set()
        self._left: set[int] = set()
        self._events: list[Event] = []  # presence: kind joined|left, drone = sender, monotonic s
        self._control: list[ControlEvent] = []
        self._closed = False
        self._sessions = SessionBook()  # which session speaks for each sender (identity.py)
        t_start = time.monotonic()
        for i in sorted(self.self_ids):  # own agents: alive by definition, not after a zenoh round trip
            self._alive.add(i)
            self._events.append(_presence(t_start, i, "joined"))
        self._publishers: dict[str, Any] = {}
        self._control_pubs: dict[str, Any] = {}
        self.name = cfg.name()  # participant name: the CN of this process's certificate
        self._tokens: list[Any] = []
        self._subs: list[Any] = []
        try:
            self._session = zenoh.open(conf)
        except Exception as exc:  # e.g. listen endpoint already in use
            raise RuntimeError(f"cannot open the zenoh session: {exc}") from exc
        try:
            s = self._session
            self.label = session_label(s)  # put on every prediction (the attachment; identity.py)
            for i in self.self_ids:
                self._sessions.own(i, self.label, self._clock())
            # Subscribers before tokens: seeing our token implies our subscribers are declared there.
            self._subs.append(s.declare_subscriber(cfg.pred_key("*"), self._on_pred))
            self._subs.append(
                s.declare_subscriber(keys.control_space(cfg.key_prefix, cfg.mission), self._on_control)
            )
            self._subs.append(
                s.liveliness().declare_subscriber(cfg.alive_key("*"), self._on_alive, history=True)
            )
            for i in sorted(self.self_ids):
                self._publisher(str(i))
            for i in sorted(self.self_ids):
                self._tokens.append(s.liveliness().declare_token(cfg.alive_key(i)))
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ Bus protocol
    @property
    def dropped(self) -> Counter[str]:
        """Snapshot of the drop counts by reason (thread-safe copy)."""
        with self._cond:
            return Counter(self._dropped)

    @property
    def delivered(self) -> int:
        return self._book.delivered

    @property
    def freshness(self) -> Freshness:
        """The receive-side book (newest messages, sender clock offsets); read it with the bus idle."""
        return self._book

    @property
    def session(self) -> Any:
        """The process's zenoh session, for other channels of the same mission (the served sim world)."""
        return self._session

    def publish(self, msg: PredictionMessage) -> None:
        """Encode (ValueError for an invalid message, as InProcBus) and put on pred/{msg.sender}."""
        self._put(str(msg.sender), encode(msg))

    def publish_raw(self, data: bytes, key_sender: int | str | None = None) -> None:
        """Put raw bytes on pred/{key_sender} (default: the sender field of the header, else "raw")."""
        data = bytes(data)
        self._put(_header_sender(data) if key_sender is None else str(key_sender), data)

    def latest(self, sender: int, now: float, stale_after: float) -> PredictionMessage | None:
        """Newest valid message of `sender`, or None if none, if the sender has left ("left") or if it
        is more than `stale_after` s old ("stale"): `now − stamp` on the mission clock (time base
        "stamps"), or measured on this receiver's clock through the sender's offset ("receiver")."""
        with self._cond:
            if sender in self._left:
                self._dropped["left"] += 1
                return None
            return self._book.latest(sender, now, stale_after)

    def close(self) -> None:
        """Undeclare tokens, subscribers and publishers, close the session (idempotent)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
            ack_thread = self._ack_thread
        if ack_thread is not None and ack_thread is not threading.current_thread():
            ack_thread.join(5.0)
        for obj in [*self._tokens, *self._subs, *self._publishers.values(), *self._control_pubs.values()]:
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._tokens.clear()
        self._subs.clear()
        self._publishers.clear()
        self._control_pubs.clear()
        session = getattr(self, "_session", None)
        if session is not None:
            with contextlib.suppress(Exception):
                session.close()

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ lock-step and presence
    def wait_for(self, expected: dict[int, int], timeout_s: float) -> set[int]:
        """Block until every sender s has a message with seq >= expected[s]; returns the senders still
        missing (empty on success). Returns early, with them, when all missing senders have left."""
        return self._wait_messages(
            lambda: {s for s, q in expected.items() if (m := self._latest.get(s)) is None or m.seq < q},
            timeout_s,
        )

    def wait_for_stamp(self, senders: set[int], stamp: float, timeout_s: float) -> set[int]:
        """Block until every sender's newest message has a stamp >= `stamp` (mission clock, s): the
        lock-step barrier of agents whose tick counts may differ (they joined at different ticks).
        Returns the senders still missing; returns early when all of them have left."""
        return self._wait_messages(
            lambda: {s for s in senders if (m := self._latest.get(s)) is None or m.stamp < stamp - 1e-12},
            timeout_s,
        )

    def _wait_messages(self, missing_now: Callable[[], set[int]], timeout_s: float) -> set[int]:
        """Wait on the condition until missing_now() (called with the lock held) is empty, only holds
        senders that have left or are quarantined (identity.py), the bus closes, or timeout_s passes;
        returns the last missing set."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                missing = missing_now()
                if not missing or missing <= self._left | self._sessions.quarantined or self._closed:
                    return missing
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return missing
                self._cond.wait(remaining)

    def wait_alive(self, senders: set[int], timeout_s: float) -> set[int]:
        """Block until every sender's token is seen (start-up barrier); returns those still missing."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                missing = set(senders) - self._alive
                remaining = deadline - time.monotonic()
                if not missing or remaining <= 0 or self._closed:
                    return missing
                self._cond.wait(remaining)

    def message_age(self, sender: int) -> float | None:
        """Seconds since `sender`'s newest valid prediction arrived, on this receiver's clock (None: none
        yet)."""
        with self._cond:
            t = self._book.received.get(sender)
        return None if t is None else self._clock() - t

    def alive(self) -> set[int]:
        with self._cond:
            return set(self._alive)

    @property
    def presence_events(self) -> list[Event]:
        """(time.monotonic() s, sender, "joined"|"left"|"second session"|"restart") in order of receipt
        (copy)."""
        with self._cond:
            return list(self._events)

    @property
    def session_reports(self) -> list[str]:
        """One line per second session heard speaking for a sender (identity.py), oldest first."""
        with self._cond:
            return [e.text for e in self._sessions.events]

    # ------------------------------------------------------------------ operator channel
    def publish_control(self, kind: str, payload: dict[str, Any]) -> None:
        """Send an operator message ("abort" | "status" | "abort_ack") with a JSON-serialisable dict
        payload (ValueError otherwise, see control.encode_control) on its key (acl.py): abort on
        control/abort, a status of drone i on control/status/i, an acknowledgement on control/ack/NAME."""
        data = encode_control(self.mission, kind, payload, sorted(self.self_ids))
        self.publish_control_raw(data, self._control_key(kind, payload))

    def publish_control_raw(self, data: bytes, key: str | None = None) -> None:
        """Put raw bytes on a control key (default: the abort key)."""
        self._check_open()
        key = key or keys.abort_key(self.cfg.key_prefix, self.mission)
        pub = self._control_pubs.get(key)
        if pub is None:
            pub = self._session.declare_publisher(
                key,
                encoding=zenoh.Encoding(CONTROL_ENCODING),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                express=True,
            )
            self._control_pubs[key] = pub
        pub.put(bytes(data))

    def _control_key(self, kind: str, payload: dict[str, Any]) -> str:
        p, m = self.cfg.key_prefix, self.mission
        if kind == ABORT:
            return keys.abort_key(p, m)
        if kind == ABORT_ACK:
            return keys.ack_key(p, m, self.name)
        drone = payload.get("drone")
        if not isinstance(drone, int) or isinstance(drone, bool) or drone not in self.self_ids:
            raise ValueError(
                f"a status must name a drone this process hosts ({sorted(self.self_ids)}), not {drone!r}"
            )
        return keys.status_key(p, m, drone)

    def control_events(self) -> list[ControlEvent]:
        """Control messages received since the last call (drained), oldest first."""
        with self._cond:
            out, self._control = self._control, []
            return out

    # ------------------------------------------------------------------ internals
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("ZenohBus is closed")

    def _publisher(self, key_sender: str) -> Any:
        pub = self._publishers.get(key_sender)
        if pub is None:
            pub = self._session.declare_publisher(
                self.cfg.pred_key(key_sender),
                encoding=zenoh.Encoding(PRED_ENCODING),
                # lock-step (simulated clock): every message is awaited, so none may be dropped (BLOCK);
                # real time: the newest wins and a late one is worthless (DROP)
                congestion_control=zenoh.CongestionControl.BLOCK
                if self.cfg.reliable
                else zenoh.CongestionControl.DROP,
                express=False,  # batched: see the module docstring
            )
            self._publishers[key_sender] = pub
        return pub

    def _put(self, key_sender: str, data: bytes) -> None:
        self._check_open()
        try:
            pub = self._publisher(key_sender)
        except Exception as exc:  # e.g. a key chunk zenoh rejects
            raise ValueError(f"cannot publish on sender key {key_sender!r}: {exc}") from exc
        pub.put(data, attachment=self.label.encode("ascii"))

    def _drop(self, reason: str) -> None:
        with self._cond:
            self._dropped[reason] += 1

    def _on_pred(self, sample: zenoh.Sample) -> None:
        """Zenoh callback thread: decode, check, keep the newest per sender. Never raises, no zenoh call."""
        try:
            key_sender = str(sample.key_expr).rsplit("/", 1)[-1]
            data = sample.payload.to_bytes()
        except Exception:
            self._drop("bad sample")
            return
        label = sample_label(sample)
        t_recv = self._clock()
        ok = key_sender.isascii() and key_sender.isdigit() and len(key_sender) <= 9
        sender = int(key_sender) if ok else -1  # -1: no sender id in the key
        with self._cond:
            n_events = len(self._sessions.events)
            if sender in self.known and not self._sessions.admit(sender, label, t_recv):
                quarantined = sender in self._sessions.quarantined
                self._dropped[TWO_STREAMS if quarantined else SECOND_SESSION] += 1
                self._events.extend(_session_event(e) for e in self._sessions.events[n_events:])
                return
            n_restarts = len(self._book.restart_events)
            msg = self._book.accept(data, key_sender, t_recv)
            if msg is not None:
                self._sessions.claim(msg.sender, label, t_recv)
                self._events.extend(self._book.restart_events[n_restarts:])  # "restart", naming the sender
            why = self._book.streams.found.get(sender)
            if why is not None and sender not in self._sessions.quarantined:
                # two streams under this label (streams.py): neither is trusted for the rest of the run
                self._sessions.quarantine(sender, label, t_recv, why)
                self._book.newest.pop(sender, None)  # fusion leaves it out from now on
                self._events.extend(_session_event(e) for e in self._sessions.events[n_events:])
            self._cond.notify_all()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            sender = int(str(sample.key_expr).rsplit("/", 1)[-1])
            joined = sample.kind == zenoh.SampleKind.PUT
        except Exception:
            self._drop("presence: bad key")
            return
        if sender not in self.known:
            self._drop("presence: unknown sender")
            return
        now = time.monotonic()
        with self._cond:
            if joined and sender not in self._alive:
                self._alive.add(sender)
                self._left.discard(sender)
                self._events.append(_presence(now, sender, "joined"))
            elif not joined and sender in self._alive:
                self._alive.discard(sender)
                self._left.add(sender)
                self._book.forget(sender)  # a restarted agent counts seq from 0, re-learns its offset
                if sender not in self.self_ids:
                    self._sessions.forget(sender)  # every session of it is gone: the next one claims it
                self._events.append(_presence(now, sender, "left"))
            self._cond.notify_all()

    def _on_control(self, sample: zenoh.Sample) -> None:
        """Zenoh callback thread: validate, queue; an abort is also queued for acknowledgement."""
        try:
            data = sample.payload.to_bytes()
            key = str(sample.key_expr)
        except Exception:
            self._drop("control: bad sample")
            return
        ev, reason = parse_control(data, self.mission, time.monotonic())
        if ev is None:
            self._drop(reason or "control: malformed")
            return
        reason = self._key_mismatch(key, ev)
        if reason:
            self._drop(reason)
            return
        with self._cond:
            self._control.append(ev)
            if ev.kind == ABORT and self.self_ids and not self._closed:
                self._acks.append(ev)
                if self._ack_thread is None:
                    self._ack_thread = threading.Thread(
                        target=self._ack_loop, name=f"abort-ack:{self.mission}", daemon=True
                    )
                    self._ack_thread.start()
            self._cond.notify_all()

    def _key_mismatch(self, key: str, ev: ControlEvent) -> str | None:
        """Why a valid control message does not belong on the key it came on (the key is what the ACL
        authenticates), or None: an abort only on control/abort, a status of drone i only on
        control/status/i, an acknowledgement only on control/ack/NAME naming drones NAME hosts."""
        p, m = self.cfg.key_prefix, self.mission
        if ev.kind == ABORT:
            ok = key == keys.abort_key(p, m)
        elif ev.kind == ABORT_ACK:
            name = key.rsplit("/", 1)[-1]
            drones = ev.payload.get("drones")
            hosted = keys.hosted_by(name, self.known)
            ok = (
                key == keys.ack_key(p, m, name)
                and isinstance(drones, list)
                and bool(drones)
                and all(isinstance(d, int) and d in hosted for d in drones)
            )
        else:
            drone = ev.payload.get("drone")
            ok = isinstance(drone, int | str) and key == keys.status_key(p, m, drone)
        return None if ok else f"control: {ev.kind} on the wrong key"

    def _ack_loop(self) -> None:
        """Publish an abort_ack for every queued abort until the bus closes; never raises."""
        while True:
            with self._cond:
                while not self._acks and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                pending, self._acks = self._acks, []
            for ev in pending:
                try:
                    self.publish_control(ABORT_ACK, ack_payload(ev, self.self_ids))
                    self.acks_sent += 1
                except Exception:  # closed meanwhile, or zenoh refused: count, keep going
                    self._drop("control: ack not sent")


__all__ = [
    "CONTROL_KINDS",
    "MAX_CONTROL_BYTES",
    "ControlEvent",
    "ZenohBus",
    "ZenohBusConfig",
    "zenoh_config",
]
