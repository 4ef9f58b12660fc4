"""Shared test helpers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from flightstack.geometry import Pose

REPO = Path(__file__).resolve().parents[1]
MISSIONS = REPO / "mission_configs"

finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
angles = st.floats(-3.14159, 3.14159, allow_nan=False, allow_infinity=False)


@st.composite
def poses(draw: st.DrawFn) -> Pose:
    return Pose.make([draw(finite), draw(finite), draw(finite)], draw(angles))


@st.composite
def twists(draw: st.DrawFn) -> np.ndarray:
    return np.array([draw(finite), draw(finite), draw(finite), draw(st.floats(-3.0, 3.0))])
