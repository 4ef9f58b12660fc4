"""The safety layer (DESIGN §7): limits and pure rules (`rules`), the per-drone wrapper (`drone`), the
mission-wide supervisor and signal handling (`supervisor`). This package re-exports their public names."""

from flightstack.safety.drone import SafeDrone
from flightstack.safety.rules import (
    EVENT_KINDS,
    EventLog,
    SafetyError,
    SafetyEvent,
    SafetyLimits,
    climb_cap,
    fence_clip,
    outside_hard_fence,
    outside_soft_fence,
    sanitize,
    saturate,
)
from flightstack.safety.supervisor import MissionSupervisor

__all__ = [
    "EVENT_KINDS",
    "EventLog",
    "MissionSupervisor",
    "SafeDrone",
    "SafetyError",
    "SafetyEvent",
    "SafetyLimits",
    "climb_cap",
    "fence_clip",
    "outside_hard_fence",
    "outside_soft_fence",
    "sanitize",
    "saturate",
]
