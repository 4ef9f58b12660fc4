"""What ArduPilot Rover needs to know where it is indoors: the EKF origin and the robot's motion-capture
pose as external navigation (pure: no I/O; drivers/scamper/driver.py sends what these decide).

**Frames.** flightstack's world frame Σw is the motion-capture frame, right-handed, z up, yaw θ about
z_w counter-clockwise (docs/equations.md). The autopilot's local frame is NED. The driver declares lab
+x to be "north": ``x_ned = x``, ``y_ned = −y``, ``z_ned = −z``, ``yaw_ned = −θ`` (the same FLU→FRD
flip the set-points already use), so a robot at lab (1, 2) facing lab +x is at NED (1, −2) with yaw 0,
facing lab +y it has yaw −π/2. With ``EK3_SRC1_YAW = 6`` (external navigation) the EKF takes this yaw as
is; no compass, no true north: the origin's latitude/longitude only anchor the EKF's local frame (logs
and map displays show the lab there), nothing moves by them.

**Time.** ``usec`` of VISION_POSITION_ESTIMATE is the pose's capture time on ``time.monotonic()`` (the
hardware backend's clock, CLOCK_MONOTONIC on Linux: time since this computer booted), in µs. ArduPilot
maps an off-board timestamp to its own clock with a jitter filter
(``GCS_MAVLINK::correct_offboard_timestamp_usec_to_ms``, libraries/GCS_MAVLink/GCS_Common.cpp), so any
monotonic clock works as long as it does not jump; the wall clock could.

**Rate and freshness.** ArduPilot's developer docs ask for the external-navigation messages "at 4hz or
higher" (ardupilot.org/dev/docs/mavlink-nongps-position-estimation.html); the visual-odometry backend
counts as unhealthy after 300 ms without one (``AP_VisualOdom_Backend::healthy``,
``AP_VISUALODOM_TIMEOUT_MS``), the EKF declares dead reckoning after 1 s without a position
(``deadReckonDeclare_ms``, AP_NavEKF3.h) and drops samples closer together than
``extNavIntervalMin_ms`` (``NavEKF3_core::writeExtNavData``). The driver sends at ``vision_hz``
(default 20 Hz) and never a pose older than ``vision_max_age_s`` (default 0.2 s): a stale pose is not
sent (counted), so the autopilot's own timeouts see the loss instead of a frozen position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightstack.hal import StampedPose

POSE_UNKNOWN_COVARIANCE = (math.nan,) + (0.0,) * 20
"""VISION_POSITION_ESTIMATE.covariance: first element NaN = unknown (MAVLink common.xml); ArduPilot then
uses its VISO_POS_M_NSE / VISO_YAW_M_NSE noise parameters (handle_common_vision_position_estimate_data)."""
ORIGIN_RETRY_S = 1.0  # SET_GPS_GLOBAL_ORIGIN + REQUEST_MESSAGE(49) again this long after the last try (s)


def lab_to_ned(p: np.ndarray, theta: float) -> tuple[float, float, float, float]:
    """Lab position p (m, z up) and yaw θ (rad, ccw) → NED (x, y, z) m and yaw (rad, clockwise from +x)."""
    x, y, z = (float(v) for v in np.asarray(p, dtype=float).reshape(3))
    return x, -y, -z, _wrap(-float(theta))


def ned_to_lab(x: float, y: float, z: float, yaw: float) -> tuple[np.ndarray, float]:
    """The inverse of `lab_to_ned`: NED (m, rad) → lab position (m, z up) and yaw θ (rad, ccw)."""
    return np.array([x, -y, -z], dtype=float), _wrap(-yaw)


def _wrap(a: float) -> float:
    """Angle wrapped to (−π, π]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


@dataclass(frozen=True)
class LabOrigin:
    """The EKF origin the driver sets: WGS84 latitude/longitude (degrees), altitude (m above MSL)."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        ok = all(map(math.isfinite, (self.lat_deg, self.lon_deg, self.alt_m)))
        if not (ok and abs(self.lat_deg) <= 90.0 and abs(self.lon_deg) <= 180.0):
            raise ValueError(f"not a WGS84 origin: {self}")

    def as_mavlink(self) -> tuple[int, int, int]:
        """SET_GPS_GLOBAL_ORIGIN's latitude, longitude (degE7) and altitude (mm)."""
        return round(self.lat_deg * 1e7), round(self.lon_deg * 1e7), round(self.alt_m * 1000.0)

    def matches(self, lat_e7: int, lon_e7: int, alt_mm: int) -> bool:
        """GPS_GLOBAL_ORIGIN reports this origin (ArduPilot keeps the altitude in cm: ±10 mm allowed)."""
        lat, lon, alt = self.as_mavlink()
        return abs(lat_e7 - lat) <= 1 and abs(lon_e7 - lon) <= 1 and abs(alt_mm - alt) <= 10


@dataclass(frozen=True)
class VisionSample:
    """The arguments of one VISION_POSITION_ESTIMATE (NED m, rad; usec on time.monotonic())."""

    usec: int
    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float
    reset_counter: int


class VisionStream:
    """Decides what each vision tick sends: the newest fresh pose, once; a stale or repeated one is not.

    ``reset_counter`` (0..255) goes up when a pose comes back after a gap (stale, or never seen): the body
    was re-acquired and may jump, which ArduPilot then takes as a position reset, not a glitch
    (``AP_VisualOdom_Backend::get_reset_timestamp_ms``).
    """

    def __init__(self, max_age_s: float) -> None:
        if not (math.isfinite(max_age_s) and max_age_s > 0.0):
            raise ValueError(f"vision_max_age_s must be finite and > 0, got {max_age_s}")
        self.max_age_s = max_age_s
        self.reset_counter = 0
        self._last_stamp: float | None = None
        self._gap = False

    def next(self, sp: StampedPose | None, now: float) -> tuple[VisionSample | None, str]:
        """(sample, "") to send, or (None, reason): "no pose", "stale", "not new", "not finite"."""
        if sp is None:
            self._gap = True
            return None, "no pose"
        if not math.isfinite(sp.stamp) or now - sp.stamp > self.max_age_s:
            self._gap = True
            return None, "stale"
        if self._last_stamp is not None and sp.stamp <= self._last_stamp:
            return None, "not new"
        try:
            x, y, z, yaw = lab_to_ned(sp.pose.p, sp.pose.theta)
        except (AttributeError, TypeError, ValueError):
            return None, "not finite"
        if not all(map(math.isfinite, (x, y, z, yaw))):
            return None, "not finite"
        if self._gap and self._last_stamp is not None:
            self.reset_counter = (self.reset_counter + 1) % 256
        self._gap = False
        self._last_stamp = sp.stamp
        return VisionSample(int(sp.stamp * 1e6), x, y, z, 0.0, 0.0, yaw, self.reset_counter), ""


@dataclass
class OriginState:
    """The EKF origin's state for one vehicle boot: sent how often, confirmed by the vehicle or not."""

    confirmed: bool = False
    reported: tuple[int, int, int] | None = None  # what GPS_GLOBAL_ORIGIN said (degE7, degE7, mm)
    sends: int = 0  # SET_GPS_GLOBAL_ORIGIN sent this boot
    last_try_s: float | None = None  # time.monotonic() of the last try to send it (s)
    boots: int = 0  # times the vehicle was seen to (re)boot: origin forgotten, sent again

    def try_due(self, now_s: float) -> bool:
        """Is a try to set the origin due at now_s (time.monotonic(), s): unconfirmed and none in the last
        ORIGIN_RETRY_S? If so it counts as made now, so two callers never both send."""
        if self.confirmed or (self.last_try_s is not None and now_s - self.last_try_s < ORIGIN_RETRY_S):
            return False
        self.last_try_s = now_s
        return True

    def forget(self) -> None:
        """The vehicle rebooted or came back after a gap: its EKF origin must be set and confirmed again."""
        self.confirmed, self.reported, self.sends, self.last_try_s = False, None, 0, None
        self.boots += 1
