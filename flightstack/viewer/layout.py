"""Where everything goes in the Rerun recording, and at which rate (no rerun import here).

Entity paths: one subtree per mode (`/<mode>/...`), the mission's static facts under `/mission/...`
(the package docstring draws the tree). Rates are rules on the tick index k (every `stride`-th tick,
k % stride == 0), so a replay and a live view of the same run log the same ticks:

* 3-D poses and trails: at most `REPLAY_3D_HZ` (replay) or `LIVE_3D_HZ` (live) of mission time;
* scalars: every tick up to `SCALAR_CAP` rows per series and mode (replay; longer recordings take every
  ⌈N / SCALAR_CAP⌉-th tick), at most `LIVE_SCALAR_HZ` of mission time live;
* live: the logging thread sends at most `LIVE_FLUSH_HZ` batches per wall-clock second, camera images at
  most `IMAGE_HZ` per drone and wall-clock second.
"""

from __future__ import annotations

import math

import numpy as np

from flightstack.recording.timeseries import LOOP_HEALTH_FIELDS

TIMELINE = "mission_time"
"""The one timeline: the mission clock of each mode (s, a Rerun duration)."""

REPLAY_3D_HZ = 20.0
"""3-D entities (poses, trails) of a replay: at most this rate of mission time (Hz)."""
SCALAR_CAP = 10_000
"""Scalars of a replay: every tick, or every ⌈N / SCALAR_CAP⌉-th of a longer mode (rows per series)."""
LIVE_3D_HZ = 10.0
"""3-D entities while flying: at most this rate of mission time (Hz)."""
LIVE_SCALAR_HZ = 50.0
"""Scalars while flying: at most this rate of mission time (Hz)."""
LIVE_FLUSH_HZ = 10.0
"""The live logging thread sends at most this many batches per wall-clock second."""
IMAGE_HZ = 2.0
"""Live camera images (JPEG): at most this many per drone and wall-clock second."""
JPEG_QUALITY = 75
TRAIL_S = 10.0
"""A trail shows the body's path over the last TRAIL_S seconds of mission time..."""
TRAIL_HZ = 5.0
"""...sampled at TRAIL_HZ (Hz), plus the current pose."""

MISSION = "/mission"

#: 4-vector series: their component names (units) in the order of the recording's last axis
POSE_ERROR_NAMES = ("x [m]", "y [m]", "z [m]", "sin θ")  # vec(g) = [p, sin θ]
VELOCITY_NAMES = ("v_x [m/s]", "v_y [m/s]", "v_z [m/s]", "ω [rad/s]")  # body velocity of the target
VARIANCE_NAMES = ("v_x [m²/s²]", "v_y [m²/s²]", "v_z [m²/s²]", "ω [rad²/s²]")

HEALTH_FIELDS = LOOP_HEALTH_FIELDS
"""Loop-health arrays of a Recording (s), logged as scalars where measured ((N,) under
`/<mode>/loop/<name>`, (N, n) under `/<mode>/<name>/drone<i>`)."""

TARGET_RGB = (255, 140, 0)
_PALETTE = (
    (31, 119, 180),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)


def drone_rgb(drone_id: int) -> tuple[int, int, int]:
    """The colour of drone `drone_id`, shared by its pose, estimate, trail, camera, region and training
    points (by id, so that an agent's recording of one drone keeps the colours of the whole fleet)."""
    return _PALETTE[(drone_id - 1) % len(_PALETTE)]


# ---- entity paths ---------------------------------------------------------------------------------------
def world(mode: str) -> str:
    return f"/{mode}/world"


def target(mode: str) -> str:
    """True target pose g_w0."""
    return f"/{mode}/world/target"


def drone(mode: str, i: int) -> str:
    """Drone i's true pose g_wi (i: the drone id)."""
    return f"/{mode}/world/drone{i}"


def estimate(mode: str, i: int) -> str:
    """Drone i's estimate ḡ_w,i of the target pose."""
    return f"/{mode}/world/estimate{i}"


def camera(mode: str, i: int) -> str:
    """Drone i's camera frame Σc (child of the drone: the mount extrinsic R_ic, t_ic)."""
    return f"/{mode}/world/drone{i}/camera"


def image(mode: str, i: int) -> str:
    """Drone i's image plane: the Pinhole (frustum) and, live, its camera images."""
    return f"/{mode}/world/drone{i}/camera/image"


def markers(mode: str, i: int) -> str:
    """Live: the marker centres drone i's agent detected in the image shown (pixels, distorted image)."""
    return f"{image(mode, i)}/markers"


def trail(mode: str, body: str) -> str:
    """The path of `body` ("target", "drone<i>", "estimate<i>") over the last TRAIL_S seconds."""
    return f"/{mode}/world/trails/{body}"


def series(mode: str, signal: str, i: int | None = None) -> str:
    """A scalar series: per drone `/<mode>/<signal>/drone<i>`, else `/<mode>/<signal>`."""
    return f"/{mode}/{signal}" if i is None else f"/{mode}/{signal}/drone{i}"


def events(mode: str) -> str:
    return f"/{mode}/events"


def region(i: int) -> str:
    return f"{MISSION}/regions/drone{i}"


def training(i: int) -> str:
    return f"{MISSION}/training/drone{i}"


# ---- rates ----------------------------------------------------------------------------------------------
def stride(dt: float, hz: float, base: int = 1) -> int:
    """The smallest multiple of `base` ticks whose period stride·dt (dt: s per tick) is at least 1/hz (s):
    every stride-th tick is at most `hz` of mission time."""
    if not (dt > 0 and math.isfinite(dt)):
        return base
    raw = max(1, math.ceil(1.0 / (hz * dt) - 1e-9))
    return base * math.ceil(raw / base)


def scalar_stride(n_ticks: int, cap: int = SCALAR_CAP) -> int:
    """Every tick up to `cap` rows, else every ⌈n_ticks / cap⌉-th."""
    return max(1, math.ceil(n_ticks / cap))


def ticks(n_ticks: int, every: int) -> np.ndarray:
    """The tick indices k < n_ticks with k % every == 0."""
    return np.arange(0, max(0, n_ticks), max(1, every))


def tick_period(t: np.ndarray) -> float:
    """The recording's tick period (s): the median step of its mission clock t (s); NaN below two ticks."""
    if t.shape[0] < 2:
        return math.nan
    return float(np.median(np.diff(t)))
