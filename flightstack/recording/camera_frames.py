"""A mode's camera frames in the run directory, `images_<mode>.jpgs`: the frames the drones' cameras
published to their agents, JPEG-encoded, at most IMAGE_HZ per drone and second of mission time; the MCAP's
foxglove.CompressedImage topics are written from it (mcap_live.py as it grows, mcap_export.py after).
Written only on rigs whose cameras give images (the simulated and the emulated lab, real Tellos); the
frames' choice is flightstack.runtime.camera_tap's.

**Format.** The 8 bytes MAGIC, then records, each RECORD (little endian: the tag TAG, the drone id u32,
the frame's stamp f64 (s, mission clock), `damaged` u8 and `since_loss` i32 (−1: None), as
flightstack.hal.Frame tags them, and the JPEG's length u32) followed by that many bytes of JPEG (baseline,
quality JPEG_QUALITY; a grey camera's frames grey). A reader takes complete records only: a record cut short
by a kill is not read, and a record whose tag or length is wrong ends the reading (counted).

**Cost.** The control loop only hands the frame's image over (`FrameWriter.offer`, never blocking: a
full queue drops the frame, counted), by reference: a flightstack.hal.Frame is frozen and every camera
makes a new array per frame (drivers/tello/camera.py, sim_backend/lab.py), and a copy of a 960 × 720 RGB
frame cost the control thread 2 ms on the loaded 2-core machine. The writer's own thread encodes
(cv2.imencode, which releases the interpreter lock; 1.8 ms of CPU for such a frame, 0.2 ms for a 320 × 240
grey one) and appends. A file stops growing at MAX_FILE_BYTES (counted); a write error ends the
file (logged once), never the flight.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import struct
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from flightstack.recording.files import IMAGES_SUFFIX

_log = logging.getLogger(__name__)

MAGIC = b"FSJPG\x00\x00\x01"
"""The first 8 bytes of the file."""
TAG = b"JPG1"
"""The first 4 bytes of every record."""
RECORD = struct.Struct("<4sIdBiI")
"""A record's header: TAG, drone id, stamp (s), damaged, since_loss (−1: None), JPEG length (B)."""
IMAGE_HZ = 2.0
"""Frames recorded per drone and second of mission time, at most."""
JPEG_QUALITY = 75
"""cv2.IMWRITE_JPEG_QUALITY of the recorded frames (0–100)."""
QUEUE_FRAMES = 8
"""Frames waiting for the encoding thread beyond which new ones are dropped (counted)."""
BUDGET_BYTES_PER_MIN = 10_000_000
"""The images' size budget (B) per minute of flight on the emulated lab, paper_experiment's two cameras
(960 × 720 colour forward, 320 × 240 grey downward) at IMAGE_HZ and JPEG_QUALITY: measured 7.3 MB
(docs/logs.md); a real camera's JPEGs grow with what it sees."""
MAX_FILE_BYTES = 256 << 20
"""Bytes after which a file takes no more frames (counted): 256 MiB, about 35 min of those two cameras."""
MAX_JPEG_BYTES = 16 << 20
"""A record announcing a longer JPEG is taken as damage: the reading stops there."""
CLOSE_WAIT_S = 5.0
"""How long (s) `close` waits for the frames queued to be encoded and written."""


def images_name(mode: str) -> str:
    """The file name of `mode`'s camera frames."""
    return f"images_{mode}{IMAGES_SUFFIX}"


@dataclass(frozen=True)
class CameraFrame:
    """One recorded frame: drone id, stamp (s, mission clock), the camera's tags (flightstack.hal.Frame)
    and the JPEG bytes."""

    drone: int
    stamp: float
    damaged: bool
    since_loss: int | None
    jpeg: bytes


def encode_record(frame: CameraFrame) -> bytes:
    """A record of the file: header and JPEG."""
    since = -1 if frame.since_loss is None else int(frame.since_loss)
    head = RECORD.pack(TAG, int(frame.drone), float(frame.stamp), int(frame.damaged), since, len(frame.jpeg))
    return head + frame.jpeg


def parse_records(buf: bytes) -> tuple[list[CameraFrame], int, str | None]:
    """(the complete records at the start of `buf`, the bytes they take, why the reading must stop: a bad
    tag or length; None when `buf` merely ends in a record not yet complete)."""
    frames: list[CameraFrame] = []
    at = 0
    while len(buf) - at >= RECORD.size:
        tag, drone, stamp, damaged, since, n = RECORD.unpack_from(buf, at)
        if tag != TAG or n > MAX_JPEG_BYTES or damaged > 1:
            return frames, at, f"a damaged record at byte {at} of the records"
        end = at + RECORD.size + n
        if end > len(buf):
            break
        jpeg = bytes(buf[at + RECORD.size : end])
        frames.append(
            CameraFrame(int(drone), float(stamp), bool(damaged), None if since < 0 else int(since), jpeg)
        )
        at = end
    return frames, at, None


class FrameTail:
    """The complete records of a growing frames file, read as they appear (mcap_live's follower).
    `error`: why the reading stopped early (a file without MAGIC, a damaged record); None while it reads."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fh: IO[bytes] | None = None
        self.error: str | None = None
        self._buf = b""
        self._magic = False

    def read(self) -> list[CameraFrame]:
        """The frames that appeared since the last call ([] before the file exists)."""
        if self.error is not None:
            return []
        if self.fh is None:
            try:
                self.fh = open(self.path, "rb")  # noqa: SIM115 (kept open: read as it grows)
            except FileNotFoundError:
                return []
        self._buf += self.fh.read()
        if not self._magic:
            if len(self._buf) < len(MAGIC):
                return []
            if self._buf[: len(MAGIC)] != MAGIC:
                self.error = f"{self.path.name}: not a frames file (no magic)"
                return []
            self._magic, self._buf = True, self._buf[len(MAGIC) :]
        frames, used, error = parse_records(self._buf)
        self._buf = self._buf[used:]
        if error is not None:
            self.error = f"{self.path.name}: {error}"
        return frames

    def close(self) -> None:
        if self.fh is not None:
            self.fh.close()
            self.fh = None


def read_frames(path: Path) -> tuple[list[CameraFrame], str | None]:
    """Every complete record of a frames file ([] when it is missing) and why the reading stopped early
    (None: it read to the end, or to a last record cut short)."""
    tail = FrameTail(path)
    try:
        return tail.read(), tail.error
    finally:
        tail.close()


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """JPEG bytes of an RGB (H, W, 3) or grey (H, W) uint8 image."""
    import cv2

    img: np.ndarray = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"cv2.imencode refused an image of shape {image.shape}")
    return buf.tobytes()


_Job = tuple[int, float, bool, "int | None", np.ndarray]


class FrameWriter:
    """Appends frames to `path` (created anew) from its own thread (module docstring). `counts`: frames
    `written`, `dropped` (queue full), `over_size` (MAX_FILE_BYTES), `failed` (encoding or writing);
    `bytes` written; `encode_s`: the thread's time spent encoding (s)."""

    def __init__(
        self,
        path: Path,
        *,
        quality: int = JPEG_QUALITY,
        queue_frames: int = QUEUE_FRAMES,
        max_bytes: int = MAX_FILE_BYTES,
    ) -> None:
        self.path = Path(path)
        self.quality = quality
        self.max_bytes = max_bytes
        self.counts: Counter[str] = Counter()
        self.bytes = 0
        self.encode_s = 0.0
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._write(MAGIC)
        self._queue: queue.Queue[_Job | None] = queue.Queue(maxsize=queue_frames)
        self._thread = threading.Thread(target=self._work, name="flightstack-camera-frames", daemon=True)
        self._thread.start()

    def offer(
        self, drone: int, stamp: float, image: np.ndarray, damaged: bool, since_loss: int | None
    ) -> bool:
        """Hand a frame to the thread (its image by reference: module docstring); False when the queue is
        full (the frame is dropped)."""
        try:
            self._queue.put_nowait((drone, stamp, damaged, since_loss, image))
            return True
        except queue.Full:
            self.counts["dropped"] += 1
            return False

    def close(self, timeout_s: float = CLOSE_WAIT_S) -> None:
        """Write what is queued (at most `timeout_s` s), then close the file; idempotent."""
        with contextlib.suppress(queue.Full):
            self._queue.put(None, timeout=timeout_s)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            _log.warning("camera frames: %s not finished within %.0f s", self.path.name, timeout_s)
            return
        self._close_fd()

    def _close_fd(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def _write(self, data: bytes) -> None:
        assert self._fd is not None
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view) :]
        self.bytes += len(data)

    def _work(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            if self._fd is None:
                self.counts["failed"] += 1
                continue
            drone, stamp, damaged, since_loss, image = job
            try:
                t0 = time.perf_counter()
                jpeg = encode_jpeg(image, self.quality)
                self.encode_s += time.perf_counter() - t0
                record = encode_record(CameraFrame(drone, stamp, damaged, since_loss, jpeg))
                if self.bytes + len(record) > self.max_bytes:
                    self.counts["over_size"] += 1
                    continue
                self._write(record)
                self.counts["written"] += 1
            except (OSError, ValueError) as exc:  # the file ends here; the flight goes on
                self.counts["failed"] += 1
                _log.error("camera frames: %s stopped (%s: %s); the flight goes on", self.path.name,
                           type(exc).__name__, exc)  # fmt: skip
                self._close_fd()


__all__ = [
    "BUDGET_BYTES_PER_MIN",
    "IMAGE_HZ",
    "JPEG_QUALITY",
    "MAGIC",
    "MAX_FILE_BYTES",
    "CameraFrame",
    "FrameTail",
    "FrameWriter",
    "encode_jpeg",
    "encode_record",
    "images_name",
    "parse_records",
    "read_frames",
]
