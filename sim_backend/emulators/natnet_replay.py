"""`NatNetReplayer`: recorded Motive packets served over loopback UDP as a Motive would serve them.

A recording (`NatNetRecording`) is a NAT_SERVERINFO packet, a NAT_MODELDEF packet and NAT_FRAMEOFDATA
packets with their recorded times, read from a pcapng capture (`read_pcapng`, a small reader of the
Ethernet/IPv4/UDP packets of a pcapng file) or from single packets (`read_packets`). The replayer answers
NAT_CONNECT with the recorded server info and NAT_REQUEST_MODELDEF with the recorded model definitions
(both from a child process: `motioncapture.connect` holds the GIL while it waits for them, see
natnet.py), then sends the recorded frames, unmodified, at their recorded offsets from the first
model-definition reply + `start_delay_s` (`pace="recorded"`), or one per `step()` call (`pace="step"`).

How the frames travel (`delivery`), and what the recorded server info is changed to say (the only bytes
changed, listed in `server_info_changes`):

- `"multicast"` (Motive's default; the recording's own: 518 frames to 239.255.42.99:1511): to the
  recorded multicast group at `data_port` through the loopback interface only (IP_MULTICAST_IF
  `host`, TTL 0: no datagram leaves the host). DataPort := `data_port` (a free port unless given:
  the recorded 1511 is shared by every test), IsMulticast := 1.
- `"unicast"`: to (client ip, `data_port`), the client ip being the sender of the last NAT_CONNECT;
  IsMulticast := 0. What libmotioncapture 1.1 reads (it binds 0.0.0.0:DataPort and never reads its
  command socket again: `MotionCaptureOptitrack::MotionCaptureOptitrack`, src/optitrack.cpp) and the
  project's emulator sends.
- `"unicast_command"`: to the sender (ip, port) of the last NAT_CONNECT, the client's command socket;
  IsMulticast := 0. What OptiTrack's own Python client reads (natnetsdk 4.1.1, NatNetClient.py: in
  unicast it binds its data socket to an ephemeral port it never tells the server and reads frames in
  `__command_thread_function`, sending NAT_KEEPALIVE from that socket); a public capture of libNatNet
  4.4 notes "UDP 1510 (unicast: cmd + frames)". Frames leave from the replayer's frame socket, not
  from its command port.

Only IPv4 loopback: `host` must be in 127.0.0.0/8, and a client address outside it is never sent to
(`counts["rejected_client"]`). Every frame datagram is logged in `sent` (`Sent`: the recording's index
and recorded offset it was decided from, its destination); `counts`: "frames", "send_error",
"connects", "modeldefs". The frame thread waits at most `WAIT_S` before it looks at the stop flag;
`close()` joins it and stops the child (1 s, then killed). A context manager.
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Literal

from . import natnet
from .natnet import NAT_CONNECT, NAT_FRAMEOFDATA, NAT_MODELDEF, NAT_REQUEST_MODELDEF, NAT_SERVERINFO
from .net import is_loopback, require_loopback

Delivery = Literal["multicast", "unicast", "unicast_command"]
Pace = Literal["recorded", "step"]
WAIT_S = 0.05  # the longest the frame thread waits before it looks at the stop flag again (s)
SERVER_INFO_BYTES = 283  # NAT_SERVERINFO of NatNet 3.0/4.x: header 4 + name 256 + 4 + 4 + 8 + 2 + 1 + 4
_DATA_PORT_AT = 4 + 256 + 4 + 4 + 8  # uint16 DataPort, then bool IsMulticast, uint8 MulticastGroup[4]
PACKET_INTERVAL_S = 1.0 / 120.0  # the spacing of frames read from single packets (no recorded time), s


@dataclass(frozen=True)
class NatNetRecording:
    """What a Motive sent: its server info and model definitions (packets with their 4-byte header) and
    its frames as (recorded time s from the first frame, NAT_FRAMEOFDATA packet)."""

    source: str
    server_info: bytes
    model_def: bytes
    frames: tuple[tuple[float, bytes], ...]

    def __post_init__(self) -> None:
        if len(self.server_info) != SERVER_INFO_BYTES or _message_id(self.server_info) != NAT_SERVERINFO:
            raise ValueError(
                f"{self.source}: the server info is not a {SERVER_INFO_BYTES}-byte NAT_SERVERINFO"
            )
        if _message_id(self.model_def) != NAT_MODELDEF:
            raise ValueError(f"{self.source}: the model definitions are not a NAT_MODELDEF packet")
        if not self.frames or any(_message_id(p) != NAT_FRAMEOFDATA for _, p in self.frames):
            raise ValueError(f"{self.source}: no frames, or a frame that is not NAT_FRAMEOFDATA")

    @property
    def natnet_version(self) -> tuple[int, int, int, int]:
        """The NatNet version the recorded server info announces."""
        v = self.server_info[4 + 256 + 4 : 4 + 256 + 8]
        return (v[0], v[1], v[2], v[3])

    @property
    def multicast_group(self) -> str:
        """The multicast group the recorded server info announces (dotted quad)."""
        return socket.inet_ntoa(self.server_info[_DATA_PORT_AT + 3 : _DATA_PORT_AT + 7])


def _message_id(packet: bytes) -> int:
    return struct.unpack_from("<H", packet)[0] if len(packet) >= 4 else -1


def udp_payloads(pcapng: bytes) -> list[tuple[float, str, int, str, int, bytes]]:
    """The IPv4/UDP datagrams of a pcapng capture with Ethernet links, as (time s, source ip, source
    port, destination ip, destination port, payload). Reads Section Header (byte order), Interface
    Description (link type, if_tsresol) and Enhanced/Simple Packet blocks; other blocks and non-UDP
    packets are skipped. ValueError on a truncated or malformed block."""
    out: list[tuple[float, str, int, str, int, bytes]] = []
    endian, i = "<", 0
    links: list[tuple[int, float]] = []  # (linktype, seconds per timestamp unit) per interface
    while i + 12 <= len(pcapng):
        btype = struct.unpack_from("<I", pcapng, i)[0]
        if btype == 0x0A0D0D0A:  # section header: its byte-order magic decides the endianness
            endian = "<" if pcapng[i + 8 : i + 12] == b"\x4d\x3c\x2b\x1a" else ">"
            links = []
        blen = struct.unpack_from(endian + "I", pcapng, i + 4)[0]
        if blen < 12 or blen % 4 or i + blen > len(pcapng):
            raise ValueError(f"malformed pcapng block at byte {i} (length {blen})")
        body = pcapng[i + 8 : i + blen - 4]
        btype = struct.unpack_from(endian + "I", pcapng, i)[0]
        if btype == 1:  # interface description
            linktype = struct.unpack_from(endian + "H", body)[0]
            links.append((linktype, _tsresol(body[8:], endian)))
        elif btype == 6:  # enhanced packet
            iface, hi, lo, caplen = struct.unpack_from(endian + "IIII", body)
            linktype, unit = links[iface]
            if linktype == 1:
                _append_udp(out, ((hi << 32) | lo) * unit, body[20 : 20 + caplen])
        i += blen
    return out


def _tsresol(options: bytes, endian: str) -> float:
    """Seconds per timestamp unit from an interface's options (if_tsresol, code 9; default 1 µs)."""
    k = 0
    while k + 4 <= len(options):
        code, n = struct.unpack_from(endian + "HH", options, k)
        if code == 0:
            break
        if code == 9 and n >= 1:
            v = options[k + 4]
            return 2.0 ** -(v & 0x7F) if v & 0x80 else 10.0**-v
        k += 4 + (n + 3) // 4 * 4
    return 1e-6


def _append_udp(out: list[tuple[float, str, int, str, int, bytes]], t: float, frame: bytes) -> None:
    if len(frame) < 14 + 20 or frame[12:14] != b"\x08\x00":
        return
    ip = frame[14:]
    ihl = (ip[0] & 0x0F) * 4
    if ip[0] >> 4 != 4 or ip[9] != 17 or len(ip) < ihl + 8:
        return
    total = struct.unpack_from(">H", ip, 2)[0]
    sport, dport, ulen = struct.unpack_from(">HHH", ip, ihl)
    payload = ip[ihl + 8 : min(ihl + ulen, total)]
    out.append((t, socket.inet_ntoa(ip[12:16]), sport, socket.inet_ntoa(ip[16:20]), dport, payload))


def read_pcapng(path: Path) -> NatNetRecording:
    """A Motive session captured in pcapng: the first NAT_SERVERINFO and NAT_MODELDEF sent by the server
    and every NAT_FRAMEOFDATA sent from its data port, timed from the first frame."""
    packets = udp_payloads(path.read_bytes())
    info = next((p for p in packets if _message_id(p[5]) == NAT_SERVERINFO), None)
    modeldef = next((p for p in packets if _message_id(p[5]) == NAT_MODELDEF), None)
    if info is None or modeldef is None:
        raise ValueError(f"{path}: no NAT_SERVERINFO or no NAT_MODELDEF in the capture")
    frames = [(t, p) for t, _, _, _, _, p in packets if _message_id(p) == NAT_FRAMEOFDATA]
    if not frames:
        raise ValueError(f"{path}: no NAT_FRAMEOFDATA in the capture")
    t0 = frames[0][0]
    return NatNetRecording(str(path), info[5], modeldef[5], tuple((t - t0, p) for t, p in frames))


def read_packets(server_info: Path, model_def: Path, frames: list[Path]) -> NatNetRecording:
    """Single recorded packets (one file each); they carry no time, so the frames are spaced by
    PACKET_INTERVAL_S."""
    return NatNetRecording(
        ", ".join(p.name for p in (server_info, model_def, *frames)),
        server_info.read_bytes(),
        model_def.read_bytes(),
        tuple((k * PACKET_INTERVAL_S, p.read_bytes()) for k, p in enumerate(frames)),
    )


@dataclass(frozen=True)
class Sent:
    """One frame datagram sent: monotonic time `t` (s), the recording's frame `index` and recorded time
    `rec_t` (s) it was decided from, and its destination."""

    t: float
    index: int
    rec_t: float
    dest: tuple[str, int]


class NatNetReplayer:
    """A `NatNetRecording` served over loopback UDP (the rules: module docstring)."""

    def __init__(
        self,
        recording: NatNetRecording,
        host: str = "127.0.0.1",
        *,
        delivery: Delivery = "multicast",
        pace: Pace = "recorded",
        data_port: int = 0,
        start_delay_s: float = 0.3,
    ) -> None:
        require_loopback(host, "host")
        if delivery not in ("multicast", "unicast", "unicast_command"):
            raise ValueError(f"delivery must be multicast, unicast or unicast_command, got {delivery!r}")
        if pace not in ("recorded", "step"):
            raise ValueError(f"pace must be 'recorded' or 'step', got {pace!r}")
        if not 0.0 <= start_delay_s < 60.0:
            raise ValueError(f"start_delay_s must be in [0, 60) s, got {start_delay_s}")
        self.recording, self.host, self.delivery, self.pace = recording, host, delivery, pace
        self.data_port, self.start_delay_s = data_port, start_delay_s
        self.group = recording.multicast_group
        self.server_info = b""  # the server info served (valid after start())
        self.server_info_changes: dict[str, tuple[object, object]] = {}  # field -> (recorded, served)
        self.command_port = 0
        self.sent: list[Sent] = []
        self.errors: list[str] = []
        self.counts: Counter[str] = Counter()
        self.client: tuple[str, int] | None = None  # the sender of the last NAT_CONNECT
        self._cond = threading.Condition()
        self._modeldef_at: float | None = None  # monotonic time of the first model-definition reply
        self._next = 0  # the next frame index
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._closed = False

    # ------------------------------------------------------------------------------------------ lifecycle
    def settings(self) -> dict[str, str]:
        """Settings for `motioncapture.connect("optitrack", settings)` (after `start()`)."""
        return {"hostname": self.host, "port_command": str(self.command_port), "interface_ip": self.host}

    def start(self) -> NatNetReplayer:
        """Start the command responder (child process) and the frame thread; returns self."""
        if self._proc is not None:
            raise RuntimeError("NatNetReplayer.start() called twice")
        if self.data_port == 0:
            from flightstack.ports import free_udp_port

            self.data_port = free_udp_port(self.host)
        self.server_info = self._served_server_info()
        self._proc = subprocess.Popen(
            [sys.executable, os.path.abspath(natnet.__file__), "--responder", self.host, "0",
             self.server_info.hex(), "--report"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )  # fmt: skip
        try:
            assert self._proc.stdin is not None
            self._proc.stdin.write(b"M " + self.recording.model_def.hex().encode() + b"\n")
            self._proc.stdin.flush()
            self.command_port = natnet.NatNetEmulator._read_port(self._proc)
        except BaseException:
            self._stop_responder()
            raise
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((self.host, 0))
        if self.delivery == "multicast":  # through loopback only, and never past this host
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.host))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._sock = sock
        targets = [("reports", self._report_loop)]
        if self.pace == "recorded":
            targets.append(("frames", self._frame_loop))
        for name, target in targets:
            thread = threading.Thread(target=target, name=f"natnet-replay-{name}", daemon=True)
            self._threads.append(thread)
            thread.start()
        return self

    def close(self) -> None:
        """Stop the threads (joined within ~1 s) and the responder (1 s, then killed); idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._stop_responder()  # the responder exits: its output ends, and with it the report thread
        deadline = time.monotonic() + 1.0
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        if self._proc is not None and self._proc.stdout is not None:
            self._proc.stdout.close()
        if self._sock is not None:
            self._sock.close()

    @property
    def threads_alive(self) -> list[str]:
        return [t.name for t in self._threads if t.is_alive()]

    def __enter__(self) -> NatNetReplayer:
        if self._proc is None:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ---------------------------------------------------------------------------------------------- frames
    @property
    def frames_left(self) -> int:
        return len(self.recording.frames) - self._next

    def wait_for_client(self, timeout_s: float) -> bool:
        """True once a client has read the model definitions (within timeout_s, s)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._modeldef_at is not None, timeout_s)

    def step(self) -> Sent | None:
        """Send the next recorded frame now (`pace="step"`); None when none is left or no client connected
        yet (unicast) or the send failed."""
        if self.pace != "step":
            raise RuntimeError("step() needs pace='step'")
        with self._cond:
            if self._next >= len(self.recording.frames):
                return None
            index, self._next = self._next, self._next + 1
        return self._send(index)

    def _destination(self) -> tuple[str, int] | None:
        if self.delivery == "multicast":
            return (self.group, self.data_port)
        client = self.client
        if client is None:
            return None
        return (client[0], self.data_port) if self.delivery == "unicast" else client

    def _send(self, index: int) -> Sent | None:
        rec_t, packet = self.recording.frames[index]
        dest = self._destination()
        if dest is None or self._sock is None:
            self.counts["no_client"] += 1
            return None
        try:
            self._sock.sendto(packet, dest)
        except OSError as exc:
            self.counts["send_error"] += 1
            if len(self.errors) < 100:
                self.errors.append(f"send frame {index} to {dest}: {exc}")
            return None
        sent = Sent(time.monotonic(), index, rec_t, dest)
        with self._cond:
            self.sent.append(sent)
            self.counts["frames"] += 1
        return sent

    def _frame_loop(self) -> None:
        with self._cond:
            while self._modeldef_at is None and not self._stop.is_set():
                self._cond.wait(WAIT_S)
            t0 = (self._modeldef_at or 0.0) + self.start_delay_s
        frames = self.recording.frames
        while not self._stop.is_set() and self._next < len(frames):
            due = t0 + frames[self._next][0]
            delay = due - time.monotonic()
            if delay > 0.0:
                self._stop.wait(min(WAIT_S, delay))
                continue
            index, self._next = self._next, self._next + 1
            self._send(index)

    # ------------------------------------------------------------------------------------------ responder
    def _served_server_info(self) -> bytes:
        """The recorded server info with DataPort, IsMulticast (and the group kept) as served."""
        info = bytearray(self.recording.server_info)
        port, multicast = struct.unpack_from("<H?", info, _DATA_PORT_AT)
        served_multicast = self.delivery == "multicast"
        struct.pack_into("<H?", info, _DATA_PORT_AT, self.data_port, served_multicast)
        if port != self.data_port:
            self.server_info_changes["DataPort"] = (port, self.data_port)
        if multicast != served_multicast:
            self.server_info_changes["IsMulticast"] = (multicast, served_multicast)
        return bytes(info)

    def _report_loop(self) -> None:
        """Who connected, when the model definitions went out (the responder's report lines)."""
        assert self._proc is not None
        natnet.report_loop(self._proc, self._stop, self._report)

    def _report(self, msg: int, ip: str, port: int) -> None:
        if not is_loopback(ip):
            self.counts["rejected_client"] += 1
            return
        with self._cond:
            if msg == NAT_CONNECT:
                self.client = (ip, port)
                self.counts["connects"] += 1
            elif msg == NAT_REQUEST_MODELDEF:
                self.counts["modeldefs"] += 1
                if self._modeldef_at is None:
                    self._modeldef_at = time.monotonic()
            self._cond.notify_all()

    def _stop_responder(self) -> None:
        natnet.stop_responder(self._proc, close_output=False)  # closed once the report thread ends


__all__ = ["NatNetRecording", "NatNetReplayer", "Sent", "read_packets", "read_pcapng", "udp_payloads"]
