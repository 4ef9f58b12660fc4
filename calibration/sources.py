"""Where calibration frames come from: a folder of images, a video file, or a live Tello stream.

Every source yields SourceFrame(name, image, error): `image` is RGB uint8 (H, W, 3) or None with `error`
saying why the frame could not be read (the wizard reports it and goes on). Opening a source that cannot
work at all (missing folder, no image files, a video OpenCV cannot open) raises SourceError.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")


class SourceError(ValueError):
    """A source that cannot be opened; the message names the path or address."""


@dataclass(frozen=True)
class SourceFrame:
    name: str
    image: np.ndarray | None
    error: str | None = None


def _to_rgb(bgr_or_gray: np.ndarray) -> np.ndarray:
    if bgr_or_gray.ndim == 2:
        return cv2.cvtColor(bgr_or_gray, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(bgr_or_gray, cv2.COLOR_BGR2RGB)


class ImageFolderSource:
    """The image files of one folder (by suffix, sorted by name); other files are listed in `ignored`."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise SourceError(f"--images {self.folder}: not a folder")
        entries = sorted(p for p in self.folder.iterdir() if p.is_file())
        self.files = [p for p in entries if p.suffix.lower() in IMAGE_SUFFIXES]
        self.ignored = [p.name for p in entries if p.suffix.lower() not in IMAGE_SUFFIXES]
        if not self.files:
            raise SourceError(
                f"--images {self.folder}: no image files ({', '.join(IMAGE_SUFFIXES)}) in the folder"
            )
        self.total: int | None = len(self.files)
        self.label = self.folder.name
        self.is_stream = False

    def frames(self) -> Iterator[SourceFrame]:
        for p in self.files:
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None:
                yield SourceFrame(p.name, None, "unreadable (not a decodable image)")
            else:
                yield SourceFrame(p.name, _to_rgb(img))


class VideoFileSource:
    """Every `every`-th frame of a video file (cv2.VideoCapture); frames are named 'frame N'."""

    def __init__(self, path: str | Path, every: int = 1) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"--video {self.path}: no such file")
        if every < 1:
            raise SourceError(f"--every: must be >= 1, got {every}")
        cap = cv2.VideoCapture(str(self.path))
        ok = cap.isOpened()
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if ok else 0
        cap.release()
        if not ok:
            raise SourceError(f"--video {self.path}: OpenCV cannot open it as a video")
        self.every = every
        self.total = (n + every - 1) // every if n > 0 else None
        self.label = self.path.stem
        self.is_stream = True

    def frames(self) -> Iterator[SourceFrame]:
        cap = cv2.VideoCapture(str(self.path))
        try:
            idx = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                if idx % self.every == 0:
                    yield SourceFrame(f"frame {idx}", _to_rgb(img))
                idx += 1
        finally:
            cap.release()
        if idx == 0:
            raise SourceError(f"--video {self.path}: no frame could be decoded (not a video OpenCV can read)")


class TelloSource:
    """Live frames from a Tello (flightstack.drivers.tello), at most `rate_hz` per second for `duration_s`
    seconds.

    The drone does not take off; only the video stream is used (`downward` selects the EDU's downward
    camera; `interface`: the network interface it is reached through, drivers/netif.py). Not covered by
    tests (needs hardware).
    """

    def __init__(
        self,
        ip: str,
        port: int = 8889,
        duration_s: float = 60.0,
        rate_hz: float = 5.0,
        downward: bool = False,
        interface: str | None = None,
    ) -> None:
        if duration_s <= 0 or rate_hz <= 0:
            raise SourceError("--duration and --rate must be > 0")
        self.ip, self.port, self.duration_s, self.rate_hz, self.downward = (
            ip,
            port,
            duration_s,
            rate_hz,
            downward,
        )
        self.interface = interface
        self.total = None
        self.label = f"tello-{ip}"
        self.is_stream = True

    def frames(self) -> Iterator[SourceFrame]:
        from flightstack.drivers.tello.camera import TelloCamera
        from flightstack.drivers.tello.config import TelloConfig
        from flightstack.drivers.tello.driver import TelloDriver

        try:
            driver = TelloDriver(
                TelloConfig(
                    host=self.ip,
                    control_port=self.port,
                    downward_camera=self.downward,
                    interface=self.interface,
                )
            )
            driver.connect()
        except Exception as exc:
            raise SourceError(f"--tello {self.ip}: cannot connect: {exc}") from None
        cam = TelloCamera(driver)
        try:
            cam.start()
            t_end = time.monotonic() + self.duration_s
            last_stamp, k = None, 0
            while time.monotonic() < t_end:
                frame = cam.latest()
                if frame is not None and frame.image is not None and frame.stamp != last_stamp:
                    last_stamp = frame.stamp
                    yield SourceFrame(f"frame {k}", np.ascontiguousarray(frame.image))
                    k += 1
                time.sleep(1.0 / self.rate_hz)
        finally:
            cam.stop()
            driver.close()
