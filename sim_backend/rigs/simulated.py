"""What the simulated rigs share: a simulated clock, nothing started for the flight, and an agent process
reaching the world that one process serves over the bus (sim_backend/served)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from flightstack.config.links import LinkSpec
from flightstack.config.mission import Mission
from flightstack.runtime.rig import AgentSeat, LoopPlanner, Preflight

if TYPE_CHECKING:
    from flightstack.sim_backend.served.client import RemoteBackend


class SimulatedRig:
    """The part of a Rig every simulated rig has in common (a rig subclasses it and sets the rest)."""

    simulated = True
    starts_emulators = False
    has_devices = False
    flies_real_drones = False
    robot_is_device = False
    applies_network_profile = False

    @contextlib.contextmanager
    def open(self, mission: Mission, log_dir: Path) -> Iterator[Mission]:
        """Nothing lives for the whole flight: the mission as it is."""
        yield mission

    def command_link(self, mission: Mission) -> LinkSpec:
        """The rc link as the rig's own `links:` describe it."""
        return mission.links.link("rc")

    def agent_backend(
        self, mission: Mission, seat: AgentSeat
    ) -> contextlib.AbstractContextManager[RemoteBackend]:
        """Drone `seat.drone_id` of the world served over `seat.session` (sim_backend/served)."""
        from flightstack.sim_backend.served.client import agent_backend

        return agent_backend(mission, seat)

    def compiled_loop(self) -> LoopPlanner | None:
        return None

    def preflight(
        self,
        mission: Mission,
        drone_ids: list[int] | None = None,
        deadline_s: float = 9.0,
        camera: bool = True,
    ) -> Preflight | None:
        """No devices: nothing to check."""
        return None
