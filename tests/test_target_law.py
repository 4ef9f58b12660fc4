"""The square law a non-holonomic robot can follow (flightstack.paper.target_law.UnicycleSquareLaw), the
rig's robot kinematics that chooses it (Mission.robot_kinematics / target_law), the simulated lab's robot
that drives as the rig says (sim_backend/lab.py ScamperSim), against closed forms."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from flightstack.cli.app import main
from flightstack.config.mission import load_mission
from flightstack.hal import StampedPose
from flightstack.paper.geometry import Pose, wrap_angle
from flightstack.paper.target_law import (
    HEADING_WEIGHT_M_PER_RAD,
    SquareLaw,
    UnicycleSquareLaw,
    square_law,
    start_phase,
)
from flightstack.runtime.phases import TargetDriver
from flightstack.sim_backend.lab import RobotParams, ScamperSim

RADII = (0.0, 0.05, 0.2, 0.5)
"""Turn radii (m): 0 = corners turned in place (differential), else rounded (ackermann); 0.5 = side/2."""


def _lap(law: UnicycleSquareLaw, n: int = 40_000) -> np.ndarray:
    """[x, y, θ] of the reference at n + 1 times evenly over one lap."""
    return np.array(
        [[*law.reference(t)[0].p[:2], law.reference(t)[0].theta] for t in np.linspace(0, law.lap_time, n + 1)]
    )


@pytest.mark.parametrize("R", RADII)
def test_lap_length_mean_speed_and_corner_rounding_closed_forms(R: float) -> None:
    law = UnicycleSquareLaw(side=1.0, speed=0.1, turn_radius=R)
    path = _lap(law)
    length = float(np.sum(np.hypot(*np.diff(path[:, :2], axis=0).T)))
    closed = 4.0 - (8.0 - 2.0 * math.pi) * R
    assert law.path_length == pytest.approx(closed, abs=1e-12)
    assert length == pytest.approx(closed, abs=1e-6)  # the sampled path's length: chords of the arcs
    assert law.distance(law.lap_time) == pytest.approx(closed, abs=1e-12)
    assert law.distance(2.5 * law.lap_time) == pytest.approx(2 * closed + law.distance(0.5 * law.lap_time))
    moving = law.lap_time - law.turning_time  # the time it moves: the mean speed then is the paper's
    assert law.path_length / moving == pytest.approx(0.1, abs=1e-12)
    speeds = {round(s.v, 12) for s in law.segments} - {0.0}
    assert speeds == {0.1}  # every segment that moves, at 0.1 m/s
    if R == 0.0:
        assert law.lap_time == pytest.approx(40.0 + 2 * math.pi / 0.5)  # + four turns in place at 0.5 rad/s
    else:
        assert law.turning_time == 0.0 and law.lap_time == pytest.approx(closed / 0.1)
    # one rotation per lap, the path closes, it stays on or inside the square
    heading = np.unwrap(path[:, 2])
    assert heading[-1] - heading[0] == pytest.approx(2 * math.pi, abs=1e-9)
    assert np.allclose(path[-1, :2], path[0, :2], atol=1e-9)
    assert np.max(np.abs(path[:, :2])) <= 0.5 + 1e-12
    # each corner is rounded by R(√2 − 1) ≤ R: the path's nearest point to the square's corner
    for cx, cy in ((0.5, -0.5), (0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5)):
        gap = float(np.min(np.hypot(path[:, 0] - cx, path[:, 1] - cy)))
        assert gap == pytest.approx(R * (math.sqrt(2) - 1), abs=2e-5)
        assert gap <= R + 1e-9


@pytest.mark.parametrize("R", RADII)
def test_heading_along_the_path_and_no_sideways_command(R: float) -> None:
    law = UnicycleSquareLaw(turn_radius=R)
    for t in np.linspace(0.0, 2 * law.lap_time, 997):
        g, v = law.reference(float(t))
        speed = math.hypot(v[0], v[1])
        if speed > 0:  # the reference moves where it heads
            assert math.atan2(v[1], v[0]) == pytest.approx(math.remainder(g.theta, 2 * math.pi), abs=1e-9)
        off = Pose.make([g.p[0] + 0.03, g.p[1] - 0.02, 0.0], g.theta + 0.2)
        assert law.command(float(t), off)[1] == 0.0  # never a sideways velocity


def _track(law: UnicycleSquareLaw, tau: float, dt: float = 0.05, sub: int = 10, laps: int = 2) -> float:
    """Max distance (m) of a unicycle driven by the law's commands (held dt s, first-order lag τ s) from
    the reference, over `laps` laps from the reference's start pose."""
    g = law.reference(0.0)[0]
    x, y, th, v, w, worst = float(g.p[0]), float(g.p[1]), g.theta, 0.0, 0.0, 0.0
    h = dt / sub
    a = 1.0 if tau == 0 else 1.0 - math.exp(-h / tau)
    for k in range(round(laps * law.lap_time / dt)):
        V = law.command(k * dt, Pose.make([x, y, 0.0], th))
        for _ in range(sub):
            v, w = v + a * (V[0] - v), w + a * (V[3] - w)
            x, y, th = x + v * math.cos(th) * h, y + v * math.sin(th) * h, th + w * h
        ref = law.reference((k + 1) * dt)[0]
        worst = max(worst, math.hypot(x - ref.p[0], y - ref.p[1]))
    return worst


@pytest.mark.parametrize("R", (0.0, 0.2))
def test_a_unicycle_driven_by_the_commands_tracks_the_reference(R: float) -> None:
    law = UnicycleSquareLaw(turn_radius=R)
    exact = _track(law, tau=0.0)
    lagged = _track(law, tau=0.2)  # the simulated lab's robot: 0.2 s first-order response
    print(f"R {R} m: max tracking error {exact * 1000:.1f} mm exact, {lagged * 1000:.1f} mm with a 0.2 s lag")
    assert exact < 0.01  # measured 4.7 mm (R = 0: the 20 Hz hold at the corners), 1.0 mm (R = 0.2)
    assert lagged < 0.04  # measured 21 mm (R = 0: stopping from 0.1 m/s behind a lag), 15 mm (R = 0.2)


def test_the_paper_law_is_refused_for_a_non_holonomic_robot() -> None:
    assert isinstance(square_law("paper", "omni", 1.0, 0.1, 0.05, 0.0, 0.0), SquareLaw)
    assert square_law("unicycle", "ackermann", 1.0, 0.1, 0.05, 0.0, 0.2).turn_radius == 0.2
    assert square_law("unicycle", "differential", 1.0, 0.1, 0.05, 0.0, 0.0).turn_radius == 0.0
    for kin in ("differential", "ackermann"):
        with pytest.raises(ValueError, match="sideways"):
            square_law("paper", kin, 1.0, 0.1, 0.05, 0.0, 0.2)
    with pytest.raises(ValueError, match="side/2"):
        UnicycleSquareLaw(turn_radius=0.6)


@pytest.mark.parametrize(
    ("rig", "kinematics", "law"),
    [
        ("ideal", "omni", "paper"),
        ("lab-sim", "differential", "unicycle"),
        ("emulated-lab", "differential", "unicycle"),
    ],
)
def test_each_rig_states_its_robot_and_the_law_follows(rig: str, kinematics: str, law: str) -> None:
    m = load_mission("paper_experiment", rig=rig)
    assert (m.robot_kinematics(), m.target_law_name()) == (kinematics, law)
    assert load_mission("paper_sim").robot_kinematics() == "omni"  # the Duffing-like field: the ideal rig


@pytest.mark.parametrize(
    ("sets", "key"),
    [
        (["target.square.law=paper"], "target.square.law"),
        (["target.robot.kinematics=diagonal"], "target.robot.kinematics"),
        (["target.robot.kinematics=ackermann"], "target.robot.min_turn_radius_m"),
        (
            ["target.robot.kinematics=ackermann", "target.robot.min_turn_radius_m=0.8"],
            "target.robot.min_turn_radius_m",
        ),
        (["target.robot.min_turn_radius_m=0.2"], "target.robot.min_turn_radius_m"),
    ],
)
def test_invalid_kinematics_or_law_exits_2_naming_the_key(
    sets: list[str], key: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", "paper_experiment", "--rig", "lab-sim", "--duration", "1", "--out", str(tmp_path / "r")]
    for s in sets:
        argv += ["--set", s]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error:") and key in err, err
    assert not (tmp_path / "r").exists()


def test_a_rig_file_with_a_bad_robot_kinematics_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = tmp_path / "rig.yaml"
    rig.write_text("rig: mine\nbackend: sim_ideal\nrobot: {kinematics: tracked}\n")
    assert main(["validate", str(rig)]) == 2
    err = capsys.readouterr().err
    assert "robot.kinematics" in err and "Traceback" not in err, err


def _drive(kinematics: str, V: list[float], seconds: float, radius: float = 0.0) -> Pose:
    t = [0.0]
    r = ScamperSim(
        Pose.make([0, 0, 0], 0.0),
        RobotParams(time_constant_s=0.05, kinematics=kinematics, min_turn_radius_m=radius),
        lambda: t[0],
    )
    dt = 0.005
    for _ in range(round(seconds / dt)):
        r.send_body_velocity(np.array(V, dtype=float))
        t[0] += dt
        r.step(t[0], dt)
    return r.pose


def test_the_simulated_robot_drives_as_its_kinematics_says() -> None:
    # differential, as ArduPilot Rover takes velocity + yaw rate: speed sign(v_x)·|(v_x, v_y)|, never sideways
    g = _drive("differential", [0.0, 0.2, 0.0, 0.0], 1.5)
    assert g.p[0] == pytest.approx(0.2 * (1.5 - 0.05), abs=2e-3) and abs(g.p[1]) < 1e-12
    g = _drive("differential", [-0.1, 0.2, 0.0, 0.0], 1.0)
    assert g.p[0] == pytest.approx(-math.hypot(0.1, 0.2) * (1.0 - 0.05), abs=2e-3) and abs(g.p[1]) < 1e-12
    g = _drive("omni", [0.0, 0.2, 0.0, 0.0], 1.5)  # the ideal, holonomic robot moves sideways
    assert g.p[1] == pytest.approx(0.2 * (1.5 - 0.05), abs=2e-3)
    # ackermann: no turn in place; a turn no tighter than its radius
    g = _drive("ackermann", [0.0, 0.0, 0.0, 0.5], 1.0, radius=0.3)
    assert g.theta == 0.0
    g = _drive("ackermann", [0.1, 0.0, 0.0, 1.0], 3 * math.pi, radius=0.3)  # ω ≤ v/R: a circle of R
    assert math.hypot(g.p[0], g.p[1] - 0.3) == pytest.approx(0.3, abs=0.01)


@pytest.mark.parametrize(("kinematics", "R"), [("differential", 0.0), ("ackermann", 0.2)])
def test_the_simulated_lab_robot_tracks_its_law(kinematics: str, R: float) -> None:
    """The simulated lab's robot (0.2 s lag, its speed and yaw-rate limits, its kinematics) on the law it is
    given, commanded at 20 Hz from its exact pose, over a lap: within 5 cm of the reference."""
    law = UnicycleSquareLaw(turn_radius=R)
    t = [0.0]
    r = ScamperSim(
        law.reference(0.0)[0], RobotParams(kinematics=kinematics, min_turn_radius_m=R), lambda: t[0]
    )
    dt, worst = 0.005, 0.0
    for k in range(round(law.lap_time / dt)):
        if k % 10 == 0:
            r.send_body_velocity(law.command(t[0], r.pose))
        t[0] += dt
        r.step(t[0], dt)
        worst = max(worst, float(np.hypot(*(r.pose.p[:2] - law.reference(t[0])[0].p[:2]))))
    print(f"{kinematics}: max tracking error over a lap {worst * 1000:.1f} mm")
    assert worst < 0.05


# ---- where a robot that stayed put starts its law ---------------------------------------------------------
LAWS_TO_PHASE = [UnicycleSquareLaw(), UnicycleSquareLaw(turn_radius=0.2), SquareLaw()]


@pytest.mark.parametrize("law", LAWS_TO_PHASE, ids=["differential", "ackermann", "paper"])
def test_start_phase_finds_the_lap_time_of_a_pose_on_the_path(law: UnicycleSquareLaw | SquareLaw) -> None:
    """A robot standing at the reference's pose of lap time t (sides, turns in place, arcs) is found at t
    (within the 0.02 s sampling), or at a lap time whose reference pose is the same."""
    for t in np.linspace(0.0, law.lap_time, 97, endpoint=False):
        g = law.reference(float(t))[0]
        t0, dist, dth = start_phase(law, g)
        g0 = law.reference(t0)[0]
        assert dist < 0.1 * 0.02 + 1e-9 and abs(dth) < 0.5 * 0.02 + 1e-9, (t, t0, dist, dth)
        assert np.hypot(*(g0.p[:2] - g.p[:2])) == pytest.approx(dist, abs=1e-12)
        assert 0.0 <= t0 < law.lap_time


def test_start_phase_tells_a_turn_in_place_apart_by_heading_and_measures_the_distance() -> None:
    law = UnicycleSquareLaw()  # corner (0.5, -0.5): the turn from heading 0 to π/2 at 0.5 rad/s after 10 s
    _, _, d0 = start_phase(law, Pose.make([0.5, -0.5, 0.0], 0.0))
    t_mid, dist, _ = start_phase(law, Pose.make([0.5, -0.5, 0.0], math.pi / 4))
    assert t_mid == pytest.approx(10.0 + (math.pi / 4) / 0.5, abs=0.02) and dist < 1e-9 and abs(d0) < 1e-9
    t_side, dist, dth = start_phase(law, Pose.make([0.0, -0.62, 0.0], 0.0))  # 0.12 m outside the first side
    assert t_side == pytest.approx(5.0, abs=0.02) and dist == pytest.approx(0.12, abs=1e-9) and dth == 0.0


@pytest.mark.parametrize("law", [UnicycleSquareLaw(), UnicycleSquareLaw(turn_radius=0.2), SquareLaw()])
def test_start_phase_finds_what_a_search_of_every_sample_finds(law: UnicycleSquareLaw | SquareLaw) -> None:
    """The coarse-then-fine search against the plain one over every 20 ms sample of the lap: the same
    smallest cost, at poses on, beside and across the path with any heading."""
    step = 0.02
    ts = np.arange(0.0, law.lap_time, step)
    ref = np.array([law.reference(float(t))[0].as_vector() for t in ts])
    rng = np.random.default_rng(11)
    for _ in range(60):
        g = Pose.make([*rng.uniform(-0.8, 0.8, 2), 0.0], float(rng.uniform(-math.pi, math.pi)))
        d_th = np.array([wrap_angle(g.theta - th) for th in ref[:, 3]])
        cost = np.hypot(ref[:, 0] - g.p[0], ref[:, 1] - g.p[1]) ** 2 + (HEADING_WEIGHT_M_PER_RAD * d_th) ** 2
        t0, dist, dth = start_phase(law, g, step)
        k = round(t0 / step)
        assert cost[k] == pytest.approx(cost.min(), rel=1e-9, abs=1e-12), (g, t0, ts[int(np.argmin(cost))])
        assert dist**2 + (HEADING_WEIGHT_M_PER_RAD * dth) ** 2 == pytest.approx(cost[k], rel=1e-9, abs=1e-12)


class _Lab:
    """A backend for TargetDriver: the robot (ScamperSim) and its motion-capture pose."""

    def __init__(self, robot: ScamperSim) -> None:
        self.robot = robot

    def target(self) -> ScamperSim:
        return self.robot

    def pose_source(self) -> _Lab:
        return self

    def latest(self, body: str) -> StampedPose | None:
        return StampedPose(0.0, self.robot.pose) if body == "target" else None


def _track_from(law: UnicycleSquareLaw, g0: Pose, start_where_it_is: bool, seconds: float = 30.0) -> float:
    """Largest distance (m) of the robot from its reference, driven by TargetDriver from g0 at 20 Hz."""
    t = [0.0]
    robot = ScamperSim(g0, RobotParams(kinematics="differential"), lambda: t[0])
    drive = TargetDriver(law, _Lab(robot), fence_xy=((-2.0, -2.0), (2.0, 2.0)))  # type: ignore[arg-type]
    if start_where_it_is:
        assert drive.start_where_it_is() is not None
    dt, worst = 0.005, 0.0
    for k in range(round(seconds / dt)):
        if k % 10 == 0:
            drive.tick(t[0])
        t[0] += dt
        robot.step(t[0], dt)
        ref = law.reference(drive.t0 + t[0])[0]
        worst = max(worst, float(np.hypot(*(robot.pose.p[:2] - ref.p[:2]))))
    return worst


def test_a_robot_left_mid_lap_by_the_last_mode_starts_its_law_where_it_stands() -> None:
    """The next mode on a rig whose robot is a device: the robot stands where the last one left it (80 s
    into a 52.6 s lap). Started there, it tracks within 5 cm; started at the lap's start, as every mode
    did, its reference is 1.3 m away and the robot is driven across the square to catch it."""
    law = UnicycleSquareLaw()
    g_end = law.reference(80.0)[0]
    here = _track_from(law, g_end, start_where_it_is=True)
    old = _track_from(law, g_end, start_where_it_is=False)
    print(
        f"tracking error from the last mode's end: {here * 1000:.1f} mm; with the law restarted: {old:.2f} m"
    )
    assert here < 0.05 and old > 0.5


def test_a_robot_off_its_path_refuses_the_start_in_one_line() -> None:
    law = UnicycleSquareLaw()
    robot = ScamperSim(Pose.make([0.0, 0.0, 0.0], 0.0), RobotParams(), lambda: 0.0)  # the square's centre
    drive = TargetDriver(law, _Lab(robot), fence_xy=((-2.0, -2.0), (2.0, 2.0)))  # type: ignore[arg-type]
    with pytest.raises(RuntimeError, match=r"stands 0\.50 m from its square's path") as err:
        drive.start_where_it_is()
    assert "\n" not in str(err.value) and "(-0.50, -0.50) m facing +0.00 rad" in str(err.value)
    assert TargetDriver(law, _Lab(robot)).start_where_it_is() is None  # a simulated rig: reset every mode
