"""Is a fresh-looking motion-capture pose believable? Checks against independent evidence: what was
commanded and what the body reports of itself.

A pose can keep arriving, marked valid and freshly stamped, yet be wrong: a stuck capture pipeline, a
frozen replay or a mislabelled body. Two checks, each against evidence the pose does not produce:

* **Frozen** (`FreezeWatch`): consecutive samples with advancing stamps are bit-identical while the body
  was being commanded to move (any command since the run of identical samples began with a speed of at
  least `MOVING_MPS` or a yaw rate of at least `MOVING_RADPS`). Motion capture of a real body never
  repeats a float sample (Motive's sub-millimetre noise; every body of the NatNet recording in
  `../shared/data/peers/natnet/` differs frame to frame); a noise-free simulation repeats samples only when
  the body stands still, which a moving command rules out. The frozen pose is judged from the first
  identical sample read after a moving command (`frozen_since`, s, the pose's clock): a body that stood
  still before it (a Tello hovering in its takeoff, ignoring rc) is no evidence.
* **Height disagreement** (`HeightAgreement`): over the last `HEIGHT_WINDOW_S`, the change of the pose's
  z and the change of the drone's own height telemetry (a Tello's `h`, cm → m) differ by more than
  `HEIGHT_DISAGREE_M`. Changes, not values: `h` is relative to the take-off surface and drifts. How far
  it strays in 2 s is read from the real flight (xg590, sim_backend/emulators/tello/recorded.py): hovering
  with `vgz` 0 and `tof` rising 6 cm, `h` fell 30 cm (5.1-7.2 s); against `tof` (which also reads steps
  in the surface below: +54 cm at 12 s with `h` still) the two changes differ by up to 0.58 m over 2 s.
  `HEIGHT_DISAGREE_M` (0.8 m) is twice `h`'s own 0.4 m, and above what `tof` adds: it catches a gross lie
  (a body swapped with one of another height, the robot's at 1 m below; a pose standing while the drone
  climbs or falls ≥ 0.4 m/s), never a slow one: the frozen check is the one for a stuck pose.
* **Motion disagreement** (`MotionAgreement`, the ground robot): over the last `MOTION_WINDOW_S`, its
  planar displacement as motion capture saw it and as its commands predict (each command held until the
  next sample, turned by the measured heading) differ by more than `MOTION_JUMP_M` plus `MOTION_LAG_S` at
  the fastest speed commanded in the window: a pose that jumped where no command took the robot (a swapped
  or mislabelled body). A robot lagging its command by up to `MOTION_LAG_S` (a first-order response of
  τ ≤ 0.5 s lags by v·τ) stays inside; a robot that does not move at all while commanded stays inside too
  (≤ 0.1 m a second at the paper's speed): the frozen check and the motion check before takeoff are for
  that.

Pure functions of the samples given; the safety layer (flightstack/safety/drone.py for drones,
flightstack/runtime/phases.py for the ground robot) decides what to do (docs/safety.md).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

MOVING_MPS = 0.05
"""A command at least this fast (m/s, norm of the linear part) moves a drone or the robot by more than
motion capture's noise within one frame period: 5 rc units on a Tello (0.01 m/s each, drivers/tello/rc.py)."""
MOVING_RADPS = 0.1
"""A commanded yaw rate at least this large (rad/s) turns the body visibly within a frame period."""
HEIGHT_WINDOW_S = 2.0
"""Window over which z and the drone's own height are compared (s)."""
HEIGHT_DISAGREE_M = 0.8
"""Largest difference between the two heights' changes over the window that is still agreement (m)."""
MOTION_WINDOW_S = 1.0
"""Window over which the robot's measured and commanded displacements are compared (s)."""
MOTION_JUMP_M = 0.15
"""Part of the motion bound that no command explains (m): far above motion capture's noise (µm to mm)."""
MOTION_LAG_S = 1.0
"""Part of the motion bound per m/s commanded (s): twice the lag of a τ = 0.5 s response."""
MOTION_GAP_S = 0.5
"""Samples further apart than this (s) restart the window: without new set-points for that long the robot
may have stopped by its own failsafe (a stalled loop held its last command for 3 s in the fault row
`loop_stall`, and the prediction read the robot's stop as a jump)."""


def moving(command: np.ndarray | None) -> bool:
    """True when `command` V = [v_x, v_y, v_z, ω_z] (m/s, rad/s) would visibly move the body."""
    if command is None or len(command) < 4:
        return False
    v = np.asarray(command, dtype=float)
    if not np.all(np.isfinite(v)):
        return False
    return bool(np.linalg.norm(v[:3]) >= MOVING_MPS or abs(v[3]) >= MOVING_RADPS)


@dataclass
class FreezeWatch:
    """Runs of identical pose samples under advancing stamps (see the module docstring)."""

    _last: np.ndarray | None = None
    _stamp: float = -math.inf  # newest stamp seen (s)
    _commanded_at: float | None = None  # stamp of the run's first sample read after a moving command (s)

    def sample(self, stamp: float, pose: np.ndarray, command: np.ndarray | None) -> None:
        """One read of the source: its sample (stamp s, pose vector) and the command last sent before it."""
        if stamp > self._stamp:
            if self._last is None or not np.array_equal(pose, self._last):
                self._last = np.array(pose, dtype=float)
                self._commanded_at = None
            elif self._commanded_at is None and moving(command):
                self._commanded_at = stamp
            self._stamp = stamp

    @property
    def frozen_since(self) -> float | None:
        """The stamp (s) of the first sample that stayed identical although the body had been commanded to
        move, None when there is none in the current run of identical samples."""
        return self._commanded_at

    def reset(self) -> None:
        self._last, self._stamp, self._commanded_at = None, -math.inf, None


@dataclass
class HeightAgreement:
    """The pose's z against the drone's own height over a sliding window (see the module docstring)."""

    window_s: float = HEIGHT_WINDOW_S
    bound_m: float = HEIGHT_DISAGREE_M
    _hist: deque[tuple[float, float, float]] = field(default_factory=deque)

    def sample(self, t: float, z_pose: float, h_own: float) -> float | None:
        """Add (t s, pose z m, own height m); the disagreement (m) over the window when it exceeds the
        bound, None otherwise (or while the window is not yet full). Non-finite values restart the window."""
        if not (math.isfinite(t) and math.isfinite(z_pose) and math.isfinite(h_own)):
            self._hist.clear()
            return None
        if self._hist and t <= self._hist[-1][0]:
            return None
        self._hist.append((t, z_pose, h_own))
        while len(self._hist) > 1 and t - self._hist[1][0] >= self.window_s:
            self._hist.popleft()
        t0, z0, h0 = self._hist[0]
        if t - t0 < self.window_s:
            return None
        d = (z_pose - z0) - (h_own - h0)
        return d if abs(d) > self.bound_m else None

    def reset(self) -> None:
        self._hist.clear()


@dataclass
class MotionAgreement:
    """A ground robot's planar displacement against its commands over a sliding window (module docstring)."""

    window_s: float = MOTION_WINDOW_S
    jump_m: float = MOTION_JUMP_M
    lag_s: float = MOTION_LAG_S
    # (t s, measured x, y m, predicted x, y m, commanded speed m/s) per sample
    _hist: deque[tuple[float, float, float, float, float, float]] = field(default_factory=deque)
    _theta: float = 0.0  # heading of the newest sample (rad, world)

    def sample(self, t: float, x: float, y: float, theta: float, command: np.ndarray | None) -> float | None:
        """Add the sample (t s; x, y m, θ rad in the world) and the command V = [v_x, v_y, 0, ω] (m/s,
        rad/s, body) in effect since the previous one (None: none); the disagreement (m) when it exceeds
        the bound over a full window, None otherwise."""
        v = np.zeros(2) if command is None else np.asarray(command, dtype=float)[:2]
        if not np.all(np.isfinite(v)):
            v = np.zeros(2)
        if self._hist and t <= self._hist[-1][0]:
            return None
        if self._hist and t - self._hist[-1][0] > MOTION_GAP_S:
            self._hist.clear()
        if self._hist:
            t1, _, _, px, py, _ = self._hist[-1]
            c, s = math.cos(self._theta), math.sin(self._theta)
            px, py = px + (c * v[0] - s * v[1]) * (t - t1), py + (s * v[0] + c * v[1]) * (t - t1)
        else:
            px, py = x, y
        self._hist.append((t, x, y, px, py, float(np.hypot(v[0], v[1]))))
        self._theta = theta
        while len(self._hist) > 1 and t - self._hist[1][0] >= self.window_s:
            self._hist.popleft()
        t0, x0, y0, px0, py0, _ = self._hist[0]
        if t - t0 < self.window_s:
            return None
        d = math.hypot((x - x0) - (px - px0), (y - y0) - (py - py0))
        bound = self.jump_m + self.lag_s * max(h[5] for h in self._hist)
        return d if d > bound else None


__all__ = [
    "HEIGHT_DISAGREE_M",
    "HEIGHT_WINDOW_S",
    "MOTION_GAP_S",
    "MOTION_JUMP_M",
    "MOTION_LAG_S",
    "MOTION_WINDOW_S",
    "MOVING_MPS",
    "MOVING_RADPS",
    "FreezeWatch",
    "HeightAgreement",
    "MotionAgreement",
    "moving",
]
