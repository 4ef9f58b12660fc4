"""What preflight reads of a drone's interface and how a socket is bound to one (drivers/netif.py), on
written routing tables and sysctl trees, the loopback interface, and a socket that refuses the binding.
The set-up they stand for is flown in tests/test_tello_interfaces.py."""

from __future__ import annotations

import errno
import socket
from pathlib import Path

import pytest

from flightstack.drivers.netif import (
    PRIVILEGE,
    InterfaceError,
    InterfaceState,
    bind_to_interface,
    interface_problem,
    interface_state,
    route_interface,
    rp_filter,
    udp_socket,
)

HEADER = "Iface\tDestination\tGateway \tFlags\tRefCnt\tUse\tMetric\tMask\t\tMTU\tWindow\tIRTT"


def route_table(tmp_path: Path, *rows: tuple[str, str, int, str]) -> Path:
    """A /proc/net/route with rows (interface, destination hex, metric, mask hex)."""
    lines = [HEADER] + [f"{i}\t{d}\t00000000\t0001\t0\t0\t{m}\t{mask}\t0\t0\t0" for i, d, m, mask in rows]
    path = tmp_path / "route"
    path.write_text("\n".join(lines) + "\n")
    return path


TELLO_NET = "000AA8C0"  # 192.168.10.0 as the kernel prints it
SLASH_24, SLASH_32, DEFAULT = "00FFFFFF", "FFFFFFFF", "00000000"


def test_the_route_the_kernel_picks_longest_prefix_then_metric_then_first_listed(tmp_path: Path) -> None:
    two = route_table(tmp_path, ("eth0", DEFAULT, 0, DEFAULT), ("wlan1", TELLO_NET, 600, SLASH_24),
                      ("wlan2", TELLO_NET, 600, SLASH_24))  # fmt: skip
    assert route_interface("192.168.10.1", two) == "wlan1"  # equal routes: the first listed
    assert route_interface("8.8.8.8", two) == "eth0"
    metric = route_table(tmp_path, ("wlan1", TELLO_NET, 601, SLASH_24), ("wlan2", TELLO_NET, 600, SLASH_24))
    assert route_interface("192.168.10.1", metric) == "wlan2"
    host = route_table(tmp_path, ("wlan1", TELLO_NET, 0, SLASH_24), ("wlan2", "010AA8C0", 900, SLASH_32))
    assert (
        route_interface("192.168.10.1", host) == "wlan2" and route_interface("192.168.10.7", host) == "wlan1"
    )
    bad = route_table(tmp_path, ("wlan1", "zz", 0, SLASH_24), ("wlan2", TELLO_NET, 0, SLASH_24))
    assert route_interface("192.168.10.1", bad) == "wlan2"  # an unreadable row is skipped
    assert route_interface("10.0.0.1", bad) is None
    assert route_interface("192.168.10.1", tmp_path / "missing") is None


def test_the_reverse_path_filter_in_force_is_the_larger_of_all_and_the_interface(tmp_path: Path) -> None:
    for name, value in (("all", "0"), ("wlan1", "1"), ("wlan2", "2")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "rp_filter").write_text(value + "\n")
    assert rp_filter("wlan1", tmp_path) == 1 and rp_filter("wlan2", tmp_path) == 2
    (tmp_path / "all" / "rp_filter").write_text("2\n")
    assert rp_filter("wlan1", tmp_path) == 2 and rp_filter("gone", tmp_path) == 2


UP = InterfaceState("wlan2", True, "up", True, "192.168.10.2", 24, rp_filter=0)


@pytest.mark.parametrize(
    ("state", "route", "expected"),
    [
        (InterfaceState("wlan9", False), None, "no network interface wlan9"),
        (
            InterfaceState("wlan2", True, "dormant", True),
            None,
            "wlan2: link dormant: join it to the drone's Wi-Fi",
        ),
        (InterfaceState("wlan2", True, "down", False), None, "link down, set down"),
        (InterfaceState("wlan2", True, "up", True), None, "wlan2: no IPv4 address"),
        (
            InterfaceState("wlan2", True, "up", True, "10.0.0.5", 24),
            None,
            "does not hold the drone's 192.168.10.1",
        ),
        (
            InterfaceState("wlan2", True, "up", True, "192.168.10.2", 24, rp_filter=1),
            "wlan1",
            "strict reverse-path filter (rp_filter 1) with the route to 192.168.10.1 through wlan1: the "
            "kernel drops this drone's datagrams arriving on wlan2; make it loose: sudo sysctl -w "
            "net.ipv4.conf.all.rp_filter=2 net.ipv4.conf.wlan2.rp_filter=2",
        ),
    ],
)
def test_an_interface_that_cannot_reach_its_drone_is_named_with_the_fix(
    state: InterfaceState, route: str | None, expected: str
) -> None:
    problem = interface_problem(state, "192.168.10.1", route)
    assert problem is not None and expected in problem, problem


def test_a_usable_interface_passes_strict_filtering_where_its_route_leaves_by_it() -> None:
    assert interface_problem(UP, "192.168.10.1", "wlan1") is None  # filter off: any route
    strict = InterfaceState("wlan2", True, "up", True, "192.168.10.2", 24, rp_filter=1)
    assert interface_problem(strict, "192.168.10.1", "wlan2") is None
    loose = InterfaceState("wlan2", True, "up", True, "192.168.10.2", 24, rp_filter=2)
    assert interface_problem(loose, "192.168.10.1", "wlan1") is None


def test_the_loopback_interface_is_read_as_up_with_its_address() -> None:
    lo = interface_state("lo")
    assert lo.exists and lo.link_up and (lo.address, lo.prefix) == ("127.0.0.1", 8), lo
    assert not interface_state("fs-no-such0").exists


def test_binding_names_the_interface_and_what_it_needs() -> None:
    with pytest.raises(InterfaceError, match="interface fs-no-such0: no such network interface"):
        udp_socket("fs-no-such0")

    class Refusing:
        def setsockopt(self, *args: object) -> None:
            raise OSError(errno.EPERM, "Operation not permitted")

    with pytest.raises(InterfaceError) as err:
        bind_to_interface(Refusing(), "wlan1")  # type: ignore[arg-type]
    assert err.value.errno == errno.EPERM and str(err.value.strerror) == f"interface wlan1: {PRIVILEGE}"
    assert "CAP_NET_RAW" in PRIVILEGE and "5.7" in PRIVILEGE


def test_a_socket_bound_to_loopback_talks_on_loopback() -> None:
    with udp_socket("lo") as rx, udp_socket("lo") as tx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(2.0)
        tx.sendto(b"state", rx.getsockname())
        assert rx.recv(16) == b"state"
        assert rx.getsockopt(socket.SOL_SOCKET, 25, 16).rstrip(b"\0") == b"lo"
