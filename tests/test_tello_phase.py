"""The Tello state parser and the telemetry phase tracker, on synthetic state streams (no sockets).

Streams are written the way the SDK documents the fields: h in cm relative to the takeoff point, vgz in dm/s
positive DOWN (as a real Tello sends it: docs/drivers.md, "What a real Tello sends"), `time` = whole seconds
of motor-on time, one packet per 0.1 s.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flightstack.drivers.tello.phase import PhaseTracker
from flightstack.drivers.tello.state import StateRejectedError, TelloTelemetry, parse_state
from flightstack.hal import FlightPhase

LINE = "mid:-1;x:0;y:0;z:0;mpry:0,0,0;pitch:0;roll:0;yaw:0;vgx:0;vgy:0;vgz:{vgz};templ:60;temph:63;"
LINE += "tof:{tof};h:{h};bat:87;baro:12.30;time:{time};agx:0.00;agy:0.00;agz:-1000.00;\r\n"


def packet(t: float, h: float, motor_s: float, vgz: float = 0.0) -> TelloTelemetry:
    text = LINE.format(vgz=round(vgz), tof=round(h) + 10, h=round(h), time=int(motor_s))
    return parse_state(text.encode("ascii"), t)


def stream(tracker: PhaseTracker, t0: float, t1: float, h, motor0: float, motors_on: bool):
    """Feed packets every 0.1 s on [t0, t1); h(t) in cm; motor time rises 1 s/s while motors_on."""
    events = []
    n = round((t1 - t0) / 0.1)
    for k in range(n):
        t = t0 + 0.1 * k
        m = motor0 + (t - t0 if motors_on else 0.0)
        events += tracker.observe(packet(t, h(t), m, vgz=-(h(t + 0.1) - h(t)) / 0.1 / 10))
    return events


def test_parser_reads_the_documented_fields() -> None:
    s = packet(3.0, 80, 12)
    assert (s.t, s.h_cm, s.tof_cm, s.motor_s, s.bat_pct, s.temph_c) == (3.0, 80, 90, 12, 87, 63)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"\xff\xfe", "not_ascii"),
        (b"h:80;" * 200, "too_long"),
        (b"h:80;tof:90;vgz:0;bat:50;", "missing_field"),
        (b"h:nan;tof:90;vgz:0;time:1;bat:50;", "not_finite"),
        (b"h:80;tof:90;vgz:0;time:1;bat:inf;", "not_finite"),
        (b"h:-1e999;tof:90;vgz:0;time:1;bat:50;", "not_finite"),  # a number beyond float: -inf
        (b"h:eighty;tof:90;vgz:0;time:1;bat:50;", "bad_number"),
        (b"h80;tof:90;", "malformed"),
        (b"h:80;\x01tof:90;", "not_printable"),
    ],
)
def test_parser_rejects_with_a_reason(data: bytes, reason: str) -> None:
    with pytest.raises(StateRejectedError) as err:
        parse_state(data, 0.0)
    assert err.value.reason == reason


@pytest.mark.parametrize(
    ("line", "implausible"),
    [
        ("h:-3000;tof:10;vgz:0;time:1;bat:50;", ("h",)),  # a real h drifts: far below the takeoff point
        ("h:80;tof:90;vgz:0;time:1;bat:150;", ("bat",)),
        ("h:4000;tof:-5;vgz:120;time:1;bat:50;yaw:200;", ("h", "tof", "vgz", "yaw")),
        ("h:-1000;tof:0;vgz:100;time:0;bat:100;", ()),  # the bounds themselves are plausible
    ],
)
def test_every_finite_value_parses_and_an_implausible_one_is_flagged(
    line: str, implausible: tuple[str, ...]
) -> None:
    s = parse_state(line.encode("ascii"), 2.0)
    assert s.implausible == implausible
    sent = dict(kv.split(":") for kv in line.strip(";").split(";"))
    assert s.fields == {k: float(v) for k, v in sent.items()}  # kept as sent, none substituted
    assert (s.h_cm, s.tof_cm, s.vgz_dm_s, s.bat_pct) == tuple(
        float(sent[k]) for k in ("h", "tof", "vgz", "bat")
    )


@given(st.binary(max_size=600))
def test_parser_never_raises_anything_else(data: bytes) -> None:
    try:
        s = parse_state(data, 0.0)
    except StateRejectedError:
        return
    assert all(math.isfinite(v) for v in s.fields.values())
    assert ("bat" in s.implausible) == (not 0 <= s.bat_pct <= 100)


def test_takeoff_hover_land_as_the_firmware_does_it() -> None:
    tr = PhaseTracker()
    stream(tr, 0.0, 1.0, lambda t: 0.0, 40.0, motors_on=False)
    assert tr.phase is FlightPhase.GROUND
    tr.takeoff_sent(1.0)
    assert tr.phase is FlightPhase.TAKING_OFF
    # 0.5 s spin-up, climb to 80 cm in 1.5 s, hover
    climb = lambda t: min(80.0, max(0.0, (t - 1.5) / 1.5 * 80.0))  # noqa: E731
    stream(tr, 1.0, 3.0, climb, 40.0, motors_on=True)
    assert tr.phase is FlightPhase.TAKING_OFF  # still climbing at 3.0 s
    stream(tr, 3.0, 4.2, climb, 42.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE  # stable for 1 s after reaching 80 cm
    assert 3.9 <= tr.phase_since <= 4.2
    tr.land_sent(10.0)
    assert tr.phase is FlightPhase.LANDING
    descend = lambda t: max(0.0, 80.0 - (t - 10.0) * 40.0)  # noqa: E731
    stream(tr, 10.0, 12.0, descend, 50.0, motors_on=True)  # touchdown at 12.0 s, motors stop
    assert tr.phase is FlightPhase.LANDING
    stream(tr, 12.0, 14.0, lambda t: 0.0, 52.0, motors_on=False)
    assert tr.phase is FlightPhase.GROUND
    assert 13.4 <= tr.phase_since <= 14.0  # motor time unchanged for 1.5 s


def test_slow_climb_is_not_stable_until_it_stops() -> None:
    tr = PhaseTracker()
    stream(tr, 0.0, 0.5, lambda t: 0.0, 0.0, motors_on=False)
    tr.takeoff_sent(0.5)
    slow = lambda t: min(80.0, (t - 0.5) * 7.0)  # noqa: E731  # 7 cm/s: 80 cm after 11.4 s
    stream(tr, 0.5, 11.9, slow, 0.0, motors_on=True)
    assert tr.phase is FlightPhase.TAKING_OFF
    stream(tr, 11.9, 13.2, slow, 11.4, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE


def test_a_takeoff_that_never_starts_returns_to_ground() -> None:
    tr = PhaseTracker()
    stream(tr, 0.0, 0.5, lambda t: 0.0, 7.0, motors_on=False)
    tr.takeoff_sent(0.5)
    stream(tr, 0.5, 3.4, lambda t: 0.0, 7.0, motors_on=False)
    assert tr.phase is FlightPhase.TAKING_OFF  # not yet no_effect_s
    stream(tr, 3.4, 3.8, lambda t: 0.0, 7.0, motors_on=False)
    assert tr.phase is FlightPhase.GROUND


def test_a_lost_land_reverts_to_airborne_and_an_auto_land_is_seen() -> None:
    tr = PhaseTracker()
    stream(tr, 0.0, 2.0, lambda t: 80.0, 30.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE  # first sample in the air
    tr.land_sent(2.0)
    stream(tr, 2.0, 5.3, lambda t: 80.0, 32.0, motors_on=True)  # nothing happens
    assert tr.phase is FlightPhase.AIRBORNE
    # an auto-land nobody asked for: down with the motors off
    stream(tr, 5.3, 7.0, lambda t: max(0.0, 80.0 - (t - 5.3) * 80.0), 35.3, motors_on=True)
    stream(tr, 7.0, 8.8, lambda t: 0.0, 37.0, motors_on=False)
    assert tr.phase is FlightPhase.GROUND


def test_hover_with_height_quantised_to_10_cm_is_not_mistaken_for_down() -> None:
    tr = PhaseTracker()
    stream(tr, 0.0, 5.0, lambda t: 80.0 + 10.0 * (int(t * 3) % 2), 0.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE


def test_takeoff_confirmed_with_height_quantised_to_10_cm() -> None:
    """Should a firmware report h in 10 cm steps, a hover flickering 80/90 cm is still stable."""
    tr = PhaseTracker()
    stream(tr, 0.0, 0.5, lambda t: 0.0, 0.0, motors_on=False)
    tr.takeoff_sent(0.5)
    stream(tr, 0.5, 2.5, lambda t: 10.0 * round(min(80.0, (t - 0.5) * 40.0) / 10.0), 0.0, motors_on=True)
    for k in range(15):  # hover: the readout flickers, the measured vertical speed is 0
        tr.observe(packet(2.5 + 0.1 * k, 80.0 + 10.0 * (k // 3 % 2), 2.0 + 0.1 * k, vgz=0.0))
    assert tr.phase is FlightPhase.AIRBORNE


# ---- a descent the driver did not command ------------------------------------------------------------------
def flying(tr: PhaseTracker) -> None:
    stream(tr, 0.0, 2.0, lambda t: 80.0, 30.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE


def test_a_descent_not_commanded_is_the_drones_own_landing() -> None:
    """Its own landing goes on to the ground: declared once the descent has lasted self_land_s (1 s)."""
    tr = PhaseTracker()
    flying(tr)
    tr.rc_sent(1.9, 0)  # the loop holds height
    descend = lambda t: max(0.0, 80.0 - (t - 2.0) * 47.0)  # noqa: E731  # 80 cm in 1.7 s
    stream(tr, 2.0, 2.9, descend, 32.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE  # 0.9 s: an ordinary descent may still stop
    stream(tr, 2.9, 3.2, descend, 32.9, motors_on=True)
    assert tr.phase is FlightPhase.LANDING and tr.self_landing
    assert 2.9 <= tr.phase_since <= 3.15  # ~1 s after the descent's start (10 Hz packets)
    stream(tr, 3.2, 3.8, descend, 33.2, motors_on=True)
    stream(tr, 3.8, 5.5, lambda t: 0.0, 33.8, motors_on=False)
    assert tr.phase is FlightPhase.GROUND and not tr.self_landing


def test_a_commanded_descent_is_not_a_landing() -> None:
    tr = PhaseTracker()
    flying(tr)
    tr.rc_sent(1.9, -40)  # the loop asks for 40 cm/s down, then its last rc stays negative
    stream(tr, 2.0, 3.0, lambda t: 80.0 - (t - 2.0) * 40.0, 32.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE
    tr.rc_sent(3.0, 0)  # stops asking; the drone's velocity lags for uncommanded_after_s
    stream(tr, 3.0, 3.5, lambda t: 40.0 - (t - 3.0) * 30.0, 33.0, motors_on=True)
    assert tr.phase is FlightPhase.AIRBORNE


def test_a_height_step_is_no_descent_and_a_stopped_descent_flies_on() -> None:
    """A step of h (an object passed over) is no descent; an uncommanded descent that stops within 0.8 s
    (what users' real flights showed) is no landing, and neither is one that stops and resumes."""
    tr = PhaseTracker()
    flying(tr)
    stream(tr, 2.0, 3.0, lambda t: 80.0 if t < 2.45 else 60.0, 32.0, motors_on=True)  # over an object
    assert tr.phase is FlightPhase.AIRBORNE
    tr2 = PhaseTracker()
    flying(tr2)
    phases = []
    for t0, t1, h in ((2.0, 2.8, lambda t: 80.0 - (t - 2.0) * 50.0), (2.8, 3.4, lambda t: 40.0)):
        for k in range(round((t1 - t0) / 0.1)):
            t = t0 + 0.1 * k
            tr2.observe(packet(t, h(t), 32.0 + t - 2.0, vgz=-(h(t + 0.1) - h(t)) / 0.1 / 10))
            phases.append(tr2.phase)
    assert set(phases) == {FlightPhase.AIRBORNE} and not tr2.self_landing


def test_its_word_that_it_lands_holds_until_its_descent_could_show() -> None:
    """`error Auto land` (landing_by_itself) while hovering: the samples before the notice showed a still
    hover, and so do the first ones after it (the descent starts later); none of them may return it to
    flying: only 0.5 s of stillness after the notice would."""
    tr = PhaseTracker()
    flying(tr)
    tr.landing_by_itself(2.0)
    assert tr.phase is FlightPhase.LANDING and tr.self_landing
    stream(tr, 2.0, 2.3, lambda t: 80.0, 32.0, motors_on=True)  # still hovering: the descent not yet begun
    assert tr.phase is FlightPhase.LANDING
    stream(tr, 2.3, 3.0, lambda t: max(0.0, 80.0 - (t - 2.3) * 120.0), 32.3, motors_on=True)
    stream(tr, 3.0, 4.7, lambda t: 0.0, 33.0, motors_on=False)
    assert tr.phase is FlightPhase.GROUND
