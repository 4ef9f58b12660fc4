"""The Tello's video as a hal.Camera (forward camera, or the EDU's downward one with `downvision 1`).

The drone streams H.264 over UDP to `video_port` of this computer after `streamon`; djitellopy's
BackgroundFrameRead decodes it with PyAV. A per-drone `video_port` (`port` command) and the downward
camera need SDK 3.0: `start()` refuses them on older firmware before sending anything.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any

from drivers.tello import DEFAULT_VIDEO_PORT, TelloCommandError, TelloDriver
from flightstack.hal import Frame

LOG = logging.getLogger("flightstack.tello")


class TelloCamera:
    """hal.Camera over the Tello's video stream (forward, or downward on the EDU with `downvision 1`).

    Frames are RGB uint8 (djitellopy's BackgroundFrameRead decodes with PyAV); each distinct decoded
    frame is stamped with the monotonic time at which this driver first saw it.
    """

    def __init__(self, driver: TelloDriver, frame_timeout_s: float = 10.0) -> None:
        self.driver = driver
        self.frame_timeout_s = frame_timeout_s
        self._reader: Any = None
        self._last: object = None
        self._placeholder: object = None
        self._stamp = -math.inf
        self.frames_seen = 0

    def start(self) -> None:
        """Select port and camera, `streamon`, open the decoder; TelloCommandError names what failed.

        Needs SDK 3.0 for a per-drone video port or the downward camera: refused before sending."""
        d = self.driver
        need = d.cfg.sdk3_features
        if need and (d.sdk_version is None or float(d.sdk_version) < 3.0):
            raise TelloCommandError(
                f"Tello {d.cfg.host} reports SDK {d.sdk_version or 'unknown'}; {', '.join(need)} needs "
                "SDK 3.0 (fly in access-point mode with the default video port instead)"
            )
        if d.cfg.video_port != DEFAULT_VIDEO_PORT:  # station mode: each drone streams to its own port
            d._control(f"port {d.cfg.state_port} {d.cfg.video_port}", d.cfg.command_timeout_s)
        if d.cfg.downward_camera:
            d._control("downvision 1", d.cfg.command_timeout_s)
        d._control("streamon", d.cfg.command_timeout_s)
        self._reader = _open_reader(d.cfg.video_port, self.frame_timeout_s)
        # djitellopy starts with a black 400x300 placeholder until the first frame is decoded: not a frame
        self._placeholder = self._reader.frame

    def latest(self) -> Frame | None:
        if self._reader is None:
            return None
        img = self._reader.frame
        if img is None or img is self._placeholder:
            return None
        if img is not self._last:
            self._last = img
            self._stamp = time.monotonic()
            self.frames_seen += 1
        return Frame(self._stamp, img, None)

    def stop(self, streamoff_timeout_s: float = 1.0) -> None:
        """Stop decoding and ask the drone to stop streaming (`streamoff`, bounded, failure ignored: the
        stream is only a load on the link, and a drone that cannot answer is handled elsewhere)."""
        if self._reader is not None:
            self._reader.stop()
            self._reader = None
            try:
                self.driver._control("streamoff", streamoff_timeout_s, attempts=1)
            except TelloCommandError as exc:
                LOG.info("tello %s: %s", self.driver.cfg.host, exc)


def _open_reader(video_port: int, timeout_s: float) -> Any:
    """djitellopy's BackgroundFrameRead on UDP `video_port`, opened within `timeout_s` (it blocks)."""
    from djitellopy.tello import BackgroundFrameRead  # lazy: only hardware and its tests need PyAV

    box: dict[str, Any] = {}

    def open_() -> None:
        try:
            box["reader"] = BackgroundFrameRead(None, f"udp://@0.0.0.0:{video_port}")
            box["reader"].start()
        except Exception as exc:
            box["error"] = exc

    th = threading.Thread(target=open_, name=f"tello-video-{video_port}", daemon=True)
    th.start()
    th.join(timeout_s)
    if "reader" in box:
        return box["reader"]
    why = box.get("error", f"no decodable video within {timeout_s:.1f} s")
    raise TelloCommandError(f"video on UDP {video_port}: {why}")
