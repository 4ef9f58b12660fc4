"""SafeDrone with background jobs (real drones): nothing the safety layer does waits for a drone.

Issue 15's observations, reproduced with fakes whose land() blocks like a Tello whose land reply is lost:
before, one tick blocked for 16 s while the other drone went unsupervised. Every assertion here is on
measured wall time or on what reached the wrapped drone.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from test_safety import LIM, FakeClock, Rig

from flightstack.hal import DroneState
from flightstack.safety import EventLog, MissionSupervisor
from tests.conftest import Bound


class BlockingLand:
    """Makes a FakeDrone's land() block until released (a Tello waiting for telemetry to show it down)."""

    def __init__(self, rig: Rig) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        rig.inner.on_land = self._block

    def _block(self) -> None:
        self.entered.set()
        assert self.release.wait(10.0), "test never released the land"


def wait_until(cond: object, timeout: float = 2.0) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():  # type: ignore[operator]
            return True
        time.sleep(0.005)
    return False


def fleet2() -> tuple[MissionSupervisor, Rig, Rig, FakeClock]:
    clock, log = FakeClock(), EventLog()
    r1 = Rig(drone_id=1, clock=clock, log=log, background=True)
    r2 = Rig(drone_id=2, clock=clock, log=log, background=True)
    for r in (r1, r2):
        assert wait_until(lambda r=r: "takeoff" in r.inner.calls)
        r.sd.tick()  # collect the takeoff job
    sup = MissionSupervisor({1: r1.sd, 2: r2.sd}, clock, LIM, log)
    return sup, r1, r2, clock


def test_a_blocking_land_never_blocks_the_tick_and_the_other_drone_stays_supervised(
    safety_bound: Bound,
) -> None:
    _sup, r1, r2, clock = fleet2()
    block = BlockingLand(r1)
    r1.move((2.5, 0.0, 1.0))  # beyond the hard fence (2.0 + 0.3): land
    worst = 0.0
    for k in range(1, 40):
        clock.t = 0.02 * k
        t0 = time.perf_counter()
        r1.sd.tick()
        r2.sd.tick()
        r2.sd.send_body_velocity(np.array([0.4, 0.0, 0.0, 0.0]))
        worst = max(worst, time.perf_counter() - t0)
        if k == 20:  # drone 2 drifts out too: it is supervised although drone 1's land still hangs
            r2.move((0.0, 2.6, 1.0))
    assert block.entered.is_set() and not r1.sd.landed and r1.sd.phase == "land_pending"
    safety_bound("longest safety tick of two drones while one land() hangs", 1e3 * worst, 10.0)
    assert r2.inner.calls.count("land") == 1 and r2.sd.landed
    assert r2.log.counts()["fence_hard_land"] == 2
    block.release.set()
    assert wait_until(lambda: (r1.sd.tick(), r1.sd.landed)[1])
    assert r1.inner.calls.count("land") == 1


def test_land_all_starts_every_landing_at_once_and_returns(safety_bound: Bound) -> None:
    sup, r1, r2, _clock = fleet2()
    blocks = [BlockingLand(r1), BlockingLand(r2)]
    t0 = time.perf_counter()
    sup.land_all("target lost")
    elapsed = time.perf_counter() - t0
    safety_bound("land_all returns while every land() hangs", 1e3 * elapsed, 50.0)
    assert all(b.entered.wait(1.0) for b in blocks)  # both landings under way in parallel
    for b in blocks:
        b.release.set()
    for r in (r1, r2):
        assert wait_until(lambda r=r: (r.sd.tick(), r.sd.landed)[1])
        assert [e.detail for e in r.log.of_kind("land") if e.drone == r.sd.drone_id] == ["target lost"]


def test_a_failed_land_is_retried_at_a_bounded_rate() -> None:
    _sup, r1, _, clock = fleet2()
    r1.inner.land_error = TimeoutError("land not confirmed")
    r1.sd.land("test")
    assert wait_until(lambda: r1.inner.calls.count("land") == 1)
    for k in range(1, 101):  # 2 s of ticks at 50 Hz
        clock.t = 0.02 * k
        r1.sd.tick()
        time.sleep(0.001)  # let a retry's worker run
    n = r1.inner.calls.count("land")
    assert 2 <= n <= 1 + 2.0 / LIM.land_retry_s + 1, n
    assert r1.log.counts()["land_failed"] == 1 and not r1.sd.landed


def test_link_loss_hovers_every_tick_lands_at_once_and_motion_capture_confirms() -> None:
    _, r1, _, clock = fleet2()
    link = {"alive": True}
    r1.inner.state = lambda: DroneState(80.0, 1.0, link["alive"], True, "flying")  # type: ignore[method-assign]
    r1.sd.send_body_velocity(np.array([0.5, 0.0, 0.0, 0.0]))
    clock.t = 0.02
    r1.sd.tick()  # link seen
    link["alive"] = False
    r1.inner.land_error = TimeoutError("no telemetry")  # the drone cannot confirm anything
    n_sent = len(r1.inner.sent)
    for k in range(2, 12):
        clock.t = 0.02 * k
        r1.sd.tick()
    new = r1.inner.sent[n_sent:]
    assert len(new) == 10 and all(not v.any() for v in new)  # rc 0 0 0 0 on every tick
    assert wait_until(lambda: "land" in r1.inner.calls)  # land sent at once, on a worker
    assert r1.log.counts()["link_lost"] == 1 and not r1.sd.landed
    r1.move((0.1, 0.0, 0.05))  # motion capture: it is on the floor
    clock.t = 0.3
    r1.sd.tick()
    assert r1.sd.landed
    assert "motion capture" in r1.log.of_kind("land")[-1].detail


def test_takeoff_runs_on_a_worker_and_a_failure_lands(safety_bound: Bound) -> None:
    clock, log = FakeClock(), EventLog()
    r = Rig(clock=clock, log=log, background=True, takeoff=False)
    started = threading.Event()

    def slow_failing_takeoff() -> None:
        started.set()
        time.sleep(0.2)
        raise TimeoutError("not airborne within 20 s")

    r.inner.takeoff = slow_failing_takeoff  # type: ignore[method-assign]
    t0 = time.perf_counter()
    r.sd.takeoff()
    safety_bound("takeoff() returns while the drone's takeoff runs", 1e3 * (time.perf_counter() - t0), 50.0)
    assert started.wait(1.0)
    assert wait_until(lambda: (r.sd.tick(), r.sd.takeoff_error is not None)[1])
    assert "TimeoutError" in (r.sd.takeoff_error or "")
    assert log.counts()["takeoff_failed"] == 1
    assert wait_until(lambda: "land" in r.inner.calls)


def test_a_land_asked_during_takeoff_is_not_confirmed_by_a_drone_still_on_the_floor() -> None:
    clock, log = FakeClock(), EventLog()
    r = Rig(p=(0.0, 0.0, 0.02), clock=clock, log=log, background=True, takeoff=False)
    go = threading.Event()
    r.inner.takeoff = lambda: go.wait(5.0) and None  # type: ignore[method-assign]
    r.inner.phase = "ground"
    r.sd.takeoff()
    r.sd.land("abort during takeoff")
    clock.t = 0.1
    r.sd.tick()
    assert not r.sd.landed  # floor pose and ground telemetry while the takeoff is still running
    go.set()
    assert wait_until(lambda: (r.sd.tick(), r.sd.landed)[1])


def test_ground_telemetry_while_its_takeoff_is_resent_is_not_a_landing_by_the_drone() -> None:
    """A lost takeoff datagram: the driver sees no motor start, its phase falls back to ground, and it
    sends takeoff again, all inside takeoff(). Telemetry showing the ground then is no landing by the
    drone: the drone stays supervised and commanded once it is up (seen on a lossy emulated radio)."""
    clock, log = FakeClock(), EventLog()
    r = Rig(clock=clock, log=log, background=True, takeoff=False)
    go = threading.Event()
    r.inner.takeoff = lambda: go.wait(5.0) and None  # type: ignore[method-assign]
    r.inner.phase = "taking_off"
    r.sd.takeoff()
    r.sd.tick()  # link seen
    r.inner.phase = "ground"  # the first takeoff had no effect; the driver sends it again
    for k in range(5):
        clock.t = 0.05 * (k + 1)
        r.sd.tick()
    assert "landed_by_drone" not in r.kinds(), r.kinds()
    r.inner.phase = "airborne"
    go.set()
    time.sleep(0.05)  # the takeoff job ends
    r.sd.tick()
    assert r.sd.takeoff_error is None
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    assert r.inner.sent and r.inner.sent[-1][0] > 0, r.kinds()


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP])
def test_hangup_quit_and_stop_signals_land_like_ctrl_c(sig: signal.Signals) -> None:
    sup, r1, r2, _ = fleet2()
    with pytest.raises(KeyboardInterrupt), sup.install_signal_handlers():
        os.kill(os.getpid(), sig)
        time.sleep(2.0)
        pytest.fail("signal not delivered")
    assert all(wait_until(lambda r=r: "land" in r.inner.calls) for r in (r1, r2))
    assert sup.signalled == sig.name


def test_a_second_ctrl_c_never_interrupts_the_landing() -> None:
    sup, r1, r2, clock = fleet2()
    interrupted_landing = False
    with sup.install_signal_handlers():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(2.0)
        except KeyboardInterrupt:
            try:  # the landing code of a run; a second Ctrl-C 20 ms after the first must not escape it
                time.sleep(0.02)
                os.kill(os.getpid(), signal.SIGINT)
                for k in range(20):
                    clock.t = 0.02 * k
                    r1.sd.tick()
                    r2.sd.tick()
                    time.sleep(0.005)
            except KeyboardInterrupt:
                interrupted_landing = True
    assert not interrupted_landing
    assert [e.detail.split(":")[0] for e in r1.log.of_kind("signal")][1] == "SIGINT after SIGINT"
    assert r1.sd.landed and r2.sd.landed


def test_a_first_signal_during_the_runs_landing_is_ignored() -> None:
    """The runner calls ignore_signals() where its landing code starts: even a first Ctrl-C there must not
    escape it (it would skip closing the drivers and disarming the robot)."""
    sup, r1, _r2, _ = fleet2()
    with sup.install_signal_handlers():
        sup.ignore_signals("the run's end (mission complete)")
        sup.land_all("mission complete")
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs here and must return
    assert "ignored" in r1.log.of_kind("signal")[-1].detail
