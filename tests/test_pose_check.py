"""flightstack.safety.pose_check: a frozen pose and a pose whose height disagrees with the drone's own, and
what the safety layer (SafeDrone) and the robot's driver (TargetDriver) do about them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flightstack.hal import DroneState, FlightPhase
from flightstack.paper.geometry import Pose
from flightstack.runtime.phases import ROBOT_FROZEN_S, TargetDriver
from flightstack.safety import EventLog
from flightstack.safety.drone import SUSPECT_LAND_AFTER_S
from flightstack.safety.pose_check import (
    HEIGHT_DISAGREE_M,
    HEIGHT_WINDOW_S,
    MOTION_JUMP_M,
    MOTION_WINDOW_S,
    FreezeWatch,
    HeightAgreement,
    MotionAgreement,
)
from flightstack.sim_backend.emulators.tello.recorded import H_DRIFT_CM_S, drifted, reported_h
from tests.conftest import PEERS, skip_or_fail_in_ci
from tests.test_safety import LIM, Rig

MOVE = np.array([0.2, 0.0, 0.0, 0.0])
STILL = np.zeros(4)


# ---- FreezeWatch -------------------------------------------------------------------------------------------
def test_identical_samples_under_fresh_stamps_while_commanded_are_frozen_from_the_first() -> None:
    w, pose = FreezeWatch(), np.array([0.0, 0.0, 1.0, 0.0])
    w.sample(1.0, pose, MOVE)
    assert w.frozen_since is None  # one sample says nothing
    w.sample(1.0, pose, MOVE)  # the same sample read again (no new frame): not evidence
    assert w.frozen_since is None
    w.sample(1.01, pose.copy(), MOVE)
    assert w.frozen_since == 1.01  # the first sample that should have moved
    w.sample(1.02, pose.copy(), MOVE)
    assert w.frozen_since == 1.01
    w.sample(1.03, pose + np.array([1e-6, 0, 0, 0]), MOVE)  # it moved: the run ends
    assert w.frozen_since is None


def test_a_body_still_before_it_was_commanded_is_judged_from_the_command() -> None:
    """A Tello hovers in its takeoff (ignoring rc) on one noise-free pose for seconds; the first moving
    command after it is evidence from the next sample on, not back to the hover's start."""
    w, pose = FreezeWatch(), np.array([0.0, 0.0, 0.85, 0.0])
    for k in range(140):  # 7 s still, commanded nothing
        w.sample(0.05 * k, pose, STILL)
    assert w.frozen_since is None
    w.sample(7.0, pose, MOVE)
    assert w.frozen_since == 7.0


def test_a_still_body_commanded_still_is_not_frozen() -> None:
    """A noise-free simulation repeats the pose of a body that stands still: not a freeze."""
    w, pose = FreezeWatch(), np.array([0.0, 0.0, 1.0, 0.0])
    for k in range(100):
        w.sample(0.01 * k, pose, STILL if k % 2 else np.array([0.01, 0.0, 0.0, 0.04]))
    assert w.frozen_since is None


def test_the_real_natnet_recording_never_repeats_a_sample() -> None:
    """Every tracked body of the recorded Motive session (518 frames, 4.3 s) differs frame to frame: the
    frozen check, fed it with a moving command throughout, never fires."""
    path = PEERS / "natnet" / "python_natnet" / "traffic.pcapng"
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    from flightstack.sim_backend.emulators.natnet_replay import read_pcapng
    from tests.natnet_strict import parse_frame

    watches: dict[int, FreezeWatch] = {}
    samples = 0
    for t, packet in read_pcapng(Path(path)).frames:
        for b in parse_frame(packet).bodies:
            if b.tracked:
                w = watches.setdefault(b.body_id, FreezeWatch())
                w.sample(t, np.concatenate([b.position, b.quaternion_xyzw]), MOVE)
                samples += 1
                assert w.frozen_since is None, (t, b.body_id)
    assert samples >= 500


# ---- HeightAgreement ---------------------------------------------------------------------------------------
def _tello_h(z_m: float, drift_cm: float) -> float:
    """A Tello's `h` (m) at true height z_m (the emulator's model of the recording)."""
    return reported_h(100.0 * z_m, drift_cm) / 100.0


def _triangle(t: float) -> float:
    """A triangle wave of slope ±1 between -1 and 1 (period 4 s)."""
    return 1.0 - abs(t % 4.0 - 2.0)


@pytest.mark.parametrize("vz", [-0.3, -0.1, 0.0, 0.1, 0.3])
def test_a_tellos_height_agrees_with_motion_capture_through_climbs_and_drift(vz: float) -> None:
    """The true height moves at |vz| (m/s, max_speed_z at most) for 20 s, up and down every 2 s; the drone's
    `h` is the recorded model (10 cm steps, drift at the recorded -3.5 cm/s up to 70 cm) read 0.1 s late;
    motion capture has 1 mm noise. No disagreement."""
    rng = np.random.default_rng(0)
    a, drift = HeightAgreement(), 0.0
    dt, lag = 0.05, 0.1
    for k in range(400):
        t = k * dt
        z, z_late = 1.0 + vz * _triangle(t), 1.0 + vz * _triangle(t - lag)
        drift = drifted(drift, H_DRIFT_CM_S, dt)
        assert a.sample(t, z + rng.normal(0, 0.001), _tello_h(z_late, drift)) is None, t


def test_a_pose_swapped_with_a_body_1_m_lower_disagrees_at_the_next_sample() -> None:
    """The drone's body label swapped with the robot's, 1 m below, while `h` reads on: the changes over the
    (full) window differ by 1 m > HEIGHT_DISAGREE_M, reported at the first sample after the swap."""
    a, dt = HeightAgreement(), 0.05
    for k in range(100):
        assert a.sample(k * dt, 1.0, 1.0) is None
    d = a.sample(100 * dt, 0.0, 1.0)
    assert d == pytest.approx(-1.0) and HEIGHT_DISAGREE_M < 1.0


def test_a_real_tellos_height_against_its_tof_never_disagrees() -> None:
    """The real flight (xg590): `h` against `tof` - 10 cm (a second height sensor, which also reads steps in
    the surface below) from liftoff to touchdown, as motion capture would stand: no disagreement; the
    worst change of one against the other over 2 s is printed (0.58 m: the surface stepping 54 cm at
    12 s while `h` held; `h` falling 30 cm in 2 s of hover while `tof` rose)."""
    path = PEERS / "tello" / "xg590_Tello_flight_log_20201018_052457.db"
    if not path.is_file():
        skip_or_fail_in_ci(f"{path} absent: the real recordings of ../shared/data/peers/ are read in place")
    from flightstack.drivers.tello.state import parse_state
    from flightstack.drivers.tello.traffic import read_xg590_db

    flight = read_xg590_db(path)
    takeoff = flight.first("sent", "takeoff")
    assert takeoff is not None
    a, worst = HeightAgreement(), HeightAgreement(bound_m=0.0)
    seen = []
    for r in flight.of("state"):
        st = parse_state(r.text.encode(), r.t - takeoff.t)
        if not 0.94 <= st.t <= 20.2:  # liftoff to touchdown (the recording's README)
            continue
        z, h = (st.tof_cm - 10.0) / 100.0, st.h_cm / 100.0
        assert a.sample(st.t, z, h) is None, st
        d = worst.sample(st.t, z, h)
        if d is not None:
            seen.append(abs(d))
    print(f"real flight: worst |change of tof - change of h| over {HEIGHT_WINDOW_S:g} s: {max(seen):.2f} m")
    assert 0.3 < max(seen) < HEIGHT_DISAGREE_M


def test_non_finite_heights_restart_the_window() -> None:
    a = HeightAgreement()
    for k in range(30):
        a.sample(0.1 * k, 1.0, 1.0 + 0.05 * k)
    assert a.sample(3.0, 1.0, math.nan) is None
    assert a.sample(3.1, 1.0, 5.0) is None  # a fresh window: nothing to compare yet


# ---- MotionAgreement ---------------------------------------------------------------------------------------
def _square_robot(seconds: float, tau: float, jump_at: float | None = None) -> list[float]:
    """A robot driving a 1 m square, open loop: 10 s at 0.1 m/s, then a quarter turn in place at 0.5 rad/s,
    its velocities a first-order response of time constant tau (s) to the commands, sampled at 20 Hz with
    1 mm noise; from jump_at (s) on its pose reads 0.3 m off. The times (s) MotionAgreement objects at."""
    rng = np.random.default_rng(1)
    m, dt, turn_s = MotionAgreement(), 0.05, (math.pi / 2) / 0.5
    x = y = th = v = w = 0.0
    out: list[float] = []
    cmd: np.ndarray | None = None
    for k in range(round(seconds / dt)):
        t = k * dt
        off = 0.3 if jump_at is not None and t >= jump_at else 0.0
        if m.sample(t, x + off + rng.normal(0, 0.001), y + rng.normal(0, 0.001), th, cmd) is not None:
            out.append(t)
        straight = t % (10.0 + turn_s) < 10.0
        cmd = np.array([0.1, 0.0, 0.0, 0.0]) if straight else np.array([0.0, 0.0, 0.0, 0.5])
        v, w = v + (cmd[0] - v) * dt / tau, w + (cmd[3] - w) * dt / tau
        x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
    return out


@pytest.mark.parametrize("tau", [0.1, 0.5])
def test_a_robot_lagging_its_commands_round_a_square_agrees(tau: float) -> None:
    assert _square_robot(45.0, tau) == []


def test_a_robot_pose_that_jumps_disagrees_within_the_window() -> None:
    late = _square_robot(20.0, 0.5, jump_at=5.0)
    assert MOTION_JUMP_M + 0.1 < 0.3  # the jump beyond the bound at 0.1 m/s
    assert late and 5.0 <= late[0] <= 5.0 + MOTION_WINDOW_S


# ---- SafeDrone -------------------------------------------------------------------------------------------
def _fly(r: Rig, seconds: float, cmd: np.ndarray, frozen: bool, dt: float = 0.05, z: float = 1.0) -> None:
    """Tick and command for `seconds`; the pose (at height z m) is stamped now, frozen or moving with the
    command."""
    t0 = r.clock.t
    x = float(r.poses.poses[r.sd.body].p[0])
    while r.clock.t < t0 + seconds - 1e-9:
        r.clock.t = round(r.clock.t + dt, 9)
        if not frozen:
            x += float(cmd[0]) * dt + 1e-6
        r.move((x, 0.0, z), stamp=r.clock.t)
        r.sd.tick()
        r.sd.send_body_velocity(cmd)


def test_a_frozen_pose_hovers_after_pose_timeout_and_lands_after_the_suspect_bound() -> None:
    r = Rig()
    _fly(r, 1.0, MOVE, frozen=False)
    t_freeze = r.clock.t  # the last live sample; the next ones repeat it
    r.poses.set(r.sd.body, tuple(r.poses.poses[r.sd.body].p), 0.0, None)
    frozen_pose = r.poses.poses[r.sd.body]
    while r.clock.t < t_freeze + 2.0 and not r.sd.landed:
        r.clock.t = round(r.clock.t + 0.05, 9)
        r.poses.poses[r.sd.body], r.poses.stamps[r.sd.body] = frozen_pose, r.clock.t
        r.sd.tick()
        r.sd.send_body_velocity(MOVE)
    onset = t_freeze + 0.05  # the first sample that should have moved
    ev = r.log.of_kind("pose_frozen")
    assert len(ev) == 1 and LIM.pose_timeout < ev[0].t - onset <= LIM.pose_timeout + 0.05 + 1e-9
    land = r.log.of_kind("pose_stale_land")
    assert len(land) == 1 and SUSPECT_LAND_AFTER_S <= land[0].t - onset <= SUSPECT_LAND_AFTER_S + 0.05
    assert r.sd.landed and "land" in r.inner.calls
    # from the event on nothing but zero velocity reached the drone
    sends = r.inner.sent[-round((land[0].t - ev[0].t) / 0.05) :]
    assert all(not np.any(v) for v in sends)


def test_a_still_pose_of_a_hovering_drone_is_believed() -> None:
    """Commanded zero (the command watchdog's hover, a converged loop), the same pose is what a noise-free
    simulation gives: no event."""
    r = Rig()
    _fly(r, 3.0, STILL, frozen=True)
    assert not {"pose_frozen", "pose_disagrees", "pose_stale_land"} & set(r.kinds()) and not r.sd.landed


class _Height:
    """The FakeDrone's state: airborne at a fixed own height (m)."""

    def __init__(self, h: float) -> None:
        self.h = h

    def __call__(self) -> DroneState:
        return DroneState(80.0, self.h, True, True, FlightPhase.AIRBORNE)


def test_a_pose_swapped_with_a_lower_body_disagrees_hovers_and_lands(monkeypatch: pytest.MonkeyPatch) -> None:
    """Motion capture shows the drone at 1.5 m, then (swapped with a body 1 m lower) at 0.5 m, while its own
    height reads on: `pose_disagrees` at the next tick, hover, land SUSPECT_LAND_AFTER_S later."""
    r = Rig(p=(0.0, 0.0, 1.5))
    monkeypatch.setattr(r.inner, "state", _Height(1.5))
    _fly(r, 3.0, MOVE, frozen=False, z=1.5)
    t_swap = r.clock.t
    _fly(r, 2.0, MOVE, frozen=False, z=0.5)
    ev = r.log.of_kind("pose_disagrees")
    assert len(ev) == 1 and 0 < ev[0].t - t_swap <= 0.05 + 1e-9, ev
    land = r.log.of_kind("pose_stale_land")
    assert len(land) == 1 and land[0].t - ev[0].t == pytest.approx(SUSPECT_LAND_AFTER_S, abs=0.06)
    assert "pose_frozen" not in r.kinds()


# ---- the ground robot --------------------------------------------------------------------------------------
class _Robot:
    def __init__(self) -> None:
        self.sent: list[np.ndarray] = []
        self.stopped = 0

    def send_body_velocity(self, V: np.ndarray) -> None:
        self.sent.append(np.asarray(V, dtype=float))

    def stop(self) -> None:
        self.stopped += 1


class _Backend:
    def __init__(self, rig: Rig, robot: _Robot) -> None:
        self.clock, self._poses, self._robot = rig.clock, rig.poses, robot

    def target(self) -> _Robot:
        return self._robot

    def pose_source(self) -> object:
        return self._poses


class _Law:
    def command(self, t: float, pose: Pose) -> np.ndarray:
        return np.array([0.1, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("bad", ["nan", "frozen"])
def test_a_robot_pose_that_is_nan_or_frozen_stops_the_robot_with_an_event(bad: str) -> None:
    rig, robot, log = Rig(), _Robot(), EventLog()
    drv = TargetDriver(_Law(), _Backend(rig, robot), None, log)  # type: ignore[arg-type]
    for k in range(1, 60):
        rig.clock.t = 0.05 * k
        x = 0.005 * k if (bad == "nan" or k < 20) else 0.1
        pose = Pose(np.array([math.nan if bad == "nan" and k >= 20 else x, 0.0, 0.0]), 0.0)
        rig.poses.poses["target"], rig.poses.stamps["target"] = pose, rig.clock.t
        drv.tick(rig.clock.t)
    events = log.of_kind("robot_pose_suspect")
    assert len(events) == 1 and robot.stopped == 1 and drv.suspect is not None
    t_bad = 0.05 * 20  # the first NaN sample, or the first that should have moved
    late = events[0].t - t_bad
    assert late <= (1e-9 if bad == "nan" else ROBOT_FROZEN_S + 0.05 + 1e-9), (bad, late)
    n_sent = len(robot.sent)
    drv.tick(rig.clock.t + 0.05)
    assert len(robot.sent) == n_sent  # stopped for good


def test_a_robot_pose_read_without_a_new_frame_is_not_frozen() -> None:
    rig, robot, log = Rig(), _Robot(), EventLog()
    drv = TargetDriver(_Law(), _Backend(rig, robot), None, log)  # type: ignore[arg-type]
    rig.poses.poses["target"], rig.poses.stamps["target"] = Pose.make((0.0, 0.0, 0.0), 0.0), 0.0
    for k in range(1, 40):  # the same stamp every tick: motion capture stopped (the age rules' case)
        rig.clock.t = 0.05 * k
        drv.tick(rig.clock.t)
    assert drv.suspect is None and not log.of_kind("robot_pose_suspect")


def test_a_gap_in_the_robots_samples_restarts_the_window() -> None:
    """A stalled loop: the last command (0.1 m/s) held for 3 s while the robot, without set-points, stopped
    by its own failsafe; the samples after the gap are not judged against the held command."""
    m = MotionAgreement()
    cmd = np.array([0.1, 0.0, 0.0, 0.0])
    for k in range(40):  # 2 s driven as commanded
        assert m.sample(0.05 * k, 0.005 * k, 0.0, 0.0, cmd) is None
    x_stop = 0.005 * 39 + 0.02  # it coasted 2 cm and stopped
    for k in range(40):  # the loop comes back 3 s later: the robot stands where it stopped
        assert m.sample(5.0 + 0.05 * k, x_stop, 0.0, 0.0, cmd) is None
