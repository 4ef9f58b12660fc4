"""An emulated device's radio: its UDP sockets pass a seeded impairment model (flightstack.netem).

`DeviceRadio` holds one `LinkModel` per named link of one device (e.g. a Tello's "command" uplink and its
"reply", "state" and "video" downlinks), sharing the device's blackout windows, and one `DelayLine`:
a scheduler thread that sends every delayed datagram at its due time, so that no device loop ever
sleeps for the network. `ImpairedSocket` wraps a device's socket:

* `sendto(data, addr)` (leaving the device): the link chosen by `route(addr)` decides; the copies to
  deliver are queued on the delay line (None: sent at once, unimpaired);
* `recvfrom(n)` (entering the device): every datagram that arrived is decided on the uplink at once
  and kept until its due time; a call returns the earliest due one and honours the caller's timeout
  (blocking, timeout, or non-blocking: `BlockingIOError`), waiting in select() on the socket or the next
  due time, whichever comes first. The device's own receive loop is unchanged.

Everything else (fileno, close, settimeout, getsockname, ...) is the wrapped socket's. Times are
time.monotonic() seconds. Counters: `radio.counts()` (per link: packets, delivered, lost, blackout,
queue, duplicated, reordered, spiked; plus delay_mean_ms of the delivered packets).
"""

from __future__ import annotations

import errno
import heapq
import itertools
import math
import select
import socket
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, Protocol

from flightstack.netem import LinkModel, NetworkProfile, blackout_windows

Address = tuple[str, int]
COUNTERS = ("packets", "delivered", "lost", "blackout", "queue", "duplicated", "reordered", "spiked")
"""The counters every link reports (LinkModel.counts), 0 included."""


def counter_row(names: tuple[str, ...], counts: Mapping[str, int], delay_sum_s: float) -> dict[str, float]:
    """A link's counters (every one of `names`, 0 included) and delay_mean_ms of what it delivered."""
    row: dict[str, float] = dict.fromkeys(names, 0.0)
    row.update(counts)
    n = counts.get("delivered", 0)
    row["delay_mean_ms"] = round(1e3 * delay_sum_s / n, 3) if n else 0.0
    return row


class Sender(Protocol):
    """Anything a datagram can leave by: a socket, or a wrapper that impairs it further on."""

    def sendto(self, data: bytes, addr: Address, /) -> int: ...


class DelayLine:
    """Sends queued datagrams at their due times from one daemon thread (started on first use).

    A datagram scheduled with a `stream` name is never sent after a newer one of the same stream: when
    it is due after a datagram scheduled later, it leaves just before that one (a stream's newer sample
    pushes the older ones out ahead of it, so a receiver sees the newest sample as soon as it is due
    and the stream stays in order)."""

    def __init__(self, name: str) -> None:
        self._cond = threading.Condition()
        self._heap: list[list[Any]] = []  # [due, seq, sender, data, addr, stream]
        self._seq = itertools.count()
        self._stream_due: dict[str, float] = {}  # per stream, the latest due time scheduled so far
        self._stop = False
        self._thread: threading.Thread | None = None
        self._name = name
        self.send_errors = 0

    def schedule(
        self, due: float, sock: Sender, data: bytes, addr: Address, stream: str | None = None
    ) -> None:
        """Send `data` from `sock` to `addr` at `due` (time.monotonic() s); `stream`: see the class."""
        with self._cond:
            if self._stop:
                return
            if stream is not None:
                if due < self._stream_due.get(stream, -math.inf):  # (in order: nothing to lower)
                    for item in self._heap:
                        if item[5] == stream and item[0] > due:
                            item[0] = due
                    heapq.heapify(self._heap)
                self._stream_due[stream] = due
            heapq.heappush(self._heap, [due, next(self._seq), sock, data, addr, stream])
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"radio-{self._name}", daemon=True)
                self._thread.start()
            self._cond.notify()

    def close(self) -> None:
        """Stop the thread (joined ≤ 1 s); what is still queued is not sent."""
        with self._cond:
            self._stop = True
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=1.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                if self._stop:
                    return
                if not self._heap:
                    self._cond.wait(0.1)
                    continue
                wait = self._heap[0][0] - time.monotonic()
                if wait > 0:
                    self._cond.wait(min(wait, 0.1))
                    continue
                _, _, sock, data, addr, _ = heapq.heappop(self._heap)
            try:
                sock.sendto(data, addr)
            except OSError:  # nobody listening yet, or the socket closed at shutdown
                self.send_errors += 1


class DeviceRadio:
    """The radio links of one emulated device under `profile`, seeded by (seed, device, link).

    links: the device's link -> the kind of link it is (flightstack.netem.LINKS), e.g. {"command": "rc",
    "video": "video"}.
    epoch: time.monotonic() from which the profile's blackout windows count (default: now)."""

    def __init__(
        self,
        prof: NetworkProfile,
        seed: int,
        device: str,
        links: dict[str, str],
        epoch: float | None = None,
    ) -> None:
        self.profile = prof
        self.device = device
        self.epoch = time.monotonic() if epoch is None else float(epoch)
        windows = blackout_windows(prof.blackouts, seed, device)
        self.blackouts = [(self.epoch + a, self.epoch + b) for a, b in windows]
        """Absolute (start, end) time.monotonic() of the device's blackouts (on its radio links)."""
        self._models = {
            name: LinkModel(
                prof.link(kind),
                seed,
                device,
                name,
                epoch=self.epoch,
                blackouts=windows if kind in prof.blackout_kinds else None,
            )
            for name, kind in links.items()
        }
        self._lock = threading.Lock()
        self.delay_line = DelayLine(device)

    def decide(self, link: str, size: int, now: float | None = None) -> list[float]:
        """Delivery times of a datagram of `size` bytes entering `link` now (thread-safe)."""
        t = time.monotonic() if now is None else now
        with self._lock:
            return self._models[link].decide(t, size)

    def applies(self, link: str) -> bool:
        """True for the device's radio links (LinkDecider)."""
        return link in self._models

    def fates(self, link: str, t: float, size: int) -> list[float]:
        """LinkDecider: `decide` at t."""
        return self.decide(link, size, t)

    def send(self, dues: list[float], sock: Sender, data: bytes, addr: Address, link: str) -> None:
        """LinkDecider: every copy on the delay line at its own due time (a packet's order is the
        model's)."""
        for due in dues:
            self.delay_line.schedule(due, sock, data, addr)

    def counts(self) -> dict[str, dict[str, float]]:
        """Per link: the model's counters and delay_mean_ms of what it delivered (JSON-ready)."""
        with self._lock:
            return {name: counter_row(COUNTERS, m.counts, m.delay_sum_s) for name, m in self._models.items()}

    def socket(
        self, sock: socket.socket, send: Callable[[Address], str | None] | None, recv: str | None
    ) -> ImpairedSocket:
        """`sock` wrapped: datagrams it sends go through link `send(addr)` (None: unimpaired), datagrams
        it receives through link `recv` (None: unimpaired)."""
        return ImpairedSocket(sock, self, send, recv)

    def close(self) -> None:
        """Stop the delay line."""
        self.delay_line.close()


class HeldDatagrams:
    """Datagrams that entered a device and wait for their due time (time.monotonic() s), earliest first,
    and the receive loop that hands them out with a socket's timeout semantics (shared by the radio's
    and the device links' sockets)."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, bytes, Any]] = []
        self._seq = itertools.count()
        self._lock = threading.Lock()

    def push(self, due: float, data: bytes, addr: Any) -> None:
        heapq.heappush(self._heap, (due, next(self._seq), data, addr))

    def next_due(self) -> float | None:
        """When the earliest held datagram is due (None: none held). Read without the receive lock (a
        receive may be waiting with it): a snapshot."""
        try:
            return float(self._heap[0][0])
        except IndexError:
            return None

    def receive(
        self,
        timeout: float | None,
        pull: Callable[[], None],
        sock: Any,
        below_due: Callable[[], float | None] | None = None,
    ) -> tuple[bytes, Any]:
        """The earliest due datagram: `pull()` decides what reached `sock`, then wait on `sock` (at most
        0.1 s at a time, less when a datagram held here or `below_due()`, one held by a wrapped socket,
        falls due first). timeout None: wait; 0: BlockingIOError at once; else TimeoutError after it."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while True:
                pull()
                now = time.monotonic()
                if self._heap and self._heap[0][0] <= now:
                    _, _, data, addr = heapq.heappop(self._heap)
                    return data, addr
                if timeout == 0.0:
                    raise BlockingIOError(errno.EAGAIN, "no datagram due")
                wait = 0.1
                for due in (self.next_due(), None if below_due is None else below_due()):
                    if due is not None:
                        wait = min(wait, due - now)
                if deadline is not None:
                    if now >= deadline:
                        raise TimeoutError("timed out")
                    wait = min(wait, deadline - now)
                select.select([sock], [], [], max(0.0, wait))


class LinkDecider(Protocol):
    """What an ImpairedSocket asks of its device's links: the radio's (DeviceRadio, every packet) or the
    rig's `links:` (device_links.DeviceLinks, every sample)."""

    def applies(self, link: str) -> bool:
        """True when `link` changes anything (else its datagrams pass at once)."""
        ...

    def fates(self, link: str, t: float, size: int) -> list[float]:
        """When the copies of a datagram of `size` bytes entering `link` at t are due ([]: lost)."""
        ...

    def send(self, dues: list[float], sock: Sender, data: bytes, addr: Address, link: str) -> None:
        """Send `data` by `sock` to `addr` at each of `dues` (the decider's own ordering rules)."""
        ...


class ImpairedSocket:
    """A device's UDP socket (or another ImpairedSocket) whose traffic passes the device's links.

    `sendto(data, addr)` (leaving the device): the link `send(addr)` decides (None, or a link the decider
    does not apply: sent at once) and the decider sends the copies when due. `recvfrom(n)` (entering the
    device): every datagram that arrived is decided on link `recv` at once and held until its due time;
    a call returns the earliest due one with the caller's timeout semantics (blocking, timeout, or
    non-blocking: `BlockingIOError`); the wrapped socket is then read without waiting (timeout 0) and a
    wrapped ImpairedSocket's held datagrams wake the wait when they fall due. `on_lost(data, t)` is
    called for each received datagram the link loses. Everything else is the wrapped socket's."""

    def __init__(
        self,
        sock: Any,
        decider: LinkDecider,
        send: Callable[[Address], str | None] | None,
        recv: str | None,
        on_lost: Callable[[bytes, float], None] | None = None,
    ) -> None:
        self._sock = sock
        self._decider = decider
        self._send = send
        self._recv = recv if recv is not None and decider.applies(recv) else None
        self._on_lost = on_lost
        self._timeout = sock.gettimeout()
        self._held = HeldDatagrams()
        if self._recv is not None:
            sock.settimeout(0.0)  # this wrapper does the waiting

    # ---- the wrapped socket's own API ----------------------------------------------------------------
    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)

    def settimeout(self, value: float | None) -> None:
        self._timeout = value
        if self._recv is None:
            self._sock.settimeout(value)

    def gettimeout(self) -> float | None:
        return self._timeout

    def setblocking(self, flag: bool) -> None:
        self.settimeout(None if flag else 0.0)

    # ---- leaving the device ----------------------------------------------------------------------------
    def sendto(self, data: bytes, addr: Address) -> int:
        """Send `data` to `addr` through its link (at once when no link applies)."""
        link = None if self._send is None else self._send(addr)
        if link is None or not self._decider.applies(link):
            return int(self._sock.sendto(data, addr))
        dues = self._decider.fates(link, time.monotonic(), len(data))
        if dues:
            self._decider.send(dues, self._sock, bytes(data), addr, link)
        return len(data)

    # ---- entering the device ---------------------------------------------------------------------------
    def next_due(self) -> float | None:
        """When the earliest datagram held for the device is due (time.monotonic() s; None: none held)."""
        return self._held.next_due()

    def recvfrom(self, bufsize: int) -> tuple[bytes, Any]:
        """The earliest due datagram that passed link `recv` (the caller's timeout semantics)."""
        if self._recv is None:
            return self._sock.recvfrom(bufsize)
        inner_due = getattr(self._sock, "next_due", None)  # a wrapped ImpairedSocket holding datagrams
        below = inner_due if callable(inner_due) else None
        return self._held.receive(self._timeout, lambda: self._pull(bufsize), self._sock, below)

    def _pull(self, bufsize: int) -> None:
        """Decide every datagram that reached the device, in arrival order."""
        assert self._recv is not None
        while True:
            try:
                data, addr = self._sock.recvfrom(bufsize)
            except (BlockingIOError, InterruptedError, TimeoutError):
                return
            now = time.monotonic()
            dues = self._decider.fates(self._recv, now, len(data))
            if not dues and self._on_lost is not None:
                self._on_lost(data, now)
            for due in dues:
                self._held.push(due, data, addr)


__all__ = [
    "DelayLine",
    "DeviceRadio",
    "HeldDatagrams",
    "ImpairedSocket",
    "LinkDecider",
    "Sender",
    "counter_row",
]
