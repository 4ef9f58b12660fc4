"""The pure rules of the ground robot's ArduPilot setup: lab ↔ NED (closed form), the origin, the vision
stream's freshness, the parameter rules and the kinematics mapping (drivers/scamper/nav.py,
drivers/scamper/vehicle.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.drivers.scamper import vehicle as sv
from flightstack.drivers.scamper.nav import (
    ORIGIN_RETRY_S,
    LabOrigin,
    OriginState,
    VisionStream,
    lab_to_ned,
    ned_to_lab,
)
from flightstack.hal import StampedPose
from flightstack.paper.geometry import Pose

pytestmark = pytest.mark.unit


def test_robot_at_lab_1_2_facing_x_in_ned_and_back() -> None:
    # lab +x = north, lab +y (left) = west, z up = -down, yaw ccw = -yaw cw
    assert lab_to_ned(np.array([1.0, 2.0, 0.3]), 0.0) == pytest.approx((1.0, -2.0, -0.3, 0.0))
    p, theta = ned_to_lab(1.0, -2.0, -0.3, 0.0)
    assert p == pytest.approx([1.0, 2.0, 0.3]) and theta == pytest.approx(0.0)
    # facing lab +y (a quarter turn left) is a quarter turn anticlockwise: NED yaw -π/2
    assert lab_to_ned(np.array([1.0, 2.0, 0.0]), math.pi / 2)[3] == pytest.approx(-math.pi / 2)
    assert ned_to_lab(1.0, -2.0, 0.0, -math.pi / 2)[1] == pytest.approx(math.pi / 2)
    # facing lab -x: yaw ±π, wrapped to (-π, π]
    assert lab_to_ned(np.zeros(3), math.pi)[3] == pytest.approx(math.pi)


@pytest.mark.parametrize("theta", np.linspace(-3.1, 3.1, 13))
def test_lab_ned_round_trip(theta: float) -> None:
    p = np.array([0.7, -1.3, 0.05])
    back, th = ned_to_lab(*lab_to_ned(p, theta))
    assert back == pytest.approx(p) and math.remainder(th - theta, 2 * math.pi) == pytest.approx(
        0.0, abs=1e-12
    )


def test_lab_origin_mavlink_units_and_validation() -> None:
    o = LabOrigin(52.0, 4.0, 1.5)
    assert o.as_mavlink() == (520_000_000, 40_000_000, 1500)
    assert o.matches(520_000_000, 40_000_000, 1500) and o.matches(520_000_001, 40_000_000, 1510)
    assert not o.matches(520_000_100, 40_000_000, 1500)
    with pytest.raises(ValueError):
        LabOrigin(91.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        LabOrigin(float("nan"), 0.0, 0.0)


def test_vision_stream_sends_fresh_new_poses_once_and_bumps_reset_after_a_gap() -> None:
    vs = VisionStream(max_age_s=0.2)
    pose = Pose.make([1.0, 2.0, 0.0], 0.0)
    s, why = vs.next(StampedPose(10.0, pose), 10.05)
    assert s is not None and why == "" and s.usec == 10_000_000 and (s.x, s.y, s.yaw) == (1.0, -2.0, 0.0)
    assert vs.next(StampedPose(10.0, pose), 10.1) == (None, "not new")
    assert vs.next(StampedPose(10.1, pose), 10.31) == (None, "stale")
    assert vs.next(None, 10.4) == (None, "no pose")
    s, _ = vs.next(StampedPose(10.5, pose), 10.55)
    assert s is not None and s.reset_counter == 1


def test_the_origin_is_tried_again_only_retry_s_after_the_last_try() -> None:
    # connect's own try and scamper-tx's ticker (another phase) ask at once: only one sends
    state = OriginState()
    assert state.try_due(100.0) and not state.try_due(100.0)
    assert not state.try_due(100.0 + ORIGIN_RETRY_S - 0.01)  # the ticker right after connect's try
    assert state.try_due(100.0 + ORIGIN_RETRY_S)
    state.confirmed = True
    assert not state.try_due(200.0)  # confirmed: never again
    state.forget()  # a reboot: at once, whatever the last try
    assert state.try_due(200.0) and state.sends == 0 and state.boots == 1


def test_external_nav_rule_names_every_parameter_to_set_in_one_line() -> None:
    v = sv.judge_external_nav({"AHRS_EKF_TYPE": 3, "EK3_SRC1_POSXY": 3, "EK3_SRC1_YAW": 1})
    assert v.status == "FAIL" and "\n" not in v.detail
    for part in ("EK3_SRC1_POSXY 6 (now 3)", "EK3_SRC1_YAW 6 (now 1)", "VISO_TYPE 1 (now unread)"):
        assert part in v.detail
    assert "AHRS_EKF_TYPE" not in v.detail
    lab = {**sv.NAV_NEEDED, "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELXY": 0, "EK3_SRC1_VELZ": 0}
    assert sv.judge_external_nav(lab).status == "PASS"
    extnav_everywhere = {**lab, "EK3_SRC1_POSZ": 6, "EK3_SRC1_VELXY": 6, "EK3_SRC1_VELZ": 6}
    assert sv.judge_external_nav(extnav_everywhere).status == "PASS"


@pytest.mark.parametrize(("name", "value", "part"), [
    ("EK3_SRC1_VELXY", 3, "EK3_SRC1_VELXY 0 (now 3)"),  # ArduPilot's default: GPS
    ("EK3_SRC1_VELZ", 3, "EK3_SRC1_VELZ 0 (now 3)"),
    ("EK3_SRC1_POSZ", 0, "EK3_SRC1_POSZ 1 (now 0)"),  # None: "Check EK3_SRC1_POSZ" at arming
    ("EK3_SRC1_POSZ", 3, "EK3_SRC1_POSZ 1 (now 3)"),
    ("EK3_SRC1_VELZ", None, "EK3_SRC1_VELZ 0 (now unread)"),
])  # fmt: skip
def test_external_nav_rule_refuses_the_other_sources_on_gps(name: str, value: int | None, part: str) -> None:
    """AP_NavEKF_Source::pre_arm_check: a source on GPS needs a GPS; indoors it is refused either way."""
    values: dict[str, float] = {**sv.NAV_NEEDED, "EK3_SRC1_POSZ": 1, "EK3_SRC1_VELXY": 0, "EK3_SRC1_VELZ": 0}
    if value is None:
        del values[name]
    else:
        values[name] = value
    v = sv.judge_external_nav(values)
    assert v.status == "FAIL" and part in v.detail and v.detail.count("(now") == 1, v.detail


def test_guided_timeout_rule() -> None:
    assert sv.judge_guided_timeout({"GUID_TIMEOUT": 3.0}, 10.0).status == "PASS"
    assert sv.judge_guided_timeout({"GUID_TIMEOUT": 5.0}, 10.0).status == "FAIL"
    assert sv.judge_guided_timeout({"GUID_TIMEOUT": 0.2}, 10.0).status == "FAIL"  # < 5 periods of 0.1 s
    assert sv.judge_guided_timeout({}, 10.0).status == "WARN"
    assert "set GUID_TIMEOUT between 0.5 and 3 s" in sv.judge_guided_timeout({"GUID_TIMEOUT": 4}, 10.0).detail


@pytest.mark.parametrize(
    ("fc", "ft", "servos", "kind"),
    [
        (1, 0, [73, 0, 74], "differential"),  # ThrottleLeft + ThrottleRight: skid steering
        (1, 0, [26, 0, 70], "ackermann"),  # GroundSteering + Throttle
        (1, 1, [33, 34, 35], "omni"),  # Omni3
        (1, 4, None, "omni"),
        (2, 0, [73, 74], "boat"),
        (3, 0, [73, 74], "differential"),  # BalanceBot: skid outputs
        (1, 0, None, "unknown"),  # FRAME_CLASS/FRAME_TYPE alone cannot tell skid from steered
        (1, 0, [73], "unknown"),
        (7, 0, [73, 74], "unknown"),
        (None, None, None, "unknown"),
    ],
)
def test_vehicle_kinematics(
    fc: float | None, ft: float | None, servos: list[float] | None, kind: str
) -> None:
    assert sv.vehicle_kinematics(fc, ft, servos) == kind


def test_kinematics_row() -> None:
    values = {"FRAME_CLASS": 1.0, "FRAME_TYPE": 0.0, "SERVO1_FUNCTION": 73.0, "SERVO3_FUNCTION": 74.0}
    v = sv.judge_kinematics(values)
    assert v.status == "PASS" and v.detail.startswith("differential (FRAME_CLASS 1, FRAME_TYPE 0")
    assert sv.judge_kinematics({"FRAME_CLASS": 1.0}).status == "WARN"
