"""Loopback MAVLink emulator of ArduPilot Rover for tests: `MavlinkRoverEmulator` (emulator), its fault
switches (faults), parameters (params), modes (modes), GUIDED set-points and motion (guided), state and
records (state), what it sends (telemetry)."""
