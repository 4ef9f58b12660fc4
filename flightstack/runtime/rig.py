"""How a rig flies (DESIGN §1): `Rig`, the rest of flightstack.config.rigs.RigFacts, and the rig a mission
flies on (`rig_of`). The rigs themselves sit above the runtime (sim_backend/rigs/, drivers/lab/) and are
reached through the registry of flightstack.config.rigs, imported on use: the simulator runs without
hardware libraries and the hardware without the simulator.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Protocol, cast

from flightstack.config.links import LinkSpec
from flightstack.config.mission import Mission
from flightstack.config.rigs import RigFacts
from flightstack.hal import Backend
from flightstack.recording.files import DeviceFiles

LoopPlanner = Callable[[Any], Any]
"""(runtime.fleet.Fleet) -> a runtime.runner.ChunkLoop that flies runs of its ticks in one compiled call,
or None for a fleet whose ticks it cannot fly."""


@dataclass(frozen=True)
class AgentSeat:
    """What an agent process hands its backend: the drone it flies, its Zenoh session (`ZenohBus.session`;
    the served world is reached through it), the file its guardian logs to and where its devices' raw
    traffic is recorded (hardware; None: nowhere)."""

    drone_id: int
    session: Any
    guardian_log: str
    devices: DeviceFiles | None = None


class Preflight(NamedTuple):
    """A rig's preflight: its table (a row per device and check) and whether no check failed."""

    table: str
    passed: bool


class Rig(RigFacts, Protocol):
    """A rig: what it is (RigFacts) and how it opens a flight."""

    def open(self, mission: Mission, log_dir: Path) -> contextlib.AbstractContextManager[Mission]:
        """What lives for the whole flight (a rig that `starts_emulators`: its emulators, logging in
        log_dir); yields the mission to fly (re-pointed at what was started)."""
        ...

    def build_backend(self, mission: Mission, devices: DeviceFiles | None) -> Backend:
        """The whole fleet in one process; devices: where real devices record their raw traffic (None:
        nowhere; a simulated rig has none)."""
        ...

    def agent_backend(self, mission: Mission, seat: AgentSeat) -> contextlib.AbstractContextManager[Backend]:
        """One drone in an agent process (`flightstack agent`); releases what it opened after the run (the
        run itself lands through Backend.close())."""
        ...

    def compiled_loop(self) -> LoopPlanner | None:
        """The planner of the rig's compiled loop (None: every tick goes through the agents)."""
        ...

    def preflight(
        self,
        mission: Mission,
        drone_ids: list[int] | None = None,
        deadline_s: float = 9.0,
        camera: bool = True,
    ) -> Preflight | None:
        """Check every device and file the flight needs, within about deadline_s (s), for `drone_ids` (None:
        every drone); None: the rig has no devices to check. ValueError for a drone the mission lacks."""
        ...


class RigDefaults:
    """What a rig does unless it says otherwise (a rig class subclasses it): nothing lives for the whole
    flight, the rc link is the mission's own `links:` rc, no compiled loop, no devices to check."""

    @contextlib.contextmanager
    def open(self, mission: Mission, log_dir: Path) -> Iterator[Mission]:
        """Nothing lives for the whole flight: the mission as it is."""
        yield mission

    def command_link(self, mission: Mission) -> LinkSpec:
        """The rc link as the rig's own `links:` describe it."""
        return mission.links.link("rc")

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


def rig_of(mission: Mission) -> Rig:
    """The rig `mission` flies on."""
    return cast(Rig, mission.rig_type)


@contextlib.contextmanager
def opened(mission: Mission, log_dir: Path | None = None) -> Iterator[Mission]:
    """What the mission's rig opens for a whole flight (Rig.open: a rig that starts emulators logs in
    log_dir, or in a temporary directory when None); yields the mission to fly."""
    rig = rig_of(mission)
    if not rig.starts_emulators:
        yield mission
        return
    with contextlib.ExitStack() as stack:
        if log_dir is None:
            log_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="flightstack-lab-")))
        yield stack.enter_context(rig.open(mission, log_dir))


def build_backend(mission: Mission, devices: DeviceFiles | None = None) -> Backend:
    """The backend of the mission's rig for the whole fleet (Rig.build_backend)."""
    return rig_of(mission).build_backend(mission, devices)


@contextlib.contextmanager
def open_agent_backend(mission: Mission, seat: AgentSeat) -> Iterator[Backend]:
    """The backend of one agent process (drone `seat.drone_id` only; Rig.agent_backend)."""
    with rig_of(mission).agent_backend(mission, seat) as backend:
        yield backend
