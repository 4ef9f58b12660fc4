"""The simulated world: rigid bodies moving with zero-order-held planar body velocities.

Integration choice: every body's body velocity is held constant between control ticks (as a real
drone or robot holds its last command), and the pose is advanced with the closed-form exponential of
planar SE(3), g ← g exp(V̂ dt). That is exact for the held input, so the stiff gains of the paper
(k = 100, k_s = 70) cost no integration error and no step-size limit beyond the control loop's own
sampling (k·dt ≪ 1). RK4 would only approximate the same flow. The target's velocity field is
re-evaluated `substeps` times per tick (1 = the target is commanded at the control rate, like a real
robot; more approximates a continuously varying field).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from flightstack.paper.geometry import Pose, integrate_body_velocity


@dataclass
class Body:
    pose: Pose
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(4))


class World:
    """Truth of the simulation: target 0 and drones by id; time in seconds."""

    def __init__(
        self,
        target_pose: Pose,
        target_field: Callable[[Pose], np.ndarray],
        drone_poses: dict[int, Pose],
        target_substeps: int = 1,
    ) -> None:
        self.t = 0.0
        self.target = Body(target_pose)
        self.target_field = target_field
        self.drones = {i: Body(p) for i, p in drone_poses.items()}
        self.substeps = target_substeps

    def command_drone(self, drone_id: int, V: np.ndarray) -> None:
        self.drones[drone_id].velocity = np.array(V, dtype=float)

    def step(self, dt: float) -> None:
        """Advance every body by dt seconds (exact for the held inputs)."""
        h = dt / self.substeps
        tgt = self.target
        for _ in range(self.substeps):
            tgt.velocity = self.target_field(tgt.pose)
            tgt.pose = integrate_body_velocity(tgt.pose, tgt.velocity, h)
        for body in self.drones.values():
            body.pose = integrate_body_velocity(body.pose, body.velocity, dt)
        self.t += dt
