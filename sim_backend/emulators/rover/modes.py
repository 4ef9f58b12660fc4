"""ArduPilot Rover's modes and what each requires (Rover/mode.h), as the rover emulator models them."""

from __future__ import annotations

from dataclasses import dataclass

MANUAL, ACRO, STEERING, HOLD, LOITER, FOLLOW, SIMPLE = 0, 1, 3, 4, 5, 6, 7
AUTO, RTL, SMART_RTL, GUIDED, INITIALISING = 10, 11, 12, 15, 16


@dataclass(frozen=True)
class ModeTraits:
    """One mode's attributes (Rover/mode.h): ``requires_position()`` / ``requires_velocity()`` (checked by
    ``Mode::enter`` while armed and by the arming checks), ``is_autopilot_mode()`` (HEARTBEAT
    GUIDED_ENABLED), ``has_manual_input()`` (MANUAL_INPUT_ENABLED), ``allows_arming()``."""

    name: str
    requires_position: bool = True  # Mode's default
    requires_velocity: bool = True
    autopilot: bool = False
    manual_input: bool = False
    allows_arming: bool = True


# ACRO requires a velocity estimate only for a vehicle without skid steering (ModeAcro::requires_velocity):
# `requires_velocity` below is the Ackermann answer; `needs_velocity` applies the frame.
ROVER_MODES: dict[int, ModeTraits] = {
    MANUAL: ModeTraits("MANUAL", False, False, manual_input=True),
    ACRO: ModeTraits("ACRO", False, True, manual_input=True),
    STEERING: ModeTraits("STEERING", False, True, manual_input=True),
    HOLD: ModeTraits("HOLD", False, False),
    LOITER: ModeTraits("LOITER", autopilot=True),
    FOLLOW: ModeTraits("FOLLOW", autopilot=True),
    SIMPLE: ModeTraits("SIMPLE"),
    AUTO: ModeTraits("AUTO", autopilot=True),
    RTL: ModeTraits("RTL", autopilot=True, allows_arming=False),
    SMART_RTL: ModeTraits("SMART_RTL", autopilot=True, allows_arming=False),
    GUIDED: ModeTraits("GUIDED", autopilot=True),
    INITIALISING: ModeTraits("INITIALISING", manual_input=True),
}


def needs_position(mode: int) -> bool:
    return ROVER_MODES[mode].requires_position


def needs_velocity(mode: int, skid_steering: bool) -> bool:
    if mode == ACRO:
        return not skid_steering
    return ROVER_MODES[mode].requires_velocity
