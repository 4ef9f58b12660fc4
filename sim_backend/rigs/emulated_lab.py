"""The `emulated-lab` rig (backend `tello` with `emulated:`): the real lab's drivers against loopback
emulators of the Tellos, the motion capture and the robot (sim_backend/emulated_lab.py), started when the
flight opens and flown as the real lab."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from flightstack.config.links import LinkSpec
from flightstack.config.mission import Mission
from flightstack.drivers.lab.rig import LabRig
from flightstack.runtime.rig import Rig


class EmulatedLabRig(LabRig):
    starts_emulators = True
    flies_real_drones = False  # loopback emulators: nothing takes off

    def check_compensation(self, mission: Mission) -> None:
        """The emulated Tello's response is known (EMULATED_TELLO_RESPONSE_S)."""

    def command_link(self, mission: Mission) -> LinkSpec:
        """The rc link as the emulated lab applies it (links.emulated)."""
        return mission.links.emulated("rc")

    @contextlib.contextmanager
    def open(self, mission: Mission, log_dir: Path) -> Iterator[Mission]:
        """The emulators on loopback, logging in log_dir; yields the mission re-pointed at them (a real lab's
        mission: start_emulators false). Every device stops when the block ends."""
        from flightstack.sim_backend.emulated_lab import running_lab

        with running_lab(mission, log_dir) as repointed:
            yield repointed


RIG: Rig = EmulatedLabRig()  # checked against the Rig protocol
