"""What an emulated Tello's camera sees: the target's markers rendered from the emulated world's poses.

The world is the motion-capture frame Σw (metres, z up, yaw counter-clockwise). A Tello emulator flies in
its own frame (x forward at takeoff heading, y right, z up, cm; yaw clockwise in degrees) from its start
pose in Σw: `drone_world_pose` converts (the emulated lab's motion capture uses it too). `CameraView`
renders one camera: the drone's pose and the target's pose in Σw → the target in the drone's body frame
(FLU) → the markers in the camera frame through the mount (`markers_in_camera`) → the project's renderer
(`render_markers`) with the calibration's intrinsics and distortion, over the floor the spec names. Everything
here is picklable data and pure functions, so a child process can build the view from a `CameraSpec`.

What the stream carries (`CameraView.frame`): the picture, as RGB (a grey camera's grey in all three
channels), or, for a calibration with a `stream` layout while the downward camera is selected (`downvision
1`), the Tello EDU's downward layout: a frame of the layout's size with the grey picture at `stream.picture`
and grey noise elsewhere. Users report the EDU's downward stream as 320 × 720 frames, the picture on top and
what looks like noise below it (DJITelloPy #213: "(720, 320, 3)"; #140: "useless green parts at the
bottom"); what the bottom holds is unknown, so it is modelled as noise whose amount makes the stream as
large as the forward camera's (DOWN_NOISE_STD; the downward bitrate itself is unmeasured).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from flightstack.paper.geometry import Pose, compose, relative
from flightstack.vision.camera_file import CameraCalibration

DOWN_NOISE_MEAN = 128
"""Mean grey level of the noise outside the picture of a downward layout (0..255)."""
DOWN_NOISE_POOL = 8
"""Noise fields drawn once per camera; each frame takes one other than its predecessor's (the encoder
references only the frame before: ultrafast, one reference frame), so the stream's size is that of fresh
noise at a fraction of the cost of drawing it."""
DOWN_NOISE_STD = 4.0
"""Standard deviation (grey levels) of that noise, i.i.d. per pixel: measured with the emulator's encoder
(make_encoder: libx264 ultrafast, zerolatency, the Tello's 3 Mbit/s ceiling; 30 fps, a 320 × 720 frame,
the picture on the tiled floor): 8.0 datagrams (11 kB) a frame, 2.65 Mbit/s, like the forward camera's
≈ 9 datagrams and 3 Mbit/s measured on a real Tello's dump (docs/drivers.md); without the ceiling 9.6
datagrams, and 21 with 8 grey levels, 1 with none."""


@dataclass(frozen=True)
class CameraSpec:
    """One emulated camera (picklable).

    calibration: the calibration as a dict (`CameraCalibration.to_dict()`; its width and height are the
    video size). R_ic: 3×3 mount (columns = camera axes in the body frame FLU); t_ic: offset (m, body).
    feature_points: (m, 3) marker centres in the target's frame (m), in the calibration's marker order.
    start: the drone's start (x, y, z m, yaw rad) in Σw. marker_radius_m, noise_std (grey levels),
    blur_px, floor ("plain" or "tiles"): the renderer's options; seed: the pixel noise's generator.
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
    floor: str = "plain"

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels of the calibration: the picture's."""
        return int(self.calibration["width"]), int(self.calibration["height"])

    def stream_size(self, downvision: bool) -> tuple[int, int]:
        """(width, height) in pixels of the frames sent: the calibration's `stream` layout while the downward
        camera is selected, else the picture's (`size`)."""
        layout = self.calibration.get("stream")
        if downvision and layout is not None:
            return int(layout["width"]), int(layout["height"])
        return self.size


def drone_world_pose(
    start: tuple[float, float, float, float], position_cm: tuple[float, float, float], yaw_deg: float
) -> Pose:
    """The pose in Σw of a Tello emulator that started at `start` (x, y, z m, yaw rad, Σw) and now is at
    `position_cm` (x forward, y right, z up, cm, from its start) with `yaw_deg` (clockwise, degrees)."""
    x, y, z = position_cm
    g0 = Pose.make(list(start[:3]), start[3])
    return compose(g0, Pose.make([x / 100.0, -y / 100.0, z / 100.0], -math.radians(yaw_deg)))


class CameraView:
    """Renders what one camera sees: `image(g_wi, g_w0)` → the picture (H × W × 3 RGB, or H × W grey for a
    grey camera, uint8); `frame(g_wi, g_w0, downvision)` → the frame the stream carries (RGB)."""

    def __init__(self, spec: CameraSpec) -> None:
        from flightstack.sim_backend.scene.render import RenderOptions
        from flightstack.vision.camera_file import calibration_from_dict

        self.spec = spec
        self.cal = calibration_from_dict(spec.calibration, "emulated camera")
        self.R_ic = np.array(spec.R_ic, dtype=float)
        self.t_ic = np.array(spec.t_ic, dtype=float)
        self.P0 = np.array(spec.feature_points, dtype=float)
        self.opts = RenderOptions(
            marker_radius_m=spec.marker_radius_m,
            noise_std=spec.noise_std,
            blur_px=spec.blur_px,
            floor=spec.floor,
        )
        self.rng = np.random.default_rng(spec.seed)
        self.noise_rng = np.random.default_rng((spec.seed, 1))  # the downward layout's noise
        self._noise: list[np.ndarray] = []
        self._last_noise = 0

    def image(self, g_wi: Pose, g_w0: Pose) -> np.ndarray:
        """The picture of a drone at g_wi looking at the target at g_w0 (both in Σw)."""
        from flightstack.sim_backend.scene.floor import floor_view
        from flightstack.sim_backend.scene.render import markers_in_camera, render_markers

        centres_c, normals_c = markers_in_camera(relative(g_wi, g_w0), self.P0, self.R_ic, self.t_ic)
        floor = floor_view(g_wi, self.R_ic, self.t_ic) if self.opts.floor != "plain" else None
        img, _, _ = render_markers(self.cal, centres_c, normals_c, self.opts, self.rng, floor)
        return img

    def true_pixels(self, g_wi: Pose, g_w0: Pose) -> np.ndarray:
        """(m, 2) where the target's feature points lie in `image(g_wi, g_w0)` (render.true_pixels)."""
        from flightstack.sim_backend.scene.render import marker_centres_in_camera, true_pixels

        return true_pixels(
            self.cal, marker_centres_in_camera(relative(g_wi, g_w0), self.P0, self.R_ic, self.t_ic)
        )

    def frame(self, g_wi: Pose, g_w0: Pose, downvision: bool) -> np.ndarray:
        """The frame the stream carries: H × W × 3 uint8 RGB of `spec.stream_size(downvision)` (the module
        docstring): the picture, laid out as the EDU's downward stream when it applies."""
        pic = self.image(g_wi, g_w0)
        layout = self.cal.stream
        if not downvision or layout is None:
            return pic if pic.ndim == 3 else np.ascontiguousarray(np.repeat(pic[:, :, None], 3, axis=2))
        if not self._noise:
            for _ in range(DOWN_NOISE_POOL):
                noise = self.noise_rng.standard_normal((layout.height, layout.width), dtype=np.float32)
                out = np.clip(noise * np.float32(DOWN_NOISE_STD) + np.float32(DOWN_NOISE_MEAN + 0.5), 0, 255)
                self._noise.append(out.astype(np.uint8))
        k = (self._last_noise + 1 + int(self.noise_rng.integers(DOWN_NOISE_POOL - 1))) % DOWN_NOISE_POOL
        self._last_noise = k
        canvas = np.empty((layout.height, layout.width, 3), dtype=np.uint8)
        canvas[...] = self._noise[k][:, :, None]
        where = canvas[layout.y : layout.y + self.cal.height, layout.x : layout.x + self.cal.width]
        where[...] = pic if pic.ndim == 3 else pic[:, :, None]
        return canvas

    def stamp_area(self, frame: np.ndarray) -> np.ndarray:
        """`index_area` of this camera's `frame`."""
        return index_area(self.cal, frame)


def index_area(cal: CameraCalibration, frame: np.ndarray) -> np.ndarray:
    """The part of a frame of camera `cal` (a view) that holds the frame index's bar code
    (tello_frames.stamp_frame_index, read_frame_index): in a frame of the calibration's stream layout, the
    noise below the picture (or above it), so that the code covers none of the picture; else the frame."""
    layout = cal.stream
    if layout is None or frame.shape[:2] != (layout.height, layout.width):
        return frame
    below = layout.y + cal.height
    if layout.height - below >= cal.height // 4:
        return frame[below:]
    return frame[: layout.y] if layout.y >= cal.height // 4 else frame


def index_is_checked(area: np.ndarray, frame: np.ndarray) -> bool:
    """Whether the bar code in `area` (index_area of `frame`) carries its check row
    (tello_frames.stamp_frame_index's `checked`): only a code outside the picture does."""
    return area.shape != frame.shape


__all__ = ["CameraSpec", "CameraView", "drone_world_pose", "index_area", "index_is_checked"]
