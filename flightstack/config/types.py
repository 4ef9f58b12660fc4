"""Building blocks of the mission schema shared by its section modules (pydantic, strict, frozen)."""

from __future__ import annotations

import enum
import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field


class Strict(BaseModel):
    """A schema section: unknown keys are errors, values are immutable once loaded."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Mode(enum.StrEnum):
    """Which prediction of the target's body velocity V_wo a drone feeds forward (the paper's three
    simulation cases, plus the simulation-only oracle). Values are the strings of `compare_modes`."""

    NONE = "none"  # no feed-forward: μ = 0
    LOCAL = "local"  # each drone's own GP expert only
    DGP = "dgp"  # the paper's distributed GP: own expert fused with the neighbours' (product of experts)
    ORACLE = "oracle"  # the true V_wo (paper's simulation only; needs the world's truth)

    @property
    def uses_gp(self) -> bool:
        """True for the modes that need trained GP experts (LOCAL, DGP)."""
        return self in (Mode.LOCAL, Mode.DGP)

    @property
    def needs_predictor(self) -> bool:
        """True for every mode with a feed-forward prediction (all but NONE)."""
        return self is not Mode.NONE


Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]

# Bounds on physical parameters: a value beyond them is a typo (a unit, a digit) that no lab or
# simulation flies; each is far beyond the shipped rigs and experiments.
MAX_DISTANCE_M = 1000.0
"""|coordinate| (m) of positions: poses, feature points, camera offsets, the square's side. A lab or motion
capture volume is ~10 m and the paper's target stays within 2 m; 1 km also keeps the renderer's and the
observer's arithmetic far from losing precision."""
MAX_ANGLE_RAD = 2 * math.pi
"""|angle| (rad) of a pose: every orientation is written within one turn either way."""
MAX_SPEED_MPS = 20.0
"""Speeds (m/s): a Tello flies at most 8 m/s, the Scamper robot ~2 m/s."""
MAX_YAW_RATE = 20.0
"""Yaw rates (rad/s): more than three turns a second (a Tello turns at most ~1.75 rad/s)."""
MAX_TIME_S = 3600.0
"""Time constants, latencies and timeouts of the simulated devices (s): an hour is no device's response."""

Coordinate = Annotated[float, Field(ge=-MAX_DISTANCE_M, le=MAX_DISTANCE_M, allow_inf_nan=False)]
Angle = Annotated[float, Field(ge=-MAX_ANGLE_RAD, le=MAX_ANGLE_RAD, allow_inf_nan=False)]
Distance = Annotated[float, Field(gt=0, le=MAX_DISTANCE_M, allow_inf_nan=False)]
Speed = Annotated[float, Field(gt=0, le=MAX_SPEED_MPS, allow_inf_nan=False)]
YawRate = Annotated[float, Field(gt=0, le=MAX_YAW_RATE, allow_inf_nan=False)]
Seconds = Annotated[float, Field(gt=0, le=MAX_TIME_S, allow_inf_nan=False)]

__all__ = [
    "MAX_ANGLE_RAD",
    "MAX_DISTANCE_M",
    "MAX_SPEED_MPS",
    "MAX_TIME_S",
    "MAX_YAW_RATE",
    "Angle",
    "Coordinate",
    "Distance",
    "Finite",
    "Mode",
    "NonNegative",
    "Positive",
    "Seconds",
    "Speed",
    "Strict",
    "YawRate",
]
