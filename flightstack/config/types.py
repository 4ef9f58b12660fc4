"""Building blocks of the mission schema shared by its section modules (pydantic, strict, frozen)."""

from __future__ import annotations

import enum
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

__all__ = ["Finite", "Mode", "NonNegative", "Positive", "Strict"]
