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

if TYPE_CHECKING:  # what a type checker sees of the names below (explicit re-exports)
    from flightstack.config.mission import Mission as Mission
    from flightstack.config.mission import MissionError as MissionError
    from flightstack.config.mission import load_mission as load_mission
    from flightstack.config.rigs import RigFacts as RigFacts
    from flightstack.config.rigs import rig_for as rig_for
    from flightstack.hal import Backend as Backend
    from flightstack.hal import Camera as Camera
    from flightstack.hal import Clock as Clock
    from flightstack.hal import Drone as Drone
    from flightstack.hal import DroneState as DroneState
    from flightstack.hal import FlightPhase as FlightPhase
    from flightstack.hal import Frame as Frame
    from flightstack.hal import GroundRobot as GroundRobot
    from flightstack.hal import PoseSource as PoseSource
    from flightstack.hal import StampedPose as StampedPose
    from flightstack.recording.run_reader import load_run as load_run
    from flightstack.recording.run_reader import read_events as read_events
    from flightstack.recording.run_reader import recording_status as recording_status
    from flightstack.recording.run_reader import resolved_mission as resolved_mission
    from flightstack.recording.timeseries import Recording as Recording
    from flightstack.runtime.flight import Flight as Flight
    from flightstack.runtime.flight import FlightResult as FlightResult
    from flightstack.runtime.flight import NotFlownError as NotFlownError
    from flightstack.runtime.rig import Rig as Rig
    from flightstack.runtime.rig import rig_of as rig_of

MODULES: dict[str, tuple[str, ...]] = {
    "flightstack.runtime.flight": ("Flight", "FlightResult", "NotFlownError"),
    "flightstack.config.mission": ("load_mission", "Mission", "MissionError"),
    "flightstack.config.rigs": ("rig_for", "RigFacts"),
    "flightstack.runtime.rig": ("Rig", "rig_of"),
    "flightstack.hal": ("Backend", "Drone", "Camera", "PoseSource", "GroundRobot", "Clock", "DroneState",
                        "FlightPhase", "Frame", "StampedPose"),
    "flightstack.recording.run_reader": ("load_run", "read_events", "resolved_mission", "recording_status"),
    "flightstack.recording.timeseries": ("Recording",),
}  # fmt: skip
API: dict[str, str] = {name: module for module, names in MODULES.items() for name in names}
"""Public name -> the module that defines it (in the order docs/api/index.md lists them)."""
__all__ = sorted(API)


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use (PEP 562)."""
    module = API.get(name)
    if module is None:
        raise AttributeError(f"module 'flightstack' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
