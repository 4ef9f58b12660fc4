"""flightstack.safety against fakes: a recording Drone, a hand-driven Clock and a settable PoseSource.

World-frame checks use an independent rotation (complex multiplication), not flightstack.paper.geometry.
"""

from __future__ import annotations

import cmath
import math
import os
import signal
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flightstack.hal import Drone, DroneState, StampedPose
from flightstack.paper.geometry import Pose
from flightstack.safety import (
    EVENT_KINDS,
    EventLog,
    MissionSupervisor,
    SafeDrone,
    SafetyError,
    SafetyEvent,
    SafetyLimits,
    saturate,
)

LIM = SafetyLimits()
BODY = "drone1"


# ---- fakes -------------------------------------------------------------------------------------------------
class FakeClock:
    """Mission time (s) advanced by hand."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    def sleep_until(self, t: float) -> None:
        self.t = max(self.t, t)


class FakePoses:
    """One settable pose per body; stamp None means "stamped now" (a live motion-capture stream), and like
    a live stream its samples are never bit-identical (x carries a 1e-9 m jitter that changes with the
    stamp: Motive's noise, which a frozen pose lacks, flightstack.safety.pose_check)."""

    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.poses: dict[str, Pose] = {}
        self.stamps: dict[str, float | None] = {}
        self.error: Exception | None = None

    def set(
        self, body: str, p: tuple[float, float, float], yaw: float = 0.0, stamp: float | None = None
    ) -> None:
        self.poses[body] = Pose.make(p, yaw)
        self.stamps[body] = stamp

    def latest(self, body: str) -> StampedPose | None:
        if self.error is not None:
            raise self.error
        if body not in self.poses:
            return None
        stamp, pose = self.stamps[body], self.poses[body]
        if stamp is None:
            now = self.clock.now()
            return StampedPose(now, Pose.make(pose.p + np.array([1e-9 * (now % 1.0), 0.0, 0.0]), pose.theta))
        return StampedPose(stamp, pose)


class FakeDrone:
    """Records every call (except state()) and every velocity it receives."""

    def __init__(self, battery: float = 80.0) -> None:
        self.calls: list[str] = []
        self.sent: list[np.ndarray] = []
        self.battery = battery
        self.land_error: BaseException | None = None
        self.estop_error: BaseException | None = None
        self.state_error: Exception | None = None
        self.on_send: Callable[[], None] | None = None
        self.on_land: Callable[[], None] | None = None
        self.phase = ""  # "" = derived from flying (True); "ground" = its telemetry shows it down

    def connect(self) -> None:
        self.calls.append("connect")

    def takeoff(self) -> None:
        self.calls.append("takeoff")

    def land(self) -> None:
        self.calls.append("land")
        if self.on_land is not None:
            self.on_land()
        if self.land_error is not None:
            raise self.land_error

    def emergency_stop(self) -> None:
        self.calls.append("emergency_stop")
        if self.estop_error is not None:
            raise self.estop_error

    def send_body_velocity(self, V: np.ndarray) -> None:
        self.calls.append("send")
        self.sent.append(np.array(V, dtype=float))
        if self.on_send is not None:
            self.on_send()

    def state(self) -> DroneState:
        if self.state_error is not None:
            raise self.state_error
        return DroneState(self.battery, 1.0, True, self.phase != "ground", self.phase)

    def close(self) -> None:
        self.calls.append("close")

    def calls_after(self, name: str) -> list[str]:
        return self.calls[self.calls.index(name) + 1 :]


class Rig:
    """One SafeDrone over a FakeDrone, with its clock, poses and log."""

    def __init__(
        self,
        p: tuple[float, float, float] = (0.0, 0.0, 1.0),
        yaw: float = 0.0,
        limits: SafetyLimits = LIM,
        battery: float = 80.0,
        takeoff: bool = True,
        drone_id: int = 1,
        clock: FakeClock | None = None,
        log: EventLog | None = None,
        background: bool = False,
    ) -> None:
        self.clock = FakeClock() if clock is None else clock
        self.poses = FakePoses(self.clock)
        self.poses.set(f"drone{drone_id}", p, yaw)
        self.inner = FakeDrone(battery)
        self.log = EventLog() if log is None else log
        self.sd = SafeDrone(
            drone_id, self.inner, self.poses, f"drone{drone_id}", self.clock, limits, self.log, background
        )
        if takeoff:
            self.sd.takeoff()

    def move(self, p: tuple[float, float, float], yaw: float = 0.0, stamp: float | None = None) -> None:
        self.poses.set(self.sd.body, p, yaw, stamp)

    def kinds(self) -> list[str]:
        return [e.kind for e in self.log.events]

    def last_sent(self) -> np.ndarray:
        return self.inner.sent[-1]


def world_xy(V: np.ndarray, yaw: float) -> tuple[float, float]:
    """Body (v_x, v_y) rotated into the world frame, by complex multiplication (independent reference)."""
    w = complex(V[0], V[1]) * cmath.exp(1j * yaw)
    return w.real, w.imag


def body_xy(vw: tuple[float, float], yaw: float) -> tuple[float, float]:
    b = complex(*vw) * cmath.exp(-1j * yaw)
    return b.real, b.imag


def within_limits(V: np.ndarray, lim: SafetyLimits = LIM) -> bool:
    return bool(
        np.all(np.isfinite(V))
        and math.hypot(V[0], V[1]) <= lim.max_speed_xy
        and abs(V[2]) <= lim.max_speed_z
        and abs(V[3]) <= lim.max_yaw_rate
    )


# ---- limits, log, protocol ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs",
    [
        {"fence_lo": (0.0, 0.0, 0.0), "fence_hi": (1.0, 0.0, 1.0)},
        {"fence_lo": (0.0, 0.0, float("nan"))},
        {"max_speed_xy": 0.0},
        {"max_yaw_rate": -1.0},
        {"hard_margin": -0.1},
        {"pose_timeout": 1.0, "pose_land_after": 0.5},
        {"land_battery": 40.0, "min_battery_takeoff": 30.0},
        {"min_battery_takeoff": 120.0},
        {"max_speed_xy": 1e9},  # beyond a Tello's top speed: limits nothing (MAX_SPEED_MPS)
        {"max_speed_z": 8.5},
        {"max_yaw_rate": 7.0},  # beyond one turn a second
        {"fence_hi": (1e9, 2.0, 2.0)},  # beyond any motion-capture volume (MAX_FENCE_M)
        {"fence_lo": (-100.0, -2.0, 0.3)},  # the hard fence (+ hard_margin 0.3) reaches -100.3 m
        {"hard_margin": 1e9},
    ],
)
def test_limits_reject_inconsistent_values(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        SafetyLimits(**kwargs)


def test_limits_accept_lists_and_compute_hard_fence() -> None:
    lim = SafetyLimits(fence_lo=[-1, -1, 0.5], fence_hi=[1, 1, 2], hard_margin=0.25)  # type: ignore[arg-type]
    assert lim.fence_lo == (-1.0, -1.0, 0.5)
    assert lim.hard_lo == (-1.25, -1.25, 0.25)
    assert lim.hard_hi == (1.25, 1.25, 2.25)


def test_event_log_is_thread_safe_and_exports() -> None:
    log = EventLog()

    def writer(k: int) -> None:
        for j in range(500):
            log.record(float(j), k, "saturated" if j % 2 else "land", f"{k}/{j}")

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(log) == 4000
    assert log.counts() == {"saturated": 2000, "land": 2000}
    d = log.events[0].to_dict()
    assert set(d) == {"t", "drone", "kind", "detail", "source", "clock", "value"}
    assert d["source"] == "safety" and d["clock"] == "mission"
    assert len(log.of_kind("land")) == 2000
    with pytest.raises(ValueError):
        log.append(SafetyEvent(0.0, None, "not_a_kind", ""))


def test_safe_drone_is_a_hal_drone() -> None:
    assert isinstance(Rig().sd, Drone)


def test_command_inside_limits_and_fence_passes_unchanged() -> None:
    r = Rig()
    V = np.array([0.2, -0.1, 0.1, -0.5])
    r.sd.send_body_velocity(V)
    np.testing.assert_array_equal(r.last_sent(), V)
    assert r.kinds() == ["takeoff"]
    np.testing.assert_array_equal(r.sd.last_command, V)


# ---- saturation and invalid commands -----------------------------------------------------------------------
def test_saturation_keeps_xy_direction_and_clips_z_and_yaw() -> None:
    r = Rig()
    V = np.array([3.0, -4.0, -2.0, 5.0])
    r.sd.send_body_velocity(V)
    out = r.last_sent()
    assert math.hypot(out[0], out[1]) == pytest.approx(LIM.max_speed_xy, rel=1e-12)
    assert out[0] * V[1] - out[1] * V[0] == pytest.approx(0.0, abs=1e-12)  # parallel
    assert out[0] * V[0] + out[1] * V[1] > 0  # same sense
    assert out[2] == -LIM.max_speed_z and out[3] == LIM.max_yaw_rate
    assert np.all(np.abs(out) <= np.abs(V))
    assert within_limits(out)


def test_saturation_event_once_per_episode() -> None:
    r = Rig()
    for _ in range(5):
        r.sd.send_body_velocity(np.array([2.0, 0.0, 0.0, 0.0]))
    assert r.log.counts()["saturated"] == 1
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))  # episode ends
    r.sd.send_body_velocity(np.array([0.0, 0.0, 0.0, 3.0]))
    assert r.log.counts()["saturated"] == 2


big = st.floats(allow_nan=False, allow_infinity=False)


@given(big, big, big, big)
def test_saturate_never_increases_a_component_and_keeps_direction(
    a: float, b: float, c: float, d: float
) -> None:
    V = np.array([a, b, c, d])
    out, _ = saturate(V, LIM)
    assert within_limits(out)
    assert np.all(np.abs(out) <= np.abs(V))
    assert np.all(out * V >= 0)  # no sign flips
    if math.hypot(out[0], out[1]) > 1e-6:  # direction of (v_x, v_y) kept
        assert math.atan2(out[1], out[0]) == pytest.approx(math.atan2(b, a), abs=1e-9)


@pytest.mark.parametrize(
    "bad",
    [
        [float("nan"), 0.1, 0.0, 0.0],
        [0.1, float("inf"), 0.0, 0.0],
        [0.0, 0.0, float("-inf"), 0.0],
        [0.1, 0.2, 0.3],
        None,
        "fast",
    ],
)
def test_invalid_command_sends_zeros_and_logs(bad: object) -> None:
    r = Rig()
    r.sd.send_body_velocity(bad)  # type: ignore[arg-type]
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))
    assert r.log.counts()["invalid_command"] == 1
    r.sd.send_body_velocity(bad)  # type: ignore[arg-type]
    assert r.log.counts()["invalid_command"] == 1  # same episode
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])


# ---- geofence ----------------------------------------------------------------------------------------------
def test_soft_fence_yaw_90_removes_outward_world_x_and_passes_inward() -> None:
    yaw = math.pi / 2
    r = Rig(p=(2.15, 0.0, 1.0), yaw=yaw)  # beyond the soft +x face (2.0), inside the hard one (2.3)
    # body -y is world +x at a yaw of 90°: further out
    out_cmd = np.array([0.0, -0.3, 0.0, 0.0])
    assert world_xy(out_cmd, yaw)[0] == pytest.approx(0.3)
    r.sd.send_body_velocity(out_cmd)
    wx, wy = world_xy(r.last_sent(), yaw)
    assert wx == pytest.approx(0.0, abs=1e-12) and wy == pytest.approx(0.0, abs=1e-12)
    # body +y is world -x: back inside, passes unchanged
    in_cmd = np.array([0.0, 0.3, 0.0, 0.2])
    r.sd.send_body_velocity(in_cmd)
    np.testing.assert_allclose(r.last_sent(), in_cmd, atol=1e-12)
    # mixed: world (+0.3 out, +0.2 along y) -> only the world-x part removed
    mixed = np.array([*body_xy((0.3, 0.2), yaw), 0.1, 0.5])
    r.sd.send_body_velocity(mixed)
    wx, wy = world_xy(r.last_sent(), yaw)
    assert wx == pytest.approx(0.0, abs=1e-12)
    assert wy == pytest.approx(0.2, abs=1e-12)
    assert r.last_sent()[2:] == pytest.approx([0.1, 0.5])
    assert r.log.counts()["fence_soft"] == 1  # one episode
    assert "land" not in r.inner.calls


def test_soft_fence_episode_ends_inside() -> None:
    r = Rig(p=(2.1, 0.0, 1.0))
    r.sd.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(r.last_sent(), np.zeros(4), atol=1e-12)
    r.move((1.9, 0.0, 1.0))
    r.sd.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(r.last_sent(), [0.2, 0.0, 0.0, 0.0])
    r.move((2.1, 0.0, 1.0))
    r.sd.send_body_velocity(np.array([0.2, 0.0, 0.0, 0.0]))
    assert r.log.counts()["fence_soft"] == 2


def test_soft_fence_vertical_faces() -> None:
    r = Rig(p=(0.0, 0.0, 2.1))  # above the ceiling
    r.sd.send_body_velocity(np.array([0.0, 0.0, 0.2, 0.0]))
    assert r.last_sent()[2] == 0.0
    r.sd.send_body_velocity(np.array([0.0, 0.0, -0.2, 0.0]))
    assert r.last_sent()[2] == -0.2
    r.move((0.0, 0.0, 0.1))  # below the soft floor (0.3), above the hard one (0.0)
    r.sd.send_body_velocity(np.array([0.0, 0.0, -0.2, 0.0]))
    assert r.last_sent()[2] == 0.0
    r.sd.send_body_velocity(np.array([0.0, 0.0, 0.2, 0.0]))
    assert r.last_sent()[2] == 0.2


soft_out = st.sampled_from([-1, 0, 1])


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(
    yaw=st.floats(-math.pi, math.pi),
    sides=st.tuples(soft_out, soft_out, soft_out),
    depth=st.floats(0.01, 0.29),
    v=st.tuples(st.floats(-0.35, 0.35), st.floats(-0.35, 0.35), st.floats(-0.3, 0.3), st.floats(-1.0, 1.0)),
)
def test_soft_fence_property_no_outward_world_component(
    yaw: float, sides: tuple[int, int, int], depth: float, v: tuple[float, float, float, float]
) -> None:
    p = [0.0, 0.0, 1.0]
    for k, s in enumerate(sides):
        if s > 0:
            p[k] = LIM.fence_hi[k] + depth
        elif s < 0:
            p[k] = LIM.fence_lo[k] - depth
    r = Rig(p=(p[0], p[1], 1.0), yaw=yaw)  # take off at a safe height, then move
    r.sd.send_body_velocity(np.zeros(4))  # arms the floor check (z >= soft floor)
    r.move((p[0], p[1], p[2]), yaw)
    V = np.array(v)
    r.sd.send_body_velocity(V)
    out = r.last_sent()
    w_in = (*world_xy(V, yaw), V[2])
    w_out = (*world_xy(out, yaw), out[2])
    for k, s in enumerate(sides):
        if s == 0:
            assert w_out[k] == pytest.approx(w_in[k], abs=1e-9)  # untouched axis
        elif s * w_in[k] > 0:
            assert w_out[k] == pytest.approx(0.0, abs=1e-9)  # outward removed
        else:
            assert w_out[k] == pytest.approx(w_in[k], abs=1e-9)  # inward kept
    assert out[3] == V[3]
    assert "land" not in r.inner.calls


def test_hard_fence_lands_and_nothing_is_sent_afterwards() -> None:
    r = Rig(p=(0.0, 0.0, 1.0))
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.clock.t = 1.0
    r.move((2.31, 0.0, 1.0))  # beyond the hard +x face (2.3)
    r.sd.send_body_velocity(np.array([-0.2, 0.0, 0.0, 0.0]))
    assert r.inner.calls[-1] == "land"
    assert r.sd.landed
    for k in range(20):
        r.clock.t = 1.0 + 0.05 * (k + 1)
        r.sd.tick()
        r.sd.send_body_velocity(np.array([-0.2, 0.0, 0.0, 0.0]))
    assert r.inner.calls_after("land") == []
    ev = r.log.of_kind("fence_hard_land")
    assert len(ev) == 1 and ev[0].t == 1.0 and ev[0].drone == 1
    assert r.log.counts()["command_after_land"] == 1
    assert r.log.counts()["land"] == 1


def test_hard_fence_checked_by_tick_without_commands() -> None:
    r = Rig()
    r.move((0.0, -2.4, 1.0))
    r.sd.tick()
    assert r.inner.calls[-1] == "land"
    assert r.log.counts()["fence_hard_land"] == 1


def test_hard_floor_ignored_on_the_ground_until_the_drone_has_climbed() -> None:
    r = Rig(p=(0.0, 0.0, 0.0))  # on the floor: the hard floor is at 0.3 - 0.3 = 0.0
    r.move((0.0, 0.0, -0.002))  # motion-capture noise below the floor during the climb
    r.clock.t = 0.05
    r.sd.tick()
    assert "land" not in r.inner.calls
    r.move((0.0, 0.0, 1.0))  # climbed into the fence: the floor is armed
    r.clock.t = 0.1
    r.sd.tick()
    r.move((0.0, 0.0, -0.01))
    r.clock.t = 0.15
    r.sd.tick()
    assert r.inner.calls[-1] == "land"
    assert r.log.counts()["fence_hard_land"] == 1


# ---- watchdog ----------------------------------------------------------------------------------------------
def test_command_watchdog_hovers_every_tick_and_logs_once_per_episode() -> None:
    """A silent loop gets zero velocity on every tick (the drivers read silence as a dead loop and land)."""
    r = Rig()
    r.clock.t = 0.4
    r.sd.tick()
    assert r.inner.sent == []
    r.clock.t = 0.6
    r.sd.tick()
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))
    for t in (0.7, 1.0, 1.5):
        r.clock.t = t
        r.sd.tick()
    assert len(r.inner.sent) == 4 and all(not v.any() for v in r.inner.sent)
    ev = r.log.of_kind("command_timeout")
    assert len(ev) == 1 and ev[0].t == 0.6
    r.clock.t = 2.0
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.clock.t = 2.4
    r.sd.tick()
    assert len(r.log.of_kind("command_timeout")) == 1
    r.clock.t = 2.6
    r.sd.tick()
    assert len(r.log.of_kind("command_timeout")) == 2
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))


def test_the_takeoff_climb_is_no_silence_of_the_loop_but_still_gets_zero_velocity() -> None:
    """While its telemetry shows the takeoff climb no command is due (the drone ignores rc): zero velocity
    is sent as before, but `command_timeout` (a dead loop) counts only from the climb's end."""
    r = Rig()
    r.inner.phase = "taking_off"
    for t in (0.6, 1.5, 2.95):
        r.clock.t = t
        r.sd.tick()
    assert len(r.inner.sent) == 3 and all(not v.any() for v in r.inner.sent)
    assert r.log.of_kind("command_timeout") == []
    r.inner.phase = "flying"  # up at 2.95 s: the loop has command_timeout (0.5 s) to speak
    r.clock.t = 3.4
    r.sd.tick()
    assert r.log.of_kind("command_timeout") == [] and len(r.inner.sent) == 4
    r.clock.t = 3.5
    r.sd.tick()
    (ev,) = r.log.of_kind("command_timeout")
    assert ev.t == 3.5 and ev.detail.startswith("no command for 0.550 s")


def test_tick_before_takeoff_or_first_command_does_nothing() -> None:
    r = Rig(takeoff=False)
    r.clock.t = 10.0
    r.sd.tick()
    assert r.inner.calls == [] and len(r.log) == 0
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))  # a sim drone that starts airborne
    np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])


# ---- stale pose --------------------------------------------------------------------------------------------
def test_stale_pose_hovers_then_lands_at_the_right_times() -> None:
    r = Rig()
    r.move((0.0, 0.0, 1.0), stamp=0.0)  # the stream freezes at t = 0
    V = np.array([0.1, 0.1, 0.0, 0.0])
    dt = 0.05
    for k in range(1, 60):
        r.clock.t = k * dt
        r.sd.tick()
        if r.sd.landed:
            break
        r.sd.send_body_velocity(V)
        if r.sd.landed:
            break
        expected = V if r.clock.t <= LIM.pose_timeout else np.zeros(4)  # stale -> hover
        np.testing.assert_array_equal(r.last_sent(), expected)
    hover = r.log.of_kind("pose_stale_hover")
    land = r.log.of_kind("pose_stale_land")
    assert len(hover) == 1 and len(land) == 1
    assert LIM.pose_timeout < hover[0].t <= LIM.pose_timeout + dt + 1e-9
    assert LIM.pose_land_after < land[0].t <= LIM.pose_land_after + dt + 1e-9
    assert r.inner.calls[-1] == "land"
    r.clock.t += 1.0
    r.sd.tick()
    r.sd.send_body_velocity(V)
    assert r.inner.calls_after("land") == []


def test_stale_pose_recovers_before_landing() -> None:
    r = Rig()
    r.move((0.0, 0.0, 1.0), stamp=0.0)
    r.clock.t = 0.35
    r.sd.tick()  # stale: hover, zeros once
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))
    n = len(r.inner.sent)
    r.clock.t = 0.4
    r.sd.tick()
    assert len(r.inner.sent) == n  # not one zero command per tick
    r.move((0.0, 0.0, 1.0))  # live again
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])
    r.move((0.0, 0.0, 1.0), stamp=0.55)
    r.clock.t = 1.0
    r.sd.tick()
    assert len(r.log.of_kind("pose_stale_hover")) == 2
    assert not r.sd.landed


def test_pose_never_seen_hovers_and_lands_counting_from_the_first_command() -> None:
    r = Rig(takeoff=False)
    r.poses.poses.clear()
    r.clock.t = 5.0
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))
    r.clock.t = 6.9
    r.sd.tick()
    assert not r.sd.landed
    r.clock.t = 7.1
    r.sd.tick()
    assert r.sd.landed and r.log.counts()["pose_stale_land"] == 1


def test_pose_source_error_is_logged_and_treated_as_stale() -> None:
    r = Rig()
    r.poses.error = ConnectionError("mocap gone")
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))  # last pose (t=0) is still fresh
    np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])
    r.clock.t = 0.4
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))
    assert r.log.counts()["pose_error"] == 1
    assert r.log.counts()["pose_stale_hover"] == 1


@pytest.mark.parametrize("ahead_s", [1e9, 30.0])
def test_pose_stamped_ahead_of_the_clock_is_not_taken_and_the_drone_still_hovers_and_lands(
    ahead_s: float,
) -> None:
    """A pose stamped ahead of the clock (another clock, or forged) would read as fresh for as long as
    its stamp is ahead: it is not taken, so the stale-pose rules still run on the last real pose."""
    r = Rig()  # live pose at t = 0
    r.clock.t = 0.05
    r.sd.tick()
    r.move((0.0, 0.0, 1.0), stamp=r.clock.t + ahead_s)  # from here on the source says "far ahead"
    V = np.array([0.1, 0.0, 0.0, 0.0])
    for k in range(2, 60):
        r.clock.t = k * 0.05
        r.sd.tick()
        if r.sd.landed:
            break
        r.sd.send_body_velocity(V)
    hover, land = r.log.of_kind("pose_stale_hover"), r.log.of_kind("pose_stale_land")
    assert len(hover) == 1 and LIM.pose_timeout < hover[0].t <= LIM.pose_timeout + 0.1
    assert len(land) == 1 and LIM.pose_land_after < land[0].t <= LIM.pose_land_after + 0.1
    errors = r.log.of_kind("pose_error")
    assert len(errors) == 1 and "ahead of the clock" in errors[0].detail


def test_pose_stamped_within_the_tolerance_is_taken() -> None:
    """A motion-capture pose stamped on arrival after the tick read its clock (milliseconds) is live."""
    r = Rig()
    for k in range(1, 40):
        r.clock.t = k * 0.05
        r.move((1e-4 * k, 0.0, 1.0), stamp=r.clock.t + 0.02)  # a live body: never bit-identical
        r.sd.tick()
        r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
        np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])
    assert r.log.counts().get("pose_error", 0) == 0 and not r.sd.landed


def test_non_finite_pose_is_ignored() -> None:
    r = Rig()
    r.poses.poses[BODY] = Pose(np.array([np.nan, 0.0, 1.0]), 0.0)
    r.clock.t = 0.4
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), np.zeros(4))


# ---- battery -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("battery", [29.9, 5.0, float("nan")])
def test_low_battery_refuses_takeoff(battery: float) -> None:
    r = Rig(takeoff=False, battery=battery)
    with pytest.raises(SafetyError):
        r.sd.takeoff()
    assert "takeoff" not in r.inner.calls
    assert r.kinds() == ["battery_refuse_takeoff"]


def test_takeoff_refused_without_fresh_pose_or_outside_hard_fence() -> None:
    r = Rig(takeoff=False)
    r.move((0.0, 0.0, 0.0), stamp=-1.0)
    with pytest.raises(SafetyError):
        r.sd.takeoff()
    r.move((2.5, 0.0, 0.0))
    with pytest.raises(SafetyError):
        r.sd.takeoff()
    assert "takeoff" not in r.inner.calls
    assert r.kinds() == ["pose_refuse_takeoff", "fence_refuse_takeoff"]
    r.move((0.0, 0.0, 0.0))
    r.sd.takeoff()
    assert r.inner.calls == ["takeoff"]


def test_low_battery_in_flight_lands_once() -> None:
    r = Rig(battery=50.0)
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.clock.t = 0.05
    r.sd.tick()
    assert not r.sd.landed
    r.inner.battery = 14.9
    r.clock.t = 0.1
    r.sd.tick()
    assert r.inner.calls[-1] == "land" and r.sd.landed
    for k in range(5):
        r.clock.t = 0.15 + 0.05 * k
        r.sd.tick()
        r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    assert r.log.counts()["battery_land"] == 1
    assert r.inner.calls_after("land") == []


def test_state_error_in_tick_is_logged_not_raised() -> None:
    r = Rig()
    r.inner.state_error = OSError("telemetry lost")
    for k in range(3):
        r.clock.t = 0.05 * (k + 1)
        r.sd.tick()
    assert r.log.counts()["drone_error"] == 1


# ---- land, emergency stop, close ---------------------------------------------------------------------------
def test_land_failure_is_logged_reraised_and_retried_by_tick() -> None:
    r = Rig()
    r.inner.land_error = TimeoutError("no reply")
    with pytest.raises(TimeoutError):
        r.sd.land()
    assert not r.sd.landed and r.log.counts()["land_failed"] == 1
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    assert r.inner.calls[-1] == "land"  # dropped: nothing sent after land was requested
    r.clock.t = 0.05
    r.sd.tick()  # the retry waits land_retry_s (a bounded rate)
    assert r.inner.calls.count("land") == 1
    r.clock.t = LIM.land_retry_s
    r.sd.tick()  # retries, still failing: no second event
    assert r.inner.calls.count("land") == 2 and r.log.counts()["land_failed"] == 1
    r.inner.land_error = None
    r.clock.t = 1.5 * LIM.land_retry_s
    r.sd.tick()
    assert r.inner.calls.count("land") == 2
    r.clock.t = 2 * LIM.land_retry_s
    r.sd.tick()
    assert r.sd.landed and r.inner.calls.count("land") == 3
    assert "send" not in r.inner.calls_after("land")


def test_emergency_stop_blocks_further_commands() -> None:
    r = Rig()
    r.sd.emergency_stop()
    assert r.sd.landed and r.sd.phase == "stopped"
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.sd.tick()
    assert r.inner.calls == ["takeoff", "emergency_stop"]


def test_close_lands_a_flying_drone_first() -> None:
    r = Rig()
    r.sd.close()
    assert r.inner.calls == ["takeoff", "land", "close"]


def test_takeoff_after_landing_rearms() -> None:
    r = Rig()
    r.sd.land()
    r.sd.takeoff()
    assert not r.sd.landed
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(r.last_sent(), [0.1, 0.0, 0.0, 0.0])


def test_request_abort_lands_on_next_tick() -> None:
    r = Rig()
    r.sd.request_abort("operator abort")
    r.sd.tick()
    assert r.sd.landed
    assert r.log.of_kind("land")[0].detail == "operator abort"


# ---- property: what reaches the drone ----------------------------------------------------------------------
anything = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(
    v=st.tuples(anything, anything, anything, anything),
    p=st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-0.5, 3.0)),
    yaw=st.floats(-math.pi, math.pi),
    age=st.floats(0.0, 3.0),
)
def test_velocity_reaching_the_drone_is_finite_and_within_limits(
    v: tuple[float, float, float, float], p: tuple[float, float, float], yaw: float, age: float
) -> None:
    r = Rig(p=(0.0, 0.0, 1.0))
    r.sd.send_body_velocity(np.array(v))
    r.clock.t = 1.0
    r.move(p, yaw, stamp=1.0 - age)
    r.sd.send_body_velocity(np.array(v))
    r.clock.t = 1.6
    r.sd.tick()
    r.sd.send_body_velocity(np.array(v))
    assert r.inner.sent, "the first command must reach the drone"
    for sent in r.inner.sent:
        assert sent.shape == (4,)
        assert within_limits(sent), sent


# ---- mission supervisor ------------------------------------------------------------------------------------
ESTOP = SafetyLimits(emergency_stop_if_land_fails=True)


def fleet(
    n: int = 3, limits: SafetyLimits = ESTOP
) -> tuple[MissionSupervisor, dict[int, Rig], FakeClock, EventLog]:
    """n drones under one supervisor (by default with motor cut on a failed land, to test that path)."""
    clock, log = FakeClock(), EventLog()
    rigs = {i: Rig(drone_id=i, clock=clock, log=log, limits=limits) for i in range(1, n + 1)}
    sup = MissionSupervisor({i: r.sd for i, r in rigs.items()}, clock, limits, log)
    return sup, rigs, clock, log


def test_target_lost_by_everyone_hovers_with_one_event() -> None:
    sup, _, clock, log = fleet(2)
    assert sup.update_visibility({1: True, 2: False}) is False
    for t in (1.0, 2.0, 3.0):  # lost by all since t = 0; 3.0 s is not longer than 3.0 s
        clock.t = t
        assert sup.update_visibility({1: False, 2: False}) is False
    clock.t = 3.05
    assert sup.update_visibility({1: False, 2: False}) is True
    clock.t = 5.0
    assert sup.update_visibility({1: False, 2: False}) is True
    ev = log.of_kind("target_lost_hover")
    assert len(ev) == 1 and ev[0].t == 3.05 and ev[0].drone is None
    clock.t = 5.1
    assert sup.update_visibility({1: False, 2: True}) is False  # re-acquired: episode over
    clock.t = 8.2
    assert sup.update_visibility({1: False, 2: False}) is True
    assert len(log.of_kind("target_lost_hover")) == 2


def test_target_lost_too_long_lands_everyone_once() -> None:
    """Hover after target_lost_hover_after (3 s), land all after target_lost_land_after (15 s), once."""
    sup, rigs, clock, log = fleet(2)
    for k in range(1, 160):
        clock.t = 0.1 * k
        sup.update_visibility({1: False, 2: False})
        if clock.t < 15.0:
            assert not any(r.sd.landed for r in rigs.values()), clock.t
    assert all(r.sd.landed for r in rigs.values())
    ev = log.of_kind("target_lost_land")
    assert len(ev) == 1 and 15.0 < ev[0].t <= 15.1 + 1e-9
    assert len(log.of_kind("land_all")) == 1


def test_target_lost_land_must_come_after_hover() -> None:
    with pytest.raises(ValueError, match="target_lost_land_after"):
        SafetyLimits(target_lost_hover_after=5.0, target_lost_land_after=4.0)


def test_target_not_lost_while_one_drone_sees_it() -> None:
    sup, _, clock, log = fleet(3)
    for k in range(100):
        clock.t = 0.1 * k
        assert sup.update_visibility({1: False, 2: k % 2 == 0, 3: False}) is False
    assert "target_lost_hover" not in log.counts()


def test_never_seen_counts_from_the_first_update() -> None:
    sup, _, clock, _ = fleet(2)
    clock.t = 10.0
    assert sup.update_visibility({}) is False
    clock.t = 13.5
    assert sup.update_visibility({1: False}) is True


def test_land_all_does_not_cut_motors_by_default_and_retries() -> None:
    sup, rigs, _, log = fleet(3, limits=SafetyLimits())
    rigs[2].inner.land_error = RuntimeError("link down")
    sup.land_all("test")
    for i in (1, 3):
        assert rigs[i].inner.calls[-1] == "land" and rigs[i].sd.landed
    assert "emergency_stop" not in rigs[2].inner.calls and not rigs[2].sd.landed
    assert log.counts()["land_failed"] == 1
    rigs[2].inner.land_error = None
    rigs[2].clock.t += SafetyLimits().land_retry_s
    rigs[2].sd.tick()  # the next control period after land_retry_s retries the land
    assert rigs[2].sd.landed and rigs[2].inner.calls[-1] == "land"


def test_land_all_lands_everyone_even_if_one_land_raises() -> None:
    sup, rigs, _, log = fleet(3)
    rigs[2].inner.land_error = RuntimeError("link down")
    sup.land_all("test")
    for i in (1, 3):
        assert rigs[i].inner.calls[-1] == "land" and rigs[i].sd.landed
    assert rigs[2].inner.calls[-2:] == ["land", "emergency_stop"]
    assert rigs[2].sd.landed
    counts = log.counts()
    assert counts["land_all"] == 1 and counts["land"] == 2
    assert counts["land_failed"] == 1 and counts["emergency_stop"] == 1
    before = [list(r.inner.calls) for r in rigs.values()]
    sup.land_all("again")  # idempotent
    assert [r.inner.calls for r in rigs.values()] == before
    assert log.counts()["land_all"] == 1


def test_land_all_continues_when_emergency_stop_fails_too() -> None:
    sup, rigs, _, log = fleet(3)
    rigs[1].inner.land_error = RuntimeError("link down")
    rigs[1].inner.estop_error = RuntimeError("still down")
    sup.land_all("test")
    assert rigs[2].sd.landed and rigs[3].sd.landed and not rigs[1].sd.landed
    assert log.counts()["emergency_stop_failed"] == 1
    rigs[1].inner.land_error = None
    sup.land_all("retry")  # the drone that was not landed is tried again
    assert rigs[1].sd.landed
    assert log.counts()["land_all"] == 2


def test_land_all_finishes_the_others_after_an_interrupt_then_reraises() -> None:
    sup, rigs, _, _ = fleet(3)
    rigs[1].inner.land_error = KeyboardInterrupt()
    with pytest.raises(KeyboardInterrupt):
        sup.land_all("test")
    assert rigs[2].sd.landed and rigs[3].sd.landed
    assert "emergency_stop" not in rigs[1].inner.calls  # interrupted, not failed: no motor cut


def test_guard_lands_all_on_exception_and_reraises() -> None:
    sup, rigs, _, log = fleet(2)
    with pytest.raises(ValueError, match="boom"), sup.guard():
        raise ValueError("boom")
    assert all(r.sd.landed for r in rigs.values())
    assert log.of_kind("land_all")[0].detail.startswith("ValueError: boom")


def test_guard_lands_all_on_keyboard_interrupt() -> None:
    sup, rigs, _, _ = fleet(2)
    with pytest.raises(KeyboardInterrupt), sup.guard():
        raise KeyboardInterrupt
    assert all(r.sd.landed for r in rigs.values())


def test_guard_does_nothing_without_exception() -> None:
    sup, rigs, _, log = fleet(2)
    with sup.guard():
        pass
    assert not any(r.sd.landed for r in rigs.values())
    assert "land_all" not in log.counts()


def _wait_for_signal() -> None:
    for _ in range(200):
        time.sleep(0.01)
    pytest.fail("signal not delivered")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_lands_all_raises_keyboard_interrupt_and_restores_handlers(sig: signal.Signals) -> None:
    sup, rigs, _, log = fleet(3)
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(KeyboardInterrupt), sup.install_signal_handlers():
        assert signal.getsignal(sig) != before[sig]
        os.kill(os.getpid(), sig)
        _wait_for_signal()
    assert all(r.sd.landed for r in rigs.values())
    assert log.of_kind("land_all")[0].detail.startswith(f"signal {sig.name};")
    assert [e.detail for e in log.of_kind("land")] == [f"signal {sig.name}"] * 3
    assert {s: signal.getsignal(s) for s in before} == before


def test_signal_handlers_restored_after_normal_exit() -> None:
    sup, rigs, _, _ = fleet(1)
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with sup.install_signal_handlers():
        pass
    assert {s: signal.getsignal(s) for s in before} == before
    assert not rigs[1].sd.landed


def test_signal_inside_a_driver_call_defers_landing_until_it_unwinds() -> None:
    sup, rigs, _, log = fleet(2)

    def kill_during_send() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        _wait_for_signal()

    rigs[1].inner.on_send = kill_during_send
    with pytest.raises(KeyboardInterrupt), sup.install_signal_handlers():
        rigs[1].sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    assert all(r.sd.landed for r in rigs.values())
    assert rigs[1].inner.calls == ["takeoff", "send", "land"]  # land only after the send unwound
    assert "deferred" in log.of_kind("signal")[0].detail


def test_signal_during_land_all_does_not_interrupt_it() -> None:
    sup, rigs, _, log = fleet(3)

    def kill_during_land() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs here and must return

    rigs[1].inner.on_land = kill_during_land
    with sup.install_signal_handlers():
        sup.land_all("mission complete")
    assert all(r.sd.landed for r in rigs.values())
    assert "ignored" in log.of_kind("signal")[0].detail


def test_every_logged_kind_is_documented() -> None:
    sup, rigs, clock, log = fleet(2)
    rigs[1].sd.send_body_velocity(np.array([9.0, 0.0, 0.0, 0.0]))
    clock.t = 10.0
    sup.update_visibility({})
    sup.land_all("end")
    assert set(log.counts()) <= EVENT_KINDS
    times = [e.t for e in log.events]
    assert times == sorted(times) and times[-1] == clock.t


def test_concurrent_land_all_lands_slow_drones_at_once() -> None:
    """Real drones' land() blocks until touchdown: with concurrent_land every drone starts landing at
    once (each land() waits until all three have started: one after the other, the first would never
    see the others start); all end landed, one event each."""
    clock = FakeClock()
    log = EventLog()
    rigs = {i: Rig(drone_id=i, clock=clock, log=log) for i in (1, 2, 3)}
    all_landing = threading.Barrier(3, timeout=30.0)
    for r in rigs.values():
        r.inner.on_land = all_landing.wait  # raises BrokenBarrierError unless the three overlap
    sup = MissionSupervisor({i: r.sd for i, r in rigs.items()}, clock, LIM, log, concurrent_land=True)
    sup.land_all("test")
    assert not all_landing.broken  # no drone waited for another's landing
    assert all(r.sd.landed for r in rigs.values())
    assert sorted(e.drone for e in log.events if e.kind == "land") == [1, 2, 3]


def test_concurrent_land_all_reraises_after_every_landing() -> None:
    """A land() that raises does not stop the others; the error is logged and the drone retried by tick()."""
    clock = FakeClock()
    log = EventLog()
    rigs = {i: Rig(drone_id=i, clock=clock, log=log) for i in (1, 2)}
    rigs[1].inner.land_error = RuntimeError("no reply")
    sup = MissionSupervisor({i: r.sd for i, r in rigs.items()}, clock, LIM, log, concurrent_land=True)
    sup.land_all("test")
    assert rigs[2].sd.landed and not rigs[1].sd.landed
    assert any(e.kind == "land_failed" and e.drone == 1 for e in log.events)


def test_a_drone_whose_telemetry_shows_it_down_is_not_commanded_again() -> None:
    """An auto-land or someone else's land: the supervisor reads the drone's phase and stops commanding."""
    r = Rig()
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.sd.tick()  # link seen, airborne
    r.inner.phase = "ground"
    r.clock.t += 0.05
    r.sd.tick()
    assert "landed_by_drone" in r.kinds() and r.sd.landed
    n = len(r.inner.sent)
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.sd.tick()
    assert len(r.inner.sent) == n and "land" not in r.inner.calls


def test_a_drone_landing_by_itself_is_commanded_no_more_and_its_landing_awaited() -> None:
    """Its driver reports it landing by itself (its `error Auto land`, its own descent): the supervisor
    records landing_by_drone at once, no velocity reaches it any more, and its land job (which sends
    nothing to a drone landing by itself: drivers/tello/flight.py) waits for the touchdown."""
    r = Rig()
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.sd.tick()  # link seen, airborne
    r.inner.phase = "landing"
    r.clock.t += 0.05
    r.sd.tick()
    assert "landing_by_drone" in r.kinds() and "land" in r.inner.calls
    n = len(r.inner.sent)
    r.sd.send_body_velocity(np.array([0.1, 0.0, 0.0, 0.0]))
    r.sd.tick()
    assert len(r.inner.sent) == n


# ---- the climb a drone's own timeout allows ---------------------------------------------------------------
class HoldingDrone(FakeDrone):
    """A FakeDrone that flies its last command on for own_timeout_s (hal.HoldsLastCommand), like a Tello."""

    own_timeout_s = 15.0


def holding_rig(z: float) -> Rig:
    rig = Rig(p=(0.0, 0.0, z), takeoff=False)
    rig.inner = HoldingDrone()
    rig.sd = SafeDrone(1, rig.inner, rig.poses, BODY, rig.clock, LIM, rig.log)
    rig.sd.takeoff()
    return rig


def test_a_drone_that_holds_its_last_command_climbs_no_faster_than_the_ceiling_allows() -> None:
    """v_z up is capped to (ceiling − z) / own timeout, once-per-episode event; down, x, y and yaw untouched;
    at the ceiling no climb at all; a drone without an own timeout is not capped."""
    rig = holding_rig(1.25)
    rig.sd.send_body_velocity(np.array([0.1, -0.2, 0.3, 0.5]))
    cap = (LIM.fence_hi[2] - 1.25) / 15.0
    assert rig.last_sent() == pytest.approx([0.1, -0.2, cap, 0.5])
    rig.sd.send_body_velocity(np.array([0.0, 0.0, 0.3, 0.0]))
    assert rig.kinds().count("climb_limited") == 1
    rig.sd.send_body_velocity(np.array([0.0, 0.0, -0.3, 0.0]))
    assert rig.last_sent()[2] == -0.3
    rig.move((0.0, 0.0, LIM.fence_hi[2] + 0.01))
    rig.sd.send_body_velocity(np.array([0.0, 0.0, 0.3, 0.0]))
    assert rig.last_sent()[2] == 0.0 and rig.kinds().count("climb_limited") == 2  # a new episode
    free = Rig(p=(0.0, 0.0, 1.25))
    free.sd.send_body_velocity(np.array([0.0, 0.0, 0.3, 0.0]))
    assert free.last_sent()[2] == 0.3 and "climb_limited" not in free.kinds()


@settings(max_examples=200, deadline=None)
@given(z0=st.floats(LIM.fence_lo[2] - 0.3, LIM.fence_hi[2] + 0.2), v=st.floats(0.0, 5.0))
def test_the_last_command_held_for_the_whole_timeout_stays_under_the_hard_ceiling(
    z0: float, v: float
) -> None:
    """Worst case of the cap on a Tello: the capped v_z turned into an integer rc (rounded, the driver's
    velocity_to_rc) and flown for the whole 15 s (a first-order lag only lowers it) ends at most
    ½ rc unit × 15 s above the soft ceiling, well inside the hard margin."""
    from flightstack.drivers.tello.config import TELLO_OWN_TIMEOUT_S
    from flightstack.drivers.tello.rc import RcGains, rc_to_velocity, velocity_to_rc

    rig = holding_rig(z0)
    rig.sd.send_body_velocity(np.array([0.0, 0.0, v, 0.0]))
    gains = RcGains()
    flown = rc_to_velocity(velocity_to_rc(rig.last_sent(), gains), gains)[2]
    z_end = z0 + max(flown, 0.0) * TELLO_OWN_TIMEOUT_S
    rounding = 0.5 * gains.z * TELLO_OWN_TIMEOUT_S  # 0.075 m of the 0.3 m margin
    assert rounding <= 0.5 * LIM.hard_margin
    if z0 <= LIM.fence_hi[2]:
        assert z_end <= LIM.fence_hi[2] + rounding + 1e-9
    else:  # above the ceiling (and below the hard one): no climb at all
        assert z_end == z0
