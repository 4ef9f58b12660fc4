"""`TelloEmulator`: the loopback UDP Tello, assembled from its layers, with its lifecycle (start/close).

Layers: ``base`` (configuration, logs, state, reply queue), ``physics`` (motion model,
phases, battery, state stream), ``commands`` (text protocol), ``video`` (H.264 stream).  This
module binds the sockets (IPv4 loopback, or inside a network namespace the caller made) and runs the
command, reply, simulation and video threads (daemons with bounded waits, joined by ``close()``).
Import it from ``tello.py``, whose docstring describes the protocol and the emulated behaviour.
"""

from __future__ import annotations

import logging
import threading
import time
from types import TracebackType

from ..net import bind_drone_sockets
from ..netns import in_netns
from .commands import TelloCommands
from .video import TelloVideoStream

LOG = logging.getLogger(f"{__package__}.tello")  # the public module's logger, as before the split


class TelloEmulator(TelloCommands, TelloVideoStream):
    """Loopback UDP emulator of one Tello drone; see the docstring of ``tello.py`` for the protocol details.

    Typical use with djitellopy::

        with TelloEmulator("127.0.0.2") as emu:
            tello = Tello("127.0.0.2")
            tello.address = emu.address  # djitellopy would otherwise send to port 8889
            tello.connect()

    Public, thread-safe read access: ``commands`` (``(time.monotonic(), text)`` of every datagram),
    ``senders`` (the same with the sender's ``(ip, port)``),
    ``rc_history`` (``(time, (a, b, c, d))`` of every valid ``rc``), ``rc_acted`` (``(time, (a, b, c, d))``
    of every change of the rc the flying drone's physics acts on, from the start of the step that first
    integrates it), ``phase_log`` (``(time, phase)`` of every
    phase transition), ``refused`` (``(time, phase at receipt, text, reply or "ignored")`` of every command
    the drone did not carry out), ``replies_sent`` (``(time, text, "normal" | "duplicate")`` of every reply
    sent), ``uplink_lost`` / ``downlink_lost`` (datagrams a link or power fault lost), ``power_log``,
    ``flying``, ``phase``, ``downvision``, ``streaming``, ``sdk_mode``, ``fps``, ``resolution``,
    ``bitrate_mbps`` (the SDK 3.0 video settings in force), ``landed_by_timeout``,
    ``landed_by_battery``, ``state_packets_sent``, ``state_packets_lost``, ``video_frames_sent``,
    ``errors``, ``rejected``.  Lists are only appended to;
    take ``list(emu.commands)`` for a snapshot. With the rig's rc link (``links``) a datagram is recorded
    when the drone acts on it: when the link delivers it, late.
    """

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
        if self.netns is None:
            cmd, tx = bind_drone_sockets(self.ip, self._port, 0.1)
        else:  # its own network namespace: an address that is not loopback, on the caller's links only
            cmd, tx = in_netns(self.netns, lambda: bind_drone_sockets(self.ip, self._port, 0.1))
        host, port = cmd.getsockname()[:2]
        if self.radio is not None:  # every datagram in and out passes the drone's radio links
            cmd = self.radio.socket(cmd, send=lambda _addr: "reply", recv="command")  # type: ignore[assignment]
            tx = self.radio.socket(tx, send=self._downlink, recv=None)  # type: ignore[assignment]
        if self.links is not None:  # the rig's links, before the radio: rc acted on late, state sent late
            cmd = self.links.socket(cmd, recv="rc", on_lost=self._link_lost)
            if self.links.applies("state"):
                tx = self.links.socket(tx, send=self._state_link)
        self._cmd_sock, self._tx_sock = cmd, tx
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
        if self.links is not None:
            self.links.close()
        if self.radio is not None:
            self.radio.close()
        for sock in (self._cmd_sock, self._tx_sock):
            if sock is not None:
                sock.close()

    def _downlink(self, addr: tuple[str, int]) -> str:
        """The radio link of a datagram the drone sends to ``addr``: ``video`` or ``state``."""
        return "video" if addr[1] == self.video_port else "state"

    def _state_link(self, addr: tuple[str, int]) -> str | None:
        """The rig's link of a datagram the drone sends to ``addr``: ``state`` (video: decided per frame)."""
        return None if addr[1] == self.video_port else "state"

    def _link_lost(self, data: bytes, t: float) -> None:
        """A datagram the rc link lost: it never reached the drone (``uplink_lost``, reason ``link``)."""
        self.uplink_lost.append((t, data.decode("utf-8", errors="replace").strip(), "link"))

    def network_counts(self) -> dict[str, dict[str, float]]:
        """What the radio did per link (``radio.DeviceRadio.counts``); empty on a perfect link."""
        return {} if self.radio is None else self.radio.counts()

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
