"""The static part of the scene, from the mission: the world's axes, each body's label, colour and axes,
each drone's camera (extrinsic and Pinhole frustum), the GP expert regions and the training inputs.

Frames: Σw (world, z up on the lab rigs; on the ideal rig z is the cameras' optical axis, as in the paper's
simulation); Σi the drone's yaw-only body frame; Σc the camera (x right, y down, z optical axis), fixed in
Σi by the mount extrinsic p_i = R_ic p_c + t_ic (flightstack.config.mission.CAMERA_MOUNTS, offset in m).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from flightstack.viewer import layout

if TYPE_CHECKING:
    from rerun import RecordingStream

    from flightstack.config.mission import Mission

_log = logging.getLogger(__name__)

IMAGE_PLANE_M = 0.3
"""Where the frustum's image plane is drawn (m along the optical axis)."""
NOMINAL_PX = 100.0
"""The ideal camera has no image bounds: its frustum is drawn as a virtual image of ±1/λ in normalised
coordinates (a 90° field of view for λ = 1) at NOMINAL_PX pixels per unit."""
REGION_MARGIN_M = 0.25
"""Expert regions are bands, open at both extremes: boxes are drawn over the run's extent plus this."""


def _rgba(rgb: tuple[int, int, int], alpha: int = 255) -> tuple[int, int, int, int]:
    return (*rgb, alpha)


def log_world(rr: ModuleType, stream: RecordingStream) -> None:
    """Σw: right-handed, z up."""
    stream.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)


def log_bodies(rr: ModuleType, stream: RecordingStream, mode: str, ids: Sequence[int]) -> None:
    """Label, colour and axes (x red, y green, z blue; 0.15 m) of the target, each drone and each estimate
    ḡ_w,i, drawn in the body's frame (its Transform3D moves them), and the colour of each trail."""
    bodies = [(layout.target(mode), "target (true g_w0)", layout.TARGET_RGB, 0.06, "target")]
    for i in ids:
        c = layout.drone_rgb(i)
        bodies.append((layout.drone(mode, i), f"drone {i}", c, 0.05, f"drone{i}"))
        bodies.append((layout.estimate(mode, i), f"ḡ_w,{i} (drone {i}'s estimate)", c, 0.03, f"estimate{i}"))
    for path, label, rgb, radius, name in bodies:
        alpha = 150 if name.startswith("estimate") else 255
        stream.log(
            path,
            rr.Points3D([[0.0, 0.0, 0.0]], labels=[label], colors=[_rgba(rgb, alpha)], radii=[radius]),
            rr.TransformAxes3D(0.15),
            static=True,
        )
        stream.log(
            layout.trail(mode, name),
            rr.LineStrips3D.from_fields(colors=[_rgba(rgb, alpha)], radii=[0.004]),
            static=True,
        )


def _intrinsics(mission: Mission, k: int) -> tuple[np.ndarray, tuple[float, float], str]:
    """(K (3, 3) px, (width, height) px, where from) of drone k's camera: its calibration file, else the
    nominal frustum of the ideal camera (NOMINAL_PX)."""
    d = mission.drones[k]
    if d.camera is not None and d.camera.calibration is not None:
        from flightstack.vision.camera_file import CalibrationError, load_calibration

        path = mission.resolve(d.camera.calibration)
        try:
            cal = load_calibration(path)
            return np.asarray(cal.camera_matrix, dtype=float), (cal.width, cal.height), str(path)
        except (OSError, CalibrationError, ValueError) as exc:  # the run dir moved to another machine
            _log.warning("drone %s: calibration %s not usable (%s); nominal frustum", d.id, path, exc)
    lam = mission.camera_model(k).focal_length
    f = NOMINAL_PX * lam
    size = 2.0 * NOMINAL_PX
    K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return K, (size, size), f"nominal (λ = {lam:g})"


def log_cameras(
    rr: ModuleType, stream: RecordingStream, mission: Mission, mode: str, ids: Sequence[int]
) -> None:
    """Each drone's camera Σc in its body frame (static Transform3D: R_ic, t_ic) and its Pinhole
    (intrinsics of the calibration, image plane drawn at IMAGE_PLANE_M)."""
    index = {d.id: k for k, d in enumerate(mission.drones)}
    for i in ids:
        k = index.get(i)
        if k is None:
            continue
        cam = mission.camera_model(k)
        stream.log(
            layout.camera(mode, i),
            rr.Transform3D(
                translation=np.asarray(cam.t_ic, dtype=float), mat3x3=np.asarray(cam.R_ic, dtype=float)
            ),
            static=True,
        )
        K, (w, h), _ = _intrinsics(mission, k)
        stream.log(
            layout.image(mode, i),
            rr.Pinhole(
                image_from_camera=K,
                resolution=[w, h],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=IMAGE_PLANE_M,
                color=_rgba(layout.drone_rgb(i)),
            ),
            static=True,
        )


def region_boxes(mission: Mission, extent_xyz: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(mins (3,), sizes (3,), label) of each drone's expert region (mission order): band k of gp.regions
    along its axis (flightstack.learning.training.bands), the open ends and the other axes over the
    points `extent_xyz` (K, 3; m) plus REGION_MARGIN_M, z over the points ± 0.05 m."""
    from flightstack.learning.training import band_text, bands

    pts = np.asarray(extent_xyz, dtype=float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        pts = np.zeros((1, 3))
    lo = pts.min(axis=0) - REGION_MARGIN_M
    hi = pts.max(axis=0) + REGION_MARGIN_M
    lo[2], hi[2] = pts[:, 2].min() - 0.05, pts[:, 2].max() + 0.05
    a = 0 if mission.gp.regions.axis == "x" else 1
    out = []
    for d, (b_lo, b_hi) in zip(mission.drones, bands(mission), strict=True):
        mins, maxs = lo.copy(), hi.copy()
        mins[a] = b_lo if math.isfinite(b_lo) else min(lo[a], b_hi - REGION_MARGIN_M)
        maxs[a] = b_hi if math.isfinite(b_hi) else max(hi[a], b_lo + REGION_MARGIN_M)
        label = f"expert of drone {d.id}: {band_text(mission.gp.regions.axis, b_lo, b_hi)}"
        out.append((mins, maxs - mins, label))
    return out


def log_regions(rr: ModuleType, stream: RecordingStream, mission: Mission, extent_xyz: np.ndarray) -> None:
    """Each drone's GP expert region as a wireframe box under /mission/regions/drone<i> (static)."""
    for d, (mins, sizes, label) in zip(mission.drones, region_boxes(mission, extent_xyz), strict=True):
        stream.log(
            layout.region(d.id),
            rr.Boxes3D(
                mins=[mins],
                sizes=[sizes],
                labels=[label],
                colors=[_rgba(layout.drone_rgb(d.id), 200)],
                fill_mode="majorwireframe",
            ),
            static=True,
        )


def log_training(
    rr: ModuleType, stream: RecordingStream, inputs: Mapping[int, np.ndarray], order: Sequence[int]
) -> None:
    """Each expert's training inputs X (M, 4: ḡ_w,i = [x, y, z, θ]) as points at their positions (static)."""
    for i in order:
        X = inputs.get(i)
        if X is None or np.asarray(X).size == 0:
            continue
        X = np.asarray(X, dtype=float)
        stream.log(
            layout.training(i),
            rr.Points3D(
                X[:, :3],
                colors=[_rgba(layout.drone_rgb(i), 220)],
                radii=[0.02],
                labels=[f"training input of expert {i}"] * X.shape[0],
                show_labels=False,
            ),
            static=True,
        )
