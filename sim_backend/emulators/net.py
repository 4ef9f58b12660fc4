"""Loopback-only networking helpers of the emulators (the Tello's, the NatNet replay's).

The emulators only ever bind and send on IPv4 loopback addresses (127.0.0.0/8); these helpers check
addresses, bind a drone's sockets and poll a condition.  Times in seconds (``time.monotonic``).
"""

from __future__ import annotations

import ipaddress
import socket
import time
from collections.abc import Callable


def is_loopback(ip: str) -> bool:
    """Return True when ``ip`` is an IPv4 address in 127.0.0.0/8."""
    try:
        return ipaddress.IPv4Address(ip) in ipaddress.IPv4Network("127.0.0.0/8")
    except ValueError:
        return False


def require_loopback(ip: str, what: str) -> None:
    """Raise ValueError naming ``what`` unless ``ip`` is in 127.0.0.0/8."""
    if not is_loopback(ip):
        raise ValueError(f"{what} must be an IPv4 loopback address (127.0.0.0/8), got {ip!r}")


def wait_until(predicate: Callable[[], bool], timeout: float, interval: float = 0.01) -> bool:
    """Poll ``predicate`` until it returns True or ``timeout`` seconds pass; return its last value."""
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return bool(predicate())
        time.sleep(interval)


def bind_drone_sockets(ip: str, port: int, timeout_s: float) -> tuple[socket.socket, socket.socket]:
    """A Tello's two UDP sockets on `ip`: the command socket on `port` (0: the OS picks; receives with
    `timeout_s`, replies from it) and the sending socket (state, video) on a free port. Both closed on
    an OSError, which is raised."""
    cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        cmd.bind((ip, port))
        cmd.settimeout(timeout_s)
        tx.bind((ip, 0))
    except OSError:
        cmd.close()
        tx.close()
        raise
    return cmd, tx
