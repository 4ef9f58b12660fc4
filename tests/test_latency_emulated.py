"""The camera's latency measured on an emulated Tello against its recorded capture times: the camera
(a child process, the `tello` video link: 300 ms + U(0, 100 ms), 30 fps, 2 % lost) looks down on the
still target while the drone yaws one way at a varying rate; the driver's receiver stamps each frame
with its plain decode time; the markers found in each frame are timed against those predicted from the
drone's poses (what motion capture would give). The estimate's mean is within ±10 ms of the true mean
capture → decode delay (the emulator's records, by each frame's bar-coded index).

Loopback only: the camera sends from 127.0.0.131.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

pytest.importorskip("av")

from flightstack.calibration.latency_video import predicted_pixels, video_delay
from flightstack.config.links import LinkSpec
from flightstack.drivers.tello_camera import VideoReceiver
from flightstack.paper.geometry import Pose
from flightstack.ports import free_udp_port
from flightstack.sim_backend.emulators.tello import TelloEmulator, read_frame_index
from flightstack.sim_backend.emulators.tello_video_process import SharedTarget, VideoPath, VideoProcess
from flightstack.sim_backend.emulators.tello_view import drone_world_pose
from flightstack.vision.camera_file import load_calibration
from flightstack.vision.markers import extract_markers
from tests.conftest import Bound
from tests.test_emulated_camera import CAL, down_camera

pytestmark = pytest.mark.system

IP_CAMERA = "127.0.0.131"
HEIGHT_CM = 90.0
FREQS_HZ = (0.37, 0.83, 1.31)


def yaw_deg(t: float) -> float:
    """The calibration pattern: clockwise at 1 rad/s ± 0.8 rad/s of incommensurate sines (never back)."""
    wobble = sum(math.sin(2 * math.pi * f * t + k) / (2 * math.pi * f) for k, f in enumerate(FREQS_HZ))
    return math.degrees(t + 0.3 * wobble)


def _fly_pattern(emu: TelloEmulator, poses: list[tuple[float, float]], stop: threading.Event) -> None:
    """Publish the pattern's pose every 10 ms (the motion capture's record: (time, yaw deg))."""
    t0 = time.monotonic()
    cam = emu.remote_video
    assert cam is not None
    while not stop.is_set():
        t = time.monotonic()
        yaw = yaw_deg(t - t0)
        cam.publish(True, 1, False, (0.0, 0.0, HEIGHT_CM), yaw)  # type: ignore[attr-defined]
        poses.append((t, yaw))
        cam.sync(emu)  # type: ignore[attr-defined]
        stop.wait(0.01)


def test_the_camera_latency_is_recovered_within_10_ms(safety_bound: Bound) -> None:
    link = LinkSpec(latency_s=0.3, jitter_s=0.1, rate_hz=30.0, loss=0.02)
    spec = down_camera()
    target = SharedTarget()
    target.write(0.0, 0.0, 0.0)  # right below the drone
    port = free_udp_port()
    path = VideoPath(seed=4, drone=1, link=link.model_dump())
    cam = VideoProcess(spec, IP_CAMERA, ("127.0.0.1", port), target, fps=30.0, path=path)
    emu = TelloEmulator(IP_CAMERA, state_port=free_udp_port(), video_port=port, video_size=cam.size)
    emu.use_remote_video(cam)  # not started: the test flies the camera itself
    rx = VideoReceiver(port, "127.0.0.1")
    poses: list[tuple[float, float]] = []
    frames: list[tuple[float, np.ndarray]] = []
    stop = threading.Event()
    feeder = threading.Thread(target=_fly_pattern, args=(emu, poses, stop), daemon=True)
    try:
        cam.start()
        cam.wait_ready()
        feeder.start()
        assert rx.wait_first_frame(10.0), emu.errors
        last, t_end = 0, time.monotonic() + 8.0
        while time.monotonic() < t_end:
            item = rx.latest()
            if item is not None and item[0] != last:
                last = item[0]
                frames.append((item[1], item[2]))  # plain decode time: no latency subtracted
            time.sleep(0.003)
        stop.set()
        feeder.join(1.0)
        cam.sync(emu)
        records = {i: tc for i, tc, _ in list(emu.video_capture_log)}
    finally:
        stop.set()
        rx.close()
        cam.close()
    cal = load_calibration(CAL)
    P0, R_ic, t_ic = (np.array(a, dtype=float) for a in (spec.feature_points, spec.R_ic, spec.t_ic))
    g_w0 = Pose.make([0.0, 0.0, 0.0], 0.0)
    t_pose = np.array([t for t, _ in poses])
    predicted = np.array(
        [predicted_pixels(cal, drone_world_pose(spec.start, (0.0, 0.0, HEIGHT_CM), y), g_w0, P0, R_ic, t_ic)
         for _, y in poses]
    )  # fmt: skip
    t_frames = np.array([t for t, _ in frames])
    found = []
    for _, img in frames:
        det = extract_markers(img, cal)
        found.append(det.pixels if det.ok else None)
    t0 = time.perf_counter()
    est = video_delay(t_pose, predicted, t_frames, found)
    solve_ms = 1e3 * (time.perf_counter() - t0)
    truth = np.array(
        [t - records[read_frame_index(img)] for t, img in frames if read_frame_index(img) in records]
    )
    error_ms = 1e3 * (est.mean_s - truth.mean())
    print(
        f"true capture → decode: mean {1e3 * truth.mean():.1f} ms, sd {1e3 * truth.std():.1f} ms "
        f"({truth.size} frames); estimate: mean {1e3 * est.mean_s:.1f} ms, sd {1e3 * est.sd_s:.1f} ms, peak "
        f"{1e3 * est.peak_s:.1f} ms (r {est.correlation:.3f}), {est.n_used}/{est.n_frames} frames timed; "
        f"error {error_ms:+.1f} ms; solved in {solve_ms:.0f} ms"
    )
    assert truth.size > 150 and est.n_used > 0.5 * len(frames), (truth.size, est)
    assert abs(error_ms) <= 10.0, error_ms
    assert abs(1e3 * (est.sd_s - truth.std())) <= 10.0, (est.sd_s, truth.std())
    safety_bound("latency estimate's solve time", solve_ms, 5000.0)
