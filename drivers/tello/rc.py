"""Body velocity ↔ Tello `rc a b c d` integers (shared by the Tello driver and the Tello-like simulator).

Drone body frame (FLU): x forward, y left, z up; yaw rate ω about +z (counter-clockwise seen from above).
Tello SDK `rc a b c d`, each an integer in −100..100: a = left/right (+ right), b = forward/backward
(+ forward), c = up/down (+ up), d = yaw (+ clockwise seen from above). Hence
    a = −v_y / g_xy,  b = v_x / g_xy,  c = v_z / g_z,  d = −ω / g_yaw
with per-drone gains g (m/s or rad/s per rc unit) from `flightstack calibrate drone`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

RC_LIMIT = 100


@dataclass(frozen=True)
class RcGains:
    """Physical velocity per rc unit: m/s (xy, z) and rad/s (yaw)."""

    xy: float = 0.01
    z: float = 0.01
    yaw: float = 0.0175

    def __post_init__(self) -> None:
        if not (self.xy > 0 and self.z > 0 and self.yaw > 0):
            raise ValueError("rc gains must be > 0")


def _to_int(x: float) -> int:
    if not math.isfinite(x):
        return 0
    return int(max(-RC_LIMIT, min(RC_LIMIT, round(x))))


def velocity_to_rc(V: np.ndarray, gains: RcGains) -> tuple[int, int, int, int]:
    """V = [v_x, v_y, v_z, ω] (body FLU) → (a, b, c, d) Python ints, rounded and clipped to ±100.

    Non-finite components become 0 (hover), never an exception: this runs in the control loop.
    """
    vx, vy, vz, w = (float(v) for v in V)
    return (_to_int(-vy / gains.xy), _to_int(vx / gains.xy), _to_int(vz / gains.z), _to_int(-w / gains.yaw))


def rc_to_velocity(rc: tuple[int, int, int, int], gains: RcGains) -> np.ndarray:
    """Inverse of velocity_to_rc (up to rounding): (a, b, c, d) → [v_x, v_y, v_z, ω]."""
    a, b, c, d = rc
    return np.array([b * gains.xy, -a * gains.xy, c * gains.z, -d * gains.yaw])
