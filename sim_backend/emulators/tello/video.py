"""The Tello emulator's video stream: render, H.264-encode and send frames over UDP.

After ``streamon`` the video thread renders ``frame_source(t, emu)`` (``t`` = stream time ``n / fps`` s of
frame ``n``; frames of ``video_size = (width, height)`` pixels, see ``frames``), encodes it with
libx264 (ultrafast, zerolatency, repeat-headers, ``gop_size`` frames between keyframes) and sends the raw
Annex-B byte stream in datagrams of at most ``MAX_VIDEO_DATAGRAM`` bytes to ``(client_ip, video_port)``.
The SDK 3.0 video settings received (``setfps``, ``setresolution``, ``setbitrate``: ``stream_format``) set
its rate, size (the picture scaled) and target bit rate. A new ``streamon`` or a new setting restarts the
encoder (a new stream epoch); a late thread skips frames rather than bursting. Every frame sent is logged
with its capture time (``video_capture_log``: index, the time.monotonic() s at which its content was taken,
the time it was sent). With ``use_remote_video`` the video is made elsewhere (``video_process``: the
emulated lab's cameras that render the flight, in a child process) and this thread only feeds it the
stream state, its format and the true pose. `TelloVideoStream` is one layer of ``TelloEmulator``
(``emulator``); ``make_encoder``, ``scaled``, ``frame_datagrams`` and ``send_frame`` are shared with the
child process. With the rig's video link (``links``, device_links) each frame leaves late as a whole, or
is lost, and each datagram of a frame that leaves may be lost by itself (the link's `datagram_loss`); its
send time is then when it was due to leave.
"""

from __future__ import annotations

import contextlib
import socket
import time
from fractions import Fraction
from typing import Any, Protocol

import numpy as np

from flightstack.drivers.tello.sdk_video import RESOLUTION_ARGS, bit_rate_bps

from .base import TelloEmulatorBase

MAX_VIDEO_DATAGRAM = 1460
"""Largest video datagram payload, like the real drone."""


AUTO_BIT_RATE_BPS = 3_000_000
"""What a Tello streams at its own (`setbitrate 0`, the default) rate (bit/s): 366–430 KB/s in the 2 s
windows of a real Tello's stream logged by TelloPy (hanyazou/TelloPy#76), 2.9–3.4 Mbit/s; about nine
1460-byte datagrams per P frame at 30 fps, as `devconx_test.h264` has (docs/drivers.md)."""


def make_encoder(size: tuple[int, int], fps: float, gop_size: int, bit_rate: int | None = None) -> Any:
    """A libx264 encoder as the emulator streams: `size` (width, height) px, `fps` frames/s, a keyframe
    every `gop_size` frames, ultrafast, zerolatency, one slice per picture (one thread: the recorded
    Tello stream's pictures are one slice each, so a lost datagram spoils the rest of its picture),
    SPS/PPS repeated before every keyframe; `bit_rate`:
    the target (bit/s: `setbitrate`; None: the Tello's own AUTO_BIT_RATE_BPS), held as a ceiling by a
    video buffer of one frame (VBV), so that a picture with detail fills about as many datagrams as a real
    one, and a plain one fewer (no filler)."""
    import av  # local import: only needed when streaming

    ctx = av.CodecContext.create("libx264", "w")
    ctx.width, ctx.height = size
    ctx.pix_fmt = "yuv420p"
    rate = Fraction(fps).limit_denominator(1001)
    ctx.framerate = rate
    ctx.time_base = 1 / rate
    ctx.gop_size = gop_size
    rate_bps = int(AUTO_BIT_RATE_BPS if bit_rate is None else bit_rate)
    ctx.bit_rate = rate_bps
    kbps = rate_bps // 1000
    vbv = f"vbv-maxrate={kbps}:vbv-bufsize={max(1, int(kbps / fps))}"
    ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "x264-params": f"repeat-headers=1:{vbv}"}
    ctx.thread_count = 1  # zerolatency cuts a picture into one slice per thread
    return ctx


StreamFormat = tuple[float, tuple[int, int], int | None]
"""What the SDK 3.0 video settings decide of a stream: frame rate (frames/s), frame size (width, height)
px, target bit rate (bit/s; None: the encoder's own)."""


def scaled(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`img` at `size` (width, height) px, as the stream carries the camera's picture (`setresolution`);
    `img` itself when it has that size already."""
    if (img.shape[1], img.shape[0]) == size:
        return img
    import cv2

    return np.ascontiguousarray(cv2.resize(img, size, interpolation=cv2.INTER_AREA))


def scaled_pixels(px: np.ndarray, source: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """Pixels (…, 2) of an image of `source` (width, height) where `scaled` puts them at `size`: each
    pixel's centre maps to the same place in the picture, u' = (u + ½)·w'/w − ½ (v likewise)."""
    if source == size:
        return px
    scale = np.array([size[0] / source[0], size[1] / source[1]])
    return (np.asarray(px, dtype=float) + 0.5) * scale - 0.5


def frame_datagrams(encoder: Any, img: np.ndarray, index: int) -> list[bytes]:
    """Encode RGB `img` as frame `index`: its Annex-B bytes in datagrams of at most MAX_VIDEO_DATAGRAM
    bytes, as the Tello splits them."""
    import av

    frame = av.VideoFrame.from_ndarray(img, format="rgb24")
    frame.pts = index
    out: list[bytes] = []
    for packet in encoder.encode(frame):
        payload = bytes(packet)
        out.extend(payload[k : k + MAX_VIDEO_DATAGRAM] for k in range(0, len(payload), MAX_VIDEO_DATAGRAM))
    return out


def send_frame(encoder: Any, sock: socket.socket, dest: tuple[str, int], img: np.ndarray, index: int) -> int:
    """Encode RGB `img` as frame `index` and send its datagrams (`frame_datagrams`) to `dest` at once (a
    refused send is ignored: nobody listening yet is fine); the bytes sent."""
    datagrams = frame_datagrams(encoder, img, index)
    for d in datagrams:
        with contextlib.suppress(OSError):
            sock.sendto(d, dest)
    return sum(len(d) for d in datagrams)


class RemoteVideo(Protocol):
    """Video made outside the emulator's process (tello_video_process.VideoProcess): the emulator's video
    thread publishes its stream state and true pose to it and copies its counters back."""

    def publish(
        self, on: bool, epoch: int, downvision: bool, position_cm: tuple[float, float, float], yaw_deg: float
    ) -> None: ...

    def configure(self, fmt: StreamFormat) -> None: ...

    def sync(self, emu: TelloEmulatorBase) -> None: ...


class TelloVideoStream(TelloEmulatorBase):
    """The video thread of the emulator (``_video_loop``) and its encoder, renderer and sender."""

    remote_video: RemoteVideo | None = None
    """Set by `use_remote_video` before `start()`: the video is rendered, encoded and sent by it."""

    def use_remote_video(self, remote: RemoteVideo) -> None:
        """Let `remote` make the video (call before `start()`); this emulator then only feeds it."""
        if self._started:
            raise RuntimeError("use_remote_video must be called before start()")
        self.remote_video = remote

    def stream_format(self) -> StreamFormat:
        """The stream's format now (call under the lock): ``fps``, ``video_size`` or, once ``setresolution``
        was received, its size (the forward camera's only: with ``downvision`` the downward picture keeps
        its own), and the ``setbitrate`` target (flightstack.config.tello_video)."""
        size = self.video_size
        if self.resolution is not None and not self.downvision:
            size = RESOLUTION_ARGS[self.resolution]
        return self.fps, size, bit_rate_bps(self.bitrate_mbps)

    def _render(self, t: float, size: tuple[int, int]) -> np.ndarray | None:
        """The frame source's picture at stream time `t` (s), at the stream's `size` (width, height) px."""
        img = np.asarray(self.frame_source(t, self))
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        width, height = self.video_size
        if img.shape != (height, width, 3) or img.dtype != np.uint8:
            self.errors.append(f"frame_source gave {img.shape} {img.dtype}, need {(height, width, 3)} uint8")
            return None
        return scaled(np.ascontiguousarray(img), size)

    def _send_frame(self, encoder: Any, img: np.ndarray, index: int, t_capture: float) -> None:
        sock = self._tx_sock
        assert sock is not None
        dest = (self.client_ip, self.video_port)
        links = self.links
        if links is None or not links.applies("video"):
            self.video_bytes_sent += send_frame(encoder, sock, dest, img, index)
            sent = time.monotonic()
        else:  # the frame leaves late, as a whole, or never (device_links)
            datagrams = frame_datagrams(encoder, img, index)
            due = links.decide("video", t_capture)
            if due is None:
                return
            for d in datagrams:
                if not links.keeps("video", t_capture, len(d)):  # a datagram lost: the frame is damaged
                    continue
                with contextlib.suppress(OSError):
                    links.send_at(due, sock, d, dest, "video")
            self.video_bytes_sent += sum(len(d) for d in datagrams)
            sent = max(due, time.monotonic())
        self.video_frames_sent += 1
        self.video_log.append((index, sent))
        self.video_capture_log.append((index, t_capture, sent))

    def _remote_video_loop(self, remote: RemoteVideo) -> None:
        """Feed the remote video every 10 ms: stream state, format and the true pose; copy its counters
        back."""
        fmt: StreamFormat | None = None
        while not self._stop.is_set():
            with self._lock:
                on = self.streaming and not self.faults.no_video
                epoch, down = self._stream_epoch, self.downvision
                pos = (float(self._pos[0]), float(self._pos[1]), float(self._pos[2]))
                yaw = float(self._yaw)
                now_fmt = self.stream_format()
            if now_fmt != fmt:  # before the state: a new epoch starts with the format of its time
                fmt = now_fmt
                remote.configure(fmt)
            remote.publish(on, epoch, down, pos, yaw)
            remote.sync(self)
            self._stop.wait(0.01)

    def _video_loop(self) -> None:
        if self.remote_video is not None:
            self._remote_video_loop(self.remote_video)
            return
        encoder: Any = None
        epoch = -1
        index = 0
        t0 = 0.0
        fmt = self.stream_format()
        period = 1.0 / fmt[0]
        while not self._stop.is_set():
            with self._lock:
                streaming, current_epoch, now_fmt = self.streaming, self._stream_epoch, self.stream_format()
            if not streaming:
                encoder = None
                self._stop.wait(0.02)
                continue
            if encoder is None or current_epoch != epoch or now_fmt != fmt:  # a new setting: a new stream
                try:
                    encoder = make_encoder(now_fmt[1], now_fmt[0], self.gop_size, now_fmt[2])
                except Exception as exc:
                    self.errors.append(f"cannot create H.264 encoder: {exc!r}")
                    self._stop.wait(0.5)
                    continue
                epoch, index, t0, fmt, period = current_epoch, 0, time.monotonic(), now_fmt, 1.0 / now_fmt[0]
            now = time.monotonic()
            due = t0 + index * period
            if due > now:
                self._stop.wait(min(due - now, 0.05))
                continue
            if now - due > 3 * period:  # fell behind: skip frames instead of bursting
                index = int((now - t0) / period)
            t = index * period
            self.video_frame_index = index
            if not self.faults.no_video and not self.downlink_blocked():
                try:
                    t_capture = time.monotonic()
                    img = self._render(t, fmt[1])
                    if img is not None:
                        self._send_frame(encoder, img, index, t_capture)
                except Exception as exc:
                    self.errors.append(f"video frame {index}: {exc!r}")
            index += 1
