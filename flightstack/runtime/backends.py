"""What a rig provides, by name, imported lazily (DESIGN §1): the runtime never imports sim_backend/ or
drivers/ (they sit above it), so the simulator runs without hardware libraries and the hardware runs
without the simulator. Each entry is "module:attribute".

- `REGISTRY`: mission `backend:` -> the builder of the whole fleet in one process: `build_backend(mission)`;
  a builder of real (or emulated) devices, not `mission.simulated`, also takes `devices` (where their raw
  traffic is recorded: flightstack.recording.files.DeviceFiles).
- `AGENT_REGISTRY`: one drone in an agent process (`flightstack agent`): `open_agent_backend(mission,
  seat)`, a context manager that releases what the agent opened (the link to the served world) after
  the run; the run itself lands through `Backend.close()` as in one process.

flightstack.runtime.flight names the rigs' compiled loops and the emulated lab the same way (`load_named`).
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from flightstack.config.mission import Mission
    from flightstack.hal import Backend
    from flightstack.recording.files import DeviceFiles

REGISTRY: dict[str, str] = {
    "sim_ideal": "flightstack.sim_backend.build:build_ideal",
    "sim_lab": "flightstack.sim_backend.build_lab:build_lab",
    "tello": "flightstack.drivers.hardware:build_tello",  # real Tellos + motion capture + Scamper
}

AGENT_REGISTRY: dict[str, str] = {
    "sim_ideal": "flightstack.sim_backend.served.client:agent_backend",  # the world serves the physics
    "sim_lab": "flightstack.sim_backend.served.client:agent_backend",
    "tello": "flightstack.drivers.hardware:agent_backend",  # this agent's Tello + mocap (+ robot)
}


@dataclass(frozen=True)
class AgentSeat:
    """What an agent process hands its backend: the drone it flies, its Zenoh session (`ZenohBus.session`;
    the served world is reached through it), the file its guardian logs to and where its devices' raw
    traffic is recorded (hardware; None: nowhere)."""

    drone_id: int
    session: Any
    guardian_log: str
    devices: DeviceFiles | None = None


def load_named(target: str) -> Callable[..., Any]:
    """The object "module:attr.attr" names (imported now)."""
    module_name, path = target.split(":")
    obj: Any = importlib.import_module(module_name)
    for name in path.split("."):
        obj = getattr(obj, name)
    return cast(Callable[..., Any], obj)


def _resolve(registry: dict[str, str], mission: Mission) -> Callable[..., Any]:
    try:
        target = registry[mission.backend]
    except KeyError:
        raise ValueError(
            f"unknown backend {mission.backend!r}; known: {', '.join(sorted(registry))}"
        ) from None
    return load_named(target)


def build_backend(mission: Mission, devices: DeviceFiles | None = None) -> Backend:
    """Build the backend the mission names; ValueError for an unknown name. devices: where a backend of
    real devices records their raw traffic (ignored by a simulated one: it has no device traffic)."""
    builder = _resolve(REGISTRY, mission)
    if devices is None or mission.simulated:
        return cast("Backend", builder(mission))
    return cast("Backend", builder(mission, devices=devices))


@contextlib.contextmanager
def open_agent_backend(mission: Mission, seat: AgentSeat) -> Iterator[Backend]:
    """The backend of one agent process (drone `seat.drone_id` only); ValueError for an unknown name."""
    with _resolve(AGENT_REGISTRY, mission)(mission, seat) as backend:
        yield cast("Backend", backend)
