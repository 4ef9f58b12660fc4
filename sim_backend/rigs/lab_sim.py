"""The `lab-sim` rig (backend `sim_lab`): the simulated lab (sim_backend/lab.py): Tellos with their rc
response and state rate, cameras rendered through their calibrations, motion capture, and a robot driven on
the square law; a simulated clock."""

from __future__ import annotations

from typing import TYPE_CHECKING

from flightstack.config.mission import Mission
from flightstack.config.rigs import LabFacts, need_cameras, need_square_law
from flightstack.recording.files import DeviceFiles
from flightstack.runtime.rig import Rig
from flightstack.sim_backend.rigs.simulated import SimulatedRig

if TYPE_CHECKING:
    from flightstack.sim_backend.build_lab import LabSimBackend


class LabSimRig(LabFacts, SimulatedRig):
    name = "sim_lab"

    def check(self, mission: Mission) -> None:
        need_square_law(mission, "the simulated lab drives the robot on the 'square' law")
        need_cameras(mission, "on the simulated lab")

    def drone_response_s(self, mission: Mission) -> float:
        """The simulated Tello's (sim.tello.time_constant_s)."""
        return mission.sim.tello.time_constant_s

    def build_backend(self, mission: Mission, devices: DeviceFiles | None) -> LabSimBackend:
        from flightstack.sim_backend.build_lab import build_lab

        return build_lab(mission)


RIG: Rig = LabSimRig()  # checked against the Rig protocol
