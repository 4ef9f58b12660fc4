"""The DJI/Ryze Tello: driver (`driver.TelloDriver`, the import path of this package), its parts (command
link, state stream, phase tracker, takeoff and land, sticks, watchdog, rejoin, video), its preflight and
its velocity-step identification. docs/drivers.md, "Tello driver", says how they fit."""

from flightstack.drivers.tello.driver import (
    DEFAULT_VIDEO_PORT,
    PreflightCheck,
    TelloCommandError,
    TelloConfig,
    TelloDriver,
    TelloLinkError,
    parse_int_reply,
    parse_sdk,
    parse_serial,
)

__all__ = [
    "DEFAULT_VIDEO_PORT",
    "PreflightCheck",
    "TelloCommandError",
    "TelloConfig",
    "TelloDriver",
    "TelloLinkError",
    "parse_int_reply",
    "parse_sdk",
    "parse_serial",
]
