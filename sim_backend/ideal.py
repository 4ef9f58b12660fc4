"""The ideal backend of the paper's simulation: exact poses, an exact camera, drones that fly V exactly.

Implements flightstack.hal (Clock, Drone, Camera, PoseSource). Nothing in flightstack imports this at
module level; the runner loads it by the mission's `backend: sim_ideal` through the registry.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from flightstack.hal import DroneState, FlightPhase, Frame, StampedPose
from flightstack.paper import kernels as kern
from flightstack.paper.geometry import Pose
from flightstack.paper.projection import CameraModel, measure_vector
from flightstack.sim_backend.world import World


class SteppedWorld(Protocol):
    """A world integrated in virtual time: `t` (s) and `step(dt)` (s)."""

    t: float

    def step(self, dt: float) -> None: ...


class VirtualClock:
    """Virtual time: sleep_until(t) integrates the world up to t in steps of at most dt."""

    def __init__(self, world: SteppedWorld, dt: float) -> None:
        self.world = world
        self.dt = dt

    def now(self) -> float:
        return self.world.t

    def sleep_until(self, t: float) -> None:
        while self.world.t < t - 1e-12:
            self.world.step(min(self.dt, t - self.world.t))


class IdealDrone:
    """A drone that realises its body-velocity command instantly and exactly."""

    def __init__(self, world: World, drone_id: int) -> None:
        self.world = world
        self.id = drone_id
        self.flying = True  # the paper's simulation starts airborne
        self.commands = 0

    def connect(self) -> None:
        pass

    def takeoff(self) -> None:
        self.flying = True

    def land(self) -> None:
        self.world.command_drone(self.id, np.zeros(4))
        self.flying = False

    def emergency_stop(self) -> None:
        self.land()

    def send_body_velocity(self, V: np.ndarray) -> None:
        V = np.asarray(V, dtype=float)
        if V.shape != (4,) or not all(map(math.isfinite, V.tolist())):
            raise ValueError(f"body velocity must be 4 finite numbers, got {V!r}")
        if self.flying:
            self.world.command_drone(self.id, V)
            self.commands += 1

    def state(self) -> DroneState:
        """Full battery, live link. height_m: the ideal world has no ground and its z is the camera's
        optical axis, not a height (a drone 1.5 m from the target along it may sit at z = −1.5), so a
        landed drone is on the ground by definition: 0.0; a flying one reports its world z, which may be
        negative (nothing reads it as below ground: the ideal rig flies without the safety layer)."""
        return DroneState(
            battery_pct=100.0,
            height_m=float(self.world.drones[self.id].pose.p[2]) if self.flying else 0.0,
            link_alive=True,
            flying=self.flying,
            phase=str(FlightPhase.AIRBORNE if self.flying else FlightPhase.GROUND),
        )

    def close(self) -> None:
        self.land()


class IdealCamera:
    """Returns the exact feature vector f(g_i0) of the true relative pose (paper eq. f)."""

    def __init__(
        self, world: World, drone_id: int, P0: np.ndarray, cam: CameraModel, sees_target: bool = True
    ):
        self.world = world
        self.id = drone_id
        self.P0 = P0
        self.cam = cam
        self.sees_target = sees_target

    def latest(self) -> Frame:
        if not self.sees_target:
            return Frame(self.world.t, None, None)
        # f(g_i0), g_i0 = g_wi⁻¹ g_w0: geometry.relative and projection.measure on pose vectors (the same
        # kernels and numbers, without the Pose in between; None where measure raises not visible)
        g_i0 = np.empty(4)
        kern.relative4(self.world.drones[self.id].pose.as_vector(), self.world.target.pose.as_vector(), g_i0)
        return Frame(self.world.t, None, measure_vector(g_i0, self.P0, self.cam))


class TruthPoseSource:
    """Motion capture without noise: bodies are 'drone<id>' and 'target'."""

    def __init__(self, world: World) -> None:
        self.world = world

    def latest(self, body: str) -> StampedPose | None:
        if body == "target":
            return StampedPose(self.world.t, self.world.target.pose)
        if body.startswith("drone"):
            try:
                return StampedPose(self.world.t, self.world.drones[int(body[5:])].pose)
            except (KeyError, ValueError):
                return None
        return None


class IdealSimBackend:
    """Backend of the paper's simulation (hal.Backend)."""

    simulated = True

    def __init__(
        self,
        world: World,
        dt: float,
        P0: np.ndarray,
        cams: dict[int, CameraModel],
        sees_target: dict[int, bool],
    ) -> None:
        """cams: each drone's camera model (focal length, mount extrinsic) by drone id."""
        self.world = world
        self.clock = VirtualClock(world, dt)
        self._drones = {i: IdealDrone(world, i) for i in world.drones}
        self._cams = {i: IdealCamera(world, i, P0, cams[i], sees_target.get(i, True)) for i in world.drones}
        self._poses = TruthPoseSource(world)

    def drone(self, drone_id: int) -> IdealDrone:
        return self._drones[drone_id]

    def camera(self, drone_id: int) -> IdealCamera:
        return self._cams[drone_id]

    def pose_source(self) -> TruthPoseSource:
        return self._poses

    def target(self) -> None:
        return None  # the target follows its velocity field inside the world

    def truth(self) -> tuple[Pose, dict[int, Pose]]:
        """(g_w0, {id: g_wi}) now: sim-only access for metrics, never used by agents."""
        return self.world.target.pose, {i: b.pose for i, b in self.world.drones.items()}

    def heartbeat(self) -> None:
        """No watchdog in simulation."""

    def close(self) -> None:
        for d in self._drones.values():
            d.close()
