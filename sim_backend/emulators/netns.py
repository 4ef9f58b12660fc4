"""Sockets inside a network namespace the caller made (`ip netns add NAME`, Linux, root).

How an emulated device gets an address that is not loopback (an access-point Tello's 192.168.10.1) with
no traffic leaving the computer: its sockets are created on a thread that first joined the namespace, and
keep it for their lifetime (a socket belongs to the namespace it was made in, whatever thread then uses
it). Nothing else of the process moves: the joining thread ends once the sockets exist. A namespace
reaches the rest of the machine only through the links its maker gave it (a veth pair into another
namespace the caller made, as tests/test_tello_interfaces.py does).
"""

from __future__ import annotations

import ctypes
import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
CLONE_NEWNET = 0x40000000
"""setns(2)'s namespace type of a network namespace (linux/sched.h)."""
NETNS_DIR = Path("/run/netns")
"""Where `ip netns add NAME` mounts the namespace NAME."""


def join(name: str) -> None:
    """Move the calling thread into network namespace `name` (OSError naming it when it cannot)."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(NETNS_DIR / name, os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"cannot join network namespace {name}: {os.strerror(err)}")
    finally:
        os.close(fd)


def in_netns(name: str, make: Callable[[], T], timeout_s: float = 10.0) -> T:
    """`make()` on a new thread that first joined network namespace `name`: the sockets it creates live
    there. Its result, or what it (or joining) raised; TimeoutError after timeout_s (s)."""
    out: list[T] = []
    failed: list[BaseException] = []

    def run() -> None:
        try:
            join(name)
            out.append(make())
        except BaseException as exc:
            failed.append(exc)

    thread = threading.Thread(target=run, name=f"netns-{name}", daemon=True)
    thread.start()
    thread.join(timeout_s)
    if failed:
        raise failed[0]
    if not out:
        raise TimeoutError(f"nothing made in network namespace {name} within {timeout_s:g} s")
    return out[0]
