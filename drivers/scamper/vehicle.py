"""Can this ArduPilot Rover be driven by flightstack indoors? The rules over its parameters for external
navigation, the GUIDED timeout and its frame (pure: no I/O; preflight reads the parameters).

Sources (ArduPilot, repository ArduPilot/ardupilot; the developer page
ardupilot.org/dev/docs/mavlink-nongps-position-estimation.html):

* ``AHRS_EKF_TYPE`` 3 = EKF3 (libraries/AP_AHRS/AP_AHRS.cpp); the external-navigation sources below are
  EKF3's.
* ``EK3_SRC1_POSXY`` and ``EK3_SRC1_YAW`` 6 = ExternalNav (``AP_NavEKF_Source::SourceXY::EXTNAV``,
  ``SourceYaw::EXTNAV``, libraries/AP_NavEKF/AP_NavEKF_Source.h): the EKF takes position and yaw from
  VISION_POSITION_ESTIMATE.
* ``EK3_SRC1_POSZ`` 1 (Baro, ArduPilot's default) or 6, ``EK3_SRC1_VELXY`` and ``EK3_SRC1_VELZ`` 0 (None:
  the driver sends no velocity) or 6 (`NAV_ALLOWED`). ``AP_NavEKF_Source::pre_arm_check``
  (libraries/AP_NavEKF/AP_NavEKF_Source.cpp) refuses to arm with POSZ 0 ("Check EK3_SRC1_POSZ") and with
  any source on GPS (3; VELXY's and VELZ's default) when the vehicle has no GPS ("EK3 sources require
  GPS"); indoors a GPS that has one gives no fix, and one that finds a fix near a window would fight the
  motion capture, so GPS is refused either way.
* ``VISO_TYPE`` 1 = MAVLink (``AP_VisualOdom::var_info``, libraries/AP_VisualOdom/AP_VisualOdom.cpp);
  with 0 ``AP_VisualOdom::handle_pose_estimate`` ignores every VISION_POSITION_ESTIMATE.
* ``GUID_TIMEOUT`` (s, default 3, range 0.1–5; Rover/Parameters.cpp): ``ModeGuided::update``
  (Rover/mode_guided.cpp) stops the robot when no velocity / turn-rate set-point came for that long
  ("target not received last … secs, stopping"). flightstack relies on it (docs/drivers.md): at most
  `MAX_GUIDED_TIMEOUT_S` (what the driver's docs promise), at least `MIN_GUIDED_SETPOINTS` set-point
  periods (lost datagrams would stop the robot mid-run).
* Kinematics: ``FRAME_CLASS`` (0 Undefined, 1 Rover, 2 Boat, 3 BalanceBot; Rover/Parameters.cpp) and
  ``FRAME_TYPE`` (0 Undefined, 1 Omni3, 2 OmniX, 3 OmniPlus, 4 Omni3Mecanum) say omni or not; they do
  **not** tell skid steering from Ackermann steering. ArduPilot decides that by the outputs:
  ``AP_MotorsUGV::have_skid_steering`` (libraries/AR_Motors/AP_MotorsUGV.cpp) is true when both
  ThrottleLeft (``SERVOn_FUNCTION`` 73) and ThrottleRight (74) are assigned; GroundSteering (26) with
  Throttle (70) is a steered (Ackermann) vehicle. So `vehicle_kinematics` takes the servo functions too.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Literal

Status = Literal["PASS", "WARN", "FAIL"]
Kinematics = Literal["differential", "ackermann", "omni", "boat", "unknown"]

NAV_NEEDED: dict[str, int] = {"AHRS_EKF_TYPE": 3, "EK3_SRC1_POSXY": 6, "EK3_SRC1_YAW": 6, "VISO_TYPE": 1}
"""What the vehicle must be set to for the driver's VISION_POSITION_ESTIMATE to be its position (above)."""
NAV_ALLOWED: dict[str, tuple[int, ...]] = {
    "EK3_SRC1_POSZ": (1, 6),
    "EK3_SRC1_VELXY": (0, 6),
    "EK3_SRC1_VELZ": (0, 6),
}
"""The other EKF3 sources indoors: the values it may keep, the first the one to set (above)."""
GUID_TIMEOUT = "GUID_TIMEOUT"
MAX_GUIDED_TIMEOUT_S = 3.0
MIN_GUIDED_SETPOINTS = 5
FRAME_CLASS, FRAME_TYPE = "FRAME_CLASS", "FRAME_TYPE"
SERVO_FUNCTIONS = tuple(f"SERVO{i}_FUNCTION" for i in range(1, 17))
SKID_LEFT, SKID_RIGHT, GROUND_STEERING = 73, 74, 26  # SRV_Channel::k_throttleLeft / Right / k_steering
OMNI_FRAME_TYPES = {1: "Omni3", 2: "OmniX", 3: "OmniPlus", 4: "Omni3Mecanum"}
PARAMETERS = (*NAV_NEEDED, *NAV_ALLOWED, GUID_TIMEOUT, FRAME_CLASS, FRAME_TYPE, *SERVO_FUNCTIONS)
"""What preflight reads for these rules (besides the GCS failsafe's: drivers/scamper/failsafe.py)."""
KINEMATICS_SOURCE = (
    "FRAME_CLASS/FRAME_TYPE (Rover/Parameters.cpp) and SERVOn_FUNCTION 73+74 skid steering "
    "(AP_MotorsUGV::have_skid_steering), 26 ground steering"
)


@dataclass(frozen=True)
class Verdict:
    """One rule's answer: status and one line."""

    status: Status
    detail: str


def _fmt(v: float | None) -> str:
    return "unread" if v is None else f"{v:g}"


def _int(v: float | None) -> int | None:
    return int(v) if v is not None and math.isfinite(v) and v == math.floor(v) else None


def judge_external_nav(values: Mapping[str, float]) -> Verdict:
    """FAIL, naming everything to set, unless every NAV_NEEDED parameter has its value and every NAV_ALLOWED
    one an allowed value."""
    wanted = {name: (want,) for name, want in NAV_NEEDED.items()} | NAV_ALLOWED
    wrong = []
    for name, allowed in wanted.items():
        have = values.get(name)
        if _int(have) not in allowed:
            wrong.append(f"{name} {allowed[0]} (now {_fmt(have)})")
    if wrong:
        return Verdict("FAIL", "no external position source: set on the vehicle " + ", ".join(wrong))
    return Verdict("PASS", ", ".join(f"{n} {_fmt(values.get(n))}" for n in wanted))


def judge_guided_timeout(values: Mapping[str, float], stream_hz: float) -> Verdict:
    """GUID_TIMEOUT within [MIN_GUIDED_SETPOINTS / stream_hz, MAX_GUIDED_TIMEOUT_S]; unread: WARN (Rover
    firmware before the parameter stopped after a fixed 3 s)."""
    lo = MIN_GUIDED_SETPOINTS / stream_hz
    want = f"set GUID_TIMEOUT between {lo:g} and {MAX_GUIDED_TIMEOUT_S:g} s on the vehicle"
    v = values.get(GUID_TIMEOUT)
    if v is None:
        return Verdict("WARN", "GUID_TIMEOUT not read (older Rover firmware stops after a fixed 3 s)")
    if not math.isfinite(v) or v > MAX_GUIDED_TIMEOUT_S:
        why = "the robot drives on its last set-point that long"
        return Verdict("FAIL", f"GUID_TIMEOUT {v:g} s: {why}; {want}")
    if v < lo:
        return Verdict(
            "FAIL", f"GUID_TIMEOUT {v:g} s: {MIN_GUIDED_SETPOINTS} lost set-points stop the robot; {want}"
        )
    return Verdict("PASS", f"GUID_TIMEOUT {v:g} s (stops that long after our last set-point)")


def vehicle_kinematics(
    frame_class: float | None, frame_type: float | None, servo_functions: Collection[float] | None = None
) -> Kinematics:
    """The vehicle's kinematics from FRAME_CLASS, FRAME_TYPE and (to tell skid from steered) the
    SERVOn_FUNCTION values; sources: the module docstring (`KINEMATICS_SOURCE`).

    "omni" for an omni FRAME_TYPE, "boat" for FRAME_CLASS 2, "differential" for skid steering (ThrottleLeft
    and ThrottleRight assigned; a BalanceBot, FRAME_CLASS 3, is one), "ackermann" for GroundSteering,
    "unknown" otherwise (e.g. no servo functions given: FRAME_CLASS/FRAME_TYPE alone cannot tell).
    """
    fc, ft = _int(frame_class), _int(frame_type)
    if fc == 2:
        return "boat"
    if fc not in (0, 1, 3):
        return "unknown"
    if fc != 3 and ft in OMNI_FRAME_TYPES:
        return "omni"
    if ft not in (0, None) and ft not in OMNI_FRAME_TYPES:
        return "unknown"
    functions = {_int(f) for f in servo_functions or ()}
    if {SKID_LEFT, SKID_RIGHT} <= functions:
        return "differential"
    if fc == 3:
        return "unknown"  # a BalanceBot drives skid outputs; without them it cannot drive
    if GROUND_STEERING in functions:
        return "ackermann"
    return "unknown"


def judge_kinematics(values: Mapping[str, float]) -> Verdict:
    """Report the kinematics the vehicle's parameters give (`vehicle_kinematics`); unknown: WARN."""
    servos = [values[n] for n in SERVO_FUNCTIONS if n in values]
    kind = vehicle_kinematics(values.get(FRAME_CLASS), values.get(FRAME_TYPE), servos if servos else None)
    said = ", ".join(f"{n} {_fmt(values.get(n))}" for n in (FRAME_CLASS, FRAME_TYPE))
    if kind in ("differential", "ackermann", "omni"):
        return Verdict("PASS", f"{kind} ({said}; {len(servos)} servo functions read)")
    return Verdict("WARN", f"{kind} ({said}; {len(servos)} servo functions read): state the kind in the rig")
