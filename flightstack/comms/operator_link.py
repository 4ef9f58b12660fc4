"""The loopback operator channel of in-process missions: `flightstack abort` from another
terminal of the same computer reaches a `flightstack fly` whose agents share the in-process bus.

    flightstack abort MISSION  --UDP-->  127.0.0.1:PORT  LoopbackOperatorListener (in the fly process)
                               <--UDP--  abort_ack {"drones": [...], "pid", "host", "abort_id"}

PORT is the mission's `bus.operator_port`, or by default `default_operator_port(mission.name)`:
20000 + CRC-32(name) mod 10000, the same in every process that reads the mission and outside the
ephemeral port ranges of Linux (32768-60999) and Windows (49152-65535).

The listener binds 127.0.0.1 only and also drops (counted "operator: foreign sender") any datagram
whose source address is not 127.0.0.1. A datagram is one control message of flightstack/comms/control.py
(JSON; at most MAX_DATAGRAM_BYTES bytes); only kind "abort" of this mission is accepted. Anything else is
dropped and counted in `dropped` ("operator: too large" | "malformed" | "other mission" |
"unknown kind" | ...); nothing a sender does raises in the listener, whose thread catches and counts
every error and keeps running. A valid abort is queued for `control_events()` (the in-process bus hands
it to the runner, which lands at its next check) and acknowledged at once, from the listener thread,
to the sending address, whatever the runner is doing.

Signed aborts. On real hardware the listener is given the operator's public key (from the
mission's `bus.certs`: `operator.pem`, checked against `ca.pem`) and accepts only datagrams of the form

    <control JSON> NUL <DER ECDSA P-256/SHA-256 signature of the JSON by operator.key>

(`signed_datagram`): any other local process can reach a loopback port, only the holder of the
operator's key can land the mission this way. Drops: "operator: unsigned", "operator: bad signature".
Simulated missions listen without a key (unsigned aborts accepted). In both, a copy of an abort id
already queued (the operator resends until acknowledged; or a replay) is acknowledged again but not
queued again (`repeats`; the last MAX_SEEN ids are kept).

Units: times are time.monotonic() seconds; POLL_S is how long `close()` may wait for the thread (s).
"""

from __future__ import annotations

import socket
import threading
import time
import zlib
from collections import Counter
from typing import TYPE_CHECKING

from flightstack.comms.certs import sign, verify
from flightstack.comms.control import (
    ABORT,
    ABORT_ACK,
    ControlEvent,
    ack_payload,
    encode_control,
    parse_control,
)

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric import ec

    from flightstack.config.mission import Mission

OPERATOR_HOST = "127.0.0.1"
MAX_DATAGRAM_BYTES = 4096  # one operator datagram (bytes); an abort is ~150
PORT_BASE = 20000
PORT_SPAN = 10000
POLL_S = 0.1  # the listener thread checks for close() this often (s)
MAX_SEEN = 1024  # abort ids remembered against replays
SEPARATOR = b"\x00"  # between the JSON and its signature (JSON text never contains NUL)


def signed_datagram(body: bytes, key: ec.EllipticCurvePrivateKey) -> bytes:
    """`body` (a control message) followed by NUL and the operator's signature of it."""
    return body + SEPARATOR + sign(key, body)


def split_signed(data: bytes) -> tuple[bytes, bytes | None]:
    """(body, signature) of a datagram; signature None when there is no separator."""
    body, sep, sig = data.partition(SEPARATOR)
    return (body, sig) if sep else (body, None)


def default_operator_port(mission_name: str) -> int:
    """The well-known loopback UDP port of a mission without `bus.operator_port`."""
    return PORT_BASE + zlib.crc32(mission_name.encode("utf-8")) % PORT_SPAN


def operator_port(mission: Mission) -> int:
    """The loopback UDP port of `mission`'s operator channel (`bus.operator_port` or the default)."""
    port = mission.bus.operator_port
    return default_operator_port(mission.name) if port is None else int(port)


class LoopbackOperatorListener:
    """Receives operator aborts on 127.0.0.1:`port`/UDP for the agents `hosted` by this process and
    acknowledges each at once; see the module docstring. Always close (a context manager)."""

    def __init__(
        self,
        mission: str,
        port: int,
        hosted: set[int] | frozenset[int],
        verifier: ec.EllipticCurvePublicKey | None = None,
    ) -> None:
        """verifier: the operator's public key; when set, only aborts it signed are accepted."""
        self.mission = mission
        self.hosted = frozenset(hosted)
        self.verifier = verifier
        self._seen: list[str] = []
        self.repeats = 0  # copies of an abort id already queued (acknowledged, not queued again)
        self._lock = threading.Lock()
        self._events: list[ControlEvent] = []
        self._dropped: Counter[str] = Counter()
        self.acks_sent = 0
        self._stop = threading.Event()
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((OPERATOR_HOST, port))
        except OSError as exc:
            sock.close()
            raise RuntimeError(
                f"operator channel: cannot listen on {OPERATOR_HOST}:{port}/udp ({exc}); is another "
                f"process of mission {mission!r} running? Set bus.operator_port to a free port"
            ) from exc
        sock.settimeout(POLL_S)
        self._sock = sock
        self.port: int = sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, name=f"operator-listener:{self.port}", daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> Counter[str]:
        """Drop counts by reason (a copy)."""
        with self._lock:
            return Counter(self._dropped)

    def control_events(self) -> list[ControlEvent]:
        """Aborts received since the last call (drained), oldest first."""
        with self._lock:
            out, self._events = self._events, []
            return out

    def close(self) -> None:
        """Stop the thread (within POLL_S) and close the socket (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(5 * POLL_S + 1.0)
        self._sock.close()

    def __enter__(self) -> LoopbackOperatorListener:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _drop(self, reason: str) -> None:
        with self._lock:
            self._dropped[reason] += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self._sock.recvfrom(MAX_DATAGRAM_BYTES + 1)
            except TimeoutError:
                continue
            except OSError:  # e.g. an ICMP error reported on the socket, or closed under us
                if self._stop.is_set():
                    return
                self._drop("operator: socket error")
                time.sleep(0.001)
                continue
            try:
                self._handle(data, addr, time.monotonic())
            except Exception:  # never let the listener die
                self._drop("operator: internal error")

    def _handle(self, data: bytes, addr: tuple[str, int], t_recv: float) -> None:
        if addr[0] != OPERATOR_HOST:
            self._drop("operator: foreign sender")
            return
        if self.verifier is not None:
            data, sig = split_signed(data)
            if sig is None:
                self._drop("operator: unsigned")
                return
            if not verify(self.verifier, data, sig):
                self._drop("operator: bad signature")
                return
        ev, reason = parse_control(
            data, self.mission, t_recv, frozenset({ABORT}), MAX_DATAGRAM_BYTES, prefix="operator"
        )
        if ev is None:
            self._drop(reason or "operator: malformed")
            return
        abort_id = ev.payload.get("id")
        with self._lock:
            if isinstance(abort_id, str) and abort_id in self._seen:
                self.repeats += 1  # a resent copy (or a replay): acknowledged again, acted on once
            else:
                if isinstance(abort_id, str):
                    self._seen = [*self._seen[-(MAX_SEEN - 1) :], abort_id]
                self._events.append(ev)
        ack = encode_control(self.mission, ABORT_ACK, ack_payload(ev, self.hosted), sorted(self.hosted))
        try:
            self._sock.sendto(ack, addr)
        except OSError:
            self._drop("operator: ack not sent")
            return
        with self._lock:
            self.acks_sent += 1


class LoopbackOperatorClient:
    """The operator's end (`flightstack abort`): sends to the listener, receives its acknowledgements."""

    def __init__(self, mission: str, port: int) -> None:
        self.mission = mission
        self.address = (OPERATOR_HOST, port)
        self.dropped: Counter[str] = Counter()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((OPERATOR_HOST, 0))

    def send(self, data: bytes) -> None:
        """One datagram to the listener; a refused or failed send is counted, not raised."""
        try:
            self._sock.sendto(data, self.address)
        except OSError:
            self.dropped["operator: send failed"] += 1

    def receive(self, timeout_s: float) -> list[ControlEvent]:
        """Acknowledgements that arrive within timeout_s (s); returns after the first datagram."""
        self._sock.settimeout(max(timeout_s, 1e-4))
        out: list[ControlEvent] = []
        try:
            data, addr = self._sock.recvfrom(MAX_DATAGRAM_BYTES + 1)
        except (TimeoutError, OSError):  # nothing yet; or ECONNREFUSED: no listener (yet)
            return out
        t = time.monotonic()
        if addr != self.address:
            self.dropped["operator: foreign sender"] += 1
            return out
        ev, reason = parse_control(
            data, self.mission, t, frozenset({ABORT_ACK}), MAX_DATAGRAM_BYTES, prefix="operator"
        )
        if ev is None:
            self.dropped[reason or "operator: malformed"] += 1
        else:
            out.append(ev)
        return out

    def close(self) -> None:
        self._sock.close()


__all__ = [
    "MAX_DATAGRAM_BYTES",
    "OPERATOR_HOST",
    "LoopbackOperatorClient",
    "LoopbackOperatorListener",
    "default_operator_port",
    "operator_port",
    "signed_datagram",
    "split_signed",
]
