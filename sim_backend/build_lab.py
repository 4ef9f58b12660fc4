"""Builds the simulated lab backend (`backend: sim_lab`) from a validated mission."""

from __future__ import annotations

import numpy as np

from flightstack.comms.bus import Bus
from flightstack.comms.delayed_bus import DelayedBus
from flightstack.config.derive import derive
from flightstack.config.links import LINKS, LinkDelays
from flightstack.config.mission import Mission
from flightstack.drivers.tello.rc import RcGains
from flightstack.paper.geometry import Pose
from flightstack.sim_backend.build import initial_drone_pose
from flightstack.sim_backend.ideal import VirtualClock
from flightstack.sim_backend.lab import (
    LabWorld,
    MocapParams,
    MocapSim,
    RenderedCamera,
    RobotParams,
    ScamperSim,
    TelloParams,
    TelloSim,
    camera_extrinsic,
)
from flightstack.sim_backend.scene.render import RenderOptions
from flightstack.vision.camera_file import load_calibration

CAMERA_RATE_HZ = 30.0
"""Frames per second of a delayed camera whose link names no rate (the Tello streams 30 fps)."""


class _LinkGenerators:
    """One LinkDelays per (link, device), each with its own generator seeded from the mission's seed, the
    link and the device, so that adding a link never changes another's draws."""

    def __init__(self, mission: Mission) -> None:
        self.mission = mission

    def get(self, name: str, device: int) -> LinkDelays:
        spec = self.mission.links.link(name)
        key = [self.mission.seed, LINKS.index(name), device]
        return LinkDelays(spec, np.random.default_rng(key))


class LabSimBackend:
    """hal.Backend of the simulated lab (virtual clock; `truth()` is the simulator's)."""

    simulated = True

    def __init__(self, mission: Mission) -> None:
        self.mission = mission
        rng = np.random.default_rng(mission.seed)
        sim = mission.sim
        g_w0 = mission.target.initial_pose.pose()
        r = mission.target.robot
        self.world: LabWorld

        def clock_now() -> float:  # the models read the world's virtual time
            return self.world.t

        links = _LinkGenerators(mission)
        self.links = links
        robot = ScamperSim(
            g_w0,
            derive(
                RobotParams,
                r,
                rename={"max_speed_mps": "max_speed"},
                skip={"kinematics", "min_turn_radius_m"},
                kinematics=mission.robot_kinematics(),
                min_turn_radius_m=r.min_turn_radius_m or 0.0,
            ),
            clock_now,
            links.get("robot", 0),
        )
        t = sim.tello
        drones = {}
        for k, d in enumerate(mission.drones):
            params = derive(
                TelloParams,
                t,
                skip={"true_rc_gains"},
                true_gains=RcGains(**t.true_rc_gains.model_dump()),
                cmd_gains=RcGains(**d.rc_gains.model_dump()),
            )
            # on the ground below the desired pose relative to the target's start, plus the offset
            above = initial_drone_pose(mission, k)
            start = Pose(np.array([above.p[0], above.p[1], 0.0]), above.theta)
            drones[d.id] = TelloSim(
                d.id, start, params, clock_now, links.get("rc", d.id), links.get("state", d.id)
            )
        m = sim.mocap
        self.mocap = MocapSim(
            derive(MocapParams, m),
            np.random.default_rng(rng.integers(2**32)),
            links.get("mocap", 0),
            clock_now,
        )
        self.world = LabWorld(robot, drones, self.mocap)
        self.world.step(0.0)  # first motion-capture frame at t = 0
        self.clock = VirtualClock(self.world, sim.world_dt_s)
        P0 = np.array(mission.target.feature_points, dtype=float)
        opts = RenderOptions(
            marker_radius_m=sim.render.marker_radius_m,
            noise_std=sim.render.noise_std,
            blur_px=sim.render.blur_px,
            region=sim.render.region,
            floor=sim.render.floor,
        )
        self.calibrations = {}
        self._cams = {}
        for d in mission.drones:
            assert d.camera is not None and d.camera.calibration is not None  # the schema, for sim_lab
            cal = load_calibration(mission.resolve(d.camera.calibration))
            R_ic, t_ic = camera_extrinsic(d.camera.mount, d.camera.offset)
            self.calibrations[d.id] = cal
            self._cams[d.id] = RenderedCamera(
                self.world, d.id, cal, R_ic, t_ic, P0, opts, np.random.default_rng(rng.integers(2**32))
            )
            if sim.render.model == "centres":
                self._cams[d.id].centres_only(sim.render.centre_noise_px)
            video = mission.links.link("video")
            if not video.perfect:
                self._cams[d.id].delay_frames(links.get("video", d.id), video.rate_hz or CAMERA_RATE_HZ)

    def delay_bus(self, bus: Bus) -> Bus:
        """`bus` as the rig's `bus` link delivers it between the agents of this process: each message
        late on the lab's clock, or lost, drawn per sender (comms.delayed_bus.DelayedBus); `bus` itself
        when the link is perfect (nothing drawn)."""
        if self.mission.links.link("bus").perfect:
            return bus
        return DelayedBus(bus, self.clock.now, lambda sender: self.links.get("bus", sender))

    def drone(self, drone_id: int) -> TelloSim:
        return self.world.drones[drone_id]

    def camera(self, drone_id: int) -> RenderedCamera:
        return self._cams[drone_id]

    def pose_source(self) -> MocapSim:
        return self.mocap

    def target(self) -> ScamperSim:
        return self.world.robot

    def truth(self) -> tuple[Pose, dict[int, Pose]]:
        return self.world.robot.pose, {i: d.pose for i, d in self.world.drones.items()}

    def heartbeat(self) -> None:
        """No watchdog in simulation."""

    def close(self) -> None:
        for d in self.world.drones.values():
            d.land()
        self.world.robot.stop()


def build_lab(mission: Mission) -> LabSimBackend:
    return LabSimBackend(mission)
