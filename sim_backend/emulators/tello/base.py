"""Configuration, logs and shared state of the loopback Tello emulator, and its reply queue.

`TelloEmulatorBase` is the bottom layer of ``TelloEmulator``: the constructor (addresses, ports, rates,
durations in s, heights in cm), the public logs every layer appends to (``commands``, ``senders``,
``rc_history``, ``phase_log``, ``refused``, ``replies_sent``, ``errors``, ``rejected``, ...; times are
``time.monotonic()`` seconds), the ground-truth state (position in cm in the world frame ``x`` forward at
takeoff heading, ``y`` right, ``z`` up; yaw in degrees clockwise; velocities in cm/s) and the FIFO reply
queue (``ReplyScheduler`` of ``faults``).  Layers on top: ``physics`` (motion model, phases,
battery, state stream), ``commands`` (the text protocol), ``video`` (the H.264 stream);
``emulator`` assembles them.  Protocol and behaviour: the docstring of ``tello.py``.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from flightstack.config.compensation import EMULATED_TELLO_RESPONSE_S
from flightstack.drivers.tello.config import TELLO_OWN_TIMEOUT_S

from ..device_links import DeviceLinks
from ..net import require_loopback
from ..radio import DeviceRadio
from .faults import ReplyScheduler, TelloFaults
from .frames import FrameSource, default_frame_source
from .recorded import (
    H_DRIFT_CM_S,
    H_DRIFT_MAX_CM,
    KEYFRAME_INTERVAL_FRAMES,
    TAKEOFF_OK_S,
    TOF_MAX_CM,
    Surface,
    flat_floor,
)

FAST_TAKEOFF_S = 0.3
"""A takeoff for tests and rigs that are not about the takeoff (s): the recorded ``TAKEOFF_OK_S`` (8.7 s,
the default) would add 8.4 s to each of their takeoffs. Pass it as ``takeoff_s`` explicitly."""


@dataclass
class DeferredReply:
    """A reply that is sent when a takeoff/landing completes."""

    addr: tuple[str, int] | None
    delay_s: float


class TelloEmulatorBase:
    """State and configuration shared by the emulator's layers (see ``TelloEmulator``)."""

    TAKEOFF_CLIMB_S = 2.0
    """Time of the climb to ``takeoff_height_cm`` when the takeoff lasts longer (it then hovers until
    ``ok``); xg590 (``recorded``): liftoff at +0.94 s, h 70 at +2.83 s."""
    MIN_TAKEOFF_BATTERY = 10
    DRAIN_FLYING_PCT_S = 0.12
    DRAIN_IDLE_PCT_S = 0.01
    TICK_S = 0.01
    MAX_STEP_S = 0.1
    """The longest physics step (s): a late step (a loaded machine) integrates at most this long."""

    def __init__(
        self,
        ip: str = "127.0.0.2",
        port: int = 0,
        state_port: int = 8890,
        client_ip: str = "127.0.0.1",
        video_port: int = 11111,
        frame_source: FrameSource | None = None,
        fps: float = 30.0,
        takeoff_s: float = TAKEOFF_OK_S,
        faults: TelloFaults | None = None,
        video_size: tuple[int, int] = (960, 720),
        *,
        auto_land_s: float = TELLO_OWN_TIMEOUT_S,
        land_s: float = 0.3,
        land_ok_s: float | None = None,
        takeoff_height_cm: float = 80.0,
        tau_s: float = EMULATED_TELLO_RESPONSE_S,
        state_hz: float = 10.0,
        gop_size: int = KEYFRAME_INTERVAL_FRAMES,
        pre_sdk_reply: str | None = None,
        reply_port_latch: bool = False,
        radio: DeviceRadio | None = None,
        links: DeviceLinks | None = None,
        takeoff_hover_s: float = 0.0,
        h_drift_cm_s: float = H_DRIFT_CM_S,
        h_drift_max_cm: float = H_DRIFT_MAX_CM,
        surface: Surface = flat_floor,
        tof_max_cm: float = TOF_MAX_CM,
        netns: str | None = None,
    ) -> None:
        """Configure the emulator; nothing is bound or started before :meth:`start`.

        Args:
            ip: loopback address the emulated drone owns (commands in, replies/state/video out); with
                ``netns``, any address of that namespace (an access-point Tello's 192.168.10.1).
            port: command port on ``ip``; 0 lets the OS pick a free one (read it from ``address``).
            state_port: client port receiving state packets (djitellopy: 8890).
            client_ip: loopback address of the client (state and video destination); with ``netns``, the
                address the client has on the link into that namespace.
            video_port: client port receiving the H.264 stream (djitellopy: ``Tello(vs_udp=...)``).
            frame_source: ``f(t, emu) -> image``; defaults to :func:`default_frame_source`.
            fps: video frame rate (frames/s; ``setfps`` changes it).
            takeoff_s: duration of the takeoff (the ``ok`` comes at its end); default the recorded
                ``recorded.TAKEOFF_OK_S`` (8.7 s), ``FAST_TAKEOFF_S`` for tests not about the takeoff.
            takeoff_hover_s: the last part of the takeoff spent hovering at height before the ``ok``
                (a real Tello stabilises at height for seconds before it answers; 0: the climb lasts
                the whole takeoff, up to ``TAKEOFF_CLIMB_S``).
            faults: fault switches (a fresh :class:`TelloFaults` when None).
            video_size: ``(width, height)`` of every frame the camera renders, even numbers; one size per
                emulator (the stream carries it at the ``setresolution`` size once one is received).
            auto_land_s: land by itself after this long without any command while flying (real: 15 s).
            land_s: duration of the landing (the motors stop at its end).
            land_ok_s: from ``land`` to its ``ok`` (s; at least land_s; None: at the touchdown). A real
                Tello answers 1.4 s after it touched down (``recorded.LAND_OK_S``).
            takeoff_height_cm: height reached by ``takeoff``.
            tau_s: time constant of the first-order velocity response to ``rc``.
            state_hz: state packet rate.
            gop_size: H.264 keyframe interval in frames (default the recorded bound,
                ``recorded.KEYFRAME_INTERVAL_FRAMES``: after a lost datagram the picture is spoilt until
                the next keyframe, 2.2 s at 30 fps).
            h_drift_cm_s: drift of the reported ``h`` while the motors run (cm/s, from each takeoff;
                default the recorded ``recorded.H_DRIFT_CM_S``; 0 turns it off).
            h_drift_max_cm: the drift's bound (cm, either sign; default the recorded
                ``recorded.H_DRIFT_MAX_CM``, 70 cm).
            surface: height (cm) of the surface below a world point ``(x, y)`` (cm), what ``tof``
                measures to (``recorded.Surface``; default the flat takeoff floor).
            tof_max_cm: range of the downward distance sensor (cm); beyond it ``tof`` reads 6553.
            pre_sdk_reply: reply to commands sent before ``command`` (None = ignore them, the default).
            reply_port_latch: Tello EDU: every reply goes to the sender of the first ``command``.
            netns: a network namespace the caller made (``ip netns add``): the drone's sockets live there
                (``emulators/netns.py``), its addresses need not be loopback and it serves any sender
                (nothing outside the caller's namespaces reaches it). None: loopback only.
            radio: the drone's impaired radio (``radio.DeviceRadio`` with links ``command`` (in),
                ``reply``, ``state`` and ``video`` (out)); None: a perfect link.
            links: the rig's links of this drone (``device_links.DeviceLinks``: ``rc`` acted on late,
                ``state`` and ``video`` leaving late, before the radio); None: none. ``state_hz`` and
                ``fps`` are the caller's (the links' rates).
        """
        if netns is None:
            require_loopback(ip, "ip")
            require_loopback(client_ip, "client_ip")
        self.netns = netns
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
        self.takeoff_hover_s = max(0.0, float(takeoff_hover_s))
        self.land_s = float(land_s)
        self.land_ok_s = self.land_s if land_ok_s is None else max(self.land_s, float(land_ok_s))
        self.auto_land_s = float(auto_land_s)
        self.takeoff_height_cm = float(takeoff_height_cm)
        self.tau_s = float(tau_s)
        self.state_hz = float(state_hz)
        self.gop_size = int(gop_size)
        if self.gop_size < 1:
            raise ValueError(f"gop_size must be at least 1, got {gop_size}")
        self.h_drift_cm_s = float(h_drift_cm_s)
        self.h_drift_max_cm = float(h_drift_max_cm)
        self.surface = surface
        self.tof_max_cm = float(tof_max_cm)
        self.pre_sdk_reply = pre_sdk_reply
        self.reply_port_latch = reply_port_latch
        self._first_client: tuple[str, int] | None = None  # sender of the first ``command``
        self._last_client: tuple[str, int] | None = None  # sender of the last datagram
        self.faults = faults if faults is not None else TelloFaults()
        self.radio = radio
        self.links = links

        self._lock = threading.RLock()
        self.commands: list[tuple[float, str]] = []
        self.senders: list[tuple[float, str, tuple[str, int]]] = []
        """``(time.monotonic(), text, sender (ip, port))`` of every datagram, as ``commands``."""
        self.rc_history: list[tuple[float, tuple[int, int, int, int]]] = []
        self.rc_acted: list[tuple[float, tuple[int, int, int, int]]] = []
        """``(start of the physics step, (a, b, c, d))`` of every change of the rc the flying drone acts on:
        the step integrates it from its start (its mean velocity over the step), so this is when the motion
        it commands begins (the truth a latency calibration is judged by; a late step on a loaded machine
        starts earlier before the receipt than TICK_S / 2)."""
        self.errors: list[str] = []
        """Problems inside the emulator (frame source, encoder, sockets); empty in a healthy run."""
        self.rejected: list[str] = []
        """Datagrams that were received but ignored (malformed ``rc``, non-loopback sender)."""
        self.phase_log: list[tuple[float, str]] = [(time.monotonic(), "landed")]
        """``(time.monotonic(), new phase)`` of every phase transition, starting with the initial
        ``landed``."""
        self.refused: list[tuple[float, str, str, str]] = []
        """``(time.monotonic(), phase at receipt, command text, reply or "ignored")`` of every command the
        drone did not carry out (see the docstring of ``tello.py``, "Refused commands"); never a command that
        succeeded."""
        self._replies = ReplyScheduler(self._lock, self.errors, blocked=self.downlink_blocked)
        self.replies_sent: list[tuple[float, str, str]] = self._replies.sent
        """``(time.monotonic(), reply text, "normal" | "duplicate" | "stray")`` of every reply datagram sent
        (recorded just before it leaves the socket)."""
        self.downlink_lost: list[tuple[float, str, str]] = self._replies.lost
        """Replies lost because the downlink was down or the drone off (``faults.downlink_down``,
        ``faults.powered_off``), as ``replies_sent``."""
        self.uplink_lost: list[tuple[float, str, str]] = []
        """``(time.monotonic(), text, "uplink_down" | "powered_off" | "link")`` of every datagram that never
        reached the drone (not in ``commands``; ``link``: lost by the rig's rc link)."""
        self.state_packets_lost = 0
        self.power_log: list[tuple[float, str]] = []
        """``(time.monotonic(), "off" | "boot")`` of every power loss and boot (``faults.powered_off``)."""
        self.landed_by_battery = False
        """True once the drone began a landing of its own on low battery (until the next takeoff)."""
        self.landed_by_itself = False
        """True once the drone began a landing of its own on ``faults.self_land_now`` (until a takeoff)."""
        self.state_packets_sent = 0
        self.last_state = ""
        self.video_frames_sent = 0
        self.video_bytes_sent = 0
        self.video_frame_index = -1
        self.video_log: deque[tuple[int, float]] = deque(maxlen=2000)
        """``(frame index, time.monotonic() when sent)`` of the most recent video frames."""
        self.video_capture_log: deque[tuple[int, float, float]] = deque(maxlen=20000)
        """``(frame index, true capture time, send time)`` (time.monotonic() s) of the most recent frames."""

        self.sdk_mode = False
        self.streaming = False
        self.downvision = False
        self.resolution: str | None = None
        """The ``setresolution`` argument received (None: none; the stream keeps ``video_size``)."""
        self.bitrate_mbps = 0
        """The ``setbitrate`` argument received: a target of n Mbit/s; 0 (auto): libx264's own choice."""
        self.landed_by_timeout = False
        self.speed_setting = 100.0
        self._phase = "landed"  # landed | takeoff | flying | landing
        self._phase_t0 = 0.0
        self._phase_z0 = 0.0
        self._phase_s = 0.0  # duration of the current takeoff/landing
        self._deferred: DeferredReply | None = None
        self._pos = np.zeros(3)  # x fwd, y right, z up [cm]
        self._yaw = 0.0  # deg, clockwise
        self._rc = np.zeros(4)  # right, fwd, up [cm/s], yaw rate [deg/s] targets
        self._vel_body = np.zeros(4)  # filtered body velocities
        self._vel_world = np.zeros(3)  # [cm/s]
        self._acc_body = np.zeros(3)  # [cm/s^2]
        self._motor_s = 0.0
        self._h_drift = 0.0  # cm added to the true height in the reported h (recorded.drifted)
        self._drain = 0.0
        self._bat_setpoint = self.faults.battery_pct
        self._last_cmd_t = time.monotonic()
        self._stream_epoch = 0
        self._powered_off = False  # the power state the simulation last acted on

        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cmd_sock: socket.socket | None = None
        self._tx_sock: socket.socket | None = None
        self._bound: tuple[str, int] | None = None
        self._started = False
        self._closed = False

    def downlink_blocked(self) -> bool:
        """True while nothing the drone sends arrives (``faults.downlink_down`` or ``faults.powered_off``)."""
        return self.faults.downlink_down or self.faults.powered_off

    # ---------------------------------------------------------------------------------------------- replies
    def send_unprompted(self, text: str) -> None:
        """Send `text` to the client now, answering nothing (a test's injection of what a drone may send of
        its own accord, e.g. ``error Auto land``; ``faults.auto_land_notice`` sends that one itself)."""
        to = self._first_client if self.reply_port_latch and self._first_client else self._last_client
        if to is not None:
            self._reply(text, to, time.monotonic(), 0.0)

    def _reply(self, text: str, addr: tuple[str, int] | None, now: float, delay: float) -> None:
        """Queue ``text`` for ``addr`` (None = lost) at ``now + delay``, FIFO; plus any duplicate."""
        self._replies.schedule(text, addr, now, delay, self.faults.duplicate_reply_after_s)

    def _reply_loop(self) -> None:
        # Replies leave from the command socket, like the real drone (source ip:port = address).
        assert self._cmd_sock is not None
        self._replies.run(self._cmd_sock, self._stop)
