"""UDP transport to Tellos: one command socket per drone, one shared state-stream receiver per local port.

Why not djitellopy's sockets (docs/architecture.md, decision 26): djitellopy keeps one reply list per drone
IP filled by a receiver thread, and matches replies to commands by order only; any stray, duplicated,
late or extra reply (a firmware that answers `rc`) shifts every later answer. Its receiver threads also
end for good on the first exception (e.g. one non-ASCII state datagram), silencing every drone of the
process. Here:

- `CommandChannel`: a UDP socket `connect()`ed to the drone's (ip, port), so the kernel delivers only that
  drone's datagrams; a reader thread stamps every reply with its receive time. Replies are kept only while
  the driver has an exchange open (`open_exchange`); any other reply is discarded and counted. Every
  request sent and every reply discarded is noted in its `ledger` (drivers/tello/replies.py: which request
  a reply answers). The drone's own notices (`error Auto land`, sent around a landing it decided on,
  whatever was asked) are never kept as a reply; they and every `error …` that arrives while no exchange
  is open and answers no request the ledger owes go to `on_error(t, text)` (the driver's), called on the
  reader thread outside every lock. Sending never blocks (a full socket buffer or a network error is
  counted and reported, not raised into a loop).
- `StateReceiver`: binds the state port (8890 on real drones) once per process and network interface,
  parses each datagram strictly (drivers/tello/state.py) and hands it to the driver registered for its
  source IP. Datagrams from any other address, and malformed ones, are dropped and counted by reason; a
  malformed one from a registered address is also reported to its driver (`on_rejected`: a run of them is
  an event, never a silent link). The thread survives every error.

Interfaces: a drone with an `interface` (TelloConfig) has its command socket and its state receiver bound
to that interface (drivers/netif.py): two access-point Tellos both at 192.168.10.1, one behind each of two
Wi-Fi adapters, then have one state receiver each, so that the interface, not the source address (which
they share), says whose state a datagram is; and each command leaves through its drone's adapter.

Every thread is a daemon with bounded waits (≤ 0.1 s) and is joined on close. No exception ends a thread:
each is counted in the owner's `counts` (its own key, e.g. `recv_error`, plus `thread_error`) and logged
with its reason at the first and then every `ErrorLog.log_every`-th occurrence (no log flood), and the
thread goes on after a short pause (≤ 0.05 s, so that a persistent error cannot spin a core).

Raw traffic (`traffic`, a drivers/tello/traffic.py TrafficWriter, optional): every datagram that crossed
the wire, as it crossed it, with its time: a command when its send succeeded ("sent", stamped just before
the send), every datagram on the command socket ("reply", also one too long or nobody waited for), every
state datagram from the drone's address ("state", also one the parser rejects). A muted or failed send did
not leave the computer and is not recorded (it is counted: `counts["muted"]`, `counts["send_error"]`).
Handing a record over is a deque append (TrafficWriter): it never blocks a thread.

Mute (guardian takeover): `CommandChannel(muted=fn)` or `chan.muted = fn`; while `fn()` returns True,
`send()` sends nothing, returns False and counts `counts["muted"]`. `fn` is called synchronously right
before every send; a `fn` that raises is counted (`muted_check_error`) and does not mute.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import ClassVar

from flightstack.drivers.device_threads import ERROR_PAUSE_S, ErrorLog, MutedCheck, evaluate_mute
from flightstack.drivers.netif import udp_socket
from flightstack.drivers.tello.replies import ReplyLedger
from flightstack.drivers.tello.state import StateRejectedError, TelloTelemetry, parse_state
from flightstack.drivers.tello.traffic import TrafficWriter

LOG = logging.getLogger("flightstack.tello")
MAX_REPLY_BYTES = 256
ErrorCallback = Callable[[float, str], None]
NOTICES = ("error auto land",)
"""Replies a Tello sends of its own accord, never an answer (lower case, prefixes): `error Auto land`
around a landing it decided on (seen in a real console transcript against a `battery?` poll right after
`land`; docs/drivers.md)."""


def is_notice(text: str) -> bool:
    """A reply that is the drone's own notice (NOTICES), not an answer to any command."""
    return text.lower().startswith(NOTICES)


class CommandChannel:
    """Commands to one drone and its replies, each reply stamped with time.monotonic() (s)."""

    def __init__(
        self,
        host: str,
        port: int,
        bind_ip: str = "",
        muted: MutedCheck | None = None,
        traffic: TrafficWriter | None = None,
        on_error: ErrorCallback | None = None,
        interface: str | None = None,
    ) -> None:
        """Connect a UDP socket to (host, port) from (bind_ip, any port), through `interface` when one is
        named (netif.InterfaceError otherwise), and start the reply reader.

        muted: the guardian's takeover check (module docstring); settable later as `self.muted`.
        traffic: where every command sent and datagram received is recorded (module docstring)."""
        self.host, self.port = host, port
        self.muted = muted
        self.traffic = traffic
        self.on_error = on_error
        self._sock = udp_socket(interface)
        try:
            self._sock.bind((bind_ip, 0))
            self._sock.connect((host, port))
        except OSError:
            self._sock.close()
            raise
        self._sock.settimeout(0.1)
        self._lock = threading.Lock()
        self._open = False
        self._replies: deque[tuple[float, str]] = deque(maxlen=32)
        self.ledger = ReplyLedger()  # the requests still owed a reply
        self.last_rx_t = -float("inf")
        self.counts: Counter[str] = Counter()
        self.errors = ErrorLog(self.counts, f"tello {host} command channel", LOG)
        self.discarded: list[tuple[float, str]] = []  # (t, text) of replies nobody waited for (last 200)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read_loop, name=f"tello-cmd-{host}", daemon=True)
        self._thread.start()

    def send(self, text: str) -> bool:
        """Send one command datagram; False (counted) if muted or the network refused it. Never blocks."""
        if self._is_muted():
            verb = text.split(" ")[0]
            self.errors.record("muted", f"{verb!r} not sent: another process took over", thread=False)
            return False
        t = time.monotonic()
        try:
            self._sock.send(text.encode("ascii"), socket.MSG_DONTWAIT)
        except (OSError, ValueError) as exc:  # ValueError: non-ASCII text or a closed socket
            self.errors.record("send_error", f"sending {text.split(' ')[0]!r}: {exc}", thread=False)
            return False
        self.counts["sent"] += 1
        self.ledger.sent(t, text)
        if self.traffic is not None:
            self.traffic.sent(t, text)
        return True

    def _is_muted(self) -> bool:
        return evaluate_mute(self.muted, self.errors)

    def open_exchange(self) -> int:
        """Start keeping replies; discard (and count) what is pending. Returns the number discarded."""
        with self._lock:
            n = len(self._replies)
            for item in self._replies:
                self._discard(item)
            self._replies.clear()
            self._open = True
            return n

    def close_exchange(self) -> None:
        with self._lock:
            for item in self._replies:
                self._discard(item)
            self._replies.clear()
            self._open = False

    def pop_reply(self) -> tuple[float, str] | None:
        """The oldest reply kept since open_exchange (or None)."""
        with self._lock:
            return self._replies.popleft() if self._replies else None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def _discard(self, item: tuple[float, str]) -> bool:
        """A reply nobody waited for: counted, kept in `discarded`, given to the request it answers.
        Returns whether it answers one."""
        answers = self.ledger.place(*item) is not None
        self.counts["reply_discarded"] += 1
        self.discarded.append(item)
        del self.discarded[:-200]
        return answers

    def _read_loop(self) -> None:
        """Reply reader thread: survives every error (counted, logged without flooding)."""
        while not self._stop.is_set():
            try:
                self._read_one()
            except Exception as exc:
                self.errors.record("reader_error", exc)
                self._stop.wait(ERROR_PAUSE_S)

    def _read_one(self) -> None:
        """Receive and file one reply (waits ≤ 0.1 s)."""
        try:
            data = self._sock.recv(2048)
        except TimeoutError:
            return
        except OSError as exc:  # e.g. ICMP port unreachable surfaced as ECONNREFUSED, ENETUNREACH: go on
            if not self._stop.is_set():
                self.errors.record("recv_error", exc)
                self._stop.wait(ERROR_PAUSE_S)
            return
        t = time.monotonic()
        if self.traffic is not None:
            self.traffic.reply(t, data)
        if len(data) > MAX_REPLY_BYTES:
            self.counts["reply_too_long"] += 1
            return
        text = data.decode("ascii", errors="replace").strip()
        notice = is_notice(text)
        with self._lock:
            self.last_rx_t = t
            self.counts["received"] += 1
            unanswered = notice
            if notice:
                self.counts["notice"] += 1
            elif self._open:
                self._replies.append((t, text))
            else:
                unanswered = not self._discard((t, text))
        if unanswered and text.lower().startswith("error") and self.on_error is not None:
            try:
                self.on_error(t, text)
            except Exception as exc:  # the driver's: counted, never the reader's end
                self.errors.record("on_error_error", exc)


StateCallback = Callable[[TelloTelemetry], None]
RejectedCallback = Callable[[float, str], None]
"""A state datagram from the drone that the parser rejected: (receive time, time.monotonic() s; reason)."""


class StateReceiver:
    """The state stream of every drone of this process on one local UDP port (shared, reference-counted)."""

    _instances: ClassVar[dict[tuple[str | None, str, int], StateReceiver]] = {}
    _instances_lock: ClassVar[threading.Lock] = threading.Lock()

    @classmethod
    def acquire(
        cls,
        host: str,
        callback: StateCallback,
        on_rejected: RejectedCallback,
        port: int = 8890,
        bind_ip: str = "",
        traffic: TrafficWriter | None = None,
        interface: str | None = None,
    ) -> StateReceiver:
        """Register `callback` for state datagrams from `host` and `on_rejected` for those of its datagrams
        that the parser rejects; binds (bind_ip, port) on first use, through `interface` when one is named:
        one receiver per interface, address and port.
        traffic: where every state datagram from `host` is recorded, as received (module docstring).

        Raises OSError naming the port when it cannot be bound (another program holds it), or the
        interface (netif.InterfaceError)."""
        key = (interface, bind_ip, port)
        with cls._instances_lock:
            rx = cls._instances.get(key)
            if rx is None:
                rx = cls(bind_ip, port, interface)
                cls._instances[key] = rx
            rx._register(host, callback, on_rejected, traffic)
            return rx

    def release(self, host: str) -> None:
        """Unregister `host`; the last one closes the port before another acquire can try to bind it."""
        with self._instances_lock:
            with self._lock:
                self._callbacks.pop(host, None)
                self._traffic.pop(host, None)
                if self._callbacks:
                    return
            self._instances.pop((self.interface, self.bind_ip, self.port), None)
            self._stop.set()
            self._thread.join(timeout=1.0)  # its recv times out within 0.1 s; it takes no registry lock
            self._sock.close()

    def __init__(self, bind_ip: str, port: int, interface: str | None = None) -> None:
        self.bind_ip, self.port, self.interface = bind_ip, port, interface
        self._sock = udp_socket(interface)
        where = f"{bind_ip or '*'}:{port}" + (f" on {interface}" if interface else "")
        try:
            self._sock.bind((bind_ip, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(exc.errno, f"cannot bind the Tello state port {where}: {exc.strerror}") from exc
        self._sock.settimeout(0.1)
        self._lock = threading.Lock()
        self._callbacks: dict[str, tuple[StateCallback, RejectedCallback]] = {}
        self._traffic: dict[str, TrafficWriter] = {}
        self.dropped: Counter[str] = Counter()  # datagrams dropped, by reason
        self.counts: Counter[str] = Counter()  # "delivered" datagrams; thread errors (ErrorLog)
        self.errors = ErrorLog(self.counts, f"tello state receiver {where}", LOG)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"tello-state-{port}", daemon=True)
        self._thread.start()

    def _register(
        self, host: str, callback: StateCallback, on_rejected: RejectedCallback, traffic: TrafficWriter | None
    ) -> None:
        with self._lock:
            self._callbacks[host] = (callback, on_rejected)
            if traffic is None:
                self._traffic.pop(host, None)
            else:
                self._traffic[host] = traffic

    def _loop(self) -> None:
        """State thread: survives every error (counted in `counts`, logged without flooding)."""
        while not self._stop.is_set():
            try:
                self._receive_one()
            except Exception as exc:
                self.errors.record("receiver_error", exc)
                self._stop.wait(ERROR_PAUSE_S)

    def _receive_one(self) -> None:
        """Receive, parse and dispatch one state datagram (waits ≤ 0.1 s)."""
        try:
            data, addr = self._sock.recvfrom(2048)
        except TimeoutError:
            return
        except OSError as exc:  # ENETUNREACH, ENOBUFS, a vanished interface...: go on reading
            if not self._stop.is_set():
                self.errors.record("recv_error", exc)
                self._stop.wait(ERROR_PAUSE_S)
            return
        t = time.monotonic()
        with self._lock:
            callbacks = self._callbacks.get(addr[0])
            traffic = self._traffic.get(addr[0])
        if traffic is not None:
            traffic.state(t, data)
        if callbacks is None:
            self.dropped["unknown_sender"] += 1
            return
        cb, on_rejected = callbacks
        try:
            sample = parse_state(data, t)
        except StateRejectedError as exc:
            self.dropped[exc.reason] += 1
            self._call(addr[0], on_rejected, t, exc.reason)
            return
        if self._call(addr[0], cb, sample):
            self.counts["delivered"] += 1

    def _call(self, host: str, callback: Callable[..., None], *args: object) -> bool:
        """Run a driver's callback; False if it raised (counted `callback_error`, logged sparsely): a
        driver bug must not silence the other drones."""
        try:
            callback(*args)
        except Exception as exc:
            self.dropped["callback_error"] += 1
            self.errors.record("callback_error", f"state callback for {host}: {type(exc).__name__}: {exc}")
            return False
        return True


class TelloLink:
    """One Tello's side of the transport: its command channel and its place on the shared state port.

    `chan` stays set after `close()` (a closed channel counts what is still sent); `rx` is None when
    closed. The mute check (module docstring) is read through `is_muted`, before every send."""

    def __init__(
        self,
        host: str,
        control_port: int,
        state_port: int = 8890,
        bind_ip: str = "",
        traffic: TrafficWriter | None = None,
        interface: str | None = None,
    ) -> None:
        """traffic: where this drone's raw traffic is recorded (module docstring); None: nowhere.
        interface: the network interface the drone is reached through (module docstring); None: any."""
        self.host, self.control_port, self.state_port, self.bind_ip = host, control_port, state_port, bind_ip
        self.interface = interface
        self.traffic = traffic
        self.chan: CommandChannel | None = None
        self.rx: StateReceiver | None = None
        self._muted: MutedCheck | None = None

    def open(
        self, on_state: StateCallback, on_rejected: RejectedCallback, on_error: ErrorCallback | None = None
    ) -> None:
        """Register `on_state` for this drone's state packets and `on_rejected` for its datagrams the parser
        rejects, then open the command channel (OSError) with `on_error` for the `error …` replies that
        answer nothing (CommandChannel)."""
        self.rx = StateReceiver.acquire(
            self.host, on_state, on_rejected, self.state_port, self.bind_ip, self.traffic, self.interface
        )
        self.chan = CommandChannel(
            self.host,
            self.control_port,
            self.bind_ip,
            muted=self.is_muted,
            traffic=self.traffic,
            on_error=on_error,
            interface=self.interface,
        )

    def close(self) -> None:
        if self.rx is not None:
            self.rx.release(self.host)
            self.rx = None
        if self.chan is not None:
            self.chan.close()

    def set_muted(self, muted: MutedCheck | None) -> None:
        self._muted = muted

    def is_muted(self) -> bool:
        m = self._muted
        return m is not None and m()
