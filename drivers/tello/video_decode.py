"""A Tello's H.264 stream decoded datagram by datagram, each picture tagged with what is known of it.

PyAV's parser cuts the datagrams into access units and FFmpeg's h264 decoder (err_detect aggressive: a
frame with a truncated slice is flagged) decodes them; flightstack.drivers.tello.video_check.StreamCheck
judges each datagram and access unit and says whether the picture was decoded through a detected loss.
Before the stream's first intact keyframe nothing is returned ("unsynced"). The video receiver
(drivers/tello/camera.py) feeds it what its socket reads; benchmarks/concealed_frames.py feeds it a stream
it loses datagrams of, so the two decode alike.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from flightstack.drivers.tello.video_check import StreamCheck


class StreamDecoder:
    """One stream's parser, decoder and StreamCheck. counts: the receiver's counters ("unsynced" and
    StreamCheck's, updated here); on_decode_error: told of every frame the decoder rejected (the stream
    goes on: the next keyframe resynchronises). Raises ImportError without PyAV."""

    def __init__(self, counts: Counter[str], on_decode_error: Callable[[Exception], object]) -> None:
        import av  # lazy: only hardware, the emulators and their tests need PyAV

        self._av: Any = av
        self.counts = counts
        self.on_decode_error = on_decode_error
        self._codec: Any = av.CodecContext.create("h264", "r")
        self._codec.options = {"err_detect": "aggressive"}  # flags a frame with a truncated slice
        self.check = StreamCheck(counts)

    def feed(self, data: bytes) -> list[tuple[np.ndarray, bool, int | None]]:
        """The pictures one datagram completed, once the stream is synchronised: each its H × W × 3 RGB
        uint8 image, whether it was decoded through a detected loss (`damaged`) and the frames since that
        loss (`since_loss`, None before any)."""
        check, out = self.check, []
        check.datagram(data)
        for packet in self._codec.parse(data):
            check.access_unit(bytes(packet))
            try:
                frames = self._codec.decode(packet)
            except self._av.error.FFmpegError as exc:
                # lost datagrams, no keyframe yet: no frame from this one
                self.on_decode_error(exc)
                check.mark_damaged()
                continue
            for frame in frames:
                if frame.is_corrupt:
                    check.mark_damaged()
                if not check.synced:
                    self.counts["unsynced"] += 1
                    continue
                out.append((frame.to_ndarray(format="rgb24"), check.damaged, check.since_loss))
        return out


__all__ = ["StreamDecoder"]
