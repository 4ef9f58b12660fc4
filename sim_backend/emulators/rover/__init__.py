"""Loopback MAVLink emulator of ArduPilot Rover for tests: `MavlinkRoverEmulator` (emulator), its fault
switches (faults), parameters (params), modes (modes), GUIDED set-points and motion (guided)."""

from .emulator import FailsafeEvent, MavlinkRoverEmulator, SetpointRecord
from .faults import RoverFaults
from .modes import ACRO, AUTO, GUIDED, HOLD, LOITER, MANUAL, ROVER_MODES, RTL, SMART_RTL, STEERING
from .params import RoverParams

__all__ = [
    "ACRO", "AUTO", "GUIDED", "HOLD", "LOITER", "MANUAL", "ROVER_MODES", "RTL", "SMART_RTL", "STEERING",
    "FailsafeEvent", "MavlinkRoverEmulator", "RoverFaults", "RoverParams", "SetpointRecord",
]  # fmt: skip
