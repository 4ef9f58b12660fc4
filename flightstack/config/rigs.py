"""The rigs, by the name a rig file gives as `backend:` (DESIGN §1, docs/architecture.md decision 40).

A rig is an object (`RigFacts` here: what the rig is and what it asks of a mission;
flightstack.runtime.rig.Rig adds how it opens a flight). Each rig lives in one module of the layer that
builds it (the simulated rigs in sim_backend/rigs/, the real lab in drivers/lab/) and is named here as
"module:attribute", imported on first use: the configuration never imports the layers above it. Every other
module asks the rig (`rig_for`, `Mission.rig_type`), never its name: adding a rig is one module and one line
of `RIGS` (tests/test_rig_registry.py does it).

A rig file with an `emulated:` section flies the rig of `EMULATED[backend]`: the same drivers against
loopback emulators of its devices (the `emulated-lab` rig).
"""

from __future__ import annotations

import functools
import importlib
from typing import Any, Protocol, cast

from flightstack.config.links import LinkSpec

AnyMission = Any
"""A flightstack.config.mission.Mission (which imports this module: named here, not imported)."""

RIGS: dict[str, str] = {
    "sim_ideal": "flightstack.sim_backend.rigs.ideal:RIG",  # the paper's simulation: exact, lock-step
    "sim_lab": "flightstack.sim_backend.rigs.lab_sim:RIG",  # the simulated lab: Tello, cameras, robot
    "tello": "flightstack.drivers.lab.rig:RIG",  # real Tellos, motion capture and the Scamper
}
"""`backend:` value -> its rig ("module:attribute")."""
EMULATED: dict[str, str] = {
    "tello": "flightstack.sim_backend.rigs.emulated_lab:RIG",  # the lab's drivers against loopback emulators
}
"""`backend:` value -> the rig that flies it against emulators (a rig file with `emulated:`)."""


class RigFacts(Protocol):
    """What a rig is, and what it asks of a mission (read by the configuration, the recording and the
    analysis; the rest of a rig: flightstack.runtime.rig.Rig)."""

    name: str
    """The `backend:` value that names it (RIGS)."""
    simulated: bool
    """A simulated clock and physics (lock-step ticks); False: real devices, or their emulators, on the wall
    clock."""
    starts_emulators: bool
    """Opening a flight starts loopback emulators of the devices (the flight flies them as the real rig)."""
    has_devices: bool
    """Real (or emulated) devices, described by the mission's `hardware:` section."""
    flies_real_drones: bool
    """Real drones take off: the operator confirms and the preflight passes first, `sim` and sweeps
    refuse it."""
    robot_is_device: bool
    """The robot is a device that is nudged inside the fence before takeoff (runtime.motion_check)."""
    safety_may_be_off: bool
    """`safety.enabled: false` is allowed (the paper's unbounded simulation only; config.rig_rules)."""
    drones_need_cameras: bool
    """Every drone has a calibrated camera (False: the ideal rig's exact cameras)."""
    default_kinematics: str
    """The robot's kinematics when the rig file does not state them (paper.target_law.KINEMATICS)."""
    world_z_down: bool
    """Σw has z along the cameras' optical axis, looking down (the paper's frame); False: the motion-capture
    frame, z up."""
    estimates_start_from_truth: bool
    """Each estimate starts at the true target pose (False: from the drone's own motion-capture pose at
    pursuit start)."""
    plots_drones: bool
    """The run's trajectory plot shows the drones' paths beside the target's."""
    applies_network_profile: bool
    """The mission's radio profile (`links.network`) impairs this rig's links."""

    def check(self, mission: AnyMission) -> None:
        """What this rig needs of a composed mission (ValueError naming the key and why)."""
        ...

    def command_link(self, mission: AnyMission) -> LinkSpec:
        """The rc link whose mean delay stands in for an unset compensation.command_delay_s."""
        ...

    def drone_response_s(self, mission: AnyMission) -> float:
        """The drone's velocity response time constant (s) for an unset compensation.response_s."""
        ...


class LabFacts:
    """What every lab rig is, simulated or real: Tellos that see through calibrated cameras, a robot that
    never moves sideways (an ArduPilot Rover on a velocity set-point: docs/drivers.md), the motion-capture
    frame, estimates that start from each drone's own pose, safety always on."""

    safety_may_be_off = False
    drones_need_cameras = True
    default_kinematics = "differential"
    world_z_down = False
    estimates_start_from_truth = False
    plots_drones = True


def backends() -> list[str]:
    """The `backend:` values a rig file may give."""
    return sorted(RIGS)


def rig_for(backend: str, emulated: bool = False) -> RigFacts:
    """The rig of `backend` (against emulators when `emulated`); ValueError naming what is known."""
    target = (EMULATED if emulated else RIGS).get(backend)
    if target is None and emulated:
        raise ValueError(no_emulators(backend))
    if target is None:
        raise ValueError(f"unknown backend {backend!r}; known: {', '.join(backends())}")
    return cast(RigFacts, load_named(target))


def no_emulators(backend: str) -> str:
    """Why a rig file of `backend` cannot have `emulated:` (nothing emulates its devices)."""
    return f"no emulators for backend {backend!r} (backends with emulators: {', '.join(EMULATED)})"


@functools.cache
def load_named(target: str) -> Any:
    """The object "module:attr.attr" names (imported on first use)."""
    module_name, path = target.split(":")
    obj: Any = importlib.import_module(module_name)
    for name in path.split("."):
        obj = getattr(obj, name)
    return obj


def need_square_law(mission: AnyMission, why: str) -> None:
    """A rig whose robot is driven on the square law (ValueError naming target.motion)."""
    if mission.target.motion != "square":
        raise ValueError(f"target.motion: {why}")


def need_cameras(mission: AnyMission, where: str) -> None:
    """A rig whose drones see through calibrated cameras (ValueError naming the drone)."""
    for d in mission.drones:
        if d.camera is None or d.camera.calibration is None:
            raise ValueError(f"drones: drone {d.id} needs a camera (calibration, mount) {where}")
