"""Protocol-level emulator of a DJI/Ryze Tello (SDK 2.0/3.0 text protocol) for tests.

The emulator speaks the real wire protocol, so an unmodified client (e.g. ``djitellopy``) can drive it:

* **Commands** arrive as UTF-8 text datagrams on ``emu.address`` (``(ip, port)``, default ip ``127.0.0.2``,
  port picked by the OS).  Replies (``ok`` / ``error ...`` / a value for read commands) are sent back to the
  sender's address *and port* from that same socket, i.e. from the emulator's own ip:port (the real drone
  answers from 192.168.10.1:8889 to the sender's port: DJITelloPy #143, a client on an OS-assigned port got
  its replies).  ``rc``, ``emergency`` and ``reboot`` get no reply, like on the real drone.
* **State** strings (``mid:-1;x:..;...;agz:..;\\r\\n``) are sent at ``state_hz`` (10 Hz) from a socket bound
  to the emulator's IP to ``(client_ip, state_port)`` (default ``127.0.0.1:8890``) once SDK mode is entered.
  ``djitellopy`` routes replies *and* state to a drone object by the datagram's **source IP only**, hence one
  loopback IP per emulated drone (``127.0.0.2``, ``127.0.0.3``, ... for swarms).
* **Video**: after ``streamon`` a thread renders ``frame_source(t, emu)`` (``t`` = stream time ``n / fps`` of
  frame ``n``), encodes it with libx264 (ultrafast, zerolatency, repeat-headers, short GOP) and sends the raw
  Annex-B byte stream in datagrams of at most 1460 bytes to ``(client_ip, video_port)`` (default port 11111).

All traffic is restricted to 127.0.0.0/8: every configured address is validated and replies to a
non-loopback sender are dropped.  All threads are daemons with bounded waits (<= 0.1 s) and ``close()``
joins them.

Fault switches live in :class:`TelloFaults` (module ``tello_faults``, re-exported here, each switch names the
user reports it is based on).  Sources cited below: *DJITelloPy #N* =
https://github.com/damiafuentes/DJITelloPy/issues/N, *Tello-Python #N* =
https://github.com/dji-sdk/Tello-Python/issues/N, the SDK 2.0 and SDK 3.0 user guides (URLs in
``tello_faults``).

Behavioural choices (the real drone's behaviour is partly undocumented; where no report was found the choice
is marked *unverified*; clients must only rely on ``ok`` versus not ``ok``, error texts differ between
firmwares):

* **Before ``command``** (not in SDK mode) the real drone's text parser is not active - the SDK docs only
  say ``command`` must be sent first and that state packets start after it.  The emulator records such
  datagrams in ``commands`` and ``refused`` (as ``"ignored"``) but does not act on them and does not reply
  (configurable with ``pre_sdk_reply``, e.g. ``"error"``).  State packets are only sent in SDK mode.
* **Firmware**: by default a Tello EDU with SDK 3.0 (``sdk?`` -> ``30``).  With ``faults.sdk_version = "20"``
  the SDK-3.0-only verbs (``port``, ``downvision``, ``setfps``, ``setbitrate``, ``setresolution``,
  ``motoron``/``motoroff``, ``multiwifi``, ``reboot``, ``keepalive``, ``hardware?``, ... see
  ``SDK3_ONLY_COMMANDS``) answer ``unknown command: <verb>`` and have no effect (DJITelloPy #92, #107, #111,
  #138).
* **Phases** ``landed`` -> ``takeoff`` -> ``flying`` -> ``landing`` -> ``landed``; every transition is
  appended to ``phase_log``.  The motors run (state field ``time``, integer motor-on seconds, rises) in every
  phase but ``landed``.
* **Takeoff**: the motors start, the drone climbs linearly to ``takeoff_height_cm`` (80 cm) within the
  takeoff's duration but in at most ``TAKEOFF_CLIMB_S`` (2 s, *unverified*), hovers (stabilising) until the
  duration has passed, then replies ``ok``.  The duration is ``takeoff_s`` (default 0.3 s to keep tests fast;
  a real takeoff answers after ~3.9 s, Tello-Python #88) or ``faults.takeoff_s`` when set (slow takeoff:
  DJITelloPy #31, djitellopy waits 20 s).  Refused with ``error battery low`` below ``MIN_TAKEOFF_BATTERY``
  percent (real drones answer ``error`` or ``error Motor stop`` on a low battery: DJITelloPy #15, #60), with
  ``error`` while flying (*unverified* text).
* **Land** descends linearly over ``land_s`` (real: ~1.7 s, Tello-Python #88), the motors stop, then ``ok``.
  ``land`` while landed answers ``error Motor stop`` (DJITelloPy #126: ``end()`` "will hang retrying land()
  and eventually throw an exception" when the drone had already landed; ``error Motor stop`` is among the
  Tello's flight replies in dji-sdk/RoboMaster-SDK's ``TelloStatus`` and what DJITelloPy #15 got from a drone
  that would not spin up).
* **Busy**: ``takeoff``, ``land`` and moves received during a takeoff or landing answer ``error Not joystick``
  (``error Auto land`` during an auto-landing) and are not executed.  *Unverified*: no report gives the
  exact reply to ``land`` during ``takeoff``; the MATLAB support package for Ryze Tello ignores ``error Not
  joystick`` and ``error Auto land`` as replies that arrive while a "previous non-blocking command was not
  run to completion", and the RoboMaster SDK lists both among the Tello's flight replies.  Read commands are
  answered at once in every phase (*unverified*; djitellopy users read state while flying).  Flight commands
  while landed answer ``error Motor stop``.
* **``rc``** sets the joystick targets only in phase ``flying``; received in any other phase it is recorded in
  ``rc_history`` and ``refused`` but has no effect.  No reply, unless ``faults.rc_replies`` (``ok`` while
  flying, ``error Not joystick`` otherwise).  A malformed ``rc`` goes to ``rejected`` and ``refused``.
* **``emergency``**: no reply (Tello-Python #85, confirmed by Ryze support: "some commands do not return";
  DJITelloPy #125), the motors stop at once and the drone drops to h = 0; an interrupted takeoff/landing never
  answers.  ``reboot`` (SDK 3.0) does the same and leaves SDK mode.
* **Auto-land**: while flying, if no datagram (any command, including ``rc``) has been received for
  ``auto_land_s`` seconds (15 s, SDK 2.0/3.0 guides "Safety Function"; DJITelloPy #141) the drone lands by
  itself and ``landed_by_timeout`` is set.
* **Refused commands**: ``refused`` holds ``(time, phase at receipt, text, reply or "ignored")`` for every
  command the drone did not carry out: ignored ones (before ``command``, ``rc`` outside ``flying``, malformed
  ``rc``), and every reply that is not ``ok`` to a control/set command or is ``error ...``/``unknown command:
  ...`` to a read command (phase errors, ``out of range``, ``error_replies``, SDK 2.0 unknown verbs).  A
  refusal whose reply was lost or silenced is still recorded.  Successful commands never appear there.
* **Replies** are sent FIFO (a reply delayed by ``reply_delay_s`` holds back later ones); every datagram sent
  is logged in ``replies_sent``.  ``faults.lost_replies`` drops the reply of given verbs (the command runs);
  ``faults.duplicate_reply_after_s`` sends each reply again later, outside the FIFO order.
* **Motion model** (ground truth, world frame ``x`` forward at takeoff heading, ``y`` right, ``z`` up, yaw
  clockwise in degrees): ``rc a b c d`` sets body-frame velocity targets of 1 cm/s per unit (a = right,
  b = forward, c = up) and 1 deg/s per unit of yaw rate (d = clockwise); the actual velocity follows with a
  first-order lag (``tau_s`` = 0.1 s).  The last ``rc`` stays in effect until the next one.  Discrete moves
  (``forward 50``, ``cw 90``, ``go ...``) are applied instantaneously.  ``vgx/vgy/vgz`` are the world
  velocities in dm/s (rounded), ``h`` the height in cm (1 cm resolution) above the takeoff point,
  ``tof = h + 10`` cm, ``x/y/z`` the integrated position in cm (a test convenience - the real drone reports
  mission-pad coordinates there), pitch/roll are 0.
* **Battery**: ``faults.battery_pct`` is the *set-point*; the reported value drains from it slowly
  (``DRAIN_FLYING_PCT_S`` / ``DRAIN_IDLE_PCT_S``) and re-bases whenever the test writes a new value.
* ``port <state> <video>`` re-targets state and video (djitellopy's ``change_vs_udp``).
* **Video size** is fixed per emulator (``video_size``).  ``downvision 1`` only flips ``emu.downvision``; the
  frame source is expected to render the downward view at the same size (the real EDU downward camera is
  320x240 grey - not emulated, to keep a single encoder per stream).
* Read-command formats follow what the real drone sends (``height?`` -> ``"80dm"``, ``temp?`` -> ``"60~63"``,
  ``time?`` -> ``"0s"``, ``speed?`` -> ``"100.0"``, ``tof?`` -> ``"900mm"``); note that djitellopy's
  ``query_height``/``query_temperature``/``query_flight_time``/``query_speed`` ``int()``-parse these and
  therefore raise ``ValueError`` against the emulator (and, by report, against real drones).

* **Several controllers** (another socket or process of the same computer, e.g. the guardian process of
  drivers/guardian.py): once in SDK mode, commands from any source port are executed, and every datagram's
  sender is logged in ``senders``.  Replies go to the sender (Tello, DJITelloPy #143: a client on an
  OS-assigned port got its replies), or, with ``reply_port_latch=True`` (Tello EDU), always to the address
  that sent the first ``command`` (DJITelloPy PR #163, on EDU drones: a second run of a script on a new
  port "hangs on client_socket.recv" while "sending commands to the drone work[s] perfectly"; PR #168
  re-binds the client to port 8889 for the EDU).  *Unverified*: whether a second ``command`` moves the
  latch; here it does not.

Not modelled: binary (non-text)
datagrams some firmwares send on the command port (carlospzlz/ctello#7), ``error No valid imu`` and
``error, high temp`` refusals, ``motoron`` motor-on mode, battery auto-land, and the gradual reply-queue
backlog users see when sending commands back to back.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import math
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from types import TracebackType
from typing import Any

import numpy as np

from .tello_faults import SDK3_ONLY_COMMANDS, ReplyScheduler, TelloFaults, has_sdk3

__all__ = [
    "SDK3_ONLY_COMMANDS",
    "FrameSource",
    "ReplyScheduler",
    "TelloEmulator",
    "TelloFaults",
    "default_frame_source",
    "free_udp_port",
    "is_loopback",
    "read_frame_index",
    "stamp_frame_index",
    "wait_until",
]

LOG = logging.getLogger(__name__)

FrameSource = Callable[[float, "TelloEmulator"], np.ndarray]
"""``frame_source(t, emu) -> HxWx3 uint8 RGB`` (or HxW grey) image of size ``emu.video_size``."""

MAX_VIDEO_DATAGRAM = 1460
"""Largest video datagram payload, like the real drone."""

INDEX_BITS = 16
"""Bits of the frame-index bar code stamped by :func:`stamp_frame_index`."""


def is_loopback(ip: str) -> bool:
    """Return True when ``ip`` is an IPv4 address in 127.0.0.0/8."""
    try:
        return ipaddress.IPv4Address(ip) in ipaddress.IPv4Network("127.0.0.0/8")
    except ValueError:
        return False


def _require_loopback(ip: str, what: str) -> None:
    if not is_loopback(ip):
        raise ValueError(f"{what} must be an IPv4 loopback address (127.0.0.0/8), got {ip!r}")


def free_udp_port(ip: str = "127.0.0.1") -> int:
    """Return a UDP port that is currently free on the loopback address ``ip``.

    The port is found by binding to port 0 and closing the socket again, so another process may grab it
    in between; good enough for tests.
    """
    _require_loopback(ip, "ip")
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


# --------------------------------------------------------------------------------------------- video helpers
def _barcode_geometry(width: int, height: int) -> tuple[int, int, int, int]:
    """Return (x0, y0, block_w, block_h) of the frame-index bar code."""
    block_w = max(4, width // (INDEX_BITS + 4))
    block_h = max(8, height // 24)
    return block_w * 2, block_h // 2, block_w, block_h


def stamp_frame_index(img: np.ndarray, index: int) -> None:
    """Draw ``index`` (mod 2**16) as a row of black/white blocks near the top edge of ``img`` (in place)."""
    height, width = img.shape[:2]
    x0, y0, bw, bh = _barcode_geometry(width, height)
    for bit in range(INDEX_BITS):
        value = 255 if (index >> bit) & 1 else 0
        img[y0 : y0 + bh, x0 + bit * bw : x0 + (bit + 1) * bw] = value


def read_frame_index(img: np.ndarray) -> int:
    """Decode the bar code written by :func:`stamp_frame_index` from a (decoded, lossy) frame."""
    height, width = img.shape[:2]
    x0, y0, bw, bh = _barcode_geometry(width, height)
    mx, my = max(1, bw // 4), max(1, bh // 4)
    index = 0
    for bit in range(INDEX_BITS):
        block = img[y0 + my : y0 + bh - my, x0 + bit * bw + mx : x0 + (bit + 1) * bw - mx]
        if float(block.mean()) > 127.0:
            index |= 1 << bit
    return index


def default_square(t: float, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """Pixel box ``(x0, y0, x1, y1)`` (exclusive ends) of the default source's square at stream time ``t``."""
    width, height = size
    side = max(4, height // 6)
    cx = width / 2 + 0.3 * width * math.cos(2.0 * math.pi * 0.25 * t)
    cy = height / 2 + 0.25 * height * math.sin(2.0 * math.pi * 0.25 * t)
    x0 = round(cx - side / 2)
    y0 = round(cy - side / 2)
    return x0, y0, x0 + side, y0 + side


def default_frame_source(t: float, emu: TelloEmulator) -> np.ndarray:
    """Synthetic RGB frame: a coloured square moving on a circle, plus the frame index as a bar code.

    Forward camera: grey background, red square.  Downward camera (``emu.downvision``): dark background,
    green square.  The frame index ``round(t * emu.fps)`` is stamped with :func:`stamp_frame_index`, so a
    test can match every decoded frame with the exact frame that was rendered (see :func:`default_square`).
    """
    width, height = emu.video_size
    down = emu.downvision
    img = np.full((height, width, 3), 60 if down else 128, dtype=np.uint8)
    x0, y0, x1, y1 = default_square(t, (width, height))
    img[max(0, y0) : max(0, y1), max(0, x0) : max(0, x1)] = (0, 255, 0) if down else (255, 0, 0)
    stamp_frame_index(img, round(t * emu.fps))
    return img


# ------------------------------------------------------------------------------------------- internals
@dataclass
class _Deferred:
    """A reply that is sent when a takeoff/landing completes."""

    addr: tuple[str, int] | None
    delay_s: float


_READ_ONLY_OK = frozenset(
    {"keepalive", "mon", "moff", "mdirection", "setbitrate", "setresolution", "setfps", "wifi", "ap", "EXT"}
)
_MOVES = {"up": (0, 0, 1), "down": (0, 0, -1), "left": (0, -1, 0), "right": (0, 1, 0)}
_MOVES |= {"forward": (1, 0, 0), "back": (-1, 0, 0)}


# ----------------------------------------------------------------------------------------------- emulator
class TelloEmulator:
    """Loopback UDP emulator of one Tello drone; see the module docstring for the protocol details.

    Typical use with djitellopy::

        with TelloEmulator("127.0.0.2") as emu:
            tello = Tello("127.0.0.2")
            tello.address = emu.address  # djitellopy would otherwise send to port 8889
            tello.connect()

    Public, thread-safe read access: ``commands`` (``(time.monotonic(), text)`` of every datagram),
    ``senders`` (the same with the sender's ``(ip, port)``),
    ``rc_history`` (``(time, (a, b, c, d))`` of every valid ``rc``), ``phase_log`` (``(time, phase)`` of every
    phase transition), ``refused`` (``(time, phase at receipt, text, reply or "ignored")`` of every command
    the drone did not carry out), ``replies_sent`` (``(time, text, "normal" | "duplicate")`` of every reply
    sent), ``flying``, ``phase``, ``downvision``, ``streaming``, ``sdk_mode``, ``landed_by_timeout``,
    ``state_packets_sent``, ``video_frames_sent``, ``errors``, ``rejected``.  Lists are only appended to;
    take ``list(emu.commands)`` for a snapshot.
    """

    TAKEOFF_CLIMB_S = 2.0
    """Time of the climb to ``takeoff_height_cm`` when the takeoff lasts longer (it then hovers until
    ``ok``)."""
    MIN_TAKEOFF_BATTERY = 10
    DRAIN_FLYING_PCT_S = 0.12
    DRAIN_IDLE_PCT_S = 0.01
    TICK_S = 0.01

    def __init__(
        self,
        ip: str = "127.0.0.2",
        port: int = 0,
        state_port: int = 8890,
        client_ip: str = "127.0.0.1",
        video_port: int = 11111,
        frame_source: FrameSource | None = None,
        fps: float = 30.0,
        takeoff_s: float = 0.3,
        faults: TelloFaults | None = None,
        video_size: tuple[int, int] = (960, 720),
        *,
        auto_land_s: float = 15.0,
        land_s: float = 0.3,
        takeoff_height_cm: float = 80.0,
        tau_s: float = 0.1,
        state_hz: float = 10.0,
        gop_size: int = 15,
        pre_sdk_reply: str | None = None,
        reply_port_latch: bool = False,
    ) -> None:
        """Configure the emulator; nothing is bound or started before :meth:`start`.

        Args:
            ip: loopback address the emulated drone owns (commands in, replies/state/video out).
            port: command port on ``ip``; 0 lets the OS pick a free one (read it from ``address``).
            state_port: client port receiving state packets (djitellopy: 8890).
            client_ip: loopback address of the client (state and video destination).
            video_port: client port receiving the H.264 stream (djitellopy: ``Tello(vs_udp=...)``).
            frame_source: ``f(t, emu) -> image``; defaults to :func:`default_frame_source`.
            fps: video frame rate.
            takeoff_s: duration of the takeoff (the ``ok`` comes at its end).
            faults: fault switches (a fresh :class:`TelloFaults` when None).
            video_size: ``(width, height)`` of every frame, even numbers; one size per emulator.
            auto_land_s: land by itself after this long without any command while flying (real: 15 s).
            land_s: duration of the landing (the ``ok`` comes at its end).
            takeoff_height_cm: height reached by ``takeoff``.
            tau_s: time constant of the first-order velocity response to ``rc``.
            state_hz: state packet rate.
            gop_size: H.264 keyframe interval in frames.
            pre_sdk_reply: reply to commands sent before ``command`` (None = ignore them, the default).
            reply_port_latch: Tello EDU: every reply goes to the sender of the first ``command``.
        """
        _require_loopback(ip, "ip")
        _require_loopback(client_ip, "client_ip")
        width, height = video_size
        if width <= 0 or height <= 0 or width % 2 or height % 2:
            raise ValueError(f"video_size must be positive even numbers, got {video_size}")
        if fps <= 0 or state_hz <= 0:
            raise ValueError("fps and state_hz must be positive")
        self.ip = ip
        self._port = port
        self.client_ip = client_ip
        self.state_port = state_port
        self.video_port = video_port
        self.frame_source: FrameSource = frame_source or default_frame_source
        self.fps = float(fps)
        self.video_size = (int(width), int(height))
        self.takeoff_s = float(takeoff_s)
        self.land_s = float(land_s)
        self.auto_land_s = float(auto_land_s)
        self.takeoff_height_cm = float(takeoff_height_cm)
        self.tau_s = float(tau_s)
        self.state_hz = float(state_hz)
        self.gop_size = int(gop_size)
        self.pre_sdk_reply = pre_sdk_reply
        self.reply_port_latch = reply_port_latch
        self._first_client: tuple[str, int] | None = None  # sender of the first ``command``
        self.faults = faults if faults is not None else TelloFaults()

        self._lock = threading.RLock()
        self.commands: list[tuple[float, str]] = []
        self.senders: list[tuple[float, str, tuple[str, int]]] = []
        """``(time.monotonic(), text, sender (ip, port))`` of every datagram, as ``commands``."""
        self.rc_history: list[tuple[float, tuple[int, int, int, int]]] = []
        self.errors: list[str] = []
        """Problems inside the emulator (frame source, encoder, sockets); empty in a healthy run."""
        self.rejected: list[str] = []
        """Datagrams that were received but ignored (malformed ``rc``, non-loopback sender)."""
        self.phase_log: list[tuple[float, str]] = [(time.monotonic(), "landed")]
        """``(time.monotonic(), new phase)`` of every phase transition, starting with the initial
        ``landed``."""
        self.refused: list[tuple[float, str, str, str]] = []
        """``(time.monotonic(), phase at receipt, command text, reply or "ignored")`` of every command the
        drone did not carry out (see the module docstring, "Refused commands"); never a command that
        succeeded."""
        self._replies = ReplyScheduler(self._lock, self.errors)
        self.replies_sent: list[tuple[float, str, str]] = self._replies.sent
        """``(time.monotonic(), reply text, "normal" | "duplicate")`` of every reply datagram sent
        (recorded just before it leaves the socket)."""
        self.state_packets_sent = 0
        self.last_state = ""
        self.video_frames_sent = 0
        self.video_bytes_sent = 0
        self.video_frame_index = -1
        self.video_log: deque[tuple[int, float]] = deque(maxlen=2000)
        """``(frame index, time.monotonic() when sent)`` of the most recent video frames."""

        self.sdk_mode = False
        self.streaming = False
        self.downvision = False
        self.landed_by_timeout = False
        self.speed_setting = 100.0
        self._phase = "landed"  # landed | takeoff | flying | landing
        self._phase_t0 = 0.0
        self._phase_z0 = 0.0
        self._phase_s = 0.0  # duration of the current takeoff/landing
        self._deferred: _Deferred | None = None
        self._pos = np.zeros(3)  # x fwd, y right, z up [cm]
        self._yaw = 0.0  # deg, clockwise
        self._rc = np.zeros(4)  # right, fwd, up [cm/s], yaw rate [deg/s] targets
        self._vel_body = np.zeros(4)  # filtered body velocities
        self._vel_world = np.zeros(3)  # [cm/s]
        self._acc_body = np.zeros(3)  # [cm/s^2]
        self._motor_s = 0.0
        self._drain = 0.0
        self._bat_setpoint = self.faults.battery_pct
        self._last_cmd_t = time.monotonic()
        self._stream_epoch = 0

        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cmd_sock: socket.socket | None = None
        self._tx_sock: socket.socket | None = None
        self._bound: tuple[str, int] | None = None
        self._started = False
        self._closed = False

    # ------------------------------------------------------------------------------------------- lifecycle
    @property
    def address(self) -> tuple[str, int]:
        """``(ip, port)`` the client must send commands to (valid after :meth:`start`)."""
        if self._bound is None:
            if self._port == 0:
                raise RuntimeError("address is only known after start() when port=0")
            return (self.ip, self._port)
        return self._bound

    def start(self) -> TelloEmulator:
        """Bind the sockets and start the command, reply, simulation and video threads."""
        if self._started:
            raise RuntimeError("emulator already started")
        cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            cmd.bind((self.ip, self._port))
            cmd.settimeout(0.1)
            tx.bind((self.ip, 0))
        except OSError:
            cmd.close()
            tx.close()
            raise
        self._cmd_sock, self._tx_sock = cmd, tx
        host, port = cmd.getsockname()[:2]
        self._bound = (str(host), int(port))
        self._started = True
        self._last_cmd_t = time.monotonic()
        for name, target in (
            ("cmd", self._command_loop),
            ("reply", self._reply_loop),
            ("sim", self._sim_loop),
            ("video", self._video_loop),
        ):
            thread = threading.Thread(target=target, name=f"tello-emu-{self.ip}-{name}", daemon=True)
            self._threads.append(thread)
            thread.start()
        return self

    def close(self) -> None:
        """Stop all threads (joined within ~1 s) and close the sockets; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._replies.wake()
        deadline = time.monotonic() + 1.5
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
            if thread.is_alive():  # pragma: no cover - would indicate a bug
                LOG.error("thread %s did not stop", thread.name)
        for sock in (self._cmd_sock, self._tx_sock):
            if sock is not None:
                sock.close()

    @property
    def threads_alive(self) -> list[str]:
        """Names of the emulator's threads that are still running."""
        return [t.name for t in self._threads if t.is_alive()]

    def __enter__(self) -> TelloEmulator:
        """Start (if not yet started) and return the emulator."""
        if not self._started:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Close the emulator."""
        self.close()

    # ------------------------------------------------------------------------------------- public helpers
    @property
    def flying(self) -> bool:
        """True while the motors run (takeoff, flight and landing phases)."""
        return self._phase != "landed"

    @property
    def phase(self) -> str:
        """``landed``, ``takeoff``, ``flying`` or ``landing``."""
        return self._phase

    @property
    def position_cm(self) -> tuple[float, float, float]:
        """Ground-truth position ``(x forward, y right, z up)`` in cm."""
        with self._lock:
            return (float(self._pos[0]), float(self._pos[1]), float(self._pos[2]))

    @property
    def yaw_deg(self) -> float:
        """Ground-truth yaw in degrees, clockwise, wrapped to [-180, 180)."""
        return _wrap_deg(self._yaw)

    @property
    def velocity_cm_s(self) -> tuple[float, float, float]:
        """Ground-truth world velocity in cm/s."""
        with self._lock:
            return (float(self._vel_world[0]), float(self._vel_world[1]), float(self._vel_world[2]))

    @property
    def battery(self) -> int:
        """Battery percentage currently reported."""
        with self._lock:
            return self._battery_locked()

    def command_texts(self) -> list[str]:
        """Snapshot of the received command texts."""
        with self._lock:
            return [text for _, text in self.commands]

    def wait_for_command(self, text: str, timeout: float, start: int = 0) -> bool:
        """Wait until a command equal to ``text`` was received (searching from index ``start``)."""
        return wait_until(lambda: text in self.command_texts()[start:], timeout)

    # ------------------------------------------------------------------------------------------- commands
    def _command_loop(self) -> None:
        sock = self._cmd_sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(2048)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    break
                time.sleep(0.01)
                continue
            text = data.decode("utf-8", errors="replace").strip()
            try:
                self._handle(text, (str(addr[0]), int(addr[1])))
            except Exception as exc:  # keep serving; surface the problem to the test
                LOG.exception("emulator failed on %r", text)
                self.errors.append(f"{text!r}: {exc!r}")

    def _handle(self, text: str, addr: tuple[str, int]) -> None:
        now = time.monotonic()
        with self._lock:
            self.commands.append((now, text))
            self.senders.append((now, text, addr))
            if not is_loopback(addr[0]):
                self.rejected.append(f"{text} (non-loopback sender {addr[0]})")
                return
            faults, phase = self.faults, self._phase
            words = text.split()
            verb, args = (words[0], words[1:]) if words else ("", [])
            delay = float(faults.reply_delay_s)
            if verb == "command" and self._first_client is None:
                self._first_client = addr
            to = self._first_client if self.reply_port_latch and self._first_client else addr
            reply_addr = None if faults.silent or verb in faults.lost_replies else to
            if not self.sdk_mode and verb != "command":
                reply = self.pre_sdk_reply
                self._refuse(now, phase, text, "ignored" if reply is None else reply)
                if reply is not None:
                    self._reply(reply, reply_addr, now, delay)
                return
            self._last_cmd_t = now
            if verb in SDK3_ONLY_COMMANDS and not has_sdk3(faults.sdk_version):
                answer: str | None = f"unknown command: {verb}"
            elif verb == "rc":
                answer = self._rc_command(args, now, phase)
            elif verb in ("emergency", "reboot"):
                self._execute_no_reply(verb, now)
                return
            elif faults.error_replies:
                answer = "error"
            else:
                answer = self._execute(verb, args, now)
                if answer is None:  # takeoff/land: replied on completion by the sim thread
                    self._deferred = _Deferred(reply_addr, delay)
                    return
            if answer is None:  # rc without a reply
                return
            if _is_refusal(verb, answer):
                self._refuse(now, phase, text, answer)
            self._reply(answer, reply_addr, now, delay)

    def _refuse(self, now: float, phase: str, text: str, reply: str) -> None:
        self.refused.append((now, phase, text, reply))

    def _rc_command(self, args: list[str], now: float, phase: str) -> str | None:
        """Apply one ``rc``; return its reply (only with ``faults.rc_replies``) or None."""
        text = text_of("rc", args)
        try:
            values = tuple(int(a) for a in args)
        except ValueError:
            values = ()
        if len(values) != 4:
            self.rejected.append(text)
            self._refuse(now, phase, text, "ignored")
            return None
        a, b, c, d = (max(-100, min(100, v)) for v in values)
        self.rc_history.append((now, (a, b, c, d)))
        if phase == "flying":
            self._rc[:] = (a, b, c, d)
            return "ok" if self.faults.rc_replies else None
        if self.faults.rc_replies:
            return "error Not joystick"
        self._refuse(now, phase, text, "ignored")
        return None

    def _execute_no_reply(self, verb: str, now: float) -> None:
        """``emergency`` (motors stop at once, the drone drops) or ``reboot``."""
        self._set_landed(now)
        self._deferred = None  # an interrupted takeoff/landing never answers
        self._pos[2] = 0.0
        if verb == "reboot":
            self.sdk_mode = False
            self._first_client = None
            self.streaming = False

    def _busy_reply(self) -> str:
        """Reply to a command that needs a settled drone while it takes off or lands."""
        auto = self.landed_by_timeout and self._phase == "landing"
        return "error Auto land" if auto else "error Not joystick"

    def _execute(self, verb: str, args: list[str], now: float) -> str | None:
        """Run one reply-expecting command; return the reply, or None when it is deferred."""
        if verb.endswith("?"):
            return self._read(verb)
        if verb == "command":
            self.sdk_mode = True
            return "ok"
        if verb == "takeoff":
            if self._phase in ("takeoff", "landing"):
                return self._busy_reply()
            if self._phase == "flying":
                return "error"
            if self._battery_locked() < self.MIN_TAKEOFF_BATTERY:
                return "error battery low"
            self._rc[:] = 0.0
            duration = self.faults.takeoff_s
            self._start_phase("takeoff", now, self.takeoff_s if duration is None else float(duration))
            self.landed_by_timeout = False
            return None
        if verb == "land":
            if self._phase == "landed":
                return "error Motor stop"
            if self._phase != "flying":
                return self._busy_reply()
            self._start_phase("landing", now, self.land_s)
            return None
        if verb == "streamon":
            if not self.streaming:
                self._stream_epoch += 1
            self.streaming = True
            return "ok"
        if verb == "streamoff":
            self.streaming = False
            return "ok"
        if verb == "downvision":
            if args not in (["0"], ["1"]):
                return "error"
            self.downvision = args[0] == "1"
            return "ok"
        if verb == "port":
            try:
                state_port, video_port = (int(a) for a in args)
            except ValueError:
                return "error"
            if not (1025 <= state_port <= 65535 and 1025 <= video_port <= 65535):
                return "error"
            self.state_port, self.video_port = state_port, video_port
            return "ok"
        if verb == "speed":
            try:
                speed = float(args[0])
            except (IndexError, ValueError):
                return "error"
            if not 10 <= speed <= 100:
                return "out of range"
            self.speed_setting = speed
            return "ok"
        if verb in ("motoron", "motoroff"):
            return "ok" if self._phase == "landed" else "error"
        if verb in _READ_ONLY_OK:
            return "ok"
        if verb in _MOVES or verb in ("cw", "ccw", "go", "curve", "jump", "flip", "stop"):
            return self._move(verb, args)
        return f"unknown command: {verb}"

    def _move(self, verb: str, args: list[str]) -> str:
        if self._phase in ("takeoff", "landing"):
            return self._busy_reply()
        if self._phase != "flying":
            return "error Motor stop"
        if verb == "stop":
            self._rc[:] = 0.0
            return "ok"
        if verb == "flip":
            return "ok" if args in (["l"], ["r"], ["f"], ["b"]) else "error"
        try:
            nums = [int(a) for a in args if not a.startswith("m")]
        except ValueError:
            return "error"
        if verb in _MOVES:
            if len(nums) != 1 or not 20 <= nums[0] <= 500:
                return "out of range"
            fwd, right, up = (nums[0] * k for k in _MOVES[verb])
            self._displace(fwd, right, up)
        elif verb in ("cw", "ccw"):
            if len(nums) != 1 or not 1 <= nums[0] <= 3600:
                return "out of range"
            self._yaw = _wrap_deg(self._yaw + (nums[0] if verb == "cw" else -nums[0]))
        elif verb == "go" and len(nums) >= 3:
            self._displace(nums[0], nums[1], nums[2])
        elif verb == "curve" and len(nums) >= 6:
            self._displace(nums[3], nums[4], nums[5])
        elif verb == "jump" and len(nums) >= 3:
            self._displace(nums[0], nums[1], nums[2])
        else:
            return "error"
        return "ok"

    def _displace(self, fwd: float, right: float, up: float) -> None:
        c, s = math.cos(math.radians(self._yaw)), math.sin(math.radians(self._yaw))
        self._pos += (fwd * c - right * s, fwd * s + right * c, up)
        self._pos[2] = max(0.0, self._pos[2])

    def _read(self, verb: str) -> str:
        h = max(0, round(float(self._pos[2])))
        values = {
            "battery?": str(self._battery_locked()),
            "speed?": f"{self.speed_setting:.1f}",
            "time?": f"{int(self._motor_s)}s",
            "height?": f"{round(h / 10)}dm",
            "temp?": "60~63",
            "attitude?": f"pitch:0;roll:0;yaw:{round(_wrap_deg(self._yaw))};",
            "baro?": f"{12.3 + h / 100:.2f}",
            "tof?": f"{(h + 10) * 10}mm",
            "acceleration?": "agx:0.00;agy:0.00;agz:-1000.00;",
            "wifi?": "90",
            "sdk?": str(self.faults.sdk_version),
            "sn?": "0TQEMU" + "".join(f"{int(o):03d}" for o in self.ip.split(".")[1:]),
            "hardware?": "TELLO",
            "active?": "ok",
        }
        return values.get(verb, f"unknown command: {verb}")

    # ---------------------------------------------------------------------------------------------- replies
    def _reply(self, text: str, addr: tuple[str, int] | None, now: float, delay: float) -> None:
        """Queue ``text`` for ``addr`` (None = lost) at ``now + delay``, FIFO; plus any duplicate."""
        self._replies.schedule(text, addr, now, delay, self.faults.duplicate_reply_after_s)

    def _reply_loop(self) -> None:
        # Replies leave from the command socket, like the real drone (source ip:port = address).
        assert self._cmd_sock is not None
        self._replies.run(self._cmd_sock, self._stop)

    # ------------------------------------------------------------------------------------------- simulation
    def _set_phase(self, phase: str, now: float) -> None:
        if phase != self._phase:
            self._phase = phase
            self.phase_log.append((now, phase))

    def _start_phase(self, phase: str, now: float, duration_s: float) -> None:
        self._set_phase(phase, now)
        self._phase_t0 = now
        self._phase_z0 = float(self._pos[2])
        self._phase_s = max(0.0, duration_s)

    def _set_landed(self, now: float) -> None:
        self._set_phase("landed", now)
        self._rc[:] = 0.0
        self._vel_body[:] = 0.0
        self._vel_world[:] = 0.0
        self._acc_body[:] = 0.0

    def _battery_locked(self) -> int:
        if self.faults.battery_pct != self._bat_setpoint:
            self._bat_setpoint = self.faults.battery_pct
            self._drain = 0.0
        return max(0, min(100, math.ceil(self._bat_setpoint - self._drain)))

    def _finish_phase(self, now: float) -> None:
        deferred, self._deferred = self._deferred, None
        if deferred is not None:
            self._reply("ok", deferred.addr, now, deferred.delay_s)

    def _step(self, now: float, dt: float) -> None:
        with self._lock:
            self._battery_locked()
            self._drain += dt * (self.DRAIN_FLYING_PCT_S if self.flying else self.DRAIN_IDLE_PCT_S)
            if self.flying:
                self._motor_s += dt
            z_before = float(self._pos[2])
            if self._phase == "takeoff":  # climb at the normal rate, then hover (stabilise) until the ok
                elapsed = now - self._phase_t0
                climb_s = max(min(self._phase_s, self.TAKEOFF_CLIMB_S), 1e-3)
                frac = min(1.0, elapsed / climb_s)
                target = max(self._phase_z0, self.takeoff_height_cm)
                self._pos[2] = self._phase_z0 + frac * (target - self._phase_z0)
                self._vel_world[:2] = 0.0
                self._vel_world[2] = (self._pos[2] - z_before) / dt
                if elapsed >= self._phase_s:
                    self._set_phase("flying", now)
                    self._last_cmd_t = now
                    self._vel_world[:] = 0.0
                    self._finish_phase(now)
            elif self._phase == "landing":
                frac = min(1.0, (now - self._phase_t0) / max(self._phase_s, 1e-3))
                self._pos[2] = self._phase_z0 * (1.0 - frac)
                self._vel_world[:2] = 0.0
                self._vel_world[2] = (self._pos[2] - z_before) / dt
                if frac >= 1.0:
                    self._set_landed(now)
                    self._finish_phase(now)
            elif self._phase == "flying":
                if now - self._last_cmd_t > self.auto_land_s:
                    self.landed_by_timeout = True
                    self._rc[:] = 0.0
                    self._start_phase("landing", now, self.land_s)
                    return
                alpha = 1.0 - math.exp(-dt / max(self.tau_s, 1e-6))
                previous = self._vel_body[:3].copy()
                self._vel_body += alpha * (self._rc - self._vel_body)
                self._acc_body = (self._vel_body[:3] - previous) / dt
                right, fwd, up, yaw_rate = self._vel_body
                c, s = math.cos(math.radians(self._yaw)), math.sin(math.radians(self._yaw))
                self._vel_world[:] = (fwd * c - right * s, fwd * s + right * c, up)
                self._pos += self._vel_world * dt
                if self._pos[2] < 0.0:
                    self._pos[2] = 0.0
                    self._vel_world[2] = 0.0
                self._yaw = _wrap_deg(self._yaw + yaw_rate * dt)

    def _state_string(self) -> str:
        with self._lock:
            x, y, z = (round(float(v)) for v in self._pos)
            vgx, vgy, vgz = (round(float(v) / 10.0) for v in self._vel_world)
            h = max(0, z)
            acc = self._acc_body / 981.0 * 1000.0
            return (
                f"mid:-1;x:{x};y:{y};z:{z};mpry:0,0,0;pitch:0;roll:0;yaw:{round(_wrap_deg(self._yaw))};"
                f"vgx:{vgx};vgy:{vgy};vgz:{vgz};templ:60;temph:63;tof:{h + 10};h:{h};"
                f"bat:{self._battery_locked()};baro:{12.3 + h / 100:.2f};time:{int(self._motor_s)};"
                f"agx:{acc[1]:.2f};agy:{acc[0]:.2f};agz:{acc[2] - 1000.0:.2f};\r\n"
            )

    def _sim_loop(self) -> None:
        sock = self._tx_sock
        assert sock is not None
        last = time.monotonic()
        next_state = last
        while not self._stop.wait(self.TICK_S):
            now = time.monotonic()
            self._step(now, min(max(now - last, 1e-4), 0.1))
            last = now
            if now < next_state:
                continue
            next_state = max(next_state + 1.0 / self.state_hz, now - 1.0 / self.state_hz)
            if not self.sdk_mode or self.faults.drop_state:
                continue
            state = self._state_string()
            try:
                sock.sendto(state.encode("ascii"), (self.client_ip, self.state_port))
            except OSError as exc:
                self.errors.append(f"state send failed: {exc!r}")
                continue
            with self._lock:
                self.last_state = state
                self.state_packets_sent += 1

    # ------------------------------------------------------------------------------------------------ video
    def _make_encoder(self) -> Any:
        import av  # local import: only needed when streaming

        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height = self.video_size
        ctx.pix_fmt = "yuv420p"
        rate = Fraction(self.fps).limit_denominator(1001)
        ctx.framerate = rate
        ctx.time_base = 1 / rate
        ctx.gop_size = self.gop_size
        ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "x264-params": "repeat-headers=1"}
        return ctx

    def _render(self, t: float) -> np.ndarray | None:
        img = np.asarray(self.frame_source(t, self))
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        width, height = self.video_size
        if img.shape != (height, width, 3) or img.dtype != np.uint8:
            self.errors.append(f"frame_source gave {img.shape} {img.dtype}, need {(height, width, 3)} uint8")
            return None
        return np.ascontiguousarray(img)

    def _send_frame(self, encoder: Any, img: np.ndarray, index: int) -> None:
        import av

        frame = av.VideoFrame.from_ndarray(img, format="rgb24")
        frame.pts = index
        sock = self._tx_sock
        assert sock is not None
        dest = (self.client_ip, self.video_port)
        for packet in encoder.encode(frame):
            payload = bytes(packet)
            for offset in range(0, len(payload), MAX_VIDEO_DATAGRAM):
                with contextlib.suppress(OSError):  # nobody listening yet is fine
                    sock.sendto(payload[offset : offset + MAX_VIDEO_DATAGRAM], dest)
            self.video_bytes_sent += len(payload)
        self.video_frames_sent += 1
        self.video_log.append((index, time.monotonic()))

    def _video_loop(self) -> None:
        encoder: Any = None
        epoch = -1
        index = 0
        t0 = 0.0
        period = 1.0 / self.fps
        while not self._stop.is_set():
            with self._lock:
                streaming, current_epoch = self.streaming, self._stream_epoch
            if not streaming:
                encoder = None
                self._stop.wait(0.02)
                continue
            if encoder is None or current_epoch != epoch:
                try:
                    encoder = self._make_encoder()
                except Exception as exc:
                    self.errors.append(f"cannot create H.264 encoder: {exc!r}")
                    self._stop.wait(0.5)
                    continue
                epoch, index, t0 = current_epoch, 0, time.monotonic()
            now = time.monotonic()
            due = t0 + index * period
            if due > now:
                self._stop.wait(min(due - now, 0.05))
                continue
            if now - due > 3 * period:  # fell behind: skip frames instead of bursting
                index = int((now - t0) / period)
            t = index * period
            self.video_frame_index = index
            if not self.faults.no_video:
                try:
                    img = self._render(t)
                    if img is not None:
                        self._send_frame(encoder, img, index)
                except Exception as exc:
                    self.errors.append(f"video frame {index}: {exc!r}")
            index += 1


def _is_refusal(verb: str, reply: str) -> bool:
    """True when ``reply`` means the drone did not carry out ``verb`` (a read command answers a value)."""
    if reply.startswith(("error", "unknown command")):
        return True
    return not verb.endswith("?") and reply != "ok"


def text_of(verb: str, args: list[str]) -> str:
    """Re-assemble a command from its verb and arguments."""
    return " ".join([verb, *args])


def _wrap_deg(angle: float) -> float:
    return (angle + 180.0) % 360.0 - 180.0
