"""The emulated Rover firmware's parameters: the values it boots with (`RoverParams`) and the live table a
ground station reads and sets (`ParamStore`), typed as ArduPilot types them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink import mavutil

mavlink = mavutil.mavlink
I8, I16, I32, F32 = (
    mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_INT16, mavlink.MAV_PARAM_TYPE_INT32,
    mavlink.MAV_PARAM_TYPE_REAL32,
)  # fmt: skip
OLD_FIRMWARE_GCS_TIMEOUT_S = 2.0  # the fixed GCS timeout of firmware without FS_GCS_TIMEOUT
# SERVOn_FUNCTION values (SRV_Channel.h): skid steering is two throttle outputs, Ackermann steering + throttle
SKID_FUNCTIONS = (73, 74)  # ThrottleLeft, ThrottleRight
ACKERMANN_FUNCTIONS = (26, 70)  # GroundSteering, Throttle
EXTERNAL_NAV = 6  # EK3_SRCn_POSXY / _YAW: ExternalNav
GPS_SOURCE = 3  # EK3_SRCn_POSXY / _VELXY / _POSZ / _VELZ: GPS


@dataclass(frozen=True)
class RoverParams:
    """The values the emulated firmware boots with; the defaults are what the lab's Scamper must be set to:
    the GCS failsafe on, Hold, 3 s + 1 s, our GCS system id 255 (docs/drivers.md, "The robot's own
    failsafe"), EKF3 with motion capture as its position and yaw source (``AHRS_EKF_TYPE`` 3,
    ``EK3_SRC1_POSXY`` / ``EK3_SRC1_YAW`` 6, ``VISO_TYPE`` 1, no GPS), the GUIDED timeout 3 s and a
    cruise speed of 0.5 m/s (``WP_SPEED`` 0: ``CRUISE_SPEED`` is the set-point speed limit).

    ``steering``: "skid" (differential: turns in place) or "ackermann" (no turn tighter than
    ``TURN_RADIUS``); it shows, as on ArduPilot, in ``SERVO1_FUNCTION`` / ``SERVO3_FUNCTION`` (73/74
    ThrottleLeft/Right or 26/70 GroundSteering/Throttle), not in ``FRAME_CLASS`` (1 Rover) / ``FRAME_TYPE``
    (0 undefined; 1-3 omni frames). ``absent``: parameters this firmware does not have (never answered).
    """

    fs_gcs_enable: int = 1
    fs_action: int = 2  # Hold
    fs_timeout_s: float = 1.0
    fs_gcs_timeout_s: float = 3.0
    gcs_sysid: int = 255
    gcs_sysid_name: str = "SYSID_MYGCS"  # or "MAV_GCS_SYSID" (newer firmware, which also has _HI)
    gcs_sysid_hi: int = 0  # MAV_GCS_SYSID_HI (only with gcs_sysid_name "MAV_GCS_SYSID")
    fs_options: int = 0
    absent: frozenset[str] = frozenset()
    rtl_speed_mps: float = 0.5  # emulator's RTL / SmartRTL speed toward home
    wp_radius_m: float = 2.0  # WP_RADIUS: RTL stops this close to home
    steering: str = "skid"
    frame_class: int = 1  # Rover
    frame_type: int = 0  # undefined (not omni)
    cruise_speed_mps: float = 0.5  # CRUISE_SPEED
    wp_speed_mps: float = 0.0  # WP_SPEED: 0 uses CRUISE_SPEED
    guid_timeout_s: float = 3.0  # GUID_TIMEOUT
    turn_radius_m: float = 0.9  # TURN_RADIUS (ArduPilot's default)
    steer_rate_max_dps: float = 120.0  # ATC_STR_RAT_MAX (deg/s)
    steer_ang_p: float = 2.0  # ATC_STR_ANG_P (1/s): heading error to turn rate
    ahrs_ekf_type: int = 3
    ek3_src1_posxy: int = EXTERNAL_NAV
    ek3_src1_yaw: int = EXTERNAL_NAV
    viso_type: int = 1  # MAVLink
    fs_ekf_action: int = 1  # Hold

    def __post_init__(self) -> None:
        if self.gcs_sysid_name not in ("SYSID_MYGCS", "MAV_GCS_SYSID"):
            raise ValueError(
                f"gcs_sysid_name must be SYSID_MYGCS or MAV_GCS_SYSID, got {self.gcs_sysid_name!r}"
            )
        if self.steering not in ("skid", "ackermann"):
            raise ValueError(f"steering must be skid or ackermann, got {self.steering!r}")

    def table(self, system_id: int) -> list[tuple[str, float, int]]:
        """(name, value, MAV_PARAM_TYPE) in index order, without the absent ones."""
        servo1, servo3 = SKID_FUNCTIONS if self.steering == "skid" else ACKERMANN_FUNCTIONS
        rows = [
            ("SYSID_THISMAV", float(system_id), I16),
            (self.gcs_sysid_name, float(self.gcs_sysid), I16),
            ("FS_ACTION", float(self.fs_action), I8),
            ("FS_TIMEOUT", float(self.fs_timeout_s), F32),
            ("FS_GCS_ENABLE", float(self.fs_gcs_enable), I8),
            ("FS_OPTIONS", float(self.fs_options), I32),
            ("FS_GCS_TIMEOUT", float(self.fs_gcs_timeout_s), F32),
            ("FS_EKF_ACTION", float(self.fs_ekf_action), I8),
            ("FS_EKF_THRESH", 0.8, F32),
            ("FRAME_CLASS", float(self.frame_class), I8),
            ("FRAME_TYPE", float(self.frame_type), I8),
            ("SERVO1_FUNCTION", float(servo1), I16),
            ("SERVO3_FUNCTION", float(servo3), I16),
            ("CRUISE_SPEED", float(self.cruise_speed_mps), F32),
            ("CRUISE_THROTTLE", 50.0, I8),
            ("WP_SPEED", float(self.wp_speed_mps), F32),
            ("WP_RADIUS", float(self.wp_radius_m), F32),
            ("RTL_SPEED", float(self.rtl_speed_mps), F32),
            ("TURN_RADIUS", float(self.turn_radius_m), F32),
            ("ATC_STR_RAT_MAX", float(self.steer_rate_max_dps), F32),
            ("ATC_STR_ANG_P", float(self.steer_ang_p), F32),
            ("GUID_TIMEOUT", float(self.guid_timeout_s), F32),
            ("GUID_OPTIONS", 0.0, I32),
            ("AHRS_EKF_TYPE", float(self.ahrs_ekf_type), I8),
            ("EK3_ENABLE", 1.0, I8),
            ("EK3_SRC1_POSXY", float(self.ek3_src1_posxy), I8),
            ("EK3_SRC1_VELXY", 0.0, I8),
            ("EK3_SRC1_POSZ", 1.0, I8),
            ("EK3_SRC1_VELZ", 0.0, I8),
            ("EK3_SRC1_YAW", float(self.ek3_src1_yaw), I8),
            ("VISO_TYPE", float(self.viso_type), I8),
            ("GPS_TYPE", 0.0, I8),
            ("ARMING_CHECK", 1.0, I32),
            ("MODE_CH", 8.0, I8),
            ("INITIAL_MODE", 0.0, I8),
        ]
        if self.gcs_sysid_name == "MAV_GCS_SYSID":
            rows.insert(2, ("MAV_GCS_SYSID_HI", float(self.gcs_sysid_hi), I16))
        return [r for r in rows if r[0] not in self.absent]


@dataclass
class ParamStore:
    """The live parameter table (index order), read with PARAM_REQUEST_*, changed with PARAM_SET."""

    rows: list[tuple[str, float, int]]
    absent: frozenset[str] = frozenset()
    _index: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._index = {name: i for i, (name, _, _) in enumerate(self.rows)}

    @classmethod
    def of(cls, params: RoverParams, system_id: int) -> ParamStore:
        return cls(params.table(system_id), params.absent)

    def has(self, name: str) -> bool:
        return name in self._index

    def get(self, name: str, default: float = math.nan) -> float:
        i = self._index.get(name)
        return default if i is None else self.rows[i][1]

    def set(self, name: str, value: float) -> int | None:
        """Set a parameter as AP_Param::set_float would (integer types rounded); its index, or None for an
        unknown name or a non-finite value."""
        i = self._index.get(name)
        if i is None or not math.isfinite(value):
            return None
        _, _, ptype = self.rows[i]
        self.rows[i] = (name, float(round(value)) if ptype != F32 else float(value), ptype)
        return i

    def is_gcs(self, sysid: int) -> bool:
        """Does a HEARTBEAT from this source system count as our GCS's (GCS::sysid_is_gcs)?"""
        if self.has("MAV_GCS_SYSID"):
            lo, hi = self.get("MAV_GCS_SYSID"), self.get("MAV_GCS_SYSID_HI", 0.0)
            return lo <= sysid <= hi if hi >= lo else sysid == lo
        return sysid == self.get("SYSID_MYGCS", -1.0)

    @property
    def gcs_lost_after_s(self) -> float:
        """FS_GCS_TIMEOUT, or the fixed 2 s of firmware without it."""
        return self.get("FS_GCS_TIMEOUT", OLD_FIRMWARE_GCS_TIMEOUT_S)

    @property
    def speed_max(self) -> float:
        """The set-point speed limit (m/s): ``Mode::get_speed_default`` is AR_WPNav's WP_SPEED, which
        falls back to CRUISE_SPEED when not positive."""
        wp = self.get("WP_SPEED", 0.0)
        return wp if wp > 0.0 else self.get("CRUISE_SPEED", 0.0)

    @property
    def skid_steering(self) -> bool:
        """AP_MotorsUGV::have_skid_steering: throttle-left and throttle-right outputs are assigned."""
        functions = {self.get("SERVO1_FUNCTION", 0.0), self.get("SERVO3_FUNCTION", 0.0)}
        return functions == {float(f) for f in SKID_FUNCTIONS}

    def ekf_sources_refusal(self) -> str | None:
        """AP_NavEKF_Source::pre_arm_check (libraries/AP_NavEKF/AP_NavEKF_Source.cpp), what this vehicle
        can fail of it: POSZ None is invalid, and a source on GPS (3) needs a GPS, which GPS_TYPE 0 has not;
        the message ArduPilot reports, or None."""
        if self.get("EK3_SRC1_POSZ", 1.0) == 0.0:
            return "Check EK3_SRC1_POSZ"
        sources = ("EK3_SRC1_POSXY", "EK3_SRC1_VELXY", "EK3_SRC1_POSZ", "EK3_SRC1_VELZ")
        if any(self.get(n, 0.0) == GPS_SOURCE for n in sources) and self.get("GPS_TYPE", 0.0) == 0.0:
            return "EK3 sources require GPS"
        return None

    @property
    def external_nav(self) -> bool:
        """EKF3 with motion capture (VISION_POSITION_ESTIMATE / ODOMETRY) as position and yaw source."""
        return (
            self.get("AHRS_EKF_TYPE") == 3
            and self.get("EK3_SRC1_POSXY") == EXTERNAL_NAV
            and self.get("EK3_SRC1_YAW") == EXTERNAL_NAV
            and self.get("VISO_TYPE", 0.0) > 0
        )
