"""flightstack: distributed-GP cooperative visual pursuit for drone networks.

What a script may import from here (`__all__`; each name is imported from its module on first use, so
`import flightstack` costs nothing and a process that needs one name loads only its module):

- flying: `Flight` (one flight of an experiment on a rig: `with Flight(mission, out) as f: f.fly()`),
  `FlightResult`, `NotFlownError`;
- experiments and rigs: `load_mission` (an experiment on a rig, or a run's resolved mission), `Mission`,
  `MissionError`; the rigs: `rig_for`, `RigFacts` (what a rig is), `Rig` (how it flies), `rig_of`;
- the hardware roles (flightstack.hal): `Backend`, `Drone`, `Camera`, `PoseSource`, `GroundRobot`,
  `Clock`, and what they report: `DroneState`, `FlightPhase`, `Frame`, `StampedPose`;
- a run directory, read back: `load_run` (every mode's `Recording`), `read_events`, `resolved_mission`,
  `recording_status`.

Everything else is the package's own: importable, but not promised to stay (docs/api/index.md).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from flightstack.config.mission import Mission, MissionError, load_mission
    from flightstack.config.rigs import RigFacts, rig_for
    from flightstack.hal import (
        Backend,
        Camera,
        Clock,
        Drone,
        DroneState,
        FlightPhase,
        Frame,
        GroundRobot,
        PoseSource,
        StampedPose,
    )
    from flightstack.recording.run_reader import load_run, read_events, recording_status, resolved_mission
    from flightstack.recording.timeseries import Recording
    from flightstack.runtime.flight import Flight, FlightResult, NotFlownError
    from flightstack.runtime.rig import Rig, rig_of

API: dict[str, str] = {
    "Flight": "flightstack.runtime.flight",
    "FlightResult": "flightstack.runtime.flight",
    "NotFlownError": "flightstack.runtime.flight",
    "load_mission": "flightstack.config.mission",
    "Mission": "flightstack.config.mission",
    "MissionError": "flightstack.config.mission",
    "rig_for": "flightstack.config.rigs",
    "RigFacts": "flightstack.config.rigs",
    "Rig": "flightstack.runtime.rig",
    "rig_of": "flightstack.runtime.rig",
    "Backend": "flightstack.hal",
    "Drone": "flightstack.hal",
    "Camera": "flightstack.hal",
    "PoseSource": "flightstack.hal",
    "GroundRobot": "flightstack.hal",
    "Clock": "flightstack.hal",
    "DroneState": "flightstack.hal",
    "FlightPhase": "flightstack.hal",
    "Frame": "flightstack.hal",
    "StampedPose": "flightstack.hal",
    "load_run": "flightstack.recording.run_reader",
    "read_events": "flightstack.recording.run_reader",
    "resolved_mission": "flightstack.recording.run_reader",
    "recording_status": "flightstack.recording.run_reader",
    "Recording": "flightstack.recording.timeseries",
}
"""Public name -> the module that defines it (in the order docs/api/index.md lists them)."""

__all__ = [
    "Backend",
    "Camera",
    "Clock",
    "Drone",
    "DroneState",
    "Flight",
    "FlightPhase",
    "FlightResult",
    "Frame",
    "GroundRobot",
    "Mission",
    "MissionError",
    "NotFlownError",
    "PoseSource",
    "Recording",
    "Rig",
    "RigFacts",
    "StampedPose",
    "load_mission",
    "load_run",
    "read_events",
    "recording_status",
    "resolved_mission",
    "rig_for",
    "rig_of",
]


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use (PEP 562)."""
    module = API.get(name)
    if module is None:
        raise AttributeError(f"module 'flightstack' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
