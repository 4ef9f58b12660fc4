"""The one picker of free loopback ports (UDP and TCP) for emulators, local Zenoh endpoints and tests.

A port is picked at random in PORT_RANGE and checked by binding it on every address at once (the wildcard
address, as a receiver that listens on all interfaces binds it: the Tello camera's video port), then
released for its user to bind: a port some other process holds on any loopback address, e.g. an emulated
Tello's on 127.0.0.6, is not free for such a user, and a check on `ip` alone would pass it.
The range lies below every common ephemeral range (Linux 32768-60999, BSD/macOS and Windows 49152-65535),
so no implicit bind (an unbound UDP socket's first sendto, a TCP client's source port) can take it between
the pick and the user's bind, and below `comms.operator_link`'s default operator ports (20000-29999) and
above the Tello's fixed ports (8889, 8890, 11111). A process never hands out the same port twice, so two
participants picked one after the other never share one. Another process may still bind a picked port
first; that cannot be excluded without keeping the socket, which the user could then not bind.
"""

from __future__ import annotations

import ipaddress
import random
import socket
import threading
from typing import Literal

PORT_RANGE = (12000, 20000)
"""[low, high) of the picked ports."""

Transport = Literal["udp", "tcp"]

_TRIES = 500
_lock = threading.Lock()
_handed_out: set[tuple[Transport, int]] = set()
_rng = random.Random()


def _require_loopback(ip: str) -> None:
    try:
        loopback = ipaddress.ip_address(ip).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise ValueError(f"ports are picked on loopback addresses only (127.0.0.0/8), got {ip!r}")


def _bindable(transport: Transport, port: int) -> bool:
    """Whether `port` is bound on no IPv4 address (bound on the wildcard address for an instant)."""
    kind = socket.SOCK_DGRAM if transport == "udp" else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, kind) as sock:
        try:
            sock.bind(("", port))
        except OSError:
            return False
    return True


def free_port(transport: Transport, ip: str = "127.0.0.1") -> int:
    """A `transport` port for the loopback address `ip` that is free now on every address and was not
    handed out before by this process. RuntimeError when none is found in PORT_RANGE after many tries."""
    _require_loopback(ip)
    with _lock:
        for _ in range(_TRIES):
            port = _rng.randrange(*PORT_RANGE)
            if (transport, port) in _handed_out or not _bindable(transport, port):
                continue
            _handed_out.add((transport, port))
            return port
    raise RuntimeError(f"no free {transport} port on {ip} in {PORT_RANGE} after {_TRIES} tries")


def free_udp_port(ip: str = "127.0.0.1") -> int:
    """A free UDP port of the loopback address `ip` (see `free_port`)."""
    return free_port("udp", ip)


def free_tcp_port(ip: str = "127.0.0.1") -> int:
    """A free TCP port of the loopback address `ip` (see `free_port`)."""
    return free_port("tcp", ip)
