"""The Tello's video as a hal.Camera (forward camera, or the EDU's downward one with `downvision 1`).

The drone streams H.264 (Annex B) over UDP to `video_port` of this computer after `streamon`.
`VideoReceiver` reads that port with its own socket and decodes with PyAV (`av.CodecContext` parser +
decoder) in one daemon thread. Why not djitellopy's BackgroundFrameRead (used before): its thread ends for
good on the first decode error or end of stream, its stop() is only seen after the next frame (a drone
that stopped streaming leaves the thread blocked forever), and its socket lives inside FFmpeg, out of reach
of any error accounting. Here the thread survives every error: a socket error (`recv_error`), a frame the
decoder rejects (`decode_error`, routine on a lossy stream: the next keyframe resynchronises), or anything
else (`reader_error`, after which the decoder is rebuilt); each is counted in `TelloCamera.counts`
(plus `thread_error` for the thread's own failures) and logged at the first and every 100th occurrence.
A frame decoded after a lost or reordered datagram, up to the next intact keyframe, is damaged: the
decoder conceals what is missing (FFmpeg copies it from the frame before), so parts of it may be smeared.
It is published all the same, tagged (`DecodedFrame.damaged`, and `since_loss`, the frames since the
loss was found: how losses are found is flightstack.drivers.tello.video_check) and counted
("concealed"): with a real Tello's keyframe interval (67 frames, 2.2 s) dropping them left the drones
blind for seconds after every lost datagram, while most of a concealed frame is right (docs/links.md,
"What the receiver does with a damaged stream"). Whether a detection in it is right is decided
downstream against a prediction from outside the image (flightstack.vision.gate), for clean frames too:
a lost middle datagram is not detectable here. Before the stream's first intact keyframe nothing is
published ("unsynced"): there is no picture to conceal from.

A per-drone `video_port` (`port` command), the downward camera and the lab file's video settings need SDK
3.0: `start()` refuses them on older firmware before sending anything, and refuses to stream when a video
setting sent at connect was not confirmed (drivers/tello/video_settings.py).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from flightstack.drivers.device_threads import ERROR_PAUSE_S, ErrorLog
from flightstack.drivers.netif import udp_socket
from flightstack.drivers.tello.config import DEFAULT_VIDEO_PORT, SETUP_ATTEMPTS, TelloCommandError, sdk3_fix
from flightstack.drivers.tello.driver import TelloDriver
from flightstack.drivers.tello.traffic import TrafficWriter
from flightstack.drivers.tello.video_decode import StreamDecoder
from flightstack.drivers.tello.video_settings import unconfirmed
from flightstack.hal import Frame, frame_truth

LOG = logging.getLogger("flightstack.tello")
STREAM_COUNT_KEYS = (
    "datagrams", "frames", "concealed", "unsynced", "decode_error", "recv_error", "reader_error",
    "thread_error", "lost_head", "lost_tail", "frame_gap", "damaged_units", "resync", "framing_off",
)  # fmt: skip
"""The receiver's counters (VideoReceiver), in the order a report lists them."""
RECV_BUFFER_BYTES = 4 << 20  # socket receive buffer asked for (the OS may grant less): a keyframe burst
MAX_DATAGRAM_BYTES = 65536


class DecodedFrame(NamedTuple):
    """One published frame: its sequence number (1, 2, …), decode time (time.monotonic() s), H × W × 3
    RGB uint8 image, and what the stream check knows of it (hal.Frame's `damaged`, `since_loss`)."""

    seq: int
    t_decoded: float
    image: np.ndarray
    damaged: bool
    since_loss: int | None


class VideoReceiver:
    """H.264 over UDP on (bind_ip, port), through `interface` when one is named (drivers/netif.py: two
    drones streaming to the same port of this computer, one behind each adapter) → the latest decoded RGB
    frame, in one daemon thread.

    `latest()` gives the newest DecodedFrame. `counts`: "datagrams", "frames" (published), "concealed"
    (published frames decoded through a detected loss), "unsynced" (decoded before the first intact
    keyframe, not published), "decode_error", "recv_error", "reader_error", "thread_error", and
    tello_video_check's ("lost_head", "lost_tail", "frame_gap", "damaged_units", "resync", "framing_off").
    Raises OSError when the port cannot be bound, ImportError without PyAV.
    """

    def __init__(
        self,
        port: int,
        bind_ip: str = "",
        counts: Counter[str] | None = None,
        traffic: TrafficWriter | None = None,
        interface: str | None = None,
    ) -> None:
        """traffic: where each datagram's length and receive time are recorded (drivers/tello/traffic.py)."""
        import av  # noqa: F401  (lazy: only hardware and its tests need PyAV; ImportError here, not later)

        self.port = port
        self.traffic = traffic
        self.counts: Counter[str] = Counter() if counts is None else counts
        self.errors = ErrorLog(self.counts, f"tello video receiver UDP {port}", LOG)
        self._sock: Any = udp_socket(interface)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
            self._sock.bind((bind_ip, port))
        except OSError:
            self._sock.close()
            raise
        self._sock.settimeout(0.1)
        self._decoder: StreamDecoder | None = None  # made at the first datagram, remade after a reader error
        self._lock = threading.Lock()
        self._latest: DecodedFrame | None = None
        self._first = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"tello-video-{port}", daemon=True)
        self._thread.start()

    def latest(self) -> DecodedFrame | None:
        """The newest published frame, or None before one."""
        with self._lock:
            return self._latest

    def wait_first_frame(self, timeout_s: float) -> bool:
        """Wait up to timeout_s (s) for the first decoded frame; True once there is one."""
        return self._first.wait(timeout_s)

    def alive(self) -> bool:
        return self._thread.is_alive()

    def close(self) -> None:
        """Stop the thread (its recv times out within 0.1 s; joined ≤ 1 s) and close the socket."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._sock.close()

    def _loop(self) -> None:
        """Reader thread: survives every error (counted, logged without flooding)."""
        while not self._stop.is_set():
            try:
                self._receive_one()
            except Exception as exc:
                self.errors.record("reader_error", exc)
                self._decoder = None  # rebuilt on the next datagram: resynchronises at the next keyframe
                self._stop.wait(ERROR_PAUSE_S)

    def _receive_one(self) -> None:
        """Receive one datagram (waits ≤ 0.1 s) and decode what it completes."""
        try:
            data, _ = self._sock.recvfrom(MAX_DATAGRAM_BYTES)
        except TimeoutError:
            return
        except OSError as exc:  # ENETUNREACH, ENOBUFS, a vanished interface...: go on reading
            if not self._stop.is_set():
                self.errors.record("recv_error", exc)
                self._stop.wait(ERROR_PAUSE_S)
            return
        if self.traffic is not None:
            self.traffic.video(time.monotonic(), len(data))
        self.counts["datagrams"] += 1
        self._decode(data)

    def _decode(self, data: bytes) -> None:
        """Feed one datagram to the stream's decoder; publish every frame it completes once the stream is
        synchronised, tagged with what tello_video_check found (module docstring)."""
        if self._decoder is None:
            self._decoder = StreamDecoder(
                self.counts, lambda exc: self.errors.record("decode_error", exc, thread=False)
            )
        for img, damaged, since_loss in self._decoder.feed(data):
            t = time.monotonic()
            with self._lock:
                seq = 1 if self._latest is None else self._latest.seq + 1
                self._latest = DecodedFrame(seq, t, img, damaged, since_loss)
            self.counts["frames"] += 1
            self.counts["concealed"] += damaged
            self._first.set()


class TelloCamera:
    """hal.Camera over the Tello's video stream (forward, or downward on the EDU with `downvision 1`).

    Frames are RGB uint8, each stamped with its estimated capture time: the time.monotonic() (s) at which
    it was decoded minus `latency_s` (the configured capture → decode latency; 0 by default, so the stamp
    is the decode time). With `to_picture` (flightstack.vision.picture.picture_of the camera's calibration),
    each frame is cut to the calibrated picture and converted to its image kind (the Tello EDU's downward
    stream is a 320 × 720 frame whose top 320 × 240 are the grey picture, as the calibration's `stream`
    says), once per decoded frame. The emulated lab
    records every frame's true capture time beside it (TelloEmulator.video_capture_log), so the estimate
    can be checked. `frames_seen` counts the distinct
    frames returned by `latest()`; `counts` holds the receiver's counters (module docstring), kept across
    restarts.
    """

    def __init__(
        self,
        driver: TelloDriver,
        frame_timeout_s: float = 10.0,
        latency_s: float = 0.0,
        to_picture: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        """frame_timeout_s: how long `start()` waits for the first decoded frame (s); latency_s: subtracted
        from the decode time to stamp a frame (s, ≥ 0); to_picture: how a decoded frame becomes the
        picture `latest` gives (flightstack.vision.picture.picture_of the camera's calibration: the EDU's
        downward stream cropped, a grey camera's frame made grey; None: the decoded frame as it is)."""
        if not (latency_s >= 0.0 and latency_s < 10.0):
            raise ValueError(f"latency_s must be in [0, 10) s, got {latency_s}")
        self.driver = driver
        self.frame_timeout_s = frame_timeout_s
        self.latency_s = float(latency_s)
        self.counts: Counter[str] = Counter()
        self.to_picture = to_picture
        self._rx: VideoReceiver | None = None
        self._last_seq = 0
        self._truth_px: np.ndarray | None = None  # the newest frame's, from an emulated camera
        self._picture: np.ndarray | None = None  # the picture of the frame numbered _last_seq
        self._last_decoded: DecodedFrame | None = None  # that frame, whole
        self.frames_seen = 0

    def start(self) -> None:
        """Open the video port, select port and camera, `streamon`, wait for the first decoded frame.

        TelloCommandError names what failed. Needs SDK 3.0 for a per-drone video port, the downward camera
        or video settings: refused before sending; and every video setting confirmed at connect."""
        d = self.driver
        need = d.cfg.sdk3_features
        if need and (d.sdk_version is None or float(d.sdk_version) < 3.0):
            raise TelloCommandError(
                f"Tello {d.cfg.host} reports SDK {d.sdk_version or 'unknown'}; {', '.join(need)} needs "
                f"SDK 3.0: {sdk3_fix(d.cfg.downward_camera)}"
            )
        refused = unconfirmed(d.cfg, d.video_outcomes)
        if refused:  # the lab file's video settings, sent at connect: no video without them
            raise TelloCommandError("; ".join(refused))
        port = d.cfg.video_port
        try:  # bound before streamon, so that the first keyframe is not lost
            rx = VideoReceiver(port, d.cfg.bind_ip, self.counts, d.traffic, d.cfg.interface)
        except (OSError, ImportError) as exc:
            raise TelloCommandError(f"video on UDP {port}: {exc}") from exc
        try:
            if port != DEFAULT_VIDEO_PORT:  # station mode: each drone streams to its own port
                d.control(f"port {d.cfg.state_port} {port}", d.cfg.command_timeout_s, SETUP_ATTEMPTS)
            if d.cfg.downward_camera:
                d.control("downvision 1", d.cfg.command_timeout_s, SETUP_ATTEMPTS)
            d.control("streamon", d.cfg.command_timeout_s, SETUP_ATTEMPTS)
            if not rx.wait_first_frame(self.frame_timeout_s):
                raise TelloCommandError(
                    f"video on UDP {port}: no decodable video within {self.frame_timeout_s:.1f} s "
                    f"({self.counts['datagrams']} datagrams, {self.counts['decode_error']} decode errors)"
                )
        except BaseException:
            rx.close()
            raise
        self._rx, self._last_seq, self._picture = rx, 0, None

    def latest(self) -> Frame | None:
        rx = self._rx
        item = None if rx is None else rx.latest()
        if item is None:
            return None
        if item.seq != self._last_seq:
            self._last_seq, self._last_decoded = item.seq, item
            self.frames_seen += 1
            truth = frame_truth(self.driver.cfg.host, self.driver.cfg.video_port)
            self._truth_px = None if truth is None else truth(item.image)  # read from the whole frame
            self._picture = None
        if self._picture is None:
            to_picture = self.to_picture
            self._picture = item.image if to_picture is None else to_picture(item.image)
        stamp = item.t_decoded - self.latency_s
        return Frame(
            stamp,
            self._picture,
            None,
            damaged=item.damaged,
            since_loss=item.since_loss,
            truth_px=self._truth_px,
        )

    @property
    def last_decoded(self) -> DecodedFrame | None:
        """The decoded frame, whole (before the cut to the calibrated picture), that `latest` last made
        its picture from; None before one. For tools that measure the stream itself (a frame's bar-coded
        index on the emulated lab), never for the loop."""
        return None if self._rx is None or self._last_seq == 0 else self._last_decoded

    def stream_counts(self) -> dict[str, int]:
        """hal.StreamCounting: the receiver's counts so far (STREAM_COUNT_KEYS, zeros too) and
        "frames_seen", the distinct frames `latest()` handed out."""
        return {**{k: int(self.counts[k]) for k in STREAM_COUNT_KEYS}, "frames_seen": self.frames_seen}

    def stop(self, streamoff_timeout_s: float = 1.0) -> None:
        """Stop decoding and ask the drone to stop streaming (`streamoff`, bounded, failure ignored: the
        stream is only a load on the link, and a drone that cannot answer is handled elsewhere)."""
        if self._rx is not None:
            self._rx.close()
            self._rx = None
            c = self.counts
            if c["concealed"] or c["lost_head"] or c["lost_tail"] or c["frame_gap"]:  # the stream's losses
                LOG.warning(
                    "tello %s video: %d frames published, %d of them concealed after a loss (lost head %d, "
                    "tail %d, frame gaps %d, decode errors %d, resyncs %d)",
                    self.driver.cfg.host, c["frames"], c["concealed"], c["lost_head"], c["lost_tail"],
                    c["frame_gap"], c["decode_error"], c["resync"],
                )  # fmt: skip
            try:
                self.driver.control("streamoff", streamoff_timeout_s, attempts=1)
            except TelloCommandError as exc:
                LOG.info("tello %s: %s", self.driver.cfg.host, exc)
