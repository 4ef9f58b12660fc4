"""What a rig allows of the safety it flies with, whatever the source of a value: the rig file, a run's
resolved mission, or a value set after the rig was composed (`flightstack run --set`, `flightstack sweep
--set`). The rules (docs/safety.md, "What a rig allows"):

1. Safety is off only on a rig that allows it (RigFacts.safety_may_be_off: the ideal rig, the paper's
   unbounded simulation): `safety_off_problem`, checked on every
   composed mission (flightstack.config.mission) and on a rig file on its own (flightstack.config.rig_check).
2. Every limit is a limit: `SafetyLimits` (flightstack.safety.rules) refuses a fence or a speed beyond what
   any lab or Tello has, on every rig and from every source.
3. A value set after the rig may tighten the rig's safety but never loosen it, and never changes which rig
   it is (`beyond_rig`): the rig file is the lab's one statement of its envelope, reviewed and checked by
   `flightstack validate`; to loosen it, edit that file.
"""

from __future__ import annotations

from typing import Any, Protocol

from flightstack.config.rigs import RigFacts


class Composed(Protocol):
    """What the rules read of a composed mission (flightstack.config.mission.Mission, which imports this
    module)."""

    @property
    def rig(self) -> str: ...
    @property
    def backend(self) -> str: ...
    @property
    def start_emulators(self) -> bool: ...
    @property
    def safety(self) -> Any: ...  # SafetySpec: `enabled` and the fields of SafetyLimits


RIG_IDENTITY = ("rig", "backend", "start_emulators")
"""Keys that say which rig a mission flies on: never changed after composition (choose the rig with
--rig)."""

LOOSER_WHEN_LARGER = (
    "max_speed_xy",
    "max_speed_z",
    "max_yaw_rate",
    "hard_margin",
    "command_timeout",
    "pose_timeout",
    "pose_land_after",
    "target_lost_hover_after",
    "target_lost_land_after",
    "land_retry_s",
    "landed_height",
)
"""Safety limits that allow more the larger they are (a faster drone, a later reaction, a landing counted
as done higher up)."""
LOOSER_WHEN_SMALLER = ("min_battery_takeoff", "land_battery")
"""Safety limits that allow more the smaller they are (flying on a lower battery)."""
FENCE = ("fence_lo", "fence_hi")
"""The soft fence: a fence set after the rig must lie inside the rig's."""
# Any other field of SafetyLimits (emergency_stop_if_land_fails: either way is a lab's trade-off, and a
# field added later until it is sorted into a table above) is the rig's alone: set after the rig, it must
# keep the rig's value.


def safety_off_problem(rig: RigFacts, enabled: object) -> str | None:
    """Why safety may not be `enabled` on `rig` (None: it may)."""
    if enabled is False and not rig.safety_may_be_off:
        return (
            "safety.enabled: false only on the ideal rig (a rig whose safety_may_be_off); "
            f"backend {rig.name!r} flies with safety on, from its rig file and from --set alike"
        )
    return None


def loosened(rig: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """Each way the safety section `now` allows more than the rig's `rig` (both as `SafetySpec.model_dump`
    dicts: `enabled` and the fields of SafetyLimits); [] when it allows nothing more. Nothing is looser
    than a rig whose safety is off."""
    if not rig.get("enabled", True):
        return []
    problems = []
    if not now.get("enabled", True):
        problems.append("safety.enabled: false (the rig flies with safety on)")
    for key in sorted(set(rig) | set(now)):
        was: Any = rig.get(key)
        new: Any = now.get(key)
        if key == "enabled" or new == was:
            continue
        if key in FENCE:
            pairs = zip(new, was, strict=True)
            inside = all(n >= w for n, w in pairs) if key == "fence_lo" else all(n <= w for n, w in pairs)
            if not inside:
                problems.append(f"safety.{key}: {_show(new)} is outside the rig's fence ({_show(was)})")
        elif key in LOOSER_WHEN_LARGER:
            if new > was:
                problems.append(f"safety.{key}: {_show(new)} is above the rig's {_show(was)}")
        elif key in LOOSER_WHEN_SMALLER:
            if new < was:
                problems.append(f"safety.{key}: {_show(new)} is below the rig's {_show(was)}")
        else:
            problems.append(f"safety.{key}: the rig's own ({_show(was)})")
    return problems


def beyond_rig(rig: Composed, now: Composed) -> str | None:
    """Why the mission `now` (the mission `rig` with values set after its composition) leaves what its
    rig allows: another rig identity (RIG_IDENTITY) or a looser safety section (`loosened`); None when it
    does not. One line, naming each key."""
    problems = [
        f"{key}: the rig's own ({getattr(rig, key)!r})"
        for key in RIG_IDENTITY
        if getattr(now, key) != getattr(rig, key)
    ]
    problems += loosened(rig.safety.model_dump(), now.safety.model_dump())
    if not problems:
        return None
    return (
        f"beyond what rig {rig.rig!r} allows: {'; '.join(problems)} (a value set after the rig may tighten "
        "its safety, never loosen it or change the rig: edit the rig file or choose another rig; "
        "docs/safety.md)"
    )


def _show(v: Any) -> str:
    """A value as a message shows it: numbers with %g, a fence corner as [x, y, z]."""
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_show(x) for x in v) + "]"
    return f"{v:g}" if isinstance(v, float) else repr(v)
