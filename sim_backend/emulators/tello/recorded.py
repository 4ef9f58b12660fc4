"""What real Tellos send, as recordings of real Tellos show it: the facts the emulator follows.

Sources: ``xg590`` = the flight log ``../shared/data/peers/tello/xg590_Tello_flight_log_20201018_052457.db``
of an original Tello (216 state lines at 10 Hz, times from the ``takeoff`` command); ``devconx`` = the raw
H.264 dump ``../shared/data/peers/tello/devconx_test.h264`` (provenance: ``../shared/data/peers/README.md``;
docs/drivers.md, "What a real Tello sends", tabulates them):

* the ``ok`` to ``takeoff`` arrives ``TAKEOFF_OK_S`` after the command (xg590: +8.70 s; liftoff at
  +0.94 s, h 70 from +2.83 s, then hovering).
* H.264 keyframes are at least ``KEYFRAME_INTERVAL_FRAMES`` apart (devconx: its first dump has an IDR
  and 59 P frames with no second IDR; the second dump's ``frame_num`` runs 7 … 66 with no IDR, so its
  last frame is 66 reference frames after its IDR (``log2_max_frame_num`` 8; a wrap at 256 would only
  make it longer) — 67 frames, 2.2 s at 30 fps, without a keyframe).
* ``vgz`` is positive **down** (dm/s): xg590 reads −1, −4, −6, −8, −8, −8, −7, −7, −5 during the climb and
  +3 … +6 during the landing. ``vgx``/``vgy`` are in the frame of yaw 0 (x along yaw 0, y to its right),
  not the body frame: at yaw −26°, ``forward 50`` read vgx +3, vgy −1 and ``left 50`` vgx −1, vgy −3.
* ``h`` (cm, relative to the takeoff point) moves in ``H_STEP_CM`` steps, every value a multiple of 10,
  and lags the true height: during the climb 12 of 20 samples equal ``floor((tof − 10) / 10) · 10``, 6
  equal the rounded value, hence ``floor``. It drifts: ``h − (tof − 10)`` over the flat floor falls from
  −3 cm at liftoff to −70 cm at rest after landing (least-squares slope ``H_DRIFT_CM_S`` = −3.5 cm/s;
  −70 cm over the 19.6 s from liftoff to rest is −3.6 cm/s), so the ramp is the recording's mean rate
  (the drift came mostly between +5.6 and +8.1 s; a ramp is the simplest process with that mean). It did
  not drift on: hovering over the flat floor from +9.1 s on, ``h − (tof − 10)`` stays within −65 … −70 cm
  (36 lines at +9.1 … +11.6 s and +17.0 … +18.0 s; between them the drone flew over a lower surface), h
  lags by up to 9 cm more while it descends to land (−79 cm), and it reads −70 cm at rest after landing.
  So the ramp saturates at ``H_DRIFT_MAX_CM`` (70 cm), the most the recording shows. Beyond the
  recording's 21 s the bound is *assumed* (no longer recording is held; another real flight is reported
  not to drift at all, users' flight logs): with the unbounded ramp it replaces, a drone hovering at
  80 cm reported h below −1000 cm from 309 s of flight on. The drift starts at each takeoff (xg590: h 0 on
  the ground before takeoff; that it restarts at a second takeoff is *unverified*).
* ``tof`` (cm) measures the distance to the surface below plus ``TOF_GROUND_CM`` (xg590: 10 on the ground
  before takeoff and after landing; 23 at h 10): it follows the terrain (xg590: 118 → 170 cm within
  0.5 s during ``left 50``, the drone passing an edge, while h stayed 40), and is ``TOF_OUT_OF_RANGE``
  beyond the sensor's range. 6553 is **not** in xg590 (its largest tof is 178); it is in the state lines
  users of real Tellos paste into their code (``tof:6553;h:0;…;time:0``, a drone on the ground that has
  not flown; e.g. the sample state strings of several GitHub Tello clients) and is 65535 mm / 10 (the
  16-bit sensor's no-reading value, in cm: an inference). ``TOF_MAX_CM``, the range, is *unverified*: no
  published number; a tellopilots user estimates "up to 3 meters distance from a surface or so (also
  depending on the texture and angle)" (https://tellopilots.com/threads/ir-height-data.6132/).

Pure functions and constants; ``physics``, ``commands`` and ``video`` apply them to the emulator's
ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable

TAKEOFF_OK_S = 8.70
"""Delay (s) of the ``ok`` to ``takeoff`` (xg590)."""
LAND_TOUCHDOWN_S = 2.83
"""From ``land`` to the touchdown (s): xg590 sent ``land`` at +17.37 s, its descent showed from +18.13 s and
``tof`` read its ground value from +20.2 s."""
LAND_OK_S = 4.23
"""From ``land`` to its ``ok`` (s): xg590 +21.60 s, 1.4 s after the touchdown; real transcripts show
3.7–4.2 s (users' console transcripts)."""
KEYFRAME_INTERVAL_FRAMES = 67
"""Frames from one H.264 IDR to the next, at least (devconx; the real interval may be longer)."""
H_STEP_CM = 10
"""Resolution of ``h`` (cm): xg590's 216 h values are all multiples of 10."""
H_DRIFT_CM_S = -3.5
"""Drift of ``h`` against the true height while the motors run (cm/s; negative: h reads low), xg590's
least-squares slope of ``h − (tof − 10)`` over the flat floor."""
H_DRIFT_MAX_CM = 70.0
"""Largest drift of ``h`` (cm, either sign): xg590's ``h − (tof − 10)`` hovering over the flat floor from
+9.1 s on and at rest after landing (beyond its 21 s *assumed*; module docstring)."""
TOF_GROUND_CM = 10
"""``tof`` of a Tello standing on the surface (cm): xg590 before takeoff and after landing."""
TOF_OUT_OF_RANGE = 6553
"""``tof`` when the sensor sees no surface (users' state lines; not in xg590)."""
TOF_MAX_CM = 300.0
"""Largest distance (cm) the downward sensor measures (*unverified*: a user's estimate, module docstring)."""

Surface = Callable[[float, float], float]
"""Height (cm) of the surface below the world point ``(x forward, y right)`` (cm), relative to the
takeoff floor: what ``tof`` measures to (a table, a step). The emulator's drone still never goes below the
takeoff floor (z ≥ 0); a surface above it is seen, not collided with."""


def flat_floor(_x: float, _y: float) -> float:
    """The default surface: the takeoff floor everywhere (0 cm)."""
    return 0.0


def reported_h(true_height_cm: float, drift_cm: float) -> int:
    """The state line's ``h`` (cm): the true height plus the drift, floored to ``H_STEP_CM`` steps."""
    return H_STEP_CM * math.floor((true_height_cm + drift_cm) / H_STEP_CM)


def drifted(drift_cm: float, rate_cm_s: float, dt_s: float, max_cm: float = H_DRIFT_MAX_CM) -> float:
    """The drift of ``h`` (cm) ``dt_s`` s after it was ``drift_cm``, ramping at ``rate_cm_s`` and held within
    ``±max_cm``."""
    return max(-max_cm, min(max_cm, drift_cm + rate_cm_s * dt_s))


def reported_tof(above_surface_cm: float, max_cm: float = TOF_MAX_CM) -> int:
    """The state line's ``tof`` (cm) at ``above_surface_cm`` over the surface below: that plus
    ``TOF_GROUND_CM``, or ``TOF_OUT_OF_RANGE`` beyond ``max_cm``."""
    if above_surface_cm > max_cm:
        return TOF_OUT_OF_RANGE
    return round(max(0.0, above_surface_cm)) + TOF_GROUND_CM


def reported_vg(velocity_cm_s: tuple[float, float, float]) -> tuple[int, int, int]:
    """``(vgx, vgy, vgz)`` in dm/s of a world velocity ``(x, y, z up)`` in cm/s: vgz positive down."""
    vx, vy, vz = velocity_cm_s
    return round(vx / 10.0), round(vy / 10.0), round(-vz / 10.0)
