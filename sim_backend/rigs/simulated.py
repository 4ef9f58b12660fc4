"""What the simulated rigs share: a simulated clock, nothing started for the flight, and an agent process
reaching the world that one process serves over the bus (sim_backend/served)."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

from flightstack.config.mission import Mission
from flightstack.runtime.rig import AgentSeat, RigDefaults

if TYPE_CHECKING:
    from flightstack.sim_backend.served.client import RemoteBackend


class SimulatedRig(RigDefaults):
    """The part of a Rig every simulated rig has in common (a rig subclasses it and sets the rest)."""

    simulated = True
    starts_emulators = False
    has_devices = False
    flies_real_drones = False
    robot_is_device = False
    applies_network_profile = False

    def agent_backend(
        self, mission: Mission, seat: AgentSeat
    ) -> contextlib.AbstractContextManager[RemoteBackend]:
        """Drone `seat.drone_id` of the world served over `seat.session` (sim_backend/served)."""
        from flightstack.sim_backend.served.client import agent_backend

        return agent_backend(mission, seat)
