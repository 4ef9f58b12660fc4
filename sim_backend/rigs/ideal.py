"""The `ideal` rig (backend `sim_ideal`): the paper's simulation (Sec. 5). Drones move exactly as
commanded, cameras are exact, the target is an omni-directional point, Σw looks down along the cameras'
optical axis, and safety may be off; ticks of a fleet it can compile fly in one call
(sim_backend/compiled_loop.py)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from flightstack.config.links import NONE, LinkSpec
from flightstack.config.mission import Mission
from flightstack.recording.files import DeviceFiles
from flightstack.runtime.rig import LoopPlanner, Rig
from flightstack.sim_backend.rigs.simulated import SimulatedRig

if TYPE_CHECKING:
    from flightstack.sim_backend.ideal import IdealSimBackend


class IdealRig(SimulatedRig):
    name = "sim_ideal"
    safety_may_be_off = True
    drones_need_cameras = False
    default_kinematics = "omni"
    world_z_down = True
    estimates_start_from_truth = True
    plots_drones = False

    def check(self, mission: Mission) -> None:
        """The ideal rig flies any experiment."""

    def command_link(self, mission: Mission) -> LinkSpec:
        """No delay: drones move as commanded."""
        return NONE

    def drone_response_s(self, mission: Mission) -> float:
        return 0.0

    def build_backend(self, mission: Mission, devices: DeviceFiles | None) -> IdealSimBackend:
        from flightstack.sim_backend.build import build_ideal

        return build_ideal(mission)

    def compiled_loop(self) -> LoopPlanner | None:
        from flightstack.sim_backend.compiled_loop import CompiledLoop

        return CompiledLoop.plan


RIG: Rig = IdealRig()  # checked against the Rig protocol
