"""Builds the ideal simulation backend from a validated mission."""

from __future__ import annotations

import numpy as np

from flightstack.config.mission import Mission
from flightstack.paper.geometry import Pose, compose, inverse
from flightstack.paper.projection import CameraModel
from flightstack.paper.target_motion import DuffingParams, duffing_body_velocity
from flightstack.sim_backend.ideal import IdealSimBackend
from flightstack.sim_backend.world import World


def initial_drone_pose(mission: Mission, index: int) -> Pose:
    """g_wi(0) = g_w0(0) g_d⁻¹ · offset: at the desired relative pose, then displaced by the offset."""
    d = mission.drones[index]
    g_w0 = mission.target.initial_pose.pose()
    return compose(compose(g_w0, inverse(d.desired_pose.pose())), d.initial_offset.pose())


def build_ideal(mission: Mission) -> IdealSimBackend:
    prm = DuffingParams(**mission.target.duffing.model_dump())
    world = World(
        target_pose=mission.target.initial_pose.pose(),
        target_field=lambda g: duffing_body_velocity(g, prm),
        drone_poses={d.id: initial_drone_pose(mission, k) for k, d in enumerate(mission.drones)},
        target_substeps=mission.target.substeps,
    )
    P0 = np.array(mission.target.feature_points, dtype=float)
    cam = CameraModel(focal_length=mission.camera.focal_length)
    return IdealSimBackend(world, mission.dt_s, P0, cam, {d.id: d.sees_target for d in mission.drones})
