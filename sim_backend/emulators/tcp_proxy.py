"""A TCP impairment proxy on loopback: put it between two processes' Zenoh link (or any TCP link) to give
it a network profile's latency, jitter, rate cap and blackouts (flightstack.netem.StreamModel).

    proxy = TcpImpairProxy(("127.0.0.1", 7447), PROFILES["crowded"].link("bus"), seed=0, name="bus")
    proxy.start()          # listens on proxy.address; a peer connects there instead of to 7447
    ...
    proxy.close()

Each accepted connection opens one to the target; each direction has its own StreamModel (seeded by
(seed, name, "<n>:up"/"<n>:down") for the n-th connection), a reader thread that stamps every chunk it
reads with its delivery time, and a writer thread that writes it then (waits bounded by 0.1 s; nothing
sleeps in a reader). An end of stream is passed on after the data before it; a reset or a failed write
closes both sides. A connection whose four threads have ended closes both its sockets and is forgotten
(its counters are kept), so a proxy serves any number of connections one after another.

Backpressure, as TCP's flow control: a direction holds at most `queue_bytes` (+ one chunk) not yet
written; when full its reader stops reading, the kernel's buffers fill and the sender's writes block,
as behind a slow link. Nothing is dropped: the stream loses no byte (a drop would corrupt it); each
time a reader waits for room is counted ("backpressure"). At most `max_connections` are open at once;
a connection beyond them is closed at once ("refused"), and a failed accept or connect (e.g. EMFILE)
is counted ("accept_errors") and retried 50 ms later, never in a busy loop. A connection whose threads
cannot all be started (the process is out of threads) is closed, counted ("thread_errors"), and the
proxy goes on accepting 50 ms later.

Only loopback addresses (127.0.0.0/8) are served. Times are time.monotonic() seconds; `counts()` sums
the models' counters over every connection, open or closed, plus "connections" (accepted), "open",
"refused", "accept_errors", "thread_errors" and "backpressure".
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
from collections.abc import Callable

from flightstack.netem import LinkProfile, StreamModel

CHUNK_BYTES = 65536
QUEUE_BYTES = 1 << 20
"""Default bound of one direction's queue (bytes not yet written): 1 MiB, about 0.4 s of the crowded
profile's video rate cap and far more than the bus's messages need in flight."""
MAX_CONNECTIONS = 256
"""Default bound of the connections open at once (each holds two sockets and four threads)."""
_RETRY_S = 0.05
_EOF = b""


class _Direction:
    """One direction of one connection: a reader and a writer thread around a bounded queue of
    (due, bytes)."""

    def __init__(
        self, src: socket.socket, dst: socket.socket, model: StreamModel, conn: _Conn, queue_bytes: int
    ) -> None:
        self.src, self.dst, self.model, self.conn = src, dst, model, conn
        self.stop = conn.stop
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self.queued = 0  # bytes in the queue
        self.queue_bytes = queue_bytes
        self.backpressure = 0  # times the reader waited for room
        self.cond = threading.Condition()
        self.lock = threading.Lock()  # the model
        self.threads = [
            threading.Thread(target=self._run, args=(self._read,), name="tcp-proxy-read", daemon=True),
            threading.Thread(target=self._run, args=(self._write,), name="tcp-proxy-write", daemon=True),
        ]

    def _run(self, body: Callable[[], None]) -> None:
        try:
            body()
        finally:
            self.conn.thread_done()

    def _room(self) -> bool:
        """Wait until the queue has room (True) or the connection stops (False)."""
        with self.cond:
            if self.queued >= self.queue_bytes:
                self.backpressure += 1
            while self.queued >= self.queue_bytes and not self.stop.is_set():
                self.cond.wait(0.1)
        return not self.stop.is_set()

    def _read(self) -> None:
        while self._room():
            try:
                ready, _, _ = select.select([self.src], [], [], 0.1)
                if not ready:
                    continue
                data = self.src.recv(CHUNK_BYTES)
            except (OSError, ValueError):  # reset, or closed by close()
                self.conn.abort()
                return
            with self.lock:
                due = self.model.decide(time.monotonic(), len(data)) if data else time.monotonic()
            with self.cond:
                self.queue.append((due, data))
                self.queued += len(data)
                self.cond.notify_all()
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
                self.queued -= len(data)
                self.cond.notify_all()
            try:
                if not data:
                    self.dst.shutdown(socket.SHUT_WR)
                    return
                self.dst.sendall(data)
            except OSError:  # the other side is gone: end this connection
                self.conn.abort()
                return


class _Conn:
    """One proxied connection: its two sockets and directions. When its last thread ends it closes both
    sockets and calls `on_done(self)`."""

    def __init__(
        self,
        client: socket.socket,
        upstream: socket.socket,
        models: tuple[StreamModel, StreamModel],
        queue_bytes: int,
        on_done: Callable[[_Conn], None],
    ) -> None:
        self.client, self.upstream = client, upstream
        self.stop = threading.Event()
        self._on_done = on_done
        self._lock = threading.Lock()
        self.ways = [
            _Direction(client, upstream, models[0], self, queue_bytes),
            _Direction(upstream, client, models[1], self, queue_bytes),
        ]
        self._live = sum(len(w.threads) for w in self.ways)

    def start(self) -> bool:
        """Start the four threads; False when one cannot be started (RuntimeError: the process is out of
        threads): then the connection is aborted, and closed once the threads already started end."""
        threads = [t for w in self.ways for t in w.threads]
        for k, t in enumerate(threads):
            try:
                t.start()
            except RuntimeError:
                self.abort()
                for _ in threads[k:]:  # never to run: what they would have counted on their end
                    self.thread_done()
                return False
        return True

    def abort(self) -> None:
        """End both directions now (wakes a writer blocked in sendall)."""
        self.stop.set()
        for sock in (self.client, self.upstream):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def close_sockets(self) -> None:
        self.client.close()
        self.upstream.close()

    def thread_done(self) -> None:
        with self._lock:
            self._live -= 1
            last = self._live == 0
        if last:
            self.close_sockets()
            self._on_done(self)

    def counts(self) -> Counter[str]:
        out: Counter[str] = Counter()
        for w in self.ways:
            with w.lock:
                out.update(w.model.counts)
            out["backpressure"] += w.backpressure
        return out


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
        queue_bytes: int = QUEUE_BYTES,
        max_connections: int = MAX_CONNECTIONS,
    ) -> None:
        """blackouts: (start, end) s after `epoch` (time.monotonic(); default: start()): nothing passes.
        queue_bytes: bound of each direction's queue (bytes); max_connections: open at once."""
        for ip in (target[0], listen_ip):
            if not ipaddress.ip_address(ip).is_loopback:
                raise ValueError(f"TcpImpairProxy serves loopback addresses only, got {ip!r}")
        if not (CHUNK_BYTES <= queue_bytes <= 1 << 30):
            raise ValueError(f"TcpImpairProxy queue_bytes must be in [{CHUNK_BYTES}, 2**30]: {queue_bytes}")
        if not (1 <= max_connections <= 4096):
            raise ValueError(f"TcpImpairProxy max_connections must be in [1, 4096], got {max_connections}")
        self.target = (str(target[0]), int(target[1]))
        self.profile = prof
        self.seed = int(seed)
        self.name = name
        self.queue_bytes = int(queue_bytes)
        self.max_connections = int(max_connections)
        self._listen = (listen_ip, int(port))
        self._blackouts = list(blackouts or [])
        self._epoch = epoch
        self._server: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._conns: set[_Conn] = set()
        self._finished: Counter[str] = Counter()  # counters of the connections that ended
        self._events: Counter[str] = Counter()  # connections, refused, accept_errors, thread_errors
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

    def _forget(self, conn: _Conn) -> None:
        with self._lock:
            if conn in self._conns:
                self._conns.discard(conn)
                self._finished.update(conn.counts())

    def _accept(self) -> None:
        assert self._server is not None
        n = 0
        while not self._stop.is_set():
            try:
                client, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:  # EMFILE, ENFILE, ENOBUFS, or closed by close(): never a busy loop
                with self._lock:
                    self._events["accept_errors"] += 1
                self._stop.wait(_RETRY_S)
                continue
            with self._lock:
                full = len(self._conns) >= self.max_connections
                if full:
                    self._events["refused"] += 1
            if full:
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2.0)
            except OSError:
                client.close()
                with self._lock:
                    self._events["accept_errors"] += 1
                self._stop.wait(_RETRY_S)
                continue
            for s in (client, upstream):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(None)  # blocking writes; reads wait in select()
            models = (self._model(n, "up"), self._model(n, "down"))
            conn = _Conn(client, upstream, models, self.queue_bytes, self._forget)
            with self._lock:
                self._conns.add(conn)
            if not conn.start():  # out of threads: this connection is refused, the next ones are not
                with self._lock:
                    self._events["thread_errors"] += 1
                self._stop.wait(_RETRY_S)
                continue
            with self._lock:
                self._events["connections"] += 1
            n += 1

    def counts(self) -> dict[str, int]:
        """The models' counters summed over every connection (open or ended), plus "connections"
        (accepted and forwarded), "open", "refused", "accept_errors", "thread_errors" and "backpressure"
        (module)."""
        with self._lock:
            conns = list(self._conns)
            out = self._finished + self._events
        for conn in conns:
            out.update(conn.counts())
        out["connections"] += 0
        out["open"] = len(conns)
        return dict(out)

    def close(self) -> None:
        """Stop accepting, close every connection (threads joined ≤ 1 s in all); idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._server is not None:
            self._server.close()
        with self._lock:
            conns = list(self._conns)
        deadline = time.monotonic() + 1.0
        for conn in conns:
            conn.abort()
        for conn in conns:
            for w in conn.ways:
                for t in w.threads:
                    if t.ident is not None:  # started (a connection refused for want of threads: not all)
                        t.join(timeout=max(0.0, deadline - time.monotonic()))
            conn.close_sockets()  # idempotent; a thread still running sees its socket closed
            self._forget(conn)

    def __enter__(self) -> TcpImpairProxy:
        return self.start() if self._server is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["MAX_CONNECTIONS", "QUEUE_BYTES", "TcpImpairProxy"]
