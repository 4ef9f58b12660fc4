"""The TCP impairment proxy's resources (sim_backend/emulators/tcp_proxy.py): a finished connection gives
back its sockets, so the 2,000th connection is forwarded under RLIMIT_NOFILE 1024; a flood meets
backpressure (the sender's writes block) and the proxy's memory stays within its queue bound. The proxy
runs in a child process (its own file limit, its own RSS); every child is bounded by a timeout and killed
in `finally`."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import pytest

from flightstack.sim_backend.emulators.tcp_proxy import QUEUE_BYTES
from tests.conftest import REPO

pytestmark = pytest.mark.system

_MANY_CONNECTIONS = r"""
import json, os, resource, socket, sys, threading, time
from flightstack.netem import LinkProfile
from flightstack.sim_backend.emulators.tcp_proxy import TcpImpairProxy

soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard))
N = int(sys.argv[1])

def serve(c):
    with c:
        while data := c.recv(4096):
            c.sendall(data)

srv = socket.create_server(("127.0.0.1", 0))
def accept():
    while True:
        c, _ = srv.accept()
        threading.Thread(target=serve, args=(c,), daemon=True).start()
threading.Thread(target=accept, daemon=True).start()

proxy = TcpImpairProxy(srv.getsockname(), LinkProfile(latency_s=0.0005), seed=0).start()
fds0 = len(os.listdir("/proc/self/fd"))
t0, max_fds = time.monotonic(), fds0
for k in range(N):
    msg = b"%d" % k
    with socket.create_connection(proxy.address, timeout=5.0) as c:
        c.sendall(msg)
        got = b""
        while len(got) < len(msg):
            part = c.recv(64)
            if not part:
                raise SystemExit(f"connection {k}: closed after {got!r}")
            got += part
        if got != msg:
            raise SystemExit(f"connection {k}: echoed {got!r}, sent {msg!r}")
    if k % 50 == 0:
        max_fds = max(max_fds, len(os.listdir("/proc/self/fd")))
elapsed = time.monotonic() - t0
deadline = time.monotonic() + 5.0
while proxy.counts()["open"] and time.monotonic() < deadline:
    time.sleep(0.01)
fds = len(os.listdir("/proc/self/fd"))
limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
print(json.dumps({"elapsed_s": elapsed, "fds_before": fds0, "fds_after": fds, "max_fds": max_fds,
                  "limit": limit, "counts": proxy.counts()}))
proxy.close()
"""


def test_the_2000th_connection_is_forwarded_under_a_1024_file_limit() -> None:
    """A child process limited to 1,024 open files echoes 2,000 connections one after another through
    the proxy: each is forwarded and echoed, and when they are done the proxy holds none of their
    sockets (two leaked per connection would exhaust the limit near the 508th)."""
    r = subprocess.run(
        [sys.executable, "-c", _MANY_CONNECTIONS, "2000"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    print(f"2,000 connections under RLIMIT_NOFILE {out['limit']}: {out}")
    assert out["limit"] == 1024
    counts = out["counts"]
    assert counts["connections"] == 2000 and counts["open"] == 0, counts
    assert counts.get("refused", 0) == 0 and counts.get("accept_errors", 0) == 0, counts
    assert out["fds_after"] <= out["fds_before"] + 4, out  # the echo server's last sockets at most


_PROXY_CHILD = r"""
import json, sys
from flightstack.netem import LinkProfile
from flightstack.sim_backend.emulators.tcp_proxy import TcpImpairProxy

port, rate = int(sys.argv[1]), float(sys.argv[2])
prof = LinkProfile(latency_s=0.001, rate_bps=rate) if rate > 0 else LinkProfile(latency_s=0.001)
proxy = TcpImpairProxy(("127.0.0.1", port), prof, seed=0, queue_bytes=int(sys.argv[3])).start()
print(json.dumps(list(proxy.address)), flush=True)
sys.stdin.read()  # until the test closes stdin
print(json.dumps(proxy.counts()), flush=True)
proxy.close()
"""


def _status_kb(pid: int, key: str) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise AssertionError(f"no {key} in /proc/{pid}/status")


@pytest.mark.parametrize(
    ("case", "rate_bps", "sink_reads"),
    [("an 8 Mbit/s rate cap", 8e6, True), ("a receiver that stops reading", 0.0, False)],
)
def test_a_300_mb_flood_meets_backpressure_and_bounded_memory(
    case: str, rate_bps: float, sink_reads: bool
) -> None:
    """A sender tries to push 300 MB through the proxy (non-blocking writes for up to 4 s) behind `case`:
    its writes block (EAGAIN) long before 300 MB, and the proxy process's peak RSS grows by less than
    2 × its queue bound + 16 MB."""
    flood, budget_s = 300 * 10**6, 4.0
    sink = socket.create_server(("127.0.0.1", 0))
    received = [0]
    stop = threading.Event()

    def drain() -> None:
        sink.settimeout(10.0)
        c, _ = sink.accept()
        with c:
            c.settimeout(0.1)
            while not stop.is_set():
                if not sink_reads:
                    time.sleep(0.05)
                    continue
                try:
                    data = c.recv(1 << 16)
                except TimeoutError:
                    continue
                if not data:
                    return
                received[0] += len(data)

    t = threading.Thread(target=drain, daemon=True)
    t.start()
    queue = QUEUE_BYTES
    child = subprocess.Popen(
        [sys.executable, "-c", _PROXY_CHILD, str(sink.getsockname()[1]), str(rate_bps), str(queue)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    try:
        assert child.stdout is not None and child.stdin is not None
        address = tuple(json.loads(child.stdout.readline()))
        rss0 = _status_kb(child.pid, "VmRSS")
        sent, blocked = 0, 0
        chunk = b"\xa5" * (1 << 16)
        with socket.create_connection(address, timeout=5.0) as c:  # type: ignore[arg-type]
            c.setblocking(False)
            t0 = time.monotonic()
            while sent < flood and time.monotonic() - t0 < budget_s:
                try:
                    sent += c.send(chunk)
                except BlockingIOError:
                    blocked += 1
                    time.sleep(0.002)
            hwm = _status_kb(child.pid, "VmHWM")
            rss = _status_kb(child.pid, "VmRSS")
            child.stdin.close()
            counts = json.loads(child.stdout.readline())
        child.wait(timeout=10)
    finally:
        stop.set()
        if child.poll() is None:
            child.kill()
            child.wait(timeout=10)
        sink.close()
        t.join(timeout=2.0)
    growth_mb = (hwm - rss0) / 1024
    bound_mb = (2 * queue) / 2**20 + 16
    print(
        f"300 MB flood behind {case}: the sender got {sent / 1e6:.1f} MB in ({blocked} blocked writes) in "
        f"{budget_s:g} s, the receiver read {received[0] / 1e6:.1f} MB; proxy RSS {rss0 / 1024:.1f} MB -> "
        f"peak {hwm / 1024:.1f} MB (now {rss / 1024:.1f}), growth {growth_mb:.1f} MB (bound "
        f"{bound_mb:.0f} MB); proxy counts {counts}"
    )
    assert blocked > 0 and sent < flood / 10, (sent, blocked)
    assert counts["backpressure"] >= 1, counts
    assert growth_mb < bound_mb, (growth_mb, bound_mb)


def accepting(server: socket.socket, handle: Callable[[socket.socket], None]) -> threading.Thread:
    """A started daemon thread that accepts on `server` (polling every 0.2 s) and hands each connection
    to `handle`, until the server is closed."""

    def run() -> None:
        server.settimeout(0.2)
        while True:
            try:
                c, _ = server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            handle(c)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_connections_beyond_the_bound_are_refused_and_counted() -> None:
    """With max_connections 2, a third connection open at the same time is closed at once (counted
    `refused`); once the first two end, a new one is forwarded again."""
    from flightstack.netem import LinkProfile
    from flightstack.sim_backend.emulators.tcp_proxy import TcpImpairProxy

    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []
    t = accepting(server, held.append)
    proxy = TcpImpairProxy(server.getsockname(), LinkProfile(), max_connections=2).start()
    clients: list[socket.socket] = []
    try:
        clients = [socket.create_connection(proxy.address, timeout=5.0) for _ in range(2)]
        deadline = time.monotonic() + 5.0
        while proxy.counts()["open"] < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        with socket.create_connection(proxy.address, timeout=5.0) as third:
            assert third.recv(1) == b""  # closed by the proxy
        assert proxy.counts()["refused"] == 1
        for c in clients:
            c.close()
        for c in list(held):
            c.close()
        while proxy.counts()["open"] and time.monotonic() < deadline:
            time.sleep(0.01)
        with socket.create_connection(proxy.address, timeout=5.0) as again:
            again.sendall(b"x")
            deadline = time.monotonic() + 5.0
            while proxy.counts()["connections"] < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
        counts = proxy.counts()
    finally:
        for c in clients:
            c.close()
        proxy.close()
        server.close()
        t.join(timeout=2.0)
    print(f"max_connections 2: {counts}")
    assert counts["connections"] == 3 and counts["refused"] == 1, counts


@pytest.mark.parametrize("fail_at", [0, 2], ids=["first thread", "third thread"])
def test_a_thread_that_cannot_start_refuses_that_connection_only(
    fail_at: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A connection whose `fail_at`-th thread cannot be started (RuntimeError, as when the process is out
    of threads) is closed and counted `thread_errors`; the accept thread lives on and forwards the next
    connection (before, it died and the proxy never accepted again)."""
    from flightstack.netem import LinkProfile
    from flightstack.sim_backend.emulators.tcp_proxy import TcpImpairProxy

    server = socket.create_server(("127.0.0.1", 0))

    def echo(c: socket.socket) -> None:
        with c:
            c.settimeout(5.0)
            while data := c.recv(1024):
                c.sendall(data)

    t = accepting(server, echo)
    start = threading.Thread.start
    calls = [0]

    def start_or_fail(self: threading.Thread) -> None:
        if self.name.startswith("tcp-proxy-") and self.name != "tcp-proxy-bus":
            calls[0] += 1
            if calls[0] == fail_at + 1:
                raise RuntimeError("can't start new thread")
        start(self)

    monkeypatch.setattr(threading.Thread, "start", start_or_fail)
    proxy = TcpImpairProxy(server.getsockname(), LinkProfile()).start()
    try:
        with socket.create_connection(proxy.address, timeout=5.0) as first:
            assert first.recv(1) == b""  # closed by the proxy
        deadline = time.monotonic() + 5.0
        while proxy.counts()["open"] and time.monotonic() < deadline:
            time.sleep(0.01)
        after_first = proxy.counts()
        with socket.create_connection(proxy.address, timeout=5.0) as second:
            second.sendall(b"ping")
            assert second.recv(4) == b"ping"
        deadline = time.monotonic() + 5.0  # a connection is counted once the proxy has seen it close
        while proxy.counts()["open"] and time.monotonic() < deadline:
            time.sleep(0.01)
        counts = proxy.counts()
    finally:
        proxy.close()
        server.close()
        t.join(timeout=2.0)
    print(f"thread {fail_at} of the first connection failed to start: {after_first}, then {counts}")
    assert after_first["thread_errors"] == 1 and after_first["open"] == 0, after_first
    assert counts["connections"] == 1 and counts["thread_errors"] == 1, counts
