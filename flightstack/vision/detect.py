"""The one entry to finding the target in a camera frame: whatever the calibration declares.

`detect_markers` is what the agent and the calibration tools call: a calibration with a `fiducial` is
searched for its ArUco marker (flightstack.vision.fiducial), one with colour `markers` for its discs
(flightstack.vision.markers); both give a `MarkerDetection` in feature-point order.
"""

from __future__ import annotations

import numpy as np

from flightstack.vision.camera_file import CameraCalibration
from flightstack.vision.fiducial import detect_fiducial
from flightstack.vision.markers import MarkerDetection, extract_markers


def detect_markers(
    image: np.ndarray, cal: CameraCalibration, *, roi: tuple[int, int, int, int] | None = None
) -> MarkerDetection:
    """The target's feature points in a frame of the calibrated picture.

    image: (cal.height, cal.width, 3) RGB or (cal.height, cal.width) grey, uint8 (a streamed frame is
        first cut to its picture: flightstack.vision.picture.picture).
    roi: the frame's hal.Frame.roi (its renderer's promise of where the markers are), or None.
    Raises ValueError when the frame cannot show what the calibration declares (a grey frame for colour
    markers), for a wrong dtype, shape or size, or a calibration without markers or fiducial.
    """
    if cal.fiducial is not None:
        return detect_fiducial(image, cal)  # (searches the whole frame: cheap, so it needs no roi)
    if isinstance(image, np.ndarray) and image.ndim == 2:
        raise ValueError(
            "a grey frame cannot show colour markers: the calibration needs `image: grey` and a `fiducial:`"
        )
    return extract_markers(image, cal, roi=roi)
