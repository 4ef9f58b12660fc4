"""The Tello emulator's video stream: render, H.264-encode and send frames over UDP.

After ``streamon`` the video thread renders ``frame_source(t, emu)`` (``t`` = stream time ``n / fps`` s of
frame ``n``; frames of ``video_size = (width, height)`` pixels, see ``tello_frames``), encodes it with
libx264 (ultrafast, zerolatency, repeat-headers, ``gop_size`` frames between keyframes) and sends the raw
Annex-B byte stream in datagrams of at most ``MAX_VIDEO_DATAGRAM`` bytes to ``(client_ip, video_port)``.
A new ``streamon`` restarts the encoder (a new stream epoch); a late thread skips frames rather than
bursting.  `TelloVideoStream` is one layer of ``TelloEmulator`` (``tello_emulator``).
"""

from __future__ import annotations

import contextlib
import time
from fractions import Fraction
from typing import Any

import numpy as np

from .tello_base import TelloEmulatorBase

MAX_VIDEO_DATAGRAM = 1460
"""Largest video datagram payload, like the real drone."""


class TelloVideoStream(TelloEmulatorBase):
    """The video thread of the emulator (``_video_loop``) and its encoder, renderer and sender."""

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
            if not self.faults.no_video and not self.downlink_blocked():
                try:
                    img = self._render(t)
                    if img is not None:
                        self._send_frame(encoder, img, index)
                except Exception as exc:
                    self.errors.append(f"video frame {index}: {exc!r}")
            index += 1
