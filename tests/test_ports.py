"""The loopback port picker: a port another process holds on any loopback address is not handed out."""

from __future__ import annotations

import socket

import pytest

from flightstack import ports


def test_a_port_held_on_another_loopback_address_is_not_free(monkeypatch: pytest.MonkeyPatch) -> None:
    """An emulated Tello holds its port on 127.0.0.6; the camera driver binds the same number on every
    address and would get EADDRINUSE, so the picker (which a check on 127.0.0.1 alone would satisfy)
    must pass over it."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
        held.bind(("127.0.0.6", 0))
        taken = held.getsockname()[1]
        picks = iter([taken, taken, ports.PORT_RANGE[0] + 1])
        monkeypatch.setattr(ports, "_rng", type("R", (), {"randrange": lambda self, a, b: next(picks)})())
        monkeypatch.setattr(ports, "_handed_out", set())
        got = ports.free_udp_port()
        assert got != taken and got == ports.PORT_RANGE[0] + 1
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
            receiver.bind(("", got))  # what the driver's video receiver does


def test_only_loopback_addresses_are_accepted() -> None:
    with pytest.raises(ValueError, match="loopback"):
        ports.free_udp_port("10.0.0.1")
