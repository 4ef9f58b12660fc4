"""The calibration's picture from a frame as a camera's stream delivers it.

A Tello EDU streaming its downward camera (`downvision 1`) sends 320 × 720 frames: the 320 × 240 grey
picture at the top, noise below (DJITelloPy issues #140 and #213; docs/drivers.md). The calibration says
where the picture lies (`stream`, flightstack.vision.camera_file.StreamLayout) and what it holds (`image`):
`picture` crops it and converts it to that kind, so every later step sees the calibrated picture.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from flightstack.vision.camera_file import CameraCalibration


def picture(frame: np.ndarray, cal: CameraCalibration) -> np.ndarray:
    """The calibrated picture of a decoded frame (H × W × 3 RGB or H × W grey, uint8).

    A frame of the stream's size (`cal.stream`) is cropped to `stream.picture`; then a grey camera's RGB
    frame becomes grey (cv2.COLOR_RGB2GRAY, the decoder's colour planes are dropped). A frame of another size
    is only converted (its size then shows the mismatch, e.g. preflight's camera check). Returns a new
    contiguous array, or `frame` itself when nothing changes.
    """
    s = cal.stream
    h, w = frame.shape[:2]
    out = frame
    if s is not None and (w, h) == (s.width, s.height) and (w, h) != (cal.width, cal.height):
        out = np.ascontiguousarray(frame[s.y : s.y + cal.height, s.x : s.x + cal.width])
    if cal.grey and out.ndim == 3:
        out = cv2.cvtColor(np.ascontiguousarray(out), cv2.COLOR_RGB2GRAY)
    return out


def picture_of(cal: CameraCalibration) -> Callable[[np.ndarray], np.ndarray]:
    """The function that makes a decoded frame of the camera of `cal` into its picture (`picture`)."""
    return lambda frame: picture(frame, cal)
