"""The ArduPilot Rover emulator's public names, where the tests and labs import them (the emulator lives
in the package `rover`)."""

from .rover import (
    ACRO,
    AUTO,
    GUIDED,
    HOLD,
    LOITER,
    MANUAL,
    ROVER_MODES,
    RTL,
    SMART_RTL,
    STEERING,
    FailsafeEvent,
    MavlinkRoverEmulator,
    RoverFaults,
    RoverParams,
    SetpointRecord,
)

__all__ = [
    "ACRO", "AUTO", "GUIDED", "HOLD", "LOITER", "MANUAL", "ROVER_MODES", "RTL", "SMART_RTL", "STEERING",
    "FailsafeEvent", "MavlinkRoverEmulator", "RoverFaults", "RoverParams", "SetpointRecord",
]  # fmt: skip
