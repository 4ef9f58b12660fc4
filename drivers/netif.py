"""Network interfaces (Linux): binding a socket to one, and what preflight reads of one.

One computer with one Wi-Fi adapter per Tello (docs/real-lab.md, "Choose a topology"): every Tello in
access-point mode is 192.168.10.1 and talks to the same ports of its computer, so neither the address nor
the port says which drone a datagram is for or from; the adapter does. A socket bound to an interface
(SO_BINDTODEVICE, `bind_to_interface`) sends only through it (the route lookup is limited to it) and
receives only what arrived on it, so each drone's command, state and video sockets, and its guardian's,
are bound to its adapter (docs/architecture.md, decision 84).

A socket stays bound to the interface it was bound to (its index): an adapter unplugged and plugged back
in flight comes back as a new interface, which the flight's and the guardian's sockets never reach; the
drone then lands by itself 15 s after its last command, as with any lost Wi-Fi.

Privilege (`binding_privilege`): on Linux before 5.7 SO_BINDTODEVICE needs CAP_NET_RAW (root, or the
capability given to the interpreter: `sudo setcap cap_net_raw+ep "$(readlink -f "$(which python3)")"`);
from 5.7 on (kernel commit c427bfec18f2) the first binding of a socket needs none, changing it still does.

What preflight checks of an interface (`interface_problem`): it exists, its link is up, it has an IPv4
address whose subnet holds the drone's, and the reverse-path filter does not drop the drone's datagrams:
with strict filtering (rp_filter 1, the larger of `conf/all` and the interface's own value) a datagram
arriving on an interface is dropped when the kernel's route back to its source leaves through another,
as it does on all but one of several adapters on the same 192.168.10.0/24 (measured in network
namespaces: tests/test_tello_interfaces.py). Reads /sys/class/net, /proc/sys/net/ipv4/conf and
/proc/net/route of this process's network namespace; sends nothing.
"""

from __future__ import annotations

import errno
import fcntl
import ipaddress
import platform
import socket
import struct
from dataclasses import dataclass
from pathlib import Path

SO_BINDTODEVICE = getattr(socket, "SO_BINDTODEVICE", 25)
"""The socket option (25 on Linux; Python names it only where the platform has it)."""
IFNAMSIZ = 16
"""Linux's interface-name buffer: at most 15 characters and the terminating NUL."""
SIOCGIFADDR, SIOCGIFNETMASK = 0x8915, 0x891B
"""ioctl requests: an interface's IPv4 address and netmask (linux/sockios.h)."""
IFF_UP = 0x1
PRIVILEGE = (
    "binding a socket to an interface (SO_BINDTODEVICE) needs CAP_NET_RAW on Linux before 5.7: run as root "
    "or give the interpreter the capability (sudo setcap cap_net_raw+ep on the file `readlink -f $(which "
    "python3)` names); from 5.7 on a socket's first binding needs no privilege"
)
"""What binding to an interface needs, and how to grant it (preflight's and the drivers' errors say it)."""
RP_FILTER_FIX = "sudo sysctl -w net.ipv4.conf.all.rp_filter=2 net.ipv4.conf.{if}.rp_filter=2"
"""How to make the reverse-path filter loose on interface {if} (it must be loose in `all` as well)."""


class InterfaceError(OSError):
    """A socket could not be bound to its interface; the message names the interface and the fix."""


def bind_to_interface(sock: socket.socket, name: str) -> None:
    """Bind `sock` to interface `name` (SO_BINDTODEVICE), before its bind(): it then sends only through
    `name` and receives only what arrived there. InterfaceError naming the interface and, on EPERM, the
    privilege it needs (PRIVILEGE); ENODEV: no such interface."""
    if platform.system() != "Linux":
        raise InterfaceError(errno.EOPNOTSUPP, f"interface {name}: binding to an interface needs Linux")
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_BINDTODEVICE, name.encode() + b"\0")
    except OSError as exc:
        if exc.errno == errno.EPERM:
            raise InterfaceError(exc.errno, f"interface {name}: {PRIVILEGE}") from exc
        if exc.errno == errno.ENODEV:
            raise InterfaceError(exc.errno, f"interface {name}: no such network interface here") from exc
        raise InterfaceError(exc.errno, f"interface {name}: SO_BINDTODEVICE: {exc.strerror}") from exc


def udp_socket(interface: str | None = None) -> socket.socket:
    """A new IPv4 UDP socket, bound to `interface` when one is named (closed again on InterfaceError)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if interface:
        try:
            bind_to_interface(sock, interface)
        except InterfaceError:
            sock.close()
            raise
    return sock


def binding_privilege() -> str | None:
    """None when this process may bind a socket to an interface (tried on the loopback interface `lo`,
    which every network namespace has), else why not with the fix (PRIVILEGE)."""
    try:
        udp_socket("lo").close()
    except InterfaceError as exc:
        return f"{exc.strerror} (kernel {platform.release()})"
    return None


@dataclass(frozen=True)
class InterfaceState:
    """What this computer knows of one interface: `operstate` as /sys/class/net says ("up", "down",
    "dormant", "unknown", ...), the administrative flag IFF_UP, its IPv4 address and prefix length (None
    without one) and its effective reverse-path filter (0 off, 1 strict, 2 loose)."""

    name: str
    exists: bool
    operstate: str = ""
    admin_up: bool = False
    address: str | None = None
    prefix: int | None = None
    rp_filter: int = 0

    @property
    def link_up(self) -> bool:
        """Up, or "unknown" with the interface set up (drivers that report no operstate, e.g. tun)."""
        return self.admin_up and self.operstate in ("up", "unknown")

    def network(self) -> ipaddress.IPv4Network | None:
        """The subnet of its address, None without one."""
        if self.address is None or self.prefix is None:
            return None
        return ipaddress.IPv4Network(f"{self.address}/{self.prefix}", strict=False)


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


def _ioctl_ipv4(name: str, request: int) -> str | None:
    """The IPv4 address an interface ioctl (SIOCGIFADDR, SIOCGIFNETMASK) reports, None without one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            out = fcntl.ioctl(s.fileno(), request, struct.pack("256s", name.encode()[: IFNAMSIZ - 1]))
        except OSError:
            return None
    return socket.inet_ntoa(out[20:24])


def rp_filter(name: str, root: Path = Path("/proc/sys/net/ipv4/conf")) -> int:
    """The reverse-path filter in force on interface `name`: the larger of `all`'s and its own (0 off,
    1 strict, 2 loose; Linux ip-sysctl.rst); 0 where it cannot be read."""
    values = []
    for part in ("all", name):
        text = _read(root / part / "rp_filter")
        values.append(int(text) if text.isdigit() else 0)
    return max(values)


def interface_state(name: str, sys_net: Path = Path("/sys/class/net")) -> InterfaceState:
    """Interface `name` as this network namespace sees it (InterfaceState)."""
    base = sys_net / name
    if not base.is_dir():
        return InterfaceState(name, exists=False)
    flags = _read(base / "flags")
    address = _ioctl_ipv4(name, SIOCGIFADDR)
    mask = _ioctl_ipv4(name, SIOCGIFNETMASK)
    prefix = None if mask is None else ipaddress.IPv4Network(f"0.0.0.0/{mask}").prefixlen
    return InterfaceState(
        name,
        exists=True,
        operstate=_read(base / "operstate"),
        admin_up=bool(int(flags, 16) & IFF_UP) if flags.startswith("0x") else False,
        address=address,
        prefix=prefix,
        rp_filter=rp_filter(name),
    )


def route_interface(ip: str, table: Path = Path("/proc/net/route")) -> str | None:
    """The interface of the main routing table's route to `ip` as the kernel picks it (longest prefix,
    then lowest metric, then the first listed): where an unbound socket's datagram to it, and the
    reverse-path filter's check of a datagram from it, leave. None when no route covers it or the table
    cannot be read."""
    target = int(ipaddress.IPv4Address(ip))
    best: tuple[int, int] | None = None
    chosen = None
    for line in _read(table).splitlines()[1:]:
        cols = line.split()
        if len(cols) < 8:
            continue
        try:  # each address a word in network byte order printed as a little-endian host's integer
            dest = struct.unpack("<I", bytes.fromhex(cols[1]))[0]
            mask = struct.unpack("<I", bytes.fromhex(cols[7]))[0]
            metric = int(cols[6])
        except (ValueError, struct.error):
            continue
        rank = (-bin(mask).count("1"), metric)
        if target & mask == dest and (best is None or rank < best):
            best, chosen = rank, cols[0]
    return chosen


def interface_problem(state: InterfaceState, drone_ip: str, route: str | None) -> str | None:
    """Why the drone at `drone_ip` cannot be reached through this interface (one line with the fix), or
    None. route: `route_interface(drone_ip)`, the interface the kernel's route to the drone leaves by."""
    name = state.name
    if not state.exists:
        return f"no network interface {name} on this computer (`ip link` lists them)"
    if not state.link_up:
        return (
            f"{name}: link {state.operstate or 'unknown'}{'' if state.admin_up else ', set down'}: "
            f"join it to the drone's Wi-Fi (TELLO-XXXXXX) and set it up (`ip link set {name} up`)"
        )
    net = state.network()
    if net is None:
        return f"{name}: no IPv4 address (the drone's DHCP gives one once joined to its Wi-Fi)"
    if ipaddress.IPv4Address(drone_ip) not in net:
        return f"{name}: {state.address}/{state.prefix} does not hold the drone's {drone_ip} (another Wi-Fi?)"
    if state.rp_filter == 1 and route is not None and route != name:
        return (
            f"{name}: strict reverse-path filter (rp_filter 1) with the route to {drone_ip} through "
            f"{route}: the kernel drops this drone's datagrams arriving on {name}; make it loose: "
            f"{RP_FILTER_FIX.format(**{'if': name})}"
        )
    return None


def describe(state: InterfaceState) -> str:
    """One line for a usable interface: link, address, reverse-path filter."""
    rp = {0: "off", 1: "strict", 2: "loose"}.get(state.rp_filter, str(state.rp_filter))
    return f"{state.name} up, {state.address}/{state.prefix}, rp_filter {rp}"
