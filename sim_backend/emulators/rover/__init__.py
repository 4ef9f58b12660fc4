"""Loopback MAVLink emulator of ArduPilot Rover for tests: `MavlinkRoverEmulator` (emulator), its fault
switches (faults), parameters (params), modes (modes), GUIDED set-points and motion (guided), state and
records (state), what it sends (telemetry)."""

from .emulator import MavlinkRoverEmulator
from .faults import RoverFaults
from .modes import ACRO, AUTO, GUIDED, HOLD, LOITER, MANUAL, ROVER_MODES, RTL, SMART_RTL, STEERING
from .params import RoverParams
from .state import FailsafeEvent, SetpointRecord

__all__ = [
    "ACRO", "AUTO", "GUIDED", "HOLD", "LOITER", "MANUAL", "ROVER_MODES", "RTL", "SMART_RTL", "STEERING",
    "FailsafeEvent", "MavlinkRoverEmulator", "RoverFaults", "RoverParams", "SetpointRecord",
]  # fmt: skip
