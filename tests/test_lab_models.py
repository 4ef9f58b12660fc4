"""Models of the simulated lab: rc mapping, Tello-like drone, ground robot, motion capture, square law."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from flightstack.config.links import LinkDelays, LinkSpec
from flightstack.drivers.tello.rc import RcGains, rc_to_velocity, velocity_to_rc
from flightstack.paper.geometry import Pose
from flightstack.paper.target_law import SquareLaw
from flightstack.sim_backend.lab import (
    MocapParams,
    MocapSim,
    RobotParams,
    ScamperSim,
    TelloParams,
    TelloSim,
)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def run(model, clock: Clock, seconds: float, dt: float = 0.005) -> None:
    for _ in range(round(seconds / dt)):
        clock.t += dt
        model.step(clock.t, dt)


def test_rc_mapping_signs_and_types() -> None:
    g = RcGains(xy=0.01, z=0.02, yaw=0.0175)
    # forward 0.3 m/s, left 0.2 m/s, up 0.1 m/s, counter-clockwise 0.35 rad/s
    rc = velocity_to_rc(np.array([0.3, 0.2, 0.1, 0.35]), g)
    assert rc == (-20, 30, 5, -20)  # a = right, b = forward, c = up, d = clockwise
    assert all(type(x) is int for x in rc)  # djitellopy rejects floats and numpy ints
    assert velocity_to_rc(np.array([5.0, -5.0, np.nan, np.inf]), g) == (100, 100, 0, 0)


@given(st.lists(st.integers(-100, 100), min_size=4, max_size=4))
def test_rc_round_trip(rc: list[int]) -> None:
    g = RcGains(0.01, 0.01, 0.0175)
    assert velocity_to_rc(rc_to_velocity(tuple(rc), g), g) == tuple(rc)


def flying_tello(params: TelloParams, rc: LinkDelays | None = None) -> tuple[TelloSim, Clock]:
    clock = Clock()
    d = TelloSim(1, Pose.make([0, 0, 0], 0.0), params, clock, rc)
    d.connect()
    d.takeoff()
    run(d, clock, 5.0)
    assert d.state().flying and math.isclose(d.pose.p[2], params.takeoff_height_m, abs_tol=0.01)
    return d, clock


def test_tello_takeoff_latency_and_first_order_response() -> None:
    p = TelloParams(time_constant_s=0.2)
    d, clock = flying_tello(p, LinkDelays(LinkSpec(latency_s=0.1)))
    t0 = clock.t
    d.send_body_velocity(np.array([0.5, 0.0, 0.0, 0.0]))
    run(d, clock, 0.095)
    assert np.allclose(d.v, 0.0)  # nothing before the latency
    run(d, clock, 0.005 + p.time_constant_s)
    # one time constant after the command takes effect: 1 − e⁻¹ of the step
    assert d.v[0] == pytest.approx(0.5 * (1 - math.exp(-1)), rel=0.03)
    assert clock.t - t0 == pytest.approx(0.3, abs=1e-9)


def test_tello_true_gain_mismatch_and_saturation() -> None:
    p = TelloParams(true_gains=RcGains(xy=0.012), cmd_gains=RcGains(xy=0.01), max_speed_xy=1.0)
    d, clock = flying_tello(p)
    d.send_body_velocity(np.array([0.4, 0.0, 0.0, 0.0]))  # rc b = 40 → really 0.48 m/s
    run(d, clock, 2.0)
    assert d.v[0] == pytest.approx(0.48, rel=1e-3)
    d.send_body_velocity(np.array([3.0, 3.0, 0.0, 0.0]))  # clipped at rc 100, then at max speed
    run(d, clock, 2.0)
    assert math.hypot(d.v[0], d.v[1]) == pytest.approx(1.0, rel=1e-3)


def test_tello_auto_land_without_commands_and_battery() -> None:
    p = TelloParams(auto_land_s=15.0, battery_pct=50.0, battery_drain_pct_per_s=1.0)
    d, clock = flying_tello(p)
    d.send_body_velocity(np.zeros(4))
    run(d, clock, 14.0)
    assert d.state().flying
    run(d, clock, 1.5)
    assert not d.state().flying and d.events[-1].kind == "auto_land_no_command"
    run(d, clock, 5.0)
    assert d.phase == "ground" and d.pose.p[2] == 0.0
    # airborne: climb 2 s + hover 3 s + 15 s until auto-land + descent 2.5 s; no drain on the ground
    assert d.state().battery_pct == pytest.approx(50.0 - (2.0 + 3.0 + 15.0 + 2.5), abs=0.1)


def test_tello_land_and_commands_ignored_on_ground() -> None:
    d, clock = flying_tello(TelloParams())
    d.land()
    run(d, clock, 4.0)
    assert d.phase == "ground"
    d.send_body_velocity(np.array([0.5, 0, 0, 0]))
    run(d, clock, 1.0)
    assert np.allclose(d.pose.p, [0, 0, 0])


def test_scamper_stops_without_commands() -> None:
    clock = Clock()
    r = ScamperSim(Pose.make([0, 0, 0], 0.0), RobotParams(time_constant_s=0.1, command_timeout_s=3.0), clock)
    r.send_body_velocity(np.array([0.2, 0.0, 0.7, 0.0]))  # z is ignored: a ground robot
    run(r, clock, 2.0)
    assert r.v[0] == pytest.approx(0.2, rel=1e-3) and r.v[2] == 0.0
    run(r, clock, 2.0)
    assert abs(r.v[0]) < 1e-3  # stopped after the 3 s timeout
    assert r.pose.p[0] == pytest.approx(0.2 * 3.0, abs=0.05)


def test_mocap_rate_noise_and_dropouts() -> None:
    m = MocapSim(
        MocapParams(rate_hz=100.0, noise_pos_m=0.001, noise_yaw_rad=0.0, dropout_prob=0.2),
        np.random.default_rng(0),
    )
    g = Pose.make([1.0, 2.0, 0.5], 0.3)
    stamps = []
    for k in range(2001):  # 10 s at 5 ms steps
        m.capture(k * 0.005, {"a": g})
        s = m.latest("a")
        if s is not None and (not stamps or s.stamp != stamps[-1]):
            stamps.append(s.stamp)
    assert m.frames == pytest.approx(1000, abs=2)
    assert m.dropped / m.frames == pytest.approx(0.2, abs=0.04)
    assert m.latest("b") is None
    err = m.latest("a").pose.p - g.p
    assert np.all(np.abs(err) < 0.005)


def test_square_reference_geometry() -> None:
    law = SquareLaw(side=1.0, speed=0.1)
    assert law.lap_time == pytest.approx(40.0)
    for t, xy in [
        (0.0, (-0.5, -0.5)),
        (5.0, (0.0, -0.5)),
        (10.0, (0.5, -0.5)),
        (15.0, (0.5, 0.0)),
        (30.0, (-0.5, 0.5)),
        (40.0, (-0.5, -0.5)),
    ]:
        g, _ = law.reference(t)
        assert np.allclose(g.p[:2], xy, atol=1e-9)
    g0, _ = law.reference(0.0)
    g1, _ = law.reference(40.0)
    assert math.isclose(math.cos(g1.theta - g0.theta), 1.0, abs_tol=1e-9)  # one full rotation per lap


def test_square_law_closed_loop_follows_the_square() -> None:
    """The robot model driven by the law stays within a few cm of the reference over a lap."""
    law = SquareLaw()
    clock = Clock()
    g0, _ = law.reference(0.0)
    r = ScamperSim(g0, RobotParams(time_constant_s=0.2), clock)
    worst = 0.0
    for k in range(int(40.0 / 0.05)):
        r.send_body_velocity(law.command(clock.t, r.pose))
        run(r, clock, 0.05)
        ref, _ = law.reference(clock.t)
        if k > 20:
            worst = max(worst, float(np.linalg.norm(r.pose.p[:2] - ref.p[:2])))
    assert worst < 0.06


def test_a_lossy_jittery_rc_link_delivers_in_arrival_order_and_counts_what_it_loses() -> None:
    """Each command takes effect latency + U(0, jitter) after it was sent (the generator's own draws,
    replayed): at every step the drone flies the command that arrived last; a lost one never arrives."""
    spec = LinkSpec(latency_s=0.05, jitter_s=0.04, loss=0.3)
    d, clock = flying_tello(TelloParams(time_constant_s=1e-4), LinkDelays(spec, np.random.default_rng(7)))
    mirror = np.random.default_rng(7)  # the same draws in the same order: lost?, then the delay
    arrivals: list[tuple[float, float]] = []  # (arrival time, commanded forward speed)
    checked = 0
    for k in range(60):
        speed = 0.01 * (k + 1)  # rc b = k + 1 exactly (gains 0.01 per unit)
        d.send_body_velocity(np.array([speed, 0.0, 0.0, 0.0]))
        if mirror.random() >= spec.loss:
            arrivals.append((clock.t + spec.latency_s + mirror.uniform(0.0, spec.jitter_s), speed))
        for _ in range(3):  # three world steps of 5 ms: a command every 15 ms, so jitter reorders some
            run(d, clock, 0.005)
            due = [a for a in arrivals if a[0] <= clock.t + 1e-9]
            if due:
                assert d.v[0] == pytest.approx(max(due)[1], abs=1e-6)
                checked += 1
    assert d.rc_link.lost_count == 60 - len(arrivals) > 0 and checked > 100
    order = [v for _, v in sorted(arrivals)]
    assert order != sorted(order)  # some commands overtook others: the drone followed arrival order


def test_delayed_motion_capture_samples_are_stamped_when_taken_and_seen_when_they_arrive() -> None:
    t = [0.0]
    mocap = MocapSim(
        MocapParams(rate_hz=100.0, noise_pos_m=0.0, noise_yaw_rad=0.0),
        np.random.default_rng(0),
        LinkDelays(LinkSpec(latency_s=0.03)),
        lambda: t[0],
    )
    body = {"drone1": Pose.make([1.0, 2.0, 3.0], 0.0)}
    mocap.capture(0.0, body)
    assert mocap.latest("drone1") is None  # taken, not yet arrived
    t[0] = 0.029
    assert mocap.latest("drone1") is None
    t[0] = 0.031
    s = mocap.latest("drone1")
    assert s is not None and s.stamp == 0.0 and np.allclose(s.pose.p, [1.0, 2.0, 3.0])
