"""One time base for real-time runs: a receiver learns each sender's clock offset when it joins
and measures message ages on its own clock, so senders whose monotonic clocks are ±10 min off are fused
and go stale exactly like a sender on the receiver's clock; lock-step runs keep comparing stamps.

The deterministic tests drive `freshness.Freshness` with a fake receiver clock; the Zenoh test runs real
sessions on 127.0.0.1 with senders that stamp on a skewed clock (time.monotonic() + skew).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from flightstack.comms.factory import free_loopback_endpoints, make_bus, zenoh_bus_config
from flightstack.comms.freshness import Freshness, OffsetPolicy
from flightstack.comms.messages import PredictionMessage, encode
from flightstack.config.mission import load_mission
from tests.conftest import MISSIONS, secured_bus

MISSION = "clock_test"
SKEWS = {0: 0.0, 1: +600.0, 2: -600.0}  # sender clock − receiver clock (s): same, 10 min ahead, behind
RECEIVER_EPOCH = 5000.0  # the receiver's clock reads true time + this (s)
PERIOD_S = 0.02  # senders publish at 50 Hz
STALE_AFTER_S = 0.3


def msg(sender: int, seq: int, stamp: float, mission: str = MISSION) -> PredictionMessage:
    one = np.ones(4)
    return PredictionMessage(mission, sender, seq, stamp, True, one * sender, one, one, one)


class FakeClock:
    """The receiver's clock (s), moved by the test."""

    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def fly_and_stop(
    time_base: str, n_messages: int = 100, policy: OffsetPolicy | None = None
) -> tuple[dict[int, list[bool]], dict[int, float | None], Freshness]:
    """Three senders (SKEWS) publish n_messages at 50 Hz, each message delayed by the same random
    1-20 ms, then stop. Returns per sender: fused (latest not None) 5 ms after each receipt, and the
    first receiver time (true s after the last send) at which its newest message reads stale."""
    clock = FakeClock(RECEIVER_EPOCH)
    book = Freshness(MISSION, set(SKEWS), time_base, clock, policy)  # type: ignore[arg-type]
    delays = np.random.default_rng(0).uniform(0.001, 0.020, n_messages)
    fused: dict[int, list[bool]] = {i: [] for i in SKEWS}
    for k in range(n_messages):
        t_true = 10.0 + k * PERIOD_S
        clock.t = RECEIVER_EPOCH + t_true + delays[k]
        for i, skew in SKEWS.items():
            assert book.accept(encode(msg(i, k + 1, RECEIVER_EPOCH + t_true + skew))) is not None
        clock.t += 0.005
        for i in SKEWS:  # `now`: the receiver's mission clock (its own time), as the runner passes it
            fused[i].append(book.latest(i, clock.t, STALE_AFTER_S) is not None)
    t_last = 10.0 + (n_messages - 1) * PERIOD_S
    stale_at: dict[int, float | None] = dict.fromkeys(SKEWS)
    for step in range(1, 2000):  # 1 ms steps for 2 s after the last send
        clock.t = RECEIVER_EPOCH + t_last + step * 1e-3 + 0.0004  # never exactly on a boundary
        for i in SKEWS:
            if stale_at[i] is None and book.latest(i, clock.t, STALE_AFTER_S) is None:
                stale_at[i] = clock.t - RECEIVER_EPOCH - t_last
    return fused, stale_at, book


def test_skewed_senders_are_fused_and_go_stale_exactly_like_a_same_clock_sender() -> None:
    fused, stale_at, book = fly_and_stop("receiver")
    assert all(fused[0]), "the same-clock sender is fused at every tick"
    assert fused[1] == fused[0] and fused[2] == fused[0]  # ±10 min: identical, tick by tick
    assert stale_at[0] is not None and stale_at[1] == stale_at[0] and stale_at[2] == stale_at[0]
    # stale once stale_after has passed since the last send, less the smallest delay (folded into the
    # offset: ages exclude the floor delay of 1-20 ms)
    assert STALE_AFTER_S <= stale_at[0] <= STALE_AFTER_S + 0.021
    for i, skew in SKEWS.items():  # offset = receiver − sender clock + min delay
        off = book.offset(i)
        assert off is not None and off == pytest.approx(-skew + 0.001, abs=1e-3)
    assert book.dropped == {"stale": 3}  # one stale read per sender, nothing else dropped


def test_comparing_stamps_across_computers_is_what_failed() -> None:
    """The time base of lock-step runs ("stamps") on these senders: the one behind is never fused (the
    failure this time base fixes); the one ahead was never stale, and is now refused. Here the
    receiver's `now` is its own clock, as on hardware before the fix."""
    fused, _, book = fly_and_stop("stamps")
    assert not any(fused[2])
    # the sender whose clock is 10 min ahead was fused forever (never stale); a stamp ahead of
    # the receiver's clock is now refused ("stamp ahead"): it fails closed instead
    assert not any(fused[1]) and book.dropped["stamp ahead"] > 0


def test_lockstep_time_base_reads_no_clock() -> None:
    """Time base "stamps" (simulated clock): ages are `now − stamp`; the receiver's clock is never read,
    so lock-step results stay bit-identical."""

    def forbidden() -> float:
        raise AssertionError("the clock was read in time base 'stamps'")

    book = Freshness(MISSION, {0}, "stamps", forbidden)
    assert book.accept(encode(msg(0, 1, 10.0))) is not None
    assert book.latest(0, 10.5, 0.5) is not None
    assert book.latest(0, 10.5 + 1e-9, 0.5) is None


def test_offset_is_the_minimum_over_the_join_window_then_frozen() -> None:
    clock = FakeClock(100.0)
    policy = OffsetPolicy(join_messages=5, join_window_s=10.0)
    book = Freshness(MISSION, {0}, "receiver", clock, policy)
    delays = [0.010, 0.004, 0.030, 0.002, 0.008, 0.001]  # the 6th is after the window: within bounds
    for k, d in enumerate(delays):
        clock.t = 100.0 + k * 0.1 + d
        assert book.accept(encode(msg(0, k + 1, 50.0 + k * 0.1))) is not None
        if k == 4:
            assert book.offset(0) == pytest.approx(50.002)  # min over the first 5
    assert book.offset(0) == pytest.approx(50.001)  # a less delayed message lowers it (within bounds)
    events = [e.kind for e in book.offset_events]
    assert events == ["offset learning", "offset frozen"]


def _sender(book: Freshness, clock: FakeClock, sender: int = 0) -> Callable[[float, float], object]:
    """publish(t_true, stamp): the message arrives 5 ms after t_true on the receiver's clock."""
    seq = [0]

    def publish(t_true: float, stamp: float) -> object:
        seq[0] += 1
        clock.t = t_true + 0.005
        return book.accept(encode(msg(sender, seq[0], stamp)))

    return publish


def test_a_sender_jumping_its_clock_fails_closed_until_it_rejoins() -> None:
    """Forward jump beyond the tolerance: dropped as "stamp ahead"; backward jump: its messages read as
    old ("stale"). Either way it stays out of fusion while it keeps sending, and is re-learned after a
    silence longer than rejoin_after_s."""
    clock = FakeClock(0.0)
    policy = OffsetPolicy(join_messages=10, rejoin_after_s=2.0, ahead_tolerance_s=0.1)
    for jump, reason in ((+1.0, "stamp ahead"), (-1.0, "stale")):
        book = Freshness(MISSION, {0}, "receiver", clock, policy)
        publish = _sender(book, clock)
        t = 0.0
        for _ in range(50):  # joins: 1 s at 50 Hz, stamps 600 s ahead of the receiver
            t += PERIOD_S
            assert publish(t, t + 600.0) is not None
        assert book.latest(0, t, 0.5) is not None
        fused_after_jump = []
        for _ in range(250):  # jumps its clock, keeps sending for 5 s
            t += PERIOD_S
            publish(t, t + 600.0 + jump)
            clock.t += 0.005
            fused_after_jump.append(book.latest(0, t, 0.5) is not None)
        # ahead: its last message before the jump is fused until 0.5 s old; behind: never
        assert not any(fused_after_jump[25 if jump > 0 else 0 :])
        assert book.dropped[reason] > 200
        t += 3.0  # silent for 3 s > rejoin_after_s: the next message opens a new join window
        assert publish(t, t + 600.0 + jump) is not None
        assert book.latest(0, t, 0.5) is not None
        assert book.offset_events[-1].kind == "offset re-learning after silence"


@pytest.mark.parametrize(("ppm", "dropped"), [(50.0, False), (1000.0, True)])
def test_clock_drift_within_the_bound_is_tracked(ppm: float, dropped: bool) -> None:
    """A sender clock running fast by 50 ppm (2.5× a typical crystal) is followed for 20 min; one running
    1000 ppm fast exceeds the bound (100 ppm + 0.1 s) and is dropped as "stamp ahead"."""
    clock = FakeClock(0.0)
    book = Freshness(MISSION, {0}, "receiver", clock, OffsetPolicy(join_messages=5))
    publish = _sender(book, clock)
    for k in range(1, 1200 * 5):  # 5 Hz for 20 min
        t = k * 0.2
        publish(t, -600.0 + t * (1 + ppm * 1e-6))
    assert (book.dropped["stamp ahead"] > 0) is dropped
    if not dropped:
        assert book.latest(0, math.nan, 0.5) is not None


def test_hardware_missions_use_the_receiver_time_base(tmp_path: Path) -> None:
    hw_name = load_mission(MISSIONS / "paper_experiment.yaml", rig="lab").name
    bus = secured_bus(tmp_path / "certs", hw_name, [1, 2], ("agents",))
    hw = load_mission(MISSIONS / "paper_experiment.yaml", {"bus": bus}, rig="lab")
    plain = {"endpoints": {"agents": free_loopback_endpoints()[0]}, "security": "plaintext"}
    sim = load_mission(MISSIONS / "paper_sim.yaml", {"bus": {"kind": "zenoh", "zenoh": plain}})
    assert zenoh_bus_config(hw, "agents", {1, 2}).time_base == "receiver"
    assert zenoh_bus_config(sim, "agents", {1, 2, 3}).time_base == "stamps"
    inproc = make_bus(load_mission(MISSIONS / "paper_sim.yaml"), "agents", {1, 2, 3})
    assert inproc.freshness.time_base == "stamps"  # type: ignore[attr-defined]  # one clock in a process
    inproc.close()


# ----------------------------------------------------------------------------------- over Zenoh
zenoh = pytest.importorskip("zenoh")
from flightstack.comms.zenoh_bus import ZenohBus, ZenohBusConfig  # noqa: E402


@contextmanager
def receivers_and_senders() -> Iterator[tuple[ZenohBus, ZenohBus, dict[int, ZenohBus]]]:
    """Two receivers (time base "receiver" and "stamps") and one sender session per SKEWS entry."""
    eps = free_loopback_endpoints(2 + len(SKEWS))
    buses: list[ZenohBus] = []
    try:
        for k, (ids, base) in enumerate(((set(), "receiver"), (set(), "stamps"))):
            others = [e for j, e in enumerate(eps) if j != k]
            cfg = ZenohBusConfig(MISSION, ids, set(SKEWS), [eps[k]], others, time_base=base)  # type: ignore[arg-type]
            buses.append(ZenohBus(cfg))
        senders = {}
        for k, i in enumerate(SKEWS, start=2):
            others = [e for j, e in enumerate(eps) if j != k]
            senders[i] = ZenohBus(ZenohBusConfig(MISSION, {i}, set(SKEWS), [eps[k]], others))
            buses.append(senders[i])
        for b in buses:
            assert b.wait_alive(set(SKEWS), 20.0) == set(), "mesh did not come up"
        yield buses[0], buses[1], senders
    finally:
        for b in buses:
            b.close()


def test_skewed_senders_over_zenoh() -> None:
    """Real sessions, real clocks: senders stamp with time.monotonic() + (0, +600, −600) s at 50 Hz for
    1.5 s, then stop together. The receiver fuses all three throughout and sees all three go stale
    within a few ms of each other, STALE_AFTER_S after the last message."""
    with receivers_and_senders() as (rx, rx_stamps, senders):
        stop = threading.Event()
        last_sent = [0.0]

        def publish_loop() -> None:
            seq = 0
            t_next = time.monotonic()
            while not stop.is_set():
                seq += 1
                for i, skew in SKEWS.items():
                    senders[i].publish(msg(i, seq, time.monotonic() + skew))
                last_sent[0] = time.monotonic()
                t_next += PERIOD_S
                time.sleep(max(0.0, t_next - time.monotonic()))

        thread = threading.Thread(target=publish_loop)
        thread.start()
        try:
            assert rx.wait_for(dict.fromkeys(SKEWS, 1), 10.0) == set()
            time.sleep(0.5)  # the join window ends (20 messages)
            fused_checks = 0
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end:
                now = time.monotonic()
                assert all(rx.latest(i, now, STALE_AFTER_S) is not None for i in SKEWS)
                fused_checks += 1
                time.sleep(0.005)
            assert rx_stamps.latest(2, time.monotonic(), STALE_AFTER_S) is None  # behind: never fused
        finally:
            stop.set()
            thread.join()
        t_stop = last_sent[0]
        stale_at: dict[int, float] = {}
        while len(stale_at) < len(SKEWS) and time.monotonic() < t_stop + 3.0:
            now = time.monotonic()
            for i in SKEWS:
                if i not in stale_at and rx.latest(i, now, STALE_AFTER_S) is None:
                    stale_at[i] = now - t_stop
            time.sleep(0.001)
        # ahead: was never stale; now refused as "stamp ahead"
        assert rx_stamps.latest(1, time.monotonic(), STALE_AFTER_S) is None
    ms = {i: round(1e3 * s, 1) for i, s in stale_at.items()}
    print(f"stale after the last send (ms) by skew: { {SKEWS[i]: v for i, v in ms.items()} }")
    assert set(stale_at) == set(SKEWS) and fused_checks > 50
    assert max(stale_at.values()) - min(stale_at.values()) < 0.03, ms
    assert all(STALE_AFTER_S - 0.03 < s < STALE_AFTER_S + 0.1 for s in stale_at.values()), ms
    assert rx.dropped.get("stamp ahead", 0) == 0
