"""The phase tracker on a real Tello's recorded flight (no sockets): the state lines of
../shared/data/peers/tello/xg590_Tello_flight_log_20201018_052457.db, fed at their recorded times, with the
takeoff and land at their recorded times. Read in place (never copied); without the recording the tests
skip, under CI=true they fail (tests/conftest.skip_or_fail_in_ci).

What the recording shows (times from the `takeoff` command; ../shared/data/peers/README.md): h climbs to
70 cm by 2.8 s, drifts to 40 cm while tof reads 100-178 cm; the `ok` to takeoff at +8.70 s (h 40 cm);
`land` at +17.37 s, the descent visible from +18.13 s, touchdown (tof 10) at +20.2 s."""

from __future__ import annotations

import random

import pytest

from flightstack.drivers.tello.phase import PhaseTracker
from flightstack.drivers.tello.state import TelloTelemetry, parse_state
from flightstack.drivers.tello.traffic import TelloSession, read_xg590_db
from flightstack.hal import FlightPhase
from tests.conftest import PEERS, skip_or_fail_in_ci

FLIGHT = PEERS / "tello" / "xg590_Tello_flight_log_20201018_052457.db"


@pytest.fixture(scope="module")
def session() -> TelloSession:
    if not FLIGHT.is_file():
        skip_or_fail_in_ci(
            f"the real Tello flight log is not at {FLIGHT} (../shared/data/peers beside the checkout)"
        )
    return read_xg590_db(FLIGHT)


def samples(s: TelloSession, keep: float = 1.0, seed: int = 0) -> list[TelloTelemetry]:
    """Every recorded state line parsed at its time (s from the takeoff command); a seeded `keep` fraction."""
    takeoff = s.first("sent", "takeoff")
    assert takeoff is not None
    rng = random.Random(seed)
    return [parse_state(r.text.encode(), r.t - takeoff.t) for r in s.of("state") if rng.random() < keep]


def command_time(s: TelloSession, text: str) -> float:
    """When `text` was sent (s from the takeoff command)."""
    takeoff, rec = s.first("sent", "takeoff"), s.first("sent", text)
    assert takeoff is not None and rec is not None
    return rec.t - takeoff.t


def test_the_recorded_takeoff_is_climbed_over_and_its_ok_is_plausible(session: TelloSession) -> None:
    """The takeoff's `ok` (+8.70 s, h 40 cm) and 0.1 s later are trusted; before the climb they are not."""
    replies = [r.t for r in session.of("reply") if r.text == "ok"]  # the second `ok` answers the takeoff
    t_ok = replies[1] - session.first("sent", "takeoff").t  # type: ignore[union-attr]
    assert 8.6 < t_ok < 8.8
    tr = PhaseTracker()
    climbed_at = over_at = None
    plausible: dict[float, bool] = {}
    h_at: dict[float, float] = {}
    for s in samples(session):
        if s.t < 0.0:
            tr.observe(s)
            continue
        if tr.phase is FlightPhase.GROUND:
            tr.hold_takeoff = True
            tr.takeoff_sent(0.0)
        for t in (0.9, t_ok, t_ok + 0.1):  # an ok at t meets the latest sample before t, as in the driver
            if t not in plausible and s.t >= t and tr.latest is not None:
                plausible[t] = tr.takeoff_answer_plausible(t)
                h_at[t] = tr.latest.h_cm
        tr.observe(s)
        if climbed_at is None and tr.climbed():
            climbed_at = s.t
        if over_at is None and tr.climb_over(s.t):
            over_at = s.t
        if s.t > t_ok + 0.2:
            break
    print(f"climbed at {climbed_at:.2f} s, climb over at {over_at:.2f} s, ok at {t_ok:.2f} s")
    assert climbed_at is not None and 1.0 < climbed_at < 2.0  # h 50 cm at +1.50 s
    assert over_at is not None and 2.5 < over_at < 4.5  # vgz 0 from +2.02 s, h 60-70 cm from +1.81 s
    assert plausible == {0.9: False, t_ok: True, t_ok + 0.1: True}, plausible
    assert h_at[t_ok] < tr.th.airborne_h_cm  # h alone would refuse the takeoff's ok


@pytest.mark.parametrize("keep", [1.0, 0.75, 0.5])
def test_the_recorded_landing_never_looks_stuck(session: TelloSession, keep: float) -> None:
    """After the recorded `land`, nothing proves the drone holding its height (so no land is re-sent),
    with every state line, with 25 % and with 50 % of them dropped (seeded); the hover before it does."""
    t_land = command_time(session, "land")
    for seed in range(5):
        tr = PhaseTracker()
        stuck_after_land, holding_in_hover = [], []
        for s in samples(session, keep, seed):
            if s.t >= 0.0 and tr.phase is FlightPhase.GROUND:
                tr.takeoff_sent(0.0)
            tr.observe(s)
            if 9.5 <= s.t <= 11.5:  # the recorded hover (h 40, tof 115-119, vgz 0)
                holding_in_hover.append(tr.holding_after_land(s.t))
            if s.t >= t_land + 1.5 and tr.holding_after_land(s.t):  # land_confirm_s after the land
                stuck_after_land.append(round(s.t, 2))
        assert stuck_after_land == [], (keep, seed, stuck_after_land)
        if keep == 1.0:
            assert all(holding_in_hover), holding_in_hover  # a drone that did not hear its land is seen


def test_the_recorded_touchdown_is_near_the_ground_by_tof_while_h_reads_minus_70(
    session: TelloSession,
) -> None:
    tr = PhaseTracker()
    last = samples(session)[-1]
    assert last.h_cm == -70 and last.tof_cm == 10
    assert tr.low(last) and tr.floor_cm(last) == 0
    hover = next(s for s in samples(session) if s.t > 12.5)
    assert hover.h_cm == 40 and hover.tof_cm > 150 and not tr.low(hover)
