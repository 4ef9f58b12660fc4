"""A TCP impairment proxy on loopback: put it between two processes' Zenoh link (or any TCP link) to give
it a network profile's latency, jitter, rate cap and blackouts (flightstack.netem.StreamModel).

    proxy = TcpImpairProxy(("127.0.0.1", 7447), PROFILES["crowded"].link("bus"), seed=0, name="bus")
    proxy.start()          # listens on proxy.address; a peer connects there instead of to 7447
    ...
    proxy.close()

Each accepted connection opens one to the target; each direction has its own StreamModel (seeded by
(seed, name, "<n>:up"/"<n>:down") for the n-th connection), a reader thread that stamps every chunk it
reads with its delivery time, and a writer thread that writes it then (waits bounded by 0.1 s; nothing
sleeps in a reader). An end of stream is passed on after the data before it; a reset closes both sides.
Only loopback addresses (127.0.0.0/8) are served. Times are time.monotonic() seconds; `counts()` sums
the models' counters over every connection plus "connections".
"""

from __future__ import annotations

import collections
import contextlib
import ipaddress
import select
import socket
import threading
import time
from collections import Counter

from flightstack.netem import LinkProfile, StreamModel

CHUNK_BYTES = 65536
_EOF = b""


class _Direction:
    """One direction of one connection: a reader and a writer thread around a queue of (due, bytes)."""

    def __init__(self, src: socket.socket, dst: socket.socket, model: StreamModel, stop: threading.Event):
        self.src, self.dst, self.model, self.stop = src, dst, model, stop
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self.cond = threading.Condition()
        self.lock = threading.Lock()  # the model
        self.threads = [
            threading.Thread(target=self._read, name="tcp-proxy-read", daemon=True),
            threading.Thread(target=self._write, name="tcp-proxy-write", daemon=True),
        ]

    def start(self) -> None:
        for t in self.threads:
            t.start()

    def _read(self) -> None:
        while not self.stop.is_set():
            try:
                ready, _, _ = select.select([self.src], [], [], 0.1)
                if not ready:
                    continue
                data = self.src.recv(CHUNK_BYTES)
            except (OSError, ValueError):  # reset, or closed by close()
                data = _EOF
            with self.lock:
                due = self.model.decide(time.monotonic(), len(data)) if data else time.monotonic()
            with self.cond:
                self.queue.append((due, data))
                self.cond.notify()
            if not data:
                return

    def _write(self) -> None:
        while not self.stop.is_set():
            with self.cond:
                if not self.queue:
                    self.cond.wait(0.1)
                    continue
                due, data = self.queue[0]
                wait = due - time.monotonic()
                if wait > 0:
                    self.cond.wait(min(wait, 0.1))
                    continue
                self.queue.popleft()
            try:
                if not data:
                    self.dst.shutdown(socket.SHUT_WR)
                    return
                self.dst.sendall(data)
            except OSError:
                self.stop.set()  # the other side is gone: end this connection
                return


class TcpImpairProxy:
    """Listens on (listen_ip, port) and forwards every connection to `target` through `prof` (module)."""

    def __init__(
        self,
        target: tuple[str, int],
        prof: LinkProfile,
        seed: int = 0,
        name: str = "bus",
        *,
        listen_ip: str = "127.0.0.1",
        port: int = 0,
        blackouts: list[tuple[float, float]] | None = None,
        epoch: float | None = None,
    ) -> None:
        """blackouts: (start, end) s after `epoch` (time.monotonic(); default: start()): nothing passes."""
        for ip in (target[0], listen_ip):
            if not ipaddress.ip_address(ip).is_loopback:
                raise ValueError(f"TcpImpairProxy serves loopback addresses only, got {ip!r}")
        self.target = (str(target[0]), int(target[1]))
        self.profile = prof
        self.seed = int(seed)
        self.name = name
        self._listen = (listen_ip, int(port))
        self._blackouts = list(blackouts or [])
        self._epoch = epoch
        self._server: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._conns: list[tuple[socket.socket, socket.socket, threading.Event, list[_Direction]]] = []
        self.address: tuple[str, int] = self._listen

    def start(self) -> TcpImpairProxy:
        """Bind and start accepting; returns self (address is then the bound one)."""
        if self._epoch is None:
            self._epoch = time.monotonic()
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(self._listen)
        server.listen(16)
        server.settimeout(0.1)
        self._server = server
        host, port = server.getsockname()[:2]
        self.address = (str(host), int(port))
        self._thread = threading.Thread(target=self._accept, name=f"tcp-proxy-{self.name}", daemon=True)
        self._thread.start()
        return self

    @property
    def epoch(self) -> float:
        """time.monotonic() the blackouts count from (s; the start unless given)."""
        if self._epoch is None:
            raise RuntimeError("TcpImpairProxy.epoch before start()")
        return self._epoch

    def _model(self, n: int, way: str) -> StreamModel:
        assert self._epoch is not None
        return StreamModel(
            self.profile, self.seed, self.name, f"{n}:{way}", epoch=self._epoch, blackouts=self._blackouts
        )

    def _accept(self) -> None:
        assert self._server is not None
        n = 0
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except (TimeoutError, OSError):
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2.0)
            except OSError:
                client.close()
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(None)  # blocking writes; reads wait in select()
            stop = threading.Event()
            ways = [
                _Direction(client, upstream, self._model(n, "up"), stop),
                _Direction(upstream, client, self._model(n, "down"), stop),
            ]
            with self._lock:
                self._conns.append((client, upstream, stop, ways))
            for w in ways:
                w.start()
            n += 1

    def counts(self) -> dict[str, int]:
        """The models' counters summed over every connection, plus "connections"."""
        out: Counter[str] = Counter()
        with self._lock:
            conns = list(self._conns)
        for *_, ways in conns:
            for w in ways:
                with w.lock:
                    out.update(w.model.counts)
        out["connections"] = len(conns)
        return dict(out)

    def close(self) -> None:
        """Stop accepting, close every connection (threads joined ≤ 1 s in all); idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._server is not None:
            self._server.close()
        with self._lock:
            conns, self._conns = list(self._conns), []
        deadline = time.monotonic() + 1.0
        for client, upstream, stop, ways in conns:
            stop.set()
            for sock in (client, upstream):  # wakes a writer blocked in sendall
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
            for w in ways:
                for t in w.threads:
                    t.join(timeout=max(0.0, deadline - time.monotonic()))
            client.close()
            upstream.close()

    def __enter__(self) -> TcpImpairProxy:
        return self.start() if self._server is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["TcpImpairProxy"]
