"""Milliseconds per simulated camera frame (flightstack.sim_backend.scene.render), by camera, target and
floor.

    python benchmarks/render_cost.py [--frames 100] [--batches 5] [--cv-threads N]

For the two simulated calibrations (320 × 240 downward, 960 × 720 forward), the colour discs and the ArUco
fiducial (the EDU camera's, grey at 320 × 240), on the plain and the tiled floor, with the noise drawn
around the target only (`region: markers`, the simulated lab's default) and over the whole frame (`full`):
the median over `batches` of the mean time of `frames` renders, the drone 0.85 m above the target (pixel
noise σ = 2). `--cv-threads 1` runs OpenCV on one thread: steadier on a shared machine. Prints one line
per case and a JSON summary (docs/performance.md).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import cv2
import numpy as np

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.config.rig import MISSION_CONFIGS
from flightstack.paper.geometry import Pose, relative
from flightstack.sim_backend.scene.floor import floor_view
from flightstack.sim_backend.scene.render import RenderOptions, markers_in_camera, render_markers_region
from flightstack.vision.camera_file import CameraCalibration, load_calibration

P0 = np.array([[0.1, 0.1, 0.15], [-0.1, 0.1, 0.15], [-0.1, -0.1, 0.15], [0.1, -0.1, 0.15]])
CAMERAS = MISSION_CONFIGS / "cameras"


def cameras() -> dict[str, CameraCalibration]:
    """The cases: each simulated camera with colour discs, and with the EDU camera's fiducial."""
    edu = load_calibration(CAMERAS / "tello_down_edu_sim.yaml")
    front = load_calibration(CAMERAS / "tello_front_sim.yaml")
    return {
        "320x240 discs": load_calibration(CAMERAS / "tello_down_sim.yaml"),
        "320x240 fiducial (grey)": edu,
        "960x720 discs": front,
        "960x720 fiducial": CameraCalibration(**{**front.__dict__, "markers": (), "fiducial": edu.fiducial}),
    }


def ms_per_frame(cal: CameraCalibration, floor: str, region: str, frames: int, batches: int) -> float:
    opts = RenderOptions(marker_radius_m=0.025, noise_std=2.0, region=region, floor=floor)
    drone, target = Pose.make([0.0, 0.0, 1.0], 0.2), Pose.make([0.05, -0.03, 0.0], 0.5)
    centres, normals = markers_in_camera(relative(drone, target), P0, CAMERA_MOUNTS["down"], np.zeros(3))
    view = floor_view(drone, CAMERA_MOUNTS["down"], np.zeros(3))
    rng = np.random.default_rng(0)
    for _ in range(5):  # caches: the undistortion grid, the floor's texture, the noise tables
        render_markers_region(cal, centres, normals, opts, rng, view)
    times = []
    for _ in range(batches):
        t0 = time.perf_counter()
        for _ in range(frames):
            render_markers_region(cal, centres, normals, opts, rng, view)
        times.append((time.perf_counter() - t0) / frames * 1e3)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--batches", type=int, default=5)
    ap.add_argument("--cv-threads", type=int, default=None, help="cv2.setNumThreads (default: OpenCV's)")
    args = ap.parse_args()
    if args.cv_threads is not None:
        cv2.setNumThreads(args.cv_threads)
    print(f"OpenCV threads: {cv2.getNumThreads()}")
    out: dict[str, float] = {}
    for name, cal in cameras().items():
        for floor in ("plain", "tiles"):
            for region in ("markers", "full"):
                ms = ms_per_frame(cal, floor, region, args.frames, args.batches)
                out[f"{name}, {floor}, {region}"] = round(ms, 3)
                print(f"{name:24s} floor {floor:5s} noise {region:7s} {ms:6.2f} ms/frame")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
