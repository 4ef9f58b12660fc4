"""`flightstack draw-lab LAB [--out FILE]`: a picture of a lab file, as SVG.

What the lab file says, drawn: the computers that fly it (one, or one per drone when access-point
drones share an address without an adapter each), their network interfaces and the processes on them
(`flightstack fly` or `agent`, the guardian, the robot's driver), the drones and the Wi-Fi each is on,
the motion-capture server and the ground robot on the lab network, and the ports each talks on.
docs/real-lab.md shows the template's (docs/lab.svg, kept current by tests/test_draw_lab.py). Plain SVG
text written here (no dependency), in fixed columns: drones, computers, lab network. Lengths in px.
"""

from __future__ import annotations

import argparse
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import escape

from flightstack.config.bus import BusSpec
from flightstack.config.hardware import HardwareSpec, TelloHardwareSpec
from flightstack.drivers.mocap import NATNET_COMMAND_PORT, TCP_PORTS
from flightstack.recording.files import atomic_write_bytes

FONT_PX = 12
CHAR_PX = 7.3
"""Advance of one character of the monospace font at FONT_PX (px; generous, so that text fits)."""
LINE_PX = 16
PAD = 8
GAP = 24
LINK_PX = 250
"""Width of the column between the drones and the computers, where the Wi-Fi links are labelled (px)."""
NET_PX = 100
"""Gap between the computers and the lab network's line (px)."""
COLOURS = {
    "drone": "#fdf2d0",
    "computer": "#eef3fb",
    "process": "#ffffff",
    "device": "#e8f5e9",
    "iface": "#d6e4f5",
}


@dataclass
class Process:
    """A process of a computer: its command line and what it talks to (one line each)."""

    name: str
    lines: list[str]


@dataclass
class Computer:
    """A computer: its name, processes, the interfaces its drones are reached through (in order), the
    one on the lab network."""

    name: str
    processes: list[Process]
    interfaces: list[str] = field(default_factory=list)
    lab_interface: str = "lab interface"


@dataclass
class Drone:
    """A Tello: its box's lines, the computer and interface it is reached through, the link's label."""

    title: str
    lines: list[str]
    computer: int
    interface: str
    link: list[str]


@dataclass
class Device:
    """A device on the lab network (motion capture, the robot)."""

    title: str
    lines: list[str]


@dataclass
class Lab:
    """Everything drawn."""

    title: str
    computers: list[Computer]
    drones: list[Drone]
    devices: list[Device]
    notes: list[str]


def _tello_lines(d: TelloHardwareSpec, hw: HardwareSpec) -> list[str]:
    return [
        f"{d.ip}: commands UDP {d.control_port}",
        f"-> state UDP {hw.state_port}, video UDP {d.video_port}",
    ]


def _talks(d: TelloHardwareSpec, hw: HardwareSpec) -> str:
    via = f" via {d.interface}" if d.interface else ""
    return f"Tello {d.id}{via}: -> {d.ip}:{d.control_port}; <- :{hw.state_port}, :{d.video_port}"


def _mocap(hw: HardwareSpec) -> Device:
    m = hw.mocap
    host = m.settings.get("hostname", "(no hostname)")
    if m.system == "optitrack":
        ports = f"NatNet: commands UDP {NATNET_COMMAND_PORT}, frames on Motive's data port"
    elif m.system in TCP_PORTS:
        ports = f"TCP {TCP_PORTS[m.system]}"
    else:
        ports = "no network (mock)"
    bodies = ", ".join(f"{k}={v}" for k, v in m.bodies.items())
    return Device(
        f"motion capture ({m.system})", [host, ports, f"bodies {bodies}" if bodies else "bodies: as named"]
    )


def _bus_line(bus: BusSpec) -> str:
    """How the process hears the operator and the other agents: Zenoh's endpoints, or the loopback abort."""
    if bus.kind == "zenoh" and bus.zenoh is not None:
        endpoints = ", ".join(f"{k} {v}" for k, v in bus.zenoh.endpoints.items())
        return f"Zenoh ({bus.zenoh.security}): {endpoints}"
    return "abort: UDP 127.0.0.1 operator port (signed)"


def lab_picture(hw: HardwareSpec, bus: BusSpec, name: str) -> Lab:
    """What to draw of lab `name`: computers, processes, drones, devices (module docstring)."""
    ids = [d.id for d in hw.drones]
    robot = [] if hw.target is None else [f"robot: MAVLink {hw.target.url}"]
    mocap_line = f"motion capture: {hw.mocap.system} client -> {hw.mocap.settings.get('hostname', '?')}"
    guardian = Process(
        "tello-guardian (started by it)",
        [
            "after a takeover: rc 0 0 0 0 + land to its Tellos,",
            "each through its own interface; robot: disarm",
        ],
    )
    station = hw.topology == "station"
    drones: list[Drone] = []
    if hw.shared_by(ids) is None:  # one process flies every drone
        fly = Process(
            "flightstack fly MISSION --rig LAB",
            [_talks(d, hw) for d in hw.drones] + [mocap_line, *robot, _bus_line(bus)],
        )
        ifaces = list(dict.fromkeys(d.interface or ("lab Wi-Fi" if station else "Wi-Fi") for d in hw.drones))
        computers = [Computer("the flight computer", [fly, guardian], ifaces)]
        for d in hw.drones:
            drones.append(
                Drone(
                    f"Tello {d.id}",
                    _tello_lines(d, hw),
                    0,
                    d.interface or ifaces[0],
                    ["lab Wi-Fi (station mode)"]
                    if station
                    else ["its own Wi-Fi, TELLO-XXXXXX", "192.168.10.0/24"],
                )
            )
        notes = [
            "one computer, one process: "
            + ("every Tello on the lab Wi-Fi (station mode)" if station else "one Wi-Fi adapter per Tello")
        ]
    else:  # access point without an adapter each: a computer per drone, agents over Zenoh
        computers = []
        for k, d in enumerate(hw.drones):
            agent = Process(
                f"flightstack agent MISSION --rig LAB --id {d.id}",
                [_talks(d, hw), mocap_line, _bus_line(bus)],
            )
            computers.append(
                Computer(f"drone {d.id}'s computer", [agent, guardian], [d.interface or "Wi-Fi"])
            )
            drones.append(Drone(f"Tello {d.id}", _tello_lines(d, hw), k, d.interface or "Wi-Fi",
                                ["its own Wi-Fi, TELLO-XXXXXX", "192.168.10.0/24"]))  # fmt: skip
        operator = [Process("flightstack abort | status MISSION", ["Zenoh: every agent"])]
        if robot:
            operator[:0] = [
                Process("flightstack target MISSION", robot),
                Process("tello-guardian (started by it)", ["after a takeover: the robot disarmed"]),
            ]
        computers.append(Computer("the operator's computer", operator))
        notes = ["a computer per drone: agents talk over Zenoh on the lab network"]
    devices = [_mocap(hw)]
    if hw.target is not None:
        devices.append(
            Device("ground robot (ArduPilot Rover)", [hw.target.url, "MAVLink: heartbeat, GUIDED set-points"])
        )
    title = f"lab file `{name}`: topology {hw.topology}, {len(hw.drones)} Tello(s)"
    if any(d.interface for d in hw.drones):
        notes.append(
            "each Tello's sockets, and the guardian's, are bound to its interface (SO_BINDTODEVICE: "
            "CAP_NET_RAW before Linux 5.7)"
        )
    return Lab(title, computers, drones, devices, notes)


# ---- SVG ------------------------------------------------------------------------------------------------
def _width(lines: list[str]) -> float:
    return max((len(s) for s in lines), default=0) * CHAR_PX + 2 * PAD


def _text(x: float, y: float, s: str, bold: bool = False, anchor: str = "start") -> str:
    weight = ' font-weight="bold"' if bold else ""
    return f'<text x="{x:.0f}" y="{y:.0f}" text-anchor="{anchor}"{weight}>{escape(s)}</text>'


def _box(x: float, y: float, w: float, h: float, fill: str) -> str:
    return (
        f'<rect x="{x:.0f}" y="{y:.0f}" width="{w:.0f}" height="{h:.0f}" rx="6" fill="{fill}" stroke="#555"/>'
    )


def _lines_box(
    out: list[str], x: float, y: float, w: float, title: str, lines: list[str], fill: str
) -> float:
    """A box with a bold title and text lines; its height (px)."""
    h = (1 + len(lines)) * LINE_PX + PAD
    out.append(_box(x, y, w, h, fill))
    out.append(_text(x + PAD, y + LINE_PX, title, bold=True))
    for k, s in enumerate(lines):
        out.append(_text(x + PAD, y + (k + 2) * LINE_PX, s))
    return h


def _line(x1: float, y1: float, x2: float, y2: float, dash: bool = False) -> str:
    style = ' stroke-dasharray="6 4"' if dash else ""
    ends = f'x1="{x1:.0f}" y1="{y1:.0f}" x2="{x2:.0f}" y2="{y2:.0f}"'
    return f'<line {ends} stroke="#333" stroke-width="1.5"{style}/>'


def _interface(out: list[str], x: float, y: float, name: str) -> None:
    """An interface's label box centred on (x, y), on a computer's edge."""
    w = len(name) * CHAR_PX + PAD
    out.append(_box(x - w / 2, y - LINE_PX / 2 - 2, w, LINE_PX + 4, COLOURS["iface"]))
    out.append(_text(x, y + 4, name, anchor="middle"))


def _computer(out: list[str], lab: Lab, index: int, x: float, y: float, w: float, inset: float) -> float:
    """Computer `index` at (x, y), its drones to its left; its height (px)."""
    c = lab.computers[index]
    drones = [d for d in lab.drones if d.computer == index]
    drone_w = max(_width([d.title, *d.lines]) for d in lab.drones)
    drone_h = [(2 + len(d.lines)) * LINE_PX for d in drones]
    procs_h = sum((1 + len(p.lines)) * LINE_PX + 2 * PAD for p in c.processes)
    h = max(LINE_PX + PAD + procs_h + PAD, sum(drone_h) + GAP * max(len(drones) - 1, 0) + 2 * PAD)
    out.append(_box(x, y, w, h, COLOURS["computer"]))
    out.append(_text(x + inset, y + LINE_PX, c.name, bold=True))
    py = y + LINE_PX + PAD
    for p in c.processes:
        py += _lines_box(out, x + inset, py, w - 2 * inset, p.name, p.lines, COLOURS["process"]) + PAD
    at: dict[str, float] = {}  # interface -> the y of its first drone's link
    dy = y + PAD
    for d, dh in zip(drones, drone_h, strict=True):
        _lines_box(out, GAP, dy, drone_w, d.title, d.lines, COLOURS["drone"])
        mid = dy + dh / 2
        if d.interface not in at:
            at[d.interface] = mid
            for k, s in enumerate(d.link):  # above the link, centred in its column
                out.append(
                    _text(
                        GAP + drone_w + LINK_PX / 2,
                        mid - 6 - (len(d.link) - 1 - k) * LINE_PX,
                        s,
                        anchor="middle",
                    )
                )
        out.append(_line(GAP + drone_w, mid, x, at[d.interface]))
        dy += dh + GAP
    for name, iy in at.items():
        _interface(out, x, iy, name)
    return h


def render_svg(lab: Lab) -> str:
    """The picture as SVG text (deterministic: the same lab gives the same bytes)."""
    out = [_text(GAP, LINE_PX + 4, lab.title, bold=True)]
    drone_w = max(_width([d.title, *d.lines]) for d in lab.drones)
    names = [n for c in lab.computers for n in [*c.interfaces, c.lab_interface]]
    inset = max(len(n) for n in names) * CHAR_PX / 2 + 2 * PAD  # room for the interfaces on the edges
    proc_w = max(_width([p.name, *p.lines]) for c in lab.computers for p in c.processes)
    comp_w = max(proc_w + 2 * inset, *(_width([c.name]) + 2 * inset for c in lab.computers))
    dev_w = max(_width([d.title, *d.lines]) for d in lab.devices)
    x_comp = GAP + drone_w + LINK_PX
    x_net = x_comp + comp_w + NET_PX
    x_dev = x_net + NET_PX
    top = float(2 * LINE_PX + GAP)
    y = top
    lab_ys: list[float] = []
    for index, c in enumerate(lab.computers):
        h = _computer(out, lab, index, x_comp, y, comp_w, inset)
        lab_ys.append(y + h / 2)
        out.append(_line(x_comp + comp_w, y + h / 2, x_net, y + h / 2))
        _interface(out, x_comp + comp_w, y + h / 2, c.lab_interface)
        y += h + GAP
    dy = top
    for dev in lab.devices:
        h = _lines_box(out, x_dev, dy, dev_w, dev.title, dev.lines, COLOURS["device"])
        lab_ys.append(dy + h / 2)
        out.append(_line(x_net, dy + h / 2, x_dev, dy + h / 2))
        dy += h + GAP
    out.append(_line(x_net, min(lab_ys) - GAP, x_net, max(lab_ys) + GAP, dash=True))
    out.append(_text(x_net, min(lab_ys) - GAP - 6, "lab network", anchor="middle"))
    bottom = max(y, dy, max(lab_ys) + 2 * GAP)
    for k, note in enumerate(lab.notes):
        out.append(_text(GAP, bottom + k * LINE_PX + 4, note))
    width = x_dev + dev_w + GAP
    height = bottom + len(lab.notes) * LINE_PX + GAP
    head = (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}" '
        f'viewBox="0 0 {width:.0f} {height:.0f}" font-family="DejaVu Sans Mono, Menlo, Consolas, monospace" '
        f'font-size="{FONT_PX}">'
    )
    background = f'<rect width="{width:.0f}" height="{height:.0f}" fill="#ffffff"/>'
    return "\n".join([head, background, *out, "</svg>"]) + "\n"


def draw(lab_file: str) -> str:
    """The SVG of a lab (rig) file: validated as `flightstack validate` does (RigError naming the key)."""
    from flightstack.config.rig import RigError, check_rig, find, kind_of, read
    from flightstack.config.rig_check import validate_rig

    src = read(find(lab_file, "rig"), "lab file")
    if kind_of(src.data) != "rig":
        raise RigError(f"{src.path}: not a rig or lab file (draw-lab draws a lab file's devices)")
    check_rig(src)
    validate_rig(src)
    if "hardware" not in src.data:
        raise RigError(f"{src.path}: hardware: no devices to draw (a lab file has `hardware:`)")
    hw = HardwareSpec.model_validate(src.data["hardware"])
    bus = BusSpec.model_validate(src.data.get("bus", {}))
    return render_svg(lab_picture(hw, bus, str(src.data["rig"])))


def refused_out(out: Path) -> str | None:
    """Why the picture may not be written to `out` (a directory, an existing path that is not a regular
    file, a missing folder), or None."""
    if out.is_dir():
        return f"{out}: is a directory (give a file name, e.g. {out / 'lab.svg'})"
    if out.exists() and not stat.S_ISREG(out.stat().st_mode):
        return f"{out}: not a regular file (a device, FIFO or socket): draw-lab writes only regular files"
    if not out.parent.is_dir():
        return f"{out}: its folder {out.parent} does not exist"
    return None


def cmd_draw_lab(args: argparse.Namespace) -> int:
    """Write the lab file's picture to --out (or stdout); exit 2 in one line for an --out it may not
    write (refused_out)."""
    out = None if args.out is None else Path(args.out)
    why_not = None if out is None else refused_out(out)
    if why_not is not None:
        print(f"error: {why_not}", file=sys.stderr)
        return 2
    svg = draw(args.lab)
    if out is None:
        sys.stdout.write(svg)
    else:
        atomic_write_bytes(out, svg.encode("utf-8"))
        print(f"wrote {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `draw-lab` to the top-level subcommands."""
    p = sub.add_parser("draw-lab")
    p.add_argument("lab", help="lab (rig) file with a hardware section, or the built-in name `lab`")
    p.add_argument("--out", default=None, metavar="FILE.svg", help="where to write the SVG (default: stdout)")
    p.set_defaults(func=cmd_draw_lab)
