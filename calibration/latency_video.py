"""The camera's latency from poses and pixels: where the target's markers should be in the image at each
motion-capture sample (the drone's and the target's poses projected through the camera's calibration and
mount), and the delay of the decoded frames' markers behind that (flightstack.calibration.latency).

Frames: Σw (motion capture's world), the drone's body FLU, the camera's Σc (OpenCV: x right, y down, z
along the optical axis); poses as flightstack.paper.geometry.Pose (m, rad).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from flightstack.calibration.latency import DelayEstimate, estimate_delay
from flightstack.paper.geometry import Pose, relative
from flightstack.sim_backend.scene.render import markers_in_camera
from flightstack.vision.camera_file import CameraCalibration


def predicted_pixels(
    cal: CameraCalibration, g_wi: Pose, g_w0: Pose, P0: np.ndarray, R_ic: np.ndarray, t_ic: np.ndarray
) -> np.ndarray:
    """(m, 2) distorted pixels (u, v) of the target's markers P0 (m, 3; target frame, m) seen by the camera
    (mount R_ic, t_ic in the body frame) of a drone at g_wi, the target at g_w0 (Σw); NaN behind the
    camera."""
    centres_c, _ = markers_in_camera(relative(g_wi, g_w0), P0, R_ic, t_ic)
    px, _ = cv2.projectPoints(centres_c, np.zeros(3), np.zeros(3), cal.camera_matrix, cal.dist_coeffs)
    out = px.reshape(-1, 2)
    out[centres_c[:, 2] <= 0] = np.nan
    return out


def video_delay(
    t_pose: np.ndarray,
    predicted: np.ndarray,
    t_frames: np.ndarray,
    found: Sequence[np.ndarray | None],
    max_lag_s: float = 1.0,
    window_s: float = 0.3,
) -> DelayEstimate:
    """The frames' delay (s) behind the poses: t_pose (n,) the poses' capture times, predicted (n, m, 2)
    their markers' pixels (predicted_pixels); t_frames (f,) each frame's stamp (its decode time on this
    computer, not corrected), found: its markers' pixels (m, 2) or None where they were not all found.
    ValueError in words when fewer than 2 poses put every marker in front of the camera."""
    pred = np.asarray(predicted, dtype=float).reshape(len(t_pose), -1)
    obs = np.full((len(t_frames), pred.shape[1]), np.nan)
    for i, px in enumerate(found):
        if px is not None:
            obs[i] = np.asarray(px, dtype=float).ravel()
    ok = np.isfinite(pred).all(axis=1)
    if ok.sum() < 2:
        raise ValueError(
            f"the markers are behind the camera at {len(ok) - int(ok.sum())} of {len(ok)} poses (need 2 "
            "in front): check the mount (R_ic, t_ic), the markers (P0) and the poses (g_wi, g_w0)"
        )
    return estimate_delay(t_pose[ok], pred[ok], np.asarray(t_frames, float), obs, max_lag_s, window_s)


__all__ = ["predicted_pixels", "video_delay"]
