"""Loopback-only networking helpers of the Tello emulator (re-exported by ``tello.py``).

The emulator only ever binds and sends on IPv4 loopback addresses (127.0.0.0/8); these helpers check
addresses, find a free UDP port and poll a condition.  Times in seconds (``time.monotonic``).
"""

from __future__ import annotations

import ipaddress
import random
import socket
import time
from collections.abc import Callable


def is_loopback(ip: str) -> bool:
    """Return True when ``ip`` is an IPv4 address in 127.0.0.0/8."""
    try:
        return ipaddress.IPv4Address(ip) in ipaddress.IPv4Network("127.0.0.0/8")
    except ValueError:
        return False


def _require_loopback(ip: str, what: str) -> None:
    if not is_loopback(ip):
        raise ValueError(f"{what} must be an IPv4 loopback address (127.0.0.0/8), got {ip!r}")


#: where free_udp_port looks: below every common ephemeral range (Linux 32768-60999, BSD/macOS and Windows
#: 49152-65535), so the kernel never hands the port to another socket's implicit bind (an unbound
#: socket's first sendto) between our pick and the driver's bind (a CI failure: "Address already in use")
PORT_RANGE = (20000, 32000)


def free_udp_port(ip: str = "127.0.0.1") -> int:
    """Return a UDP port that is currently free on the loopback address ``ip``.

    Picked at random in PORT_RANGE and checked by binding it; another test may still bind it in between,
    but no ephemeral (implicit) bind can take it. Falls back to a kernel-chosen port after 200 tries.
    """
    _require_loopback(ip, "ip")
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(*PORT_RANGE)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind((ip, port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((ip, 0))
        return int(sock.getsockname()[1])


def wait_until(predicate: Callable[[], bool], timeout: float, interval: float = 0.01) -> bool:
    """Poll ``predicate`` until it returns True or ``timeout`` seconds pass; return its last value."""
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return bool(predicate())
        time.sleep(interval)
