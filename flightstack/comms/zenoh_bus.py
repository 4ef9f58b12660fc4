"""Prediction messages over Zenoh (DESIGN §6): the network implementation of the `Bus` protocol.

Key layout (one mission = one key space; `prefix` defaults to "flightstack"):
    {prefix}/{mission}/pred/{sender}     PredictionMessage bytes (messages.encode), one key per sender
    {prefix}/{mission}/alive/{sender}    liveliness token, one per agent hosted by a process
    {prefix}/{mission}/control           operator channel, UTF-8 JSON (flightstack/comms/control.py)
                                         {"mission": str, "kind": "abort"|"status"|"abort_ack",
                                          "payload": {...}, "origin": [ids of the publishing process]}

Delivery and QoS. One callback subscriber on `{prefix}/{mission}/pred/*` receives every sender. The
callback hands the bytes to `freshness.Freshness.accept` (decode, sequence and sender-clock checks; pure
Python, no zenoh call, never blocks on anything but a short lock), which keeps the newest valid message
per sender in a dict: a ring buffer of depth 1 *per sender*.
A `RingChannel(1)` handler would not do: on a wildcard subscription it keeps the newest sample of *any*
sender and silently loses the others; one RingChannel per sender would not see unknown or mismatched
senders (which must be counted) and would force `wait_for` to poll. The default FIFO handler blocks the
session when Python is slow. Bad messages are dropped and counted in `dropped` by reason (the reasons of
`decode`, plus "key sender mismatch", "old or duplicate seq", "stale", "stamp ahead", "left",
"control: ..."), exactly like `InProcBus`. Predictions are reliable; congestion control is DROP in real
time (a newer one follows next tick) and BLOCK when `reliable` is set (lock-step simulations wait for
every message, so a dropped one would stall a tick for the whole lock-step timeout). They are *not*
express: zenoh's tx queue holds only 2 batches per priority and a DROP message that finds both taken
for 1 ms is discarded; express puts every message in its own batch, so a burst from a CPU-starved process
lost messages in testing, while batched messages share one batch (the batch is flushed as soon as the link
is free: hop latency p50 unchanged, ~0.3 ms between two processes on loopback). Control messages are
express, congestion control BLOCK (never dropped), priority INTERACTIVE_HIGH.

Own-process loopback. A Zenoh session receives its own publications (verified with zenoh 1.10.2: the
sample is delivered to the local subscriber asynchronously, on the subscriber's callback thread), so
messages of agents hosted in this process take the same path as remote ones: encode -> Zenoh -> decode.
`wait_for` covers own senders too; the result is identical to `InProcBus`, where publish = decode.

Lock-step. `wait_for({sender: seq})` blocks (threading.Condition, no polling) until each sender's newest
message has seq >= the expected one, or the sender has left, or the timeout expires. A runner that
publishes, waits, then reads gets bit-identical results to the in-process bus.

Presence. Each process declares a liveliness token per hosted agent *after* declaring its subscribers,
so a peer that sees the token has also received the subscriber declarations (same link, in order) and
its next publication reaches that process. A liveliness subscriber (history=True) tracks `alive()` and
appends `presence_events` (monotonic time s, sender, "joined"|"left"); agents of this process are alive
(and "joined") from construction on. A killed process closes its TCP
links and is seen as left in ~0.1-0.2 s; a hung one (stopped, partitioned) only after `lease_ms` (the
transport lease; keep-alives every lease/4). A sender that has left reads as None (counted "left") and
its newest message and sequence number are forgotten, so a restarted agent (seq from 0) is accepted.

Time base (issue 15, freshness.py). `cfg.time_base` "stamps" (the default; lock-step runs on a simulated
clock): a message's age is `now − stamp` on the mission clock, as the in-process bus. "receiver" (real
time, set by `factory.make_bus` for hardware missions): each sender's stamps are on its own computer's
monotonic clock; the receiver learns a bounded offset per sender when it joins (first messages, or
after `rejoin_after_s` of silence, or after it left the bus) and measures ages on its own
time.monotonic() through it. `now` passed to `latest` is then unused.

Abort acknowledgement (issue 15). A process hosting agents (`self_ids` not empty) answers every valid
"abort" it receives with an "abort_ack" control message (control.ack_payload: abort id, its drone ids,
pid, host) as soon as the subscriber callback has it: the callback queues it and the bus's ack thread
publishes it (the callback itself never calls zenoh). The abort is also queued for `control_events()`:
the runner lands at its next check. Operator tools and the served world (no agents) do not acknowledge.

Threading. Zenoh-python runs callbacks on its own (non-daemon) threads; all shared state is guarded by
one lock/condition; the callbacks never call zenoh. The ack thread (daemon, started at the first abort)
only publishes. `close()` ends the ack thread, undeclares everything and closes the session, which ends
zenoh's threads: always close (the class is a context manager).

Units: message stamps and `latest(now, stale_after)` are mission-clock seconds; `presence_events` and
`ControlEvent.time` are `time.monotonic()` seconds; `lease_ms` is milliseconds; `timeout_s` seconds.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

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
from flightstack.comms.freshness import TIME_BASES, Freshness, OffsetPolicy, TimeBase
from flightstack.comms.messages import MAGIC, MAX_MISSION_NAME, PredictionMessage, encode

TLS_PATH_KEYS = frozenset(
    {
        "root_ca_certificate",
        "listen_certificate",
        "listen_private_key",
        "connect_certificate",
        "connect_private_key",
    }
)
_KEY_FORBIDDEN = frozenset("*$?#/")


@dataclass(frozen=True)
class ZenohBusConfig:
    """Where and how one process joins the mission's Zenoh network (peer mode, no multicast scouting).

    Peers do not relay for each other: give each process a `listen` endpoint and `connect` it to the
    endpoints of all the others (full mesh), e.g. "tcp/127.0.0.1:17447" or "tls/host:port" with `tls`.
    `tls`: keys of zenoh's transport/link/tls (root_ca_certificate, listen_certificate,
    listen_private_key, connect_certificate, connect_private_key: file paths; enable_mtls,
    verify_name_on_connect: bool). `usrpwd`: (user, password) sent to peers; a peer checks it only if it
    sets "transport/auth/usrpwd/dictionary_file" (through `extra_json5`). `extra_json5`: raw zenoh config
    keys -> JSON5 text, applied last (can override anything set here, e.g. access_control).
    """

    mission: str
    self_ids: set[int]
    known_senders: set[int]
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    lease_ms: int = 1000
    key_prefix: str = "flightstack"
    tls: dict[str, Any] | None = None
    usrpwd: tuple[str, str] | None = None
    extra_json5: dict[str, str] = field(default_factory=dict)
    reliable: bool = False  # predictions never dropped under congestion (lock-step sims wait for each)
    time_base: TimeBase = "stamps"  # "receiver": real time across computers (module docstring)

    def pred_key(self, sender: int | str) -> str:
        return f"{self.key_prefix}/{self.mission}/pred/{sender}"

    def alive_key(self, sender: int | str) -> str:
        return f"{self.key_prefix}/{self.mission}/alive/{sender}"

    def control_key(self) -> str:
        return f"{self.key_prefix}/{self.mission}/control"


def _insert(conf: zenoh.Config, key: str, json5: str, name: str | None = None) -> None:
    try:
        conf.insert_json5(key, json5)
    except Exception as exc:  # zenoh.ZError: unknown key, bad JSON5, bad endpoint, ...
        raise ValueError(f"invalid zenoh config {name or key!r}: {exc}") from exc


def _validate(cfg: ZenohBusConfig) -> None:
    if not isinstance(cfg.mission, str) or not cfg.mission:
        raise ValueError("invalid 'mission': must be a non-empty string")
    if len(cfg.mission.encode("utf-8")) > MAX_MISSION_NAME:
        raise ValueError(f"invalid 'mission': longer than {MAX_MISSION_NAME} bytes")
    if "/" in cfg.mission or set(cfg.mission) & _KEY_FORBIDDEN:
        raise ValueError(f"invalid 'mission': {cfg.mission!r} is not a plain key-expression chunk")
    prefix = cfg.key_prefix
    if not isinstance(prefix, str) or any(not c or set(c) & _KEY_FORBIDDEN for c in prefix.split("/")):
        raise ValueError(f"invalid 'key_prefix': {prefix!r} is not a plain key expression")
    try:
        zenoh.KeyExpr(cfg.pred_key(0))
    except Exception as exc:
        raise ValueError(f"invalid 'mission'/'key_prefix': {exc}") from exc
    for name, ids in (("self_ids", cfg.self_ids), ("known_senders", cfg.known_senders)):
        if not all(isinstance(i, int) and 0 <= i < 2**16 for i in ids):
            raise ValueError(f"invalid {name!r}: ids must be integers in [0, 65535]")
    if not set(cfg.self_ids) <= set(cfg.known_senders):
        raise ValueError("invalid 'self_ids': every hosted agent must also be in known_senders")
    if cfg.time_base not in TIME_BASES:
        raise ValueError(f"invalid 'time_base': {cfg.time_base!r} (expected one of {TIME_BASES})")
    if not isinstance(cfg.lease_ms, int) or cfg.lease_ms <= 0:
        raise ValueError("invalid 'lease_ms': must be a positive integer (milliseconds)")
    for name, eps in (("listen", cfg.listen), ("connect", cfg.connect)):
        if isinstance(eps, str) or not all(isinstance(e, str) and "/" in e for e in eps):
            raise ValueError(f"invalid {name!r}: expected a list of '<protocol>/<address>' endpoints")


def zenoh_config(cfg: ZenohBusConfig) -> zenoh.Config:
    """The zenoh.Config of `cfg`: peer mode, multicast scouting off, explicit endpoints, lease.

    Raises ValueError naming the offending key for anything zenoh (or this check) rejects."""
    _validate(cfg)
    conf = zenoh.Config()
    _insert(conf, "mode", '"peer"')
    _insert(conf, "scouting/multicast/enabled", "false")
    # Do not wait 500 ms in zenoh.open for scouting: connections are explicit, and declarations made
    # before a link comes up are propagated when it does (retries: connect/retry, default ~1 s).
    _insert(conf, "scouting/delay", "0")
    _insert(conf, "listen/endpoints", json.dumps(list(cfg.listen)), "listen")
    _insert(conf, "connect/endpoints", json.dumps(list(cfg.connect)), "connect")
    _insert(conf, "transport/link/tx/lease", str(cfg.lease_ms), "lease_ms")
    if cfg.tls is not None:
        if not isinstance(cfg.tls, dict):
            raise ValueError("invalid 'tls': expected a dict")
        for k, v in cfg.tls.items():
            if k in TLS_PATH_KEYS and not Path(str(v)).is_file():
                raise ValueError(f"invalid 'tls.{k}': no such file {v!r}")
            _insert(conf, f"transport/link/tls/{k}", json.dumps(v), f"tls.{k}")
    if cfg.usrpwd is not None:
        if len(cfg.usrpwd) != 2 or not all(isinstance(s, str) and s for s in cfg.usrpwd):
            raise ValueError("invalid 'usrpwd': expected (user, password), non-empty strings")
        _insert(conf, "transport/auth/usrpwd/user", json.dumps(cfg.usrpwd[0]), "usrpwd")
        _insert(conf, "transport/auth/usrpwd/password", json.dumps(cfg.usrpwd[1]), "usrpwd")
    for k, v in cfg.extra_json5.items():
        if not isinstance(v, str):
            raise ValueError(f"invalid zenoh config {k!r}: value must be JSON5 text (str)")
        _insert(conf, k, v)
    return conf


def _header_sender(data: bytes) -> str:
    """The sender field of a message header, as a key chunk ("raw" when there is no readable header)."""
    if len(data) >= 8 and data[:4] == MAGIC:
        return str(int.from_bytes(data[6:8], "little"))
    return "raw"


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
        self._book = Freshness(cfg.mission, self.known, cfg.time_base, self._clock, policy)
        self._latest = self._book.newest  # the same dict: newest valid message per sender
        self._dropped: Counter[str] = self._book.dropped  # the same counter: every drop reason
        self._acks: list[ControlEvent] = []  # aborts to acknowledge (the ack thread publishes)
        self._ack_thread: threading.Thread | None = None
        self.acks_sent = 0
        self._alive: set[int] = set()
        self._left: set[int] = set()
        self._events: list[tuple[float, int, str]] = []
        self._control: list[ControlEvent] = []
        self._closed = False
        t_start = time.monotonic()
        for i in sorted(self.self_ids):  # own agents: alive by definition, not after a zenoh round trip
            self._alive.add(i)
            self._events.append((t_start, i, "joined"))
        self._publishers: dict[str, Any] = {}
        self._tokens: list[Any] = []
        self._subs: list[Any] = []
        try:
            self._session = zenoh.open(conf)
        except Exception as exc:  # e.g. listen endpoint already in use
            raise RuntimeError(f"cannot open the zenoh session: {exc}") from exc
        try:
            s = self._session
            # Subscribers before tokens: seeing our token implies our subscribers are declared there.
            self._subs.append(s.declare_subscriber(cfg.pred_key("*"), self._on_pred))
            self._subs.append(s.declare_subscriber(cfg.control_key(), self._on_control))
            self._subs.append(
                s.liveliness().declare_subscriber(cfg.alive_key("*"), self._on_alive, history=True)
            )
            for i in sorted(self.self_ids):
                self._publisher(str(i))
            self._control_pub = s.declare_publisher(
                cfg.control_key(),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                express=True,
            )
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
        for obj in [*self._tokens, *self._subs, *self._publishers.values()]:
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._tokens.clear()
        self._subs.clear()
        self._publishers.clear()
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
        senders that have left, the bus closes, or timeout_s passes; returns the last missing set."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._cond:
            while True:
                missing = missing_now()
                if not missing or missing <= self._left or self._closed:
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
    def presence_events(self) -> list[tuple[float, int, str]]:
        """(time.monotonic() s, sender, "joined"|"left") in order of receipt (copy)."""
        with self._cond:
            return list(self._events)

    # ------------------------------------------------------------------ operator channel
    def publish_control(self, kind: str, payload: dict[str, Any]) -> None:
        """Send an operator message ("abort" | "status" | "abort_ack") with a JSON-serialisable dict
        payload (ValueError otherwise, see control.encode_control)."""
        self.publish_control_raw(encode_control(self.mission, kind, payload, sorted(self.self_ids)))

    def publish_control_raw(self, data: bytes) -> None:
        self._check_open()
        self._control_pub.put(bytes(data))

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
        pub.put(data)

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
        t_recv = self._clock()
        with self._cond:
            if self._book.accept(data, key_sender, t_recv) is not None:
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
                self._events.append((now, sender, "joined"))
            elif not joined and sender in self._alive:
                self._alive.discard(sender)
                self._left.add(sender)
                self._book.forget(sender)  # a restarted agent counts seq from 0, re-learns its offset
                self._events.append((now, sender, "left"))
            self._cond.notify_all()

    def _on_control(self, sample: zenoh.Sample) -> None:
        """Zenoh callback thread: validate, queue; an abort is also queued for acknowledgement."""
        try:
            data = sample.payload.to_bytes()
        except Exception:
            self._drop("control: bad sample")
            return
        ev, reason = parse_control(data, self.mission, time.monotonic())
        if ev is None:
            self._drop(reason or "control: malformed")
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
