"""What an emulated Tello's camera sees (sim_backend/emulators/tello/view.py): the markers rendered from the
drone's and the target's poses through the calibration, each mount with its own calibration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.config.mission import CAMERA_MOUNTS
from flightstack.paper.geometry import Pose
from flightstack.sim_backend.emulators.tello.view import CameraSpec, CameraView, drone_world_pose
from flightstack.vision.camera_file import load_calibration
from flightstack.vision.markers import extract_markers
from tests.conftest import MISSIONS

P0 = ((0.1, 0.1, 0.15), (-0.1, 0.1, 0.15), (-0.1, -0.1, 0.15), (0.1, -0.1, 0.15))


def spec(mount: str, cal_file: str, start: tuple[float, float, float, float] = (0, 0, 0, 0)) -> CameraSpec:
    return CameraSpec(
        calibration=load_calibration(MISSIONS / "cameras" / cal_file).to_dict(),
        R_ic=tuple(tuple(r) for r in CAMERA_MOUNTS[mount].tolist()),
        t_ic=(0.0, 0.0, 0.0),
        feature_points=P0,
        start=start,
    )


def centroid(view: CameraView, g_wi: Pose, g_w0: Pose) -> np.ndarray:
    det = extract_markers(view.image(g_wi, g_w0), view.cal)
    assert det.pixels is not None, det.reason
    return np.asarray(det.pixels).mean(axis=0)


def test_drone_world_pose_turns_the_emulator_frame_into_the_world() -> None:
    """The emulator flies x forward, y right (cm), yaw clockwise (deg) from its start in Σw (FLU)."""
    g = drone_world_pose((1.0, 2.0, 0.0, math.pi / 2), (100.0, 50.0, 80.0), -90.0)
    assert np.allclose(g.p, [1.0 + 0.5, 2.0 + 1.0, 0.8]) and g.theta == pytest.approx(math.pi)


def test_the_downward_image_follows_the_drone_and_the_target_with_the_expected_signs() -> None:
    view = CameraView(spec("down", "tello_down_sim.yaml"))
    assert view.image(Pose.make([0, 0, 1.0], 0), Pose.make([0, 0, 0], 0)).shape == (240, 320, 3)
    hover = Pose.make([-0.15, 0.0, 1.0], 0.0)  # the target 0.15 m ahead, 0.85 m below the camera
    c0 = centroid(view, hover, Pose.make([0.0, 0.0, 0.0], 0.0))
    # the target ahead of the drone: the top half of the image (camera y = the body's backward axis)
    assert c0[1] < 120 - 30 and abs(c0[0] - 160) < 2
    # the target moves forward (world x): up in the image; to the left (world y): left in the image
    assert centroid(view, hover, Pose.make([0.1, 0.0, 0.0], 0.0))[1] < c0[1] - 20
    assert centroid(view, hover, Pose.make([0.0, 0.1, 0.0], 0.0))[0] < c0[0] - 20
    # the drone yaws counter-clockwise: the target ahead swings to its right, right in the image
    assert centroid(view, Pose.make([-0.15, 0.0, 1.0], 0.3), Pose.make([0.0, 0.0, 0.0], 0.0))[0] > c0[0] + 8


def test_the_forward_camera_has_its_own_calibration_and_sees_what_is_ahead() -> None:
    view = CameraView(spec("forward", "tello_front_sim.yaml"))
    drone = Pose.make([-1.5, 0.0, 0.65], 0.0)  # 1.5 m behind the markers, 0.5 m above them
    img = view.image(drone, Pose.make([0.0, 0.0, 0.0], 0.0))
    assert img.shape == (720, 960, 3)
    c0 = centroid(view, drone, Pose.make([0.0, 0.0, 0.0], 0.0))
    assert abs(c0[0] - 480) < 3 and c0[1] > 360  # below the horizon
    assert centroid(view, drone, Pose.make([0.0, 0.2, 0.0], 0.0))[0] < c0[0] - 50  # left in the world
    # turned away (yaw π): nothing of the target in the image
    back = view.image(Pose.make([-1.5, 0.0, 0.65], math.pi), Pose.make([0.0, 0.0, 0.0], 0.0))
    assert extract_markers(back, view.cal).pixels is None
