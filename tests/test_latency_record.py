"""The latency calibration's recorder (flightstack.calibration.latency_record) over the hal interfaces, on
a simulated clock: a drone that acts on each command 60 ms + U(0, 20 ms) late through a 0.1 s lag, motion
capture at 120 Hz, a camera whose frames (30 fps) become available 300 ms + U(0, 100 ms) after capture.
The recorded session gives back both delays (the camera's: of the frames seen, the newest available at
each poll, which favours the earlier ones)."""

from __future__ import annotations

import math

import numpy as np

from flightstack.calibration.latency_record import Geometry, rc_levels, record_rc, record_video
from flightstack.calibration.latency_video import predicted_pixels
from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.hal import Frame, StampedPose
from flightstack.paper.geometry import Pose
from flightstack.vision.camera_file import load_calibration
from tests.conftest import MISSIONS

CAL = MISSIONS / "cameras" / "tello_down_sim.yaml"
P0 = np.array([(0.1, 0.1, 0.15), (-0.1, 0.1, 0.15), (-0.1, -0.1, 0.15), (0.1, -0.1, 0.15)])
GEOMETRY = Geometry(str(CAL), CAMERA_MOUNTS["down"], np.zeros(3), P0, "drone1", "target")
HEIGHT_M = 0.9


class World:
    """The simulated clock, a drone's yaw (rad) and its history, on 1 ms steps."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.t, self.yaw, self.rate = 0.0, 0.0, 0.0
        self.pending: list[tuple[float, float]] = []  # (when it acts, yaw rate rad/s)
        self.target_rate = 0.0
        self.history_t, self.history_yaw = [0.0], [0.0]
        self.frames: dict[int, tuple[float, float]] = {}  # index -> (capture time, available time)

    def now(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        end = self.t + dt
        while self.t < end:
            self.t += 0.001
            for due, v in [p for p in self.pending if p[0] <= self.t]:
                self.target_rate = v
                self.pending.remove((due, v))
            self.rate += (self.target_rate - self.rate) * (1.0 - math.exp(-0.001 / 0.1))
            self.yaw += self.rate * 0.001
            self.history_t.append(self.t)
            self.history_yaw.append(self.yaw)

    def yaw_at(self, t: float) -> float:
        return float(np.interp(t, self.history_t, self.history_yaw))

    # hal.Drone
    def send_body_velocity(self, V: np.ndarray) -> None:
        self.pending.append((self.t + 0.06 + self.rng.uniform(0.0, 0.02), float(V[3])))

    # hal.PoseSource
    def latest(self, body: str) -> StampedPose | None:
        ts = math.floor(self.t * 120.0) / 120.0
        if body == "target":
            return StampedPose(ts, Pose.make([0.0, 0.0, 0.0], 0.0))
        return StampedPose(ts, Pose.make([0.0, 0.0, HEIGHT_M], self.yaw_at(ts)))


class LateCamera:
    """hal.Camera: frames taken every 1/30 s, each available 300 ms + U(0, 100 ms) later (in order),
    stamped when available, with the markers' true pixels as `features`."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.cal = load_calibration(CAL)
        self.pixels: dict[int, np.ndarray] = {}

    def latest(self) -> Frame | None:
        w = self.world
        k = int(w.t * 30.0)
        while k not in w.frames and k >= 0:
            w.frames[k] = (k / 30.0, k / 30.0 + 0.3 + w.rng.uniform(0.0, 0.1))
            k -= 1
        ready = [i for i, (_, ta) in w.frames.items() if ta <= w.t]
        if not ready:
            return None
        i = max(ready)
        tc, ta = w.frames[i]
        if i not in self.pixels:
            g_wi = Pose.make([0.0, 0.0, HEIGHT_M], w.yaw_at(tc))
            g_w0 = Pose.make([0.0, 0.0, 0.0], 0.0)
            self.pixels[i] = predicted_pixels(self.cal, g_wi, g_w0, P0, GEOMETRY.R_ic, GEOMETRY.t_ic)
        return Frame(ta, None, self.pixels[i])


def test_the_recorded_video_session_gives_back_the_cameras_delay() -> None:
    world = World(seed=1)
    cam = LateCamera(world)
    record = record_video(world, cam, world, GEOMETRY, lambda f: f.features, world.now, world.sleep, 10.0)
    est = record.estimate()
    capture = {ta: tc for tc, ta in world.frames.values()}
    ages = np.array([t - capture[t] for t in record.t_frames])  # the frames seen (the newest available)
    assert ages.size > 150 and record.t_pose.size > 1000
    assert abs(est.mean_s - ages.mean()) < 0.003 and abs(est.sd_s - ages.std()) < 0.003, (est, ages.mean())


def test_the_recorded_rc_session_gives_back_the_commands_delay() -> None:
    world = World(seed=2)
    record = record_rc(world, world, "drone1", world.now, world.sleep, rc_levels(20, seed=3))
    est = record.estimate()
    assert abs(est.mean_s - 0.07) < 0.01 and abs(est.tau_s - 0.1) <= 0.03, est
    assert est.n_steps >= 15
