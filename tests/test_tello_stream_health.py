"""drivers/tello/stream_health.py on synthetic state lines (no sockets): an implausible value is one event per
field per episode, a run of rejected datagrams one event per run, and the note that `link_lost` carries;
drivers/tello/status.py recording them as the driver's events; preflight's battery check, the one decision
an implausible value changes (drivers/tello/preflight.py)."""

from __future__ import annotations

import pytest

from flightstack.drivers.tello.phase import PhaseThresholds
from flightstack.drivers.tello.preflight import battery_check
from flightstack.drivers.tello.state import TelloTelemetry, parse_state
from flightstack.drivers.tello.status import DriverEvents, DriverStatus
from flightstack.drivers.tello.stream_health import StreamHealth


def line(t: float, h: float, extra: str = "") -> TelloTelemetry:
    """A parsed state line received at `t` (s) with `h` (cm) and `extra` fields."""
    return parse_state(f"h:{h:g};tof:90;vgz:0;time:5;bat:80;{extra}".encode("ascii"), t)


def test_an_implausible_field_is_one_event_per_episode() -> None:
    health = StreamHealth(1.0)
    events = [health.accepted(line(0.1 * k, h)) for k, h in enumerate([0, -1500, -1600, -3000, -500, -1200])]
    # two episodes of h: −1500 … −3000, then (after −500, within the bounds) −1200
    assert events == [[], ["h=-1500 outside [-1000, 3000]"], [], [], [], ["h=-1200 outside [-1000, 3000]"]]


def test_a_line_without_the_field_does_not_end_its_episode() -> None:
    health = StreamHealth(1.0)
    extras = ["yaw:200;", "", "yaw:250;", "yaw:10;", "yaw:-190;tof:-5;"]
    events = [health.accepted(line(0.1 * k, 80, extra)) for k, extra in enumerate(extras)]
    assert [e for e in events if e] == [
        ["yaw=200 outside [-180, 180]"],
        ["tof=-5 outside [0, 10000]", "yaw=-190 outside [-180, 180]"],
    ]


def test_a_run_of_rejected_datagrams_is_one_event_and_a_valid_line_ends_it() -> None:
    health = StreamHealth(1.0)
    assert health.rejected_note() == ""
    runs = [health.rejected(0.1 * k, "not_finite" if k % 3 else "malformed") for k in range(30)]  # 3 s
    assert [(k, r) for k, r in enumerate(runs) if r is not None] == [
        (10, "11 state datagrams from the drone rejected over 1.00 s, none valid (not_finite 7, malformed 4)")
    ]
    assert health.rejected_note().startswith("; 30 state datagrams from the drone rejected over 2.90 s")
    assert health.accepted(line(3.0, 80)) == [] and health.rejected_note() == ""
    again = [health.rejected(3.0 + 0.1 * k, "bad_number") for k in range(12)]  # a new run: a second event
    assert [r for r in again if r is not None] == [
        "11 state datagrams from the drone rejected over 1.00 s, none valid (bad_number 11)"
    ]


def test_rejected_datagrams_far_apart_are_silence_not_a_run() -> None:
    """A gap longer than run_s between two rejected datagrams starts a new run: one rejected datagram,
    silence, another one is no run of 5 s."""
    health = StreamHealth(1.0)
    assert [health.rejected(t, "malformed") for t in (0.0, 5.0, 5.5, 7.0)] == [None] * 4
    assert (
        health.rejected_note()
        == "; 1 state datagrams from the drone rejected over 0.00 s, none valid (malformed 1)"
    )


def test_the_driver_records_them_as_events_and_counts_every_implausible_line() -> None:
    events = DriverEvents("127.0.0.1")
    status = DriverStatus(PhaseThresholds(), 1.0, events)
    for k, h in enumerate([0, -1500, -1600, -3000]):
        status.observe(line(0.1 * k, h))
    for k in range(12):
        status.reject(1.0 + 0.1 * k, "not_finite")
    kinds = [(e.kind, e.detail) for e in events.events if e.kind != "phase"]
    assert kinds == [
        ("state_implausible", "h=-1500 outside [-1000, 3000]"),
        (
            "state_rejected_run",
            "11 state datagrams from the drone rejected over 1.00 s, none valid (not_finite 11)",
        ),
    ]
    assert events.counts["state_implausible"] == 3
    assert status.fields["h"] == -3000  # used as sent


@pytest.mark.parametrize(
    ("bat", "ok", "detail"),
    [
        (87.0, True, "87 % (min 30 %)"),
        (100.0, True, "100 % (min 30 %)"),
        (150.0, False, "150 % (min 30 %): above 100 %, implausible"),  # parsed, but proves no charge
        (12.0, False, "12 % (min 30 %)"),
        (None, False, "not reported"),
    ],
)
def test_a_battery_reading_above_100_percent_fails_preflight(
    bat: float | None, ok: bool, detail: str
) -> None:
    check = battery_check(bat, 30.0)
    assert (check.name, check.ok, check.detail) == ("battery", ok, detail)
