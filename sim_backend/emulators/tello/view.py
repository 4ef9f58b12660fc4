"""What an emulated Tello's camera sees: the target's markers rendered from the emulated world's poses.

The world is the motion-capture frame Σw (metres, z up, yaw counter-clockwise). A Tello emulator flies in
its own frame (x forward at takeoff heading, y right, z up, cm; yaw clockwise in degrees) from its start
pose in Σw: `drone_world_pose` converts (the emulated lab's motion capture uses it too). `CameraView`
renders one camera: the drone's pose and the target's pose in Σw → the target in the drone's body frame
(FLU) → the markers in the camera frame through the mount (`markers_in_camera`) → the project's renderer
(`render_markers`) with the calibration's intrinsics and distortion. Everything here is picklable data
and pure functions, so a child process can build the view from a `CameraSpec`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from flightstack.paper.geometry import Pose, compose, relative


@dataclass(frozen=True)
class CameraSpec:
    """One emulated camera (picklable).

    calibration: the calibration as a dict (`CameraCalibration.to_dict()`; its width and height are the
    video size). R_ic: 3×3 mount (columns = camera axes in the body frame FLU); t_ic: offset (m, body).
    feature_points: (m, 3) marker centres in the target's frame (m), in the calibration's marker order.
    start: the drone's start (x, y, z m, yaw rad) in Σw. marker_radius_m, noise_std (grey levels),
    blur_px: the renderer's options; seed: the pixel noise's generator.
    """

    calibration: dict[str, Any]
    R_ic: tuple[tuple[float, ...], ...]
    t_ic: tuple[float, ...]
    feature_points: tuple[tuple[float, ...], ...]
    start: tuple[float, float, float, float]
    marker_radius_m: float = 0.03
    noise_std: float = 0.0
    blur_px: float = 0.0
    seed: int = 0

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels of the calibration, hence of the video."""
        return int(self.calibration["width"]), int(self.calibration["height"])


def drone_world_pose(
    start: tuple[float, float, float, float], position_cm: tuple[float, float, float], yaw_deg: float
) -> Pose:
    """The pose in Σw of a Tello emulator that started at `start` (x, y, z m, yaw rad, Σw) and now is at
    `position_cm` (x forward, y right, z up, cm, from its start) with `yaw_deg` (clockwise, degrees)."""
    x, y, z = position_cm
    g0 = Pose.make(list(start[:3]), start[3])
    return compose(g0, Pose.make([x / 100.0, -y / 100.0, z / 100.0], -math.radians(yaw_deg)))


class CameraView:
    """Renders what one camera sees: `image(g_wi, g_w0)` → H × W × 3 uint8 RGB."""

    def __init__(self, spec: CameraSpec) -> None:
        from flightstack.sim_backend.render import RenderOptions
        from flightstack.vision.camera_file import calibration_from_dict

        self.spec = spec
        self.cal = calibration_from_dict(spec.calibration, "emulated camera")
        self.R_ic = np.array(spec.R_ic, dtype=float)
        self.t_ic = np.array(spec.t_ic, dtype=float)
        self.P0 = np.array(spec.feature_points, dtype=float)
        self.opts = RenderOptions(
            marker_radius_m=spec.marker_radius_m, noise_std=spec.noise_std, blur_px=spec.blur_px
        )
        self.rng = np.random.default_rng(spec.seed)

    def image(self, g_wi: Pose, g_w0: Pose) -> np.ndarray:
        """The frame of a drone at g_wi looking at the target at g_w0 (both in Σw)."""
        from flightstack.sim_backend.render import markers_in_camera, render_markers

        centres_c, normals_c = markers_in_camera(relative(g_wi, g_w0), self.P0, self.R_ic, self.t_ic)
        img, _, _ = render_markers(self.cal, centres_c, normals_c, self.opts, self.rng)
        return img

    def true_pixels(self, g_wi: Pose, g_w0: Pose) -> np.ndarray:
        """(m, 2) where the target's feature points lie in `image(g_wi, g_w0)` (render.true_pixels)."""
        from flightstack.sim_backend.render import marker_centres_in_camera, true_pixels

        return true_pixels(
            self.cal, marker_centres_in_camera(relative(g_wi, g_w0), self.P0, self.R_ic, self.t_ic)
        )


__all__ = ["CameraSpec", "CameraView", "drone_world_pose"]
