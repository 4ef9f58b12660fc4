"""The simulated lab's `state`, `robot` and `bus` links: the drones' telemetry arrives late at its rate,
the ground robot acts on its commands late, the messages between agents arrive late on the lab's clock;
each link's decisions are seeded (the same seed gives the same decisions), and a perfect link draws
nothing (tests/fingerprints.py holds the perfect rigs' recordings bit for bit)."""

from __future__ import annotations

import math

import numpy as np

from flightstack.comms.bus import InProcBus
from flightstack.comms.delayed_bus import LOST, DelayedBus
from flightstack.comms.messages import PredictionMessage
from flightstack.config.links import LinkDelays, LinkSpec
from flightstack.config.mission import load_mission
from flightstack.paper.geometry import Pose
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS
from flightstack.sim_backend.build_lab import LabSimBackend
from flightstack.sim_backend.lab import RobotParams, ScamperSim, TelloParams, TelloSim
from tests.conftest import fly_mode

WORLD_DT = 0.005  # the lab-sim rig's world step (s)


def _lab(links: dict[str, object], seconds: float = 2.0, seed: int = 0):
    return load_mission(
        "paper_experiment",
        {"duration_s": seconds, "compare_modes": ["none"], "links": links, "seed": seed},
        rig="lab-sim",
    )


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _msg(sender: int, seq: int, stamp: float) -> PredictionMessage:
    z = np.zeros(4)
    return PredictionMessage("m", sender, seq, stamp, True, z, z, np.ones(4), np.ones(4))


# ---- state ---------------------------------------------------------------------------------------------
def test_telemetry_arrives_late_at_its_rate_on_the_labs_clock() -> None:
    """A state link of 0.1 s + U(0, 0.02 s) at 10 Hz: the takeoff shows in state() between 0.1 s and
    0.1 + 0.02 + 1/10 s (+ a world step) after it happened; before the first sample, the phase is unknown."""
    spec = LinkSpec(latency_s=0.1, jitter_s=0.02, rate_hz=10.0)
    backend = LabSimBackend(_lab({"profile": "perfect", "state": spec.model_dump()}))
    world, d = backend.world, backend.drone(1)
    assert d.state().phase == "unknown" and not d.state().link_alive  # nothing has arrived yet
    while world.t < 0.2:
        world.step(WORLD_DT)
    assert d.state().phase == "ground"
    d.connect()
    d.takeoff()
    t_truth = world.t
    while d.state().phase != "taking_off":
        world.step(WORLD_DT)
        assert world.t < t_truth + 1.0
    late = world.t - t_truth
    assert 0.1 <= late <= 0.1 + 0.02 + 0.1 + WORLD_DT + 1e-9, late
    arrivals = []
    while world.t < 3.0:  # the seen state changes at most once per sample (10 Hz)
        before = d.state()
        world.step(WORLD_DT)
        if d.state() is not before:
            arrivals.append(world.t)
    gaps = np.diff(arrivals)
    assert gaps.min() >= 0.1 - 0.02 - 1e-9 and abs(np.mean(gaps) - 0.1) < 0.005, gaps


def test_a_perfect_state_link_is_the_present_and_draws_nothing() -> None:
    rng = np.random.default_rng(7)
    before = rng.bit_generator.state
    clock = Clock()
    d = TelloSim(1, Pose.make([0, 0, 0], 0.0), TelloParams(), clock, None, LinkDelays(LinkSpec(), rng))
    assert d.telemetry is None
    d.connect()
    d.takeoff()
    d.step(0.01, 0.01)
    assert d.state().phase == "taking_off" and d.state().link_alive
    assert rng.bit_generator.state == before


# ---- robot ---------------------------------------------------------------------------------------------
def test_the_robot_acts_late_and_loses_commands_with_seeded_decisions() -> None:
    def robot(seed: int, loss: float = 0.0) -> tuple[ScamperSim, Clock]:
        clock = Clock()
        link = LinkDelays(LinkSpec(latency_s=0.2, jitter_s=0.01, loss=loss), np.random.default_rng(seed))
        return ScamperSim(Pose.make([0, 0, 0], 0.0), RobotParams(time_constant_s=0.1), clock, link), clock

    r, clock = robot(0)
    r.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
    moved_at = None
    while clock.t < 1.0:
        clock.t += 0.001
        r.step(clock.t, 0.001)
        if moved_at is None and r.v[0] > 0:
            moved_at = clock.t
    assert moved_at is not None and 0.2 <= moved_at <= 0.21 + 0.001 + 1e-9, moved_at

    def lost_pattern(seed: int) -> list[bool]:
        r, clock = robot(seed, loss=0.3)
        out = []
        assert r.link is not None
        for _ in range(200):
            n = r.link.lost_count
            r.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
            out.append(r.link.lost_count > n)
            clock.t += 0.05
            r.step(clock.t, 0.05)
        return out

    a, b, c = lost_pattern(1), lost_pattern(1), lost_pattern(2)
    assert a == b and a != c
    assert 0.2 < np.mean(a) < 0.4  # about 30 % lost


def test_a_perfect_robot_link_acts_at_once_and_draws_nothing() -> None:
    rng = np.random.default_rng(3)
    before = rng.bit_generator.state
    clock = Clock()
    r = ScamperSim(Pose.make([0, 0, 0], 0.0), RobotParams(), clock, LinkDelays(LinkSpec(), rng))
    r.send_body_velocity(np.array([0.3, 0.0, 0.0, 0.0]))
    r.step(0.01, 0.01)
    assert r.v[0] > 0 and r.link is None and rng.bit_generator.state == before


# ---- bus -----------------------------------------------------------------------------------------------
def test_a_message_arrives_on_the_labs_clock_late_by_the_bus_link() -> None:
    """Bus link 0.12 s + U(0, 0.03 s): each message is first readable between 0.12 and 0.15 s (+ a world
    step) after it was published, measured on the lab's world clock."""
    spec = {"latency_s": 0.12, "jitter_s": 0.03}
    backend = LabSimBackend(_lab({"profile": "perfect", "bus": spec}))
    inner = InProcBus("m", {1, 2})
    bus = backend.delay_bus(inner)
    assert isinstance(bus, DelayedBus) and bus.clock == backend.clock.now
    world, measured = backend.world, []
    for seq in range(1, 21):
        t0 = world.t
        bus.publish(_msg(1, seq, t0))
        while (m := bus.latest(1, world.t, 10.0)) is None or m.seq != seq:
            world.step(WORLD_DT)
        measured.append(world.t - t0)
        world.step(0.2)  # well apart
    assert all(0.12 <= d <= 0.15 + WORLD_DT + 1e-9 for d in measured), measured
    assert np.std(measured) > 0.003  # the jitter is drawn
    assert len(bus.delays) == 20  # one per message


def test_bus_decisions_are_seeded_per_sender_and_a_perfect_bus_is_untouched() -> None:
    def decisions(seed: int, sender: int) -> tuple[list[float], int]:
        backend = LabSimBackend(_lab({"bus": {"latency_s": 0.05, "jitter_s": 0.05, "loss": 0.2}}, seed=seed))
        bus = backend.delay_bus(InProcBus("m", {1, 2}))
        assert isinstance(bus, DelayedBus)
        for seq in range(1, 101):
            bus.publish(_msg(sender, seq, 0.0))
        return bus.delays, bus.lost[sender]

    assert decisions(0, 1) == decisions(0, 1)
    assert decisions(0, 1) != decisions(1, 1) and decisions(0, 1) != decisions(0, 2)
    d, lost = decisions(0, 1)
    assert 5 <= lost <= 40 and len(d) == 100 - lost
    inner = InProcBus("m", {1, 2})
    assert LabSimBackend(_lab({"profile": "tello"})).delay_bus(inner) is inner  # tello's bus is at once


def test_messages_of_one_sender_arrive_in_order_and_losses_are_counted() -> None:
    clock = Clock()
    draws = iter([0.3, 0.0, 0.1])

    class Link:
        def lost(self) -> bool:
            return False

        def delay(self) -> float:
            return next(draws)

    inner = InProcBus("m", {1})
    bus = DelayedBus(inner, clock, lambda sender: Link())
    for seq in (1, 2, 3):
        bus.publish(_msg(1, seq, 0.0))
    assert bus.delays == [0.3, 0.3, 0.3]  # the later ones wait for the first (TCP)
    clock.t = 0.3
    assert bus.latest(1, 0.3, 1.0).seq == 3 and not inner.dropped  # in order: none refused
    lossy = DelayedBus(
        InProcBus("m", {1}), clock, lambda s: LinkDelays(LinkSpec(loss=0.5), np.random.default_rng(0))
    )
    for seq in range(1, 41):
        lossy.publish(_msg(1, seq, 0.3))
    assert lossy.dropped[LOST] == lossy.lost[1] > 0


# ---- a whole run ---------------------------------------------------------------------------------------
def test_a_run_with_late_state_robot_and_bus_is_seeded() -> None:
    links = {"profile": "tello", "bus": {"latency_s": 0.03, "jitter_s": 0.02, "loss": 0.1}}
    a = fly_mode(_lab(links), "none")
    b = fly_mode(_lab(links), "none")
    c = fly_mode(_lab(links, seed=1), "none")
    assert a.ticks_done == a.t.size and not a.error
    for f in ARRAY_FIELDS:
        if f not in MACHINE_FIELDS:
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert not np.array_equal(a.g_w0, c.g_w0) or not np.array_equal(a.g_bar_w, c.g_bar_w)
    assert math.isfinite(float(np.nanmean(a.g_bar_w)))
    assert a.bus_dropped.get(LOST, 0) > 0 and a.bus_dropped == b.bus_dropped  # the fleet's bus is the lab's
