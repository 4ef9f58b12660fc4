"""What the rover emulator knows and records: its state (`RoverState`, guarded by the emulator's lock) and
the records a test reads (`FailsafeEvent`, `SetpointRecord`). Units: s (emulator monotonic), m, m/s, rad."""

from __future__ import annotations

from dataclasses import dataclass, field

from .guided import GuidedTarget
from .modes import HOLD


@dataclass(frozen=True)
class FailsafeEvent:
    """One GCS failsafe action: t (emulator monotonic s), FS_ACTION value, mode (and armed) after it."""

    t: float
    action: int
    mode: int
    armed: bool


@dataclass(frozen=True)
class SetpointRecord:
    """One received SET_POSITION_TARGET_LOCAL_NED (t: emulator monotonic time, s); ``applied``: the
    handler set a GUIDED target from it; ``reason`` why not."""

    t: float
    frame: int
    type_mask: int
    vx: float
    vy: float
    yaw_rate: float
    applied: bool
    reason: str = ""


@dataclass
class RoverState:
    mode: int = HOLD
    armed: bool = False
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    vel: tuple[float, float, float] = (0.0, 0.0, 0.0)  # body NED: speed fwd, 0 sideways (m/s), r cw (rad/s)
    target: GuidedTarget | None = None  # ModeGuided's attitude target (have_attitude_target)
    target_t: float = 0.0
    rtl_speed: float = 0.0
    commands: list[tuple[int, float, int]] = field(default_factory=list)  # (command, param, result)
    acks_sent: list[tuple[int, int]] = field(default_factory=list)  # (command, result), every copy
    dropped: list[int] = field(default_factory=list)  # command ids lost on the way in
    home: tuple[float, float] | None = None  # NED x, y (m) at arming: where RTL drives to
    gcs_last_seen: float | None = None  # last HEARTBEAT from the GCS system id (monotonic s)
    fs_on: bool = False  # GCS lost (FS_GCS_TIMEOUT passed)
    fs_start: float = 0.0
    fs_triggered: bool = False  # failsafe.triggered: the action for this loss was taken
    ekf_failsafe: bool = False  # failsafe.ekf
    param_replies: int = 0  # PARAM_VALUE messages sent (duplicates included)
    origin: tuple[int, int, int] | None = None  # EKF origin: lat, lon (degE7), alt (mm)
    vision_t: float | None = None  # last valid external-navigation message (monotonic s)
    vision_count: int = 0
    texts: list[tuple[float, int, str]] = field(default_factory=list)  # STATUSTEXT sent (t, severity, text)
    intervals: dict[int, list[float]] = field(default_factory=dict)  # msg id -> [period s, next due]
