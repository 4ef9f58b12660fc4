"""Loopback emulator of an OptiTrack Motive NatNet server (3.0 or 4.1; unicast or multicast; Up Axis z or y).

Subset of NatNet implemented (little-endian, every packet starts with ``uint16 message id, uint16 payload
bytes``), exactly what libmotioncapture's ``MotionCaptureOptitrack`` (PyPI ``motioncapture`` 1.1) reads:

* Command port (UDP, ``127.0.0.1:<command_port>``, OS-assigned by default), request → reply to the sender:

  - ``NAT_CONNECT`` (0) → ``NAT_SERVERINFO`` (1): ``char szName[256]`` ("Motive"), ``uint8 Version[4]``,
    ``uint8 NatNetVersion[4]`` (3.0.0.0 or 4.1.0.0), ``uint64 HighResClockFrequency`` (ticks/s), ``uint16
    DataPort``, ``bool IsMulticast``, ``uint8 MulticastGroupAddress[4]`` (239.255.42.99 or 0.0.0.0).
  - ``NAT_REQUEST_MODELDEF`` (4) → ``NAT_MODELDEF`` (5): ``int32 nDatasets``, then per rigid body
    ``int32 type`` = 1, ``char name[]`` (NUL-terminated), ``int32 ID``, ``int32 parentID`` = -1,
    ``float32 x/y/z offset`` = 0 (libmotioncapture ADDS these to every position), ``int32 nMarkers`` = 0.
  - anything else (keep-alives, NatNet 4 "client connect" 2, ...) is ignored.

* Data: ``NAT_FRAMEOFDATA`` (7) at ``rate_hz`` to where `delivery` says (NatNet 3.0 below; 4.1: see
  `frame_packet`): ``int32 frame``,
  ``int32 nMarkerSets`` = 0, ``int32 nOtherMarkers`` = 0, ``int32 nRigidBodies`` and per body ``int32 ID``,
  ``float32 x, y, z`` (m), ``float32 qx, qy, qz, qw``, ``float32 meanError`` = 0, ``int16 params`` (bit 0:
  tracking valid); then ``int32 nSkeletons, nLabeledMarkers, nForcePlates, nDevices`` = 0, ``uint32
  timecode, timecodeSub``, ``float64 timestamp`` (s since start), ``uint64`` camera mid-exposure / data
  received / transmit timestamps (ticks), ``int16 params`` = 0, ``int32 eod`` = 0.

libmotioncapture sends ``NAT_CONNECT`` and ``NAT_REQUEST_MODELDEF`` once from an ephemeral port of
``hostname`` (setting; an IPv4 literal, it is not resolved) to ``port_command`` (setting, default
1510), reads the data port from the server info, binds 0.0.0.0:DataPort (joining the multicast group on
``interface_ip``, setting, default 0.0.0.0, when the server says multicast) and parses the newest frame of
each ``waitForNextFrame()``. ``rigidBodies`` then holds only
bodies with the tracking-valid bit set, named by the model definition read at connect time (a body first
defined after the client connected is unknown to it). Both "omitted from the frame" and "tracked = 0" make a
body vanish from ``rigidBodies``; ``faults.lost_bodies`` flags them untracked (what Motive does) unless
``faults.lost_omit`` is set.

Why a child process: ``motioncapture.connect`` does NOT release the GIL while it waits (blocking, no
timeout) for the server's replies, so a command responder running as a thread of the client's interpreter
could never answer. The command port is therefore served by a small child process (this file run as a
script with ``--responder``; it only imports the standard library and exits when its stdin closes, on
``close()``, or after ``RESPONDER_MAX_LIFETIME_S``). Frames are streamed by a thread of this process.

Frames: positions in the emulated motion-capture world frame (m, z up); quaternions (w, x, y, z) of the body
in that frame (sent as they are given, not normalised).
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import os
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .device_links import DeviceLinks
    from .radio import DeviceRadio

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_FRAMEOFDATA = 7
NATNET_VERSION = (3, 0, 0, 0)  # the default layout (Motive 2.1, the recorded real packets)
NATNET_VERSIONS = ((3, 0, 0, 0), (4, 1, 0, 0))  # the layouts this emulator writes
MULTICAST_GROUP = "239.255.42.99"  # Motive's default Multicast Interface (the recorded packets' group)
UP_AXES = ("z", "y")
DELIVERIES = ("unicast", "unicast_command", "multicast")
SERVER_VERSION = (2, 3, 0, 0)  # the emulated Motive version (informational)
CLOCK_TICKS_PER_S = 10_000_000  # HighResClockFrequency advertised in the server info (ticks/s)
RESPONDER_START_TIMEOUT_S = 5.0  # max wait for the child process to report its port
RESPONDER_MAX_LIFETIME_S = 600.0  # the child exits by itself after this long (s)

Vec3 = Sequence[float]
QuatWXYZ = Sequence[float]
PoseProvider = Callable[[], tuple[Vec3, QuatWXYZ]]  # position (m), quaternion (w, x, y, z)


@dataclass
class NatNetFaults:
    """Fault switches; a test may flip them at any time (read by the streaming thread every frame).

    silent:      answer no command (connect blocks) and send no frame, as if no server were there.
    drop_frames: keep answering commands but stop streaming frames.
    lost_bodies: names of bodies reported as lost: flagged "tracking valid = 0" in every frame (default),
                 or left out of the frames when `lost_omit` is True. libmotioncapture hides both.
    lost_omit:   see `lost_bodies`.
    frozen_bodies: names of bodies whose pose is held at what it was in the first frame after they were
                 named, in every later frame with its fresh frame number, time stamp and "tracking valid"
                 (a stuck capture pipeline, a frozen replay; Motive itself never repeats a tracked sample).
    """

    silent: bool = False
    drop_frames: bool = False
    lost_bodies: set[str] = field(default_factory=set)
    lost_omit: bool = False
    frozen_bodies: set[str] = field(default_factory=set)


def _pack_packet(message_id: int, payload: bytes) -> bytes:
    return struct.pack("<HH", message_id, len(payload) & 0xFFFF) + payload


def _block_size(version: Sequence[int]) -> bool:
    """NatNet 4.1 and later write each frame block's and each description's byte count."""
    return tuple(version[:2]) >= (4, 1)


def server_info_packet(
    data_port: int,
    name: str = "Motive",
    version: Sequence[int] = NATNET_VERSION,
    multicast: bool = False,
    group: str = MULTICAST_GROUP,
) -> bytes:
    """NAT_SERVERINFO reply (sender_server layout, the same in NatNet 3.0 and 4.x) advertising `data_port`,
    the NatNet `version` and unicast or multicast to `group`."""
    payload = (
        name.encode("ascii")[:255].ljust(256, b"\0")
        + bytes(SERVER_VERSION)
        + bytes(version)
        + struct.pack("<QH?", CLOCK_TICKS_PER_S, data_port, multicast)
        + socket.inet_aton(group if multicast else "0.0.0.0")
    )
    return _pack_packet(NAT_SERVERINFO, payload)


def model_def_packet(bodies: Sequence[tuple[str, int]], version: Sequence[int] = NATNET_VERSION) -> bytes:
    """NAT_MODELDEF reply describing rigid bodies given as (name, id); offsets are zero, no markers. NatNet
    4.1 writes each description's byte count after its type (natnetsdk `__unpack_data_descriptions`)."""
    out = [struct.pack("<i", len(bodies))]
    for name, body_id in bodies:
        desc = name.encode("utf-8") + b"\0" + struct.pack("<iifffi", body_id, -1, 0.0, 0.0, 0.0, 0)
        size = struct.pack("<i", len(desc)) if _block_size(version) else b""
        out.append(struct.pack("<i", 1) + size + desc)
    return _pack_packet(NAT_MODELDEF, b"".join(out))


def frame_packet(
    frame: int,
    t_s: float,
    bodies: Sequence[tuple[int, Vec3, QuatWXYZ, bool]],
    version: Sequence[int] = NATNET_VERSION,
) -> bytes:
    """NAT_FRAMEOFDATA at time t_s (s) with rigid bodies (id, position m, (w,x,y,z), tracked).

    NatNet 3.0, or 4.1 (natnetsdk `__unpack_mocap_data`, libmotioncapture `waitForNextFrame`): every
    block count is followed by the block's byte count, an asset block follows the skeletons, and the
    suffix carries the precision timestamp (uint32 s, uint32 fraction) before its params (4.0 and later)."""
    sized = _block_size(version)

    def block(count: int, body: bytes = b"") -> bytes:
        return struct.pack("<i", count) + (struct.pack("<i", len(body)) if sized else b"") + body

    rb = b"".join(
        struct.pack("<i3f4ffh", body_id, *(float(v) for v in p), *(float(q[k]) for k in (1, 2, 3, 0)), 0.0,
                    1 if tracked else 0)
        for body_id, p, q, tracked in bodies
    )  # fmt: skip
    out = [struct.pack("<i", frame), block(0), block(0), block(len(bodies), rb), block(0)]
    if sized:
        out.append(block(0))  # assets
    out += [block(0), block(0), block(0)]  # labeled markers, force plates, devices
    ticks = int(t_s * CLOCK_TICKS_PER_S)
    out.append(struct.pack("<IIdQQQ", 0, 0, t_s, ticks, ticks, ticks))
    if version[0] >= 4:
        out.append(struct.pack("<II", int(t_s), int((t_s % 1.0) * 2**32) & 0xFFFFFFFF))
    out.append(struct.pack("<hi", 0, 0))
    return _pack_packet(NAT_FRAMEOFDATA, b"".join(out))


def y_up(position: Vec3, quaternion_wxyz: QuatWXYZ) -> tuple[Vec3, QuatWXYZ]:
    """A pose of the z-up world as Motive streams it with Up Axis = Y (its default): the frame turned by
    -90° about x, so (x, y, z) -> (x, z, -y), and the body's orientation re-expressed in it (a level body
    yawed ψ about z is a rotation by ψ about y, as in the recorded frame 162734)."""
    x, y, z = (float(v) for v in position)
    w, qx, qy, qz = (float(v) for v in quaternion_wxyz)
    return (x, z, -y), (w, qx, qz, -qy)


@dataclass
class _Body:
    body_id: int
    position: Vec3  # m, 3 floats
    quaternion_wxyz: QuatWXYZ  # 4 floats
    provider: PoseProvider | None = None


class NatNetEmulator:
    """A NatNet 3.0 unicast server on loopback: command port in a child process, frames from a thread.

    bodies:       initial rigid bodies, name -> (position (3,) m, quaternion (w, x, y, z)); ids 1, 2, ...
    rate_hz:      frame rate (Hz), deadline-paced.
    host:         loopback address the server binds and streams to (must be in 127.0.0.0/8).
    command_port: 0 = OS-assigned (see `command_port` after `start()`).
    data_port:    0 = a free port picked at `start()`; the client binds it, the emulator sends to it.
    faults:       see `NatNetFaults`.
    radio:        the frames' network (`radio.DeviceRadio` with a link "frames"; None: perfect). The
                  connect handshake (the child process) is not impaired: `motioncapture.connect` waits
                  for its replies without a timeout, holding the GIL, so a lost reply would hang it.
    links:        the rig's links of the motion capture (`device_links.DeviceLinks`: each frame leaves
                  late by the "mocap" link, or is lost, before the radio); None: none. The frame's
                  timestamp stays the time it was taken.
    Motive's options (docs/drivers.md, "What a real Motive sends", names their sources):
    natnet_version: (3, 0, 0, 0) (Motive 2.1, the recorded packets) or (4, 1, 0, 0) (Motive 3.x: block
                  byte counts, an asset block, precision timestamps).
    up_axis:      "z" (what flightstack needs) or "y" (Motive's default Up Axis): poses are given in the
                  z-up world and streamed turned as Motive turns them (`y_up`).
    delivery:     "unicast": frames to (host, data_port), what libmotioncapture 1.1 reads (it binds
                  0.0.0.0:DataPort); "unicast_command": to the sender of the last NAT_CONNECT (the
                  client's command socket), as Motive sends unicast frames (what natnetsdk reads);
                  "multicast": to MULTICAST_GROUP:data_port through the loopback interface only (TTL 0),
                  Motive's default Transmission Type.
    """

    def __init__(
        self,
        bodies: dict[str, tuple[Vec3, QuatWXYZ]] | None = None,
        rate_hz: float = 100.0,
        host: str = "127.0.0.1",
        command_port: int = 0,
        data_port: int = 0,
        faults: NatNetFaults | None = None,
        radio: DeviceRadio | None = None,
        links: DeviceLinks | None = None,
        natnet_version: Sequence[int] = NATNET_VERSION,
        up_axis: str = "z",
        delivery: str = "unicast",
    ) -> None:
        if delivery not in DELIVERIES:
            raise ValueError(f"delivery must be one of {DELIVERIES}, got {delivery!r}")
        if tuple(natnet_version) not in NATNET_VERSIONS:
            raise ValueError(f"natnet_version must be one of {NATNET_VERSIONS}, got {tuple(natnet_version)}")
        if up_axis not in UP_AXES:
            raise ValueError(f"up_axis must be one of {UP_AXES}, got {up_axis!r}")
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"NatNetEmulator only serves loopback addresses, got {host!r}")
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be finite and > 0, got {rate_hz}")
        self.host = host
        self.rate_hz = rate_hz
        self.command_port = command_port
        self.data_port = data_port
        self.faults = faults or NatNetFaults()
        self._frozen: dict[str, tuple[Vec3, QuatWXYZ]] = {}  # frozen_bodies: the pose each is held at
        self.radio = radio
        self.links = links
        self.natnet_version = tuple(natnet_version)
        self.up_axis = up_axis
        self.delivery = delivery
        self.multicast = delivery == "multicast"
        self.client: tuple[str, int] | None = None  # the sender of the last NAT_CONNECT (unicast_command)
        self.frames_sent = 0  # NAT_FRAMEOFDATA packets sent so far
        self.provider_errors: list[str] = []  # "name: exception" of pose providers that raised
        self._bodies: dict[str, _Body] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reports: threading.Thread | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._sent_modeldef: bytes | None = None
        self._sent_silent: bool | None = None
        self._t0 = time.monotonic()
        for name, (p, q) in (bodies or {}).items():
            self.set_body(name, p, q)

    # ---- bodies ---------------------------------------------------------------------------------------
    def set_body(self, name: str, position: Vec3, quaternion_wxyz: QuatWXYZ) -> None:
        """Set (or add) body `name` at position (3,) m with orientation (w, x, y, z); clears its provider.

        A body added after a client connected is unknown to that client (model definitions are read once).
        """
        p = tuple(float(v) for v in position)
        q = tuple(float(v) for v in quaternion_wxyz)
        if len(p) != 3 or len(q) != 4:
            raise ValueError(f"position must have 3 and quaternion 4 components, got {len(p)} and {len(q)}")
        with self._lock:
            b = self._bodies.get(name)
            if b is None:
                self._bodies[name] = _Body(len(self._bodies) + 1, p, q)
            else:
                b.position, b.quaternion_wxyz, b.provider = p, q, None

    def set_pose_provider(self, name: str, fn: PoseProvider | None) -> None:
        """Stream body `name` from fn() -> (position (3,) m, quaternion (w, x, y, z)), called at each frame.

        The body must exist (`set_body` first, which also gives the pose used if fn raises). None removes it.
        """
        with self._lock:
            if name not in self._bodies:
                raise KeyError(f"unknown body {name!r}; call set_body() first")
            self._bodies[name].provider = fn

    def network_counts(self) -> dict[str, dict[str, float]]:
        """What the radio did per link (`radio.DeviceRadio.counts`); empty on a perfect link."""
        return {} if self.radio is None else self.radio.counts()

    def body_names(self) -> list[str]:
        with self._lock:
            return list(self._bodies)

    # ---- lifecycle ------------------------------------------------------------------------------------
    def settings(self) -> dict[str, str]:
        """Settings for `motioncapture.connect("optitrack", settings)` (valid after `start()`)."""
        if self._proc is None:
            raise RuntimeError("NatNetEmulator.settings() before start()")
        return {"hostname": self.host, "port_command": str(self.command_port), "interface_ip": self.host}

    def start(self) -> NatNetEmulator:
        """Start the command responder (child process) and the frame thread; returns self."""
        if self._proc is not None:
            raise RuntimeError("NatNetEmulator.start() called twice")
        if self.data_port == 0:
            from flightstack.ports import free_udp_port  # (the responder imports only the stdlib)

            self.data_port = free_udp_port(self.host)
        self._proc = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), "--responder", self.host, str(self.command_port),
             server_info_packet(self.data_port, version=self.natnet_version, multicast=self.multicast).hex(),
             "--report"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )  # fmt: skip
        try:
            self._sync_responder()
            self.command_port = self._read_port(self._proc)
        except BaseException:
            self._stop_responder()
            raise
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((self.host, 0))
        if self.multicast:  # through loopback only, and never past this host
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.host))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._sock = sock if self.radio is None else self.radio.socket(sock, lambda _a: "frames", None)  # type: ignore[assignment]
        if self.links is not None and self.links.applies("mocap"):
            self._sock = self.links.socket(self._sock, send=lambda _a: "mocap")
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="natnet-emu", daemon=True)
        self._thread.start()
        self._reports = threading.Thread(
            target=report_loop,
            args=(self._proc, self._stop, self._report),
            name="natnet-emu-reports",
            daemon=True,
        )
        self._reports.start()
        return self

    def _report(self, msg: int, ip: str, port: int) -> None:
        if msg == NAT_CONNECT and ipaddress.ip_address(ip).is_loopback:
            self.client = (ip, port)

    def close(self) -> None:
        """Stop the frame thread (joined within 1 s) and the responder (1 s, then killed). Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=1.0)
        if self._reports is not None:
            self._reports.join(timeout=1.0)
        if self.links is not None:
            self.links.close()
        if self.radio is not None:
            self.radio.close()
        if self._sock is not None:
            self._sock.close()
        self._stop_responder()

    def __enter__(self) -> NatNetEmulator:
        if self._proc is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- internals ------------------------------------------------------------------------------------
    @staticmethod
    def _read_port(proc: subprocess.Popen[bytes]) -> int:
        assert proc.stdout is not None
        fd = proc.stdout.fileno()
        deadline = time.monotonic() + RESPONDER_START_TIMEOUT_S
        buf = b""
        while b"\n" not in buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0 or proc.poll() is not None:
                raise RuntimeError(f"NatNet responder did not start (exit code {proc.poll()})")
            ready, _, _ = select.select([fd], [], [], min(remaining, 0.1))
            if ready:
                chunk = os.read(fd, 256)
                if not chunk:
                    raise RuntimeError("NatNet responder closed its output before reporting its port")
                buf += chunk
        word, port = buf.split(b"\n", 1)[0].split()
        if word != b"PORT":
            raise RuntimeError(f"unexpected NatNet responder output {buf!r}")
        return int(port)

    def _sync_responder(self) -> None:
        """Tell the responder the current model definition and silence (only what changed)."""
        with self._lock:
            defs = [(name, b.body_id) for name, b in self._bodies.items()]
        modeldef = model_def_packet(defs, self.natnet_version)
        silent = bool(self.faults.silent)
        lines = []
        if modeldef != self._sent_modeldef:
            lines.append(b"M " + modeldef.hex().encode() + b"\n")
        if silent != self._sent_silent:
            lines.append(b"S 1\n" if silent else b"S 0\n")
        if not lines or self._proc is None or self._proc.stdin is None:
            return
        with contextlib.suppress(OSError, ValueError):
            self._proc.stdin.write(b"".join(lines))
            self._proc.stdin.flush()
            self._sent_modeldef, self._sent_silent = modeldef, silent

    def _stop_responder(self) -> None:
        stop_responder(self._proc)

    def _frame_bodies(self) -> list[tuple[int, Vec3, QuatWXYZ, bool]]:
        lost, omit = set(self.faults.lost_bodies), self.faults.lost_omit
        frozen = set(self.faults.frozen_bodies)
        for name in set(self._frozen) - frozen:
            del self._frozen[name]
        with self._lock:
            items = [
                (n, b.body_id, b.position, b.quaternion_wxyz, b.provider) for n, b in self._bodies.items()
            ]
        out: list[tuple[int, Vec3, QuatWXYZ, bool]] = []
        for name, body_id, p, q, provider in items:
            if name in lost and omit:
                continue
            if provider is not None:
                try:
                    p, q = provider()
                except Exception as exc:  # a broken provider must not kill the stream
                    self.provider_errors.append(f"{name}: {type(exc).__name__}: {exc}")
            if name in frozen:
                p, q = self._frozen.setdefault(name, (p, q))
            if self.up_axis == "y":
                p, q = y_up(p, q)
            out.append((body_id, p, q, name not in lost))
        return out

    def _destination(self) -> tuple[str, int] | None:
        if self.delivery == "multicast":
            return (MULTICAST_GROUP, self.data_port)
        if self.delivery == "unicast_command":
            return self.client
        return (self.host, self.data_port)

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            self._sync_responder()
            if not (self.faults.silent or self.faults.drop_frames) and self._sock is not None:
                now = time.monotonic()
                bodies = self._frame_bodies()
                pkt = frame_packet(self.frames_sent + 1, now - self._t0, bodies, self.natnet_version)
                dest = self._destination()
                with contextlib.suppress(OSError):
                    if dest is not None:
                        self._sock.sendto(pkt, dest)
                        self.frames_sent += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (e.g. GIL held by a blocking connect): do not burst
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(0.0, delay))


def report_loop(
    proc: subprocess.Popen[bytes], stop: threading.Event, handle: Callable[[int, str, int], None]
) -> None:
    """Read a responder's report lines ("<message id> <sender ip> <sender port>", after its "PORT" line)
    until `stop` or its output closes; malformed lines are skipped."""
    if proc.stdout is None:
        return
    fd, buf = proc.stdout.fileno(), b""
    while not stop.is_set():
        ready, _, _ = select.select([fd], [], [], 0.05)
        if not ready:
            continue
        try:
            chunk = os.read(fd, 4096)
        except (OSError, ValueError):
            return
        if not chunk:
            return
        buf += chunk
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            words = line.decode("ascii", errors="replace").split()
            if len(words) == 3 and words[0].isdigit() and words[2].isdigit():
                handle(int(words[0]), words[1], int(words[2]))


# ---- command responder (child process) -------------------------------------------------------------------
def stop_responder(proc: subprocess.Popen[bytes] | None, close_output: bool = True) -> None:
    """Stop a responder process (`Q` on its stdin, killed after 1 s) and, if `close_output`, close its
    output (False: a thread still reads it to its end); None: nothing."""
    if proc is None:
        return
    with contextlib.suppress(OSError, ValueError):
        if proc.stdin is not None:
            proc.stdin.write(b"Q\n")
            proc.stdin.close()
    try:
        proc.wait(timeout=1.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=1.0)
    if close_output and proc.stdout is not None:
        proc.stdout.close()


def _responder_main(host: str, port: int, server_info_hex: str, report: bool = False) -> int:
    """Answer NAT_CONNECT / NAT_REQUEST_MODELDEF on host:port; controlled by lines on stdin.

    stdin lines: "M <hex>" new model-definition packet, "S 1"/"S 0" silent on/off, "Q" quit; EOF quits.
    Prints "PORT <n>" once bound; with `report`, also "<message id> <sender ip> <sender port>" for every
    request answered (the replayer streams to the sender of NAT_CONNECT). Exits after
    RESPONDER_MAX_LIFETIME_S in any case.
    """
    server_info = bytes.fromhex(server_info_hex)
    modeldef = model_def_packet([])
    silent = False
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, port))
    sys.stdout.write(f"PORT {sock.getsockname()[1]}\n")
    sys.stdout.flush()
    stdin_fd = sys.stdin.fileno()
    buf = b""
    deadline = time.monotonic() + RESPONDER_MAX_LIFETIME_S
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([sock, stdin_fd], [], [], 0.5)
            if stdin_fd in ready:
                chunk = os.read(stdin_fd, 1 << 16)
                if not chunk:
                    return 0
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    if line.startswith(b"M "):
                        modeldef = bytes.fromhex(line[2:].decode())
                    elif line.startswith(b"S "):
                        silent = line[2:] == b"1"
                    elif line == b"Q":
                        return 0
            if sock in ready:
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    continue
                if silent or len(data) < 2:
                    continue
                (msg,) = struct.unpack_from("<H", data)
                with contextlib.suppress(OSError):
                    if msg == NAT_CONNECT:
                        sock.sendto(server_info, addr)
                    elif msg == NAT_REQUEST_MODELDEF:
                        sock.sendto(modeldef, addr)
                    else:
                        continue
                    if report:
                        sys.stdout.write(f"{msg} {addr[0]} {addr[1]}\n")
                        sys.stdout.flush()
        return 0
    finally:
        sock.close()


if __name__ == "__main__":
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--responder":
        report = sys.argv[5:] == ["--report"]
        sys.exit(_responder_main(sys.argv[2], int(sys.argv[3]), sys.argv[4], report))
    sys.exit("usage: natnet.py --responder HOST PORT SERVER_INFO_HEX [--report]")
