"""Builds the ideal simulation backend (the `ideal` rig, backend sim_ideal) from a validated mission.

The target follows the experiment's law inside the world: the paper simulation's Duffing-like field, or
the paper experiment's square law (eq. scamper_vel, or the unicycle law for a non-holonomic robot: the
rig's robot.kinematics) evaluated on the target's exact pose and the world's
time. Each drone's exact camera uses the same camera model as its observer: the normalised image plane
with the experiment's mount and offset when it names a camera, else the focal length of `camera:`.
"""

from __future__ import annotations

import numpy as np

from flightstack.config.mission import Mission
from flightstack.paper.geometry import Pose, compose, inverse
from flightstack.paper.target_motion import DuffingField, DuffingParams
from flightstack.sim_backend.ideal import IdealSimBackend
from flightstack.sim_backend.world import World


def initial_drone_pose(mission: Mission, index: int) -> Pose:
    """g_wi(0) = g_w0(0) g_d⁻¹ · offset: at the desired relative pose, then displaced by the offset."""
    d = mission.drones[index]
    g_w0 = mission.target.initial_pose.pose()
    return compose(compose(g_w0, inverse(d.desired_pose.pose())), d.initial_offset.pose())


def build_ideal(mission: Mission) -> IdealSimBackend:
    world = World(
        target_pose=mission.target.initial_pose.pose(),
        target_field=lambda g: np.zeros(4),
        drone_poses={d.id: initial_drone_pose(mission, k) for k, d in enumerate(mission.drones)},
        target_substeps=mission.target.substeps,
    )
    if mission.target.motion == "duffing":
        prm = DuffingParams(**mission.target.duffing.model_dump())
        world.target_field = DuffingField(prm)  # a class, not a lambda: the compiled loop reads its prm
    else:  # the square law, on the world's clock (the reference starts at t = 0)
        law = mission.target_law()  # the paper's (omni) or the unicycle law (Mission.target_law)
        world.target_field = lambda g: law.command(world.t, g)
    P0 = np.array(mission.target.feature_points, dtype=float)
    cams = {d.id: mission.camera_model(k) for k, d in enumerate(mission.drones)}
    return IdealSimBackend(world, mission.dt_s, P0, cams, {d.id: d.sees_target for d in mission.drones})
