"""The paper's experiment target law (Sec. 6, eq. scamper_vel): the ground robot drives a square.

Reference g_d(t): a point moving at `speed` (m/s) along a square of side `side` (m) centred at the
origin of Σw, counter-clockwise, starting at the square's corner (−side/2, −side/2), with yaw
θ_d(t) = θ_d(0) + 2π t / T_lap (one full rotation per lap, T_lap = 4·side/speed).
v_d is the reference's body velocity, so R(θ_d) v_d is its world velocity.

Robot command (the paper's eq. scamper_vel, with Ad_{−R(θ)} read as Ad_{Rᵀ(θ)}, world → body):
    V_w0 = Ad_{Rᵀ(θ_w0)} ( [R(θ_d) v_d ; ω_d] − k vec(g_w0 g_d⁻¹) ),   k = 0.05 s⁻¹ in the paper.
The robot moves in the plane: the z components are zeroed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightstack.paper.geometry import Pose, compose, inverse, rotate_twist, vec


@dataclass(frozen=True)
class SquareLaw:
    side: float = 1.0  # m
    speed: float = 0.1  # m/s
    gain: float = 0.05  # 1/s, the paper's 0.05
    theta0: float = 0.0  # rad, reference yaw at t = 0

    @property
    def lap_time(self) -> float:
        return 4.0 * self.side / self.speed

    def reference(self, t: float) -> tuple[Pose, np.ndarray]:
        """(g_d(t), world velocity [ẋ, ẏ, 0, ω_d]) of the reference at time t (s)."""
        h = self.side / 2.0
        s = (t * self.speed) % (4.0 * self.side)  # arc length along the lap
        leg, r = int(s // self.side), s % self.side
        corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
        dirs = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)]
        (x0, y0), (dx, dy) = corners[leg], dirs[leg]
        omega = 2.0 * math.pi / self.lap_time
        g = Pose.make([x0 + r * dx, y0 + r * dy, 0.0], self.theta0 + omega * t)
        return g, np.array([self.speed * dx, self.speed * dy, 0.0, omega])

    def command(self, t: float, g_w0: Pose) -> np.ndarray:
        """Body-velocity command V_w0 (m/s, rad/s) for the robot at measured pose g_w0."""
        g_d, v_world = self.reference(t)
        err = vec(compose(g_w0, inverse(g_d)))
        V_world = v_world - self.gain * err
        V = rotate_twist(-g_w0.theta, V_world)  # Ad_{Rᵀ(θ_w0)}
        V[2] = 0.0
        return V
