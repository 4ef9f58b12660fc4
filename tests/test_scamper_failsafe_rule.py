"""The Scamper GCS-failsafe rule (drivers/scamper/failsafe.py) branch by branch, and the PARAM_VALUE
collector of drivers/scamper/params.py on hand-made messages (duplicates, order, strangers, bad values)."""

from __future__ import annotations

import math

import pytest

pytest.importorskip("pymavlink")

from pymavlink import mavutil

from flightstack.drivers.scamper.failsafe import (
    MAV_GCS_SYSID,
    MAV_GCS_SYSID_HI,
    SYSID_MYGCS,
    enough,
    judge_gcs_failsafe,
)
from flightstack.drivers.scamper.params import ParamCollector, check_name

pytestmark = pytest.mark.unit
mavlink = mavutil.mavlink

LAB = {"FS_GCS_ENABLE": 1.0, "FS_ACTION": 2.0, "FS_GCS_TIMEOUT": 3.0, "FS_TIMEOUT": 1.0, SYSID_MYGCS: 255.0}
OURS = {"flightstack": 255, "guardian": 255}


def judge(**changes: float | None) -> tuple[str, str]:
    values = {k: v for k, v in {**LAB, **changes}.items() if v is not None}
    verdict = judge_gcs_failsafe(values, OURS)
    return verdict.status, verdict.detail


def test_the_lab_settings_pass_and_say_what_they_are() -> None:
    status, detail = judge()
    assert status == "PASS", detail
    assert "FS_ACTION 2 (Hold)" in detail and "acts 4 s after our last heartbeat" in detail
    assert "SYSID_MYGCS 255 = our system id" in detail


@pytest.mark.parametrize(
    ("name", "needed"),
    [("FS_GCS_ENABLE", None), ("FS_ACTION", None), ("FS_GCS_TIMEOUT", None), ("FS_TIMEOUT", None)],
)
def test_a_parameter_not_read_fails_naming_it(name: str, needed: None) -> None:
    status, detail = judge(**{name: needed})
    assert status == "FAIL" and f"could not read {name}" in detail


def test_no_gcs_sysid_under_either_name_fails_naming_both() -> None:
    status, detail = judge(SYSID_MYGCS=None)
    assert status == "FAIL" and "could not read SYSID_MYGCS (or MAV_GCS_SYSID)" in detail


def test_failsafe_disabled_fails_with_the_value_needed() -> None:
    status, detail = judge(FS_GCS_ENABLE=0.0)
    assert status == "FAIL" and "FS_GCS_ENABLE = 0 (disabled" in detail and "needed 1" in detail


def test_enable_2_passes_noting_the_auto_mission() -> None:
    status, detail = judge(FS_GCS_ENABLE=2.0)
    assert status == "PASS" and "AUTO mission would continue" in detail


@pytest.mark.parametrize("value", [3.0, 1.5, -1.0, math.nan])
def test_unknown_enable_value_fails(value: float) -> None:
    status, detail = judge(FS_GCS_ENABLE=value)
    assert status == "FAIL" and "FS_GCS_ENABLE" in detail and "not a known value" in detail


@pytest.mark.parametrize(
    ("action", "words"),
    [(0, "Nothing"), (1, "RTL: it drives back home"), (3, "SmartRTL or RTL"), (4, "SmartRTL or Hold"),
     (6, "Loiter or Hold")],
)  # fmt: skip
def test_actions_that_keep_driving_fail(action: int, words: str) -> None:
    status, detail = judge(FS_ACTION=float(action))
    assert status == "FAIL"
    assert f"FS_ACTION = {action} ({words}" in detail and "needed 2 (Hold)" in detail


@pytest.mark.parametrize(("action", "words"), [(2, "Hold"), (5, "Terminate (disarms)")])
def test_actions_that_stop_pass(action: int, words: str) -> None:
    status, detail = judge(FS_ACTION=float(action))
    assert status == "PASS" and f"FS_ACTION {action} ({words})" in detail


@pytest.mark.parametrize("value", [7.0, 2.5, -1.0])
def test_unknown_action_fails(value: float) -> None:
    status, detail = judge(FS_ACTION=value)
    assert status == "FAIL" and "not a known action" in detail


def test_ardupilot_default_timeouts_are_too_slow() -> None:
    status, detail = judge(FS_GCS_TIMEOUT=5.0, FS_TIMEOUT=1.5)  # ArduPilot's defaults
    assert status == "FAIL"
    assert "FS_GCS_TIMEOUT 5 + FS_TIMEOUT 1.5 = 6.5 s" in detail and "more than 5 s" in detail
    assert "needed FS_GCS_TIMEOUT 3, FS_TIMEOUT 1" in detail


def test_delay_at_the_bound_passes_and_just_over_fails() -> None:
    assert judge(FS_GCS_TIMEOUT=4.0, FS_TIMEOUT=1.0)[0] == "PASS"
    assert judge(FS_GCS_TIMEOUT=4.0, FS_TIMEOUT=1.01)[0] == "FAIL"


def test_a_hair_trigger_failsafe_warns() -> None:
    status, detail = judge(FS_GCS_TIMEOUT=1.0, FS_TIMEOUT=1.0)
    assert status == "WARN" and "two lost heartbeats" in detail
    assert judge(FS_GCS_TIMEOUT=2.0, FS_TIMEOUT=1.0)[0] == "PASS"  # 3 periods: three lost in a row


@pytest.mark.parametrize(("lost", "persist"), [(-1.0, 1.0), (3.0, math.inf), (math.nan, 1.0)])
def test_invalid_times_fail(lost: float, persist: float) -> None:
    status, detail = judge(FS_GCS_TIMEOUT=lost, FS_TIMEOUT=persist)
    assert status == "FAIL" and "not a valid time" in detail


def test_another_gcs_sysid_fails_naming_ours() -> None:
    status, detail = judge(SYSID_MYGCS=1.0)
    assert status == "FAIL"
    assert "SYSID_MYGCS 1 (the failsafe watches another ground station" in detail
    assert "flightstack 255, guardian 255" in detail and "needed 255" in detail


def test_a_guardian_with_another_sysid_is_named() -> None:
    verdict = judge_gcs_failsafe(LAB, {"flightstack": 255, "guardian": 254})
    assert verdict.status == "FAIL" and "heartbeats of guardian 254" in verdict.detail


def test_non_integer_sysid_fails() -> None:
    assert judge(SYSID_MYGCS=255.5)[0] == "FAIL"


def test_newer_firmware_name_and_range() -> None:
    newer = {k: v for k, v in LAB.items() if k != SYSID_MYGCS}
    ok = judge_gcs_failsafe({**newer, MAV_GCS_SYSID: 255.0, MAV_GCS_SYSID_HI: 0.0}, OURS)
    assert ok.status == "PASS" and "MAV_GCS_SYSID 255 = our system id" in ok.detail
    ranged = judge_gcs_failsafe({**newer, MAV_GCS_SYSID: 250.0, MAV_GCS_SYSID_HI: 255.0}, OURS)
    assert ranged.status == "PASS" and "MAV_GCS_SYSID 250..MAV_GCS_SYSID_HI 255" in ranged.detail
    below = judge_gcs_failsafe({**newer, MAV_GCS_SYSID: 250.0, MAV_GCS_SYSID_HI: 254.0}, OURS)
    assert below.status == "FAIL" and "needed 255" in below.detail
    hi_under_lo = judge_gcs_failsafe({**newer, MAV_GCS_SYSID: 1.0, MAV_GCS_SYSID_HI: 0.0}, OURS)
    assert hi_under_lo.status == "FAIL"  # HI < lo: only 1 counts


def test_the_newer_name_wins_when_both_answer() -> None:
    verdict = judge_gcs_failsafe({**LAB, MAV_GCS_SYSID: 1.0, MAV_GCS_SYSID_HI: 0.0}, OURS)
    assert verdict.status == "FAIL" and "MAV_GCS_SYSID 1" in verdict.detail


def test_every_problem_is_reported_not_only_the_first() -> None:
    status, detail = judge(FS_GCS_ENABLE=0.0, FS_ACTION=1.0, FS_GCS_TIMEOUT=5.0, SYSID_MYGCS=1.0)
    assert status == "FAIL"
    for name in ("FS_GCS_ENABLE = 0", "FS_ACTION = 1", "= 6 s", "SYSID_MYGCS 1"):
        assert name in detail


def test_enough_needs_every_required_and_one_sysid() -> None:
    assert enough(LAB)
    assert not enough({k: v for k, v in LAB.items() if k != "FS_TIMEOUT"})
    newer = {k: v for k, v in LAB.items() if k != SYSID_MYGCS}
    assert not enough(newer)
    assert not enough({**newer, MAV_GCS_SYSID: 255.0})  # its _HI too
    assert enough({**newer, MAV_GCS_SYSID: 255.0, MAV_GCS_SYSID_HI: 0.0})


# ---- the PARAM_VALUE collector --------------------------------------------------------------------------
def param_value(
    name: str, value: float, ptype: int = mavlink.MAV_PARAM_TYPE_INT8, src: tuple[int, int] = (1, 1)
) -> object:
    """A PARAM_VALUE as pymavlink decodes it from the wire (packed by `src`, parsed back)."""
    sender = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    raw = mavlink.MAVLink_param_value_message(name.encode(), value, ptype, 7, 0).pack(sender)
    return mavlink.MAVLink(None, 255, 190).parse_char(raw)


def test_collector_matches_by_name_in_any_order_and_counts_duplicates() -> None:
    col = ParamCollector((1, 1), ["FS_ACTION", "FS_TIMEOUT", "FS_GCS_ENABLE"])
    assert col.offer(param_value("FS_TIMEOUT", 1.0, mavlink.MAV_PARAM_TYPE_REAL32))
    assert col.offer(param_value("FS_ACTION", 2.0))
    assert col.offer(param_value("FS_ACTION", 2.0))  # the same reply twice
    assert col.missing() == ("FS_GCS_ENABLE",)
    assert col.offer(param_value("FS_ACTION", 0.0))  # changed meanwhile: the last one counts
    assert col.values == {"FS_TIMEOUT": 1.0, "FS_ACTION": 0.0}
    assert col.dropped == {"duplicate": 1, "changed": 1}


@pytest.mark.parametrize(
    ("msg_args", "reason"),
    [
        (("FS_ACTION", 2.0, mavlink.MAV_PARAM_TYPE_INT8, (2, 1)), "other source"),
        (("FS_ACTION", 2.0, mavlink.MAV_PARAM_TYPE_INT8, (1, 191)), "other source"),
        (("SYSID_THISMAV", 1.0, mavlink.MAV_PARAM_TYPE_INT16, (1, 1)), "not asked for"),
        (("FS_TIMEOUT", math.nan, mavlink.MAV_PARAM_TYPE_REAL32, (1, 1)), "not finite"),
        (("FS_TIMEOUT", math.inf, mavlink.MAV_PARAM_TYPE_REAL32, (1, 1)), "not finite"),
        (("FS_ACTION", 2.5, mavlink.MAV_PARAM_TYPE_INT8, (1, 1)), "not an integer of its type"),
        (("FS_ACTION", 300.0, mavlink.MAV_PARAM_TYPE_INT8, (1, 1)), "not an integer of its type"),
        (("FS_ACTION", 2.0, 42, (1, 1)), "unknown param_type"),
    ],
)
def test_collector_drops_what_it_cannot_trust(msg_args: tuple, reason: str) -> None:
    name, value, ptype, src = msg_args
    col = ParamCollector((1, 1), ["FS_ACTION", "FS_TIMEOUT"])
    assert not col.offer(param_value(name, value, ptype, src))
    assert col.values == {} and col.dropped == {reason: 1}


def test_collector_drops_other_messages_and_junk() -> None:
    col = ParamCollector((1, 1), ["FS_ACTION"])
    hb = mavlink.MAVLink_heartbeat_message(10, 3, 0, 4, 3, 3)
    assert not col.offer(mavlink.MAVLink(None, 255, 190).parse_char(hb.pack(mavlink.MAVLink(None, 1, 1))))
    assert not col.offer(object())
    assert col.dropped == {"not PARAM_VALUE": 1, "malformed": 1}


@pytest.mark.parametrize("name", ["", "A" * 17, "FS ACTIÖN", "FS\x00X"])
def test_parameter_names_are_checked(name: str) -> None:
    with pytest.raises(ValueError, match="not a MAVLink parameter name"):
        check_name(name)
