"""Every time that enters delay compensation is checked against the tick's own clock: a frame's or a pose's
stamp not finite or ahead of the tick is dropped, counted once and never stored; the estimates' and
commands' times are refused when not finite; `CommandModel.predict` costs what the commands kept cost,
whatever its horizon; and the horizon (the rc link's latency where it stands in for the command delay)
is bounded at validation, through a rig, an included links file and `--set`."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from flightstack.cli import app as cli
from flightstack.hal import Frame, StampedPose
from flightstack.paper import kernels as kern
from flightstack.paper.delay_compensation import (
    AHEAD_TOLERANCE_S,
    FRAME_AHEAD,
    FRAME_NOT_FINITE,
    MAX_DELAY_S,
    MAX_STEPS_PER_SEGMENT,
    POSE_AHEAD,
    POSE_NOT_FINITE,
    CommandModel,
    Compensation,
    EstimateHistory,
    PoseHistory,
    stamp_refusal,
)
from flightstack.safety import SafetyLimits
from tests.conftest import Bound

pytestmark = pytest.mark.unit

BAD_STAMPS = (1e9, math.inf, -math.inf, math.nan)


@pytest.mark.parametrize("what", ["frame", "pose"])
def test_a_stamp_not_finite_or_ahead_of_the_tick_is_refused(what: str) -> None:
    t = 12.5
    for ok in (t, t - 3.0, t + AHEAD_TOLERANCE_S, -1e9):
        assert stamp_refusal(ok, t, what) is None, ok
    ahead, not_finite = (FRAME_AHEAD, FRAME_NOT_FINITE) if what == "frame" else (POSE_AHEAD, POSE_NOT_FINITE)
    assert stamp_refusal(t + AHEAD_TOLERANCE_S + 1e-9, t, what) == ahead
    assert stamp_refusal(1e9, t, what) == ahead
    for bad in (math.inf, -math.inf, math.nan):
        assert stamp_refusal(bad, t, what) == not_finite
    assert stamp_refusal(t, math.nan, what) == ahead  # nothing enters against a broken tick clock


def test_the_histories_and_the_command_model_never_store_a_time_not_finite() -> None:
    g, u = np.array([0.1, 0.2, 1.0, 0.3]), np.array([0.1, 0.0, 0.0, 0.2])
    poses, estimates, commands = PoseHistory(1.0), EstimateHistory(1.0), CommandModel(0.05, 0.1, 1.0)
    for k in range(5):
        assert poses.add(0.1 * k, g) and estimates.add(0.1 * k, g, u) and commands.sent(0.1 * k, u)
    kept = (list(poses._t), list(estimates._t), len(commands))
    for bad in (math.nan, math.inf, -math.inf):
        assert not poses.add(bad, g)
        assert not estimates.add(bad, g, u)
        assert not commands.sent(bad, u)
        assert poses.at(bad) is None and estimates.at(bad) is None  # NaN once raised IndexError here
        with pytest.raises(ValueError, match="finite"):
            commands.predict(g, bad, 1.0)
        with pytest.raises(ValueError, match="finite"):
            commands.predict(g, 0.4, bad)
    assert (list(poses._t), list(estimates._t), len(commands)) == kept
    assert poses.add(0.5, g)  # and the next real sample is taken
    # an estimate at an earlier tick replaces every one at or after it: the times stay ordered
    assert estimates.add(0.25, g, u) and list(estimates._t) == [0.0, 0.1, 0.2, 0.25]


@pytest.mark.parametrize(
    "field",
    [("command_delay_s", 3600.0), ("response_s", math.inf), ("history_s", 0.0), ("command_delay_s", -1.0)],
)
def test_compensation_refuses_delays_beyond_its_bound(field: tuple[str, float]) -> None:
    name, value = field
    kw = {"command_delay_s": 0.05, "response_s": 0.1, "history_s": 1.0, name: value}
    with pytest.raises(ValueError, match=name):
        Compensation(**kw)
    assert Compensation(MAX_DELAY_S, MAX_DELAY_S, MAX_DELAY_S).horizon_s == 2 * MAX_DELAY_S


def test_predict_far_ahead_costs_the_commands_kept_not_the_horizon(
    monkeypatch: pytest.MonkeyPatch, safety_bound: Bound
) -> None:
    """1e6 s ahead took more than 15 s (one 10 ms step after the other); now a span of one command is at
    most MAX_STEPS_PER_SEGMENT steps and one step for its rest. Counted in integration steps (exact) and
    timed (the best of 5 calls: the cost, not the machine's load)."""
    m = CommandModel(delay_s=0.05, tau_s=0.1, keep_s=1.0)
    for k in range(40):
        m.sent(0.05 * k, np.array([0.2, -0.1, 0.05, 0.3]) * (1 if k % 2 else -1))
    g, t = np.array([0.1, 0.2, 1.0, 0.3]), 0.05 * 39
    steps = 0
    integrate = kern.integrate4

    def counted(*a: Any) -> None:
        nonlocal steps
        steps += 1
        integrate(*a)

    monkeypatch.setattr(kern, "integrate4", counted)
    near = m.predict(g, t, t + 0.15)
    steps_near, steps = steps, 0
    far = m.predict(g, t, t + 1e6)
    steps_far = steps
    monkeypatch.undo()
    assert steps_near == 15  # 0.15 s in 10 ms steps, as before the bound
    assert steps_far <= (len(m) + 1) * (MAX_STEPS_PER_SEGMENT + 1) + 1
    # at rest on its last command for 1e6 s: where that constant twist takes the drone
    assert np.all(np.isfinite(far)) and np.all(np.isfinite(near))
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        m.predict(g, t, t + 1e6)
        best = min(best, time.perf_counter() - t0)
    print(f"predict 1e6 s ahead: {steps_far} steps (0.15 s ahead: {steps_near}), {best * 1e3:.2f} ms")
    safety_bound("CommandModel.predict 1e6 s ahead (best of 5)", best * 1e3, 10.0)


def test_predict_beyond_the_steps_is_the_settled_twist() -> None:
    """After the steps the velocity has settled on the acting command: the rest is its constant twist."""
    V = np.array([0.2, 0.0, 0.1, 0.05])
    m = CommandModel(delay_s=0.0, tau_s=0.1, keep_s=1.0)
    m.sent(0.0, V)
    g = np.zeros(4)
    span = MAX_STEPS_PER_SEGMENT * 0.01
    at_span = m.predict(g, 0.0, span)
    far = m.predict(g, 0.0, span + 50.0)
    expected = np.empty(4)
    kern.integrate4(at_span, V, 50.0, expected)
    np.testing.assert_allclose(far, expected, atol=1e-9)


# ---- the agent: a bad stamp is dropped, counted once, and changes nothing else ----------------------


class _World:
    """One agent's devices in a scripted world: a still target, the drone flying a fixed body velocity;
    frames every tick `delay_s` late, poses of the tick. `bad`: tick index -> what to give instead
    (("frame" | "pose", stamp)), a copy of what the tick would have given the tick before, stamped so."""

    def __init__(self, bad: dict[int, tuple[str, float]] | None = None, delay_s: float = 0.3) -> None:
        from flightstack.paper.projection import measure_vector

        self.k, self.t, self.delay_s, self.bad = 0, 0.0, delay_s, bad or {}
        self.g_w0 = np.array([0.0, 0.0, 0.0, 0.1])
        self.g_wi0 = np.array([0.15, -0.1, 1.2, 0.0])
        self.V = np.array([0.2, 0.1, 0.0, 0.1])
        self.measure = measure_vector
        self.sent: list[np.ndarray] = []

    def g_wi(self, t: float) -> np.ndarray:
        out = np.empty(4)
        kern.integrate4(self.g_wi0, self.V, t, out)
        return out

    def _frame(self, k: int) -> Frame:
        from tests.test_delay_compensation import DOWN, P0, rel

        taken = max(0.0, 0.05 * k - self.delay_s)
        return Frame(taken, None, self.measure(rel(self.g_wi(taken), self.g_w0), P0, DOWN))

    def _pose(self, k: int) -> StampedPose:
        from flightstack.paper.geometry import Pose

        g = self.g_wi(0.05 * k)
        return StampedPose(0.05 * k, Pose(g[:3], float(g[3])))

    def latest(self, body: str | None = None) -> Any:
        # every odd tick repeats the even tick's sample (a source slower than the loop): a bad sample
        # there takes the place of a repeat, so the clean run is what the bad one must equal
        kind, stamp = self.bad.get(self.k, ("", 0.0))
        src = self.k - self.k % 2
        if body is not None:
            p = self._pose(src)
            return StampedPose(stamp, p.pose) if kind == "pose" else p
        f = self._frame(src)
        return Frame(stamp, f.image, f.features) if kind == "frame" else f

    def send_body_velocity(self, V: np.ndarray) -> None:
        self.sent.append(np.array(V))

    def publish(self, msg: Any) -> None:
        pass


def _fly(world: _World, compensation: Compensation | None, ticks: int = 40) -> list[Any]:
    from tests.test_delay_compensation import _agent

    return _ticks(_agent(world, compensation), world, ticks)  # type: ignore[arg-type]


def _ticks(agent: Any, world: _World, ticks: int) -> list[Any]:
    """Fly `agent` in `world` for `ticks` ticks of 0.05 s; each tick's record."""
    records = []
    for k in range(ticks):
        world.k, world.t = k, 0.05 * k
        agent.sense_and_publish(world.t)
        agent.fuse_control_act(world.t)
        records.append(agent.last)
    return records


def _same_flight(a: list[Any], b: list[Any]) -> None:
    for ra, rb in zip(a, b, strict=True):
        for name in ("e_e_meas", "u_c", "u_e", "V_cmd", "mu_used"):
            np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name), err_msg=name)
        np.testing.assert_array_equal(ra.g_bar_w.as_vector(), rb.g_bar_w.as_vector())
        assert (ra.visible, ra.rejection, ra.own_pose_fresh) == (rb.visible, rb.rejection, rb.own_pose_fresh)
        np.testing.assert_array_equal([ra.frame_age, ra.pose_age], [rb.frame_age, rb.pose_age])


@pytest.mark.parametrize("kind", ["frame", "pose"])
@pytest.mark.parametrize("compensated", [True, False])
def test_a_bad_stamp_leaves_the_agent_as_without_it_and_is_counted_once(kind: str, compensated: bool) -> None:
    """Stamps 1e9, ±inf and NaN in place of repeats (ticks 9, 13, 17, 21), the NaN one read on three
    ticks in a row (its source had nothing newer): every tick equals the clean flight's, and each bad
    sample is counted once. Before, a frame stamped 1e9 became the newest used and every later frame
    was refused "frame out of order", a pose stamped 1e9 froze the pose history, and a NaN frame stamp
    raised IndexError in sense_late."""
    comp = Compensation(0.05, 0.1, history_s=1.0) if compensated else None
    clean = _fly(_World(), comp)
    bad = {9: (kind, 1e9), 13: (kind, math.inf), 17: (kind, -math.inf), 21: (kind, math.nan)}
    bad |= {22: (kind, math.nan), 23: (kind, math.nan)}  # the same NaN sample read again (22: a repeat too)
    flown = _fly(_World(bad), comp)
    _same_flight(flown[:22], clean[:22])  # tick 22 has a new sample in the clean run, the NaN again here
    ahead, not_finite = (FRAME_AHEAD, FRAME_NOT_FINITE) if kind == "frame" else (POSE_AHEAD, POSE_NOT_FINITE)
    counts = [(k, r.dropped) for k, r in enumerate(flown) if r.dropped]
    assert counts == [(9, [ahead]), (13, [not_finite]), (17, [not_finite]), (21, [not_finite])]
    assert all(r.visible for r in flown[12:]) and all(r.own_pose_fresh for r in flown)
    assert not any(r.rejection for r in flown[12:])  # no "frame out of order" after the 1e9 frame


@pytest.mark.parametrize(
    "ahead", [AHEAD_TOLERANCE_S, 0.05, 0.0], ids=["at the tolerance", "within it", "at the tick"]
)
def test_a_frame_stamped_ahead_of_its_stream_holds_no_later_frame_back(ahead: float) -> None:
    """Frames 0.3 s late, but the one of tick 9 stamped `ahead` s after its tick (accepted, used as
    current): every later frame is used as in the clean flight. Before, it became the newest frame used
    and the next 6-8 were refused "frame out of order" (8 at exactly AHEAD_TOLERANCE_S)."""
    comp = Compensation(0.05, 0.1, history_s=1.0)
    clean = _fly(_World(), comp)
    flown = _fly(_World({9: ("frame", 0.05 * 9 + ahead)}), comp)
    assert not any(r.dropped for r in flown)  # within the tolerance: not refused
    assert [r.rejection for r in flown] == [r.rejection for r in clean]
    assert [r.visible for r in flown] == [r.visible for r in clean]


def test_a_bad_own_pose_is_a_dropout_once_the_last_good_one_is_too_old() -> None:
    """The last accepted pose stands in for a refused one only while the safety layer would call it
    fresh (pose_timeout): a source that keeps giving bad stamps makes the drone hover, not fly on an old
    pose."""
    world = _World({k: ("pose", 1e9 + k) for k in range(10, 40)})
    limits = SafetyLimits()
    fresh = [r.own_pose_fresh for r in _fly_limited(world, None, limits, 30)]
    last_good = 0.05 * 8  # tick 9 repeats tick 8's pose; 10 on are bad
    stale_from = next(k for k in range(30) if 0.05 * k - last_good > limits.pose_timeout)
    assert fresh[:stale_from] == [True] * stale_from and not any(fresh[stale_from:])
    assert all(np.all(V == 0) for V in world.sent[stale_from:])  # hovers


@pytest.mark.parametrize("compensated", [True, False])
def test_an_own_pose_stamped_in_the_past_is_as_stale_as_its_stamp(compensated: bool) -> None:
    """Own poses stamped 1 s (or 1e9 s) in the past in place of repeats: older than the one already used,
    each is ignored and the flight is the clean one. From tick 10 on every pose 1 s old (a replay, a
    stuck clock), or one old stamp repeated: the drone hovers once the last fresh one is pose_timeout old,
    and the command never exceeds the clean flight's. Before, the compensated command was predicted from
    the old pose over every command since its stamp: 4.8 m/s, 8.4e7 m/s when the stamp repeated."""
    comp = Compensation(0.05, 0.1, history_s=1.0) if compensated else None
    clean = _fly(_World(), comp)
    isolated = {9: ("pose", 0.05 * 9 - 1.0), 13: ("pose", -1e9), 17: ("pose", 0.05 * 17 - 0.5)}
    _same_flight(_fly(_World(isolated), comp), clean)
    limits = SafetyLimits()
    clean_world = _World()
    _fly_limited(clean_world, comp, limits)
    peak = max(float(np.abs(V).max()) for V in clean_world.sent)
    for bad in (
        {k: ("pose", 0.05 * k - 1.0) for k in range(10, 40)},
        {k: ("pose", 0.2) for k in range(10, 40)},
    ):
        world = _World(bad)
        flown = _fly_limited(world, comp, limits)
        last_good = 0.05 * 8  # tick 9 repeats tick 8's pose; 10 on are old
        stale_from = next(k for k in range(40) if 0.05 * k - last_good > limits.pose_timeout)
        fresh = [r.own_pose_fresh for r in flown]
        assert fresh[:stale_from] == [True] * stale_from and not any(fresh[stale_from:])
        assert all(np.all(V == 0) for V in world.sent[stale_from:])  # hovers
        assert max(float(np.abs(V).max()) for V in world.sent) <= peak + 1e-9


def _fly_limited(world: _World, compensation: Compensation | None, limits: Any, ticks: int = 40) -> list[Any]:
    """_fly with an agent that knows the safety limits (pose_timeout), as the runner's agents do."""
    from flightstack.paper.control import Gains
    from flightstack.paper.geometry import Pose
    from flightstack.runtime.agent import Agent, AgentConfig
    from tests.test_delay_compensation import DOWN, P0

    gains = Gains.make([1.0] * 4, [1.0] * 4, 0.0)
    cfg = AgentConfig(
        "m", 1, "drone1", Pose(np.array([0.0, 0.0, -1.2]), 0.0), P0, DOWN, gains, "none", "poe", (), 0.5,
        command_limits=limits, compensation=compensation,
    )  # fmt: skip
    g0 = Pose(world.g_w0[:3].copy(), float(world.g_w0[3]))
    return _ticks(Agent(cfg, world, world, world, world, None, g0), world, ticks)  # type: ignore[arg-type]


# ---- a flight: the recording is the clean one's but for the counters --------------------------------


class _Thinned:
    """A backend whose drones' cameras and poses give, on every odd tick (by its clock) from tick `start`
    on, what they gave on the tick before (sources slower than the loop); on the ticks of `bad`, a copy
    stamped `bad[k]`."""

    def __init__(self, inner: Any, dt: float, bad: dict[int, tuple[str, float]], start: int) -> None:
        self.inner, self.dt, self.bad, self.start = inner, dt, bad, start
        self.clock = inner.clock
        self._cams: dict[int, Any] = {}
        self._poses = _ThinnedPoses(self)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def tick(self) -> int:
        return round(self.clock.now() / self.dt)

    def held(self, k: int) -> bool:
        """Whether tick k repeats the tick before."""
        return k >= self.start and k % 2 == 1

    def camera(self, drone_id: int) -> Any:
        if drone_id not in self._cams:
            self._cams[drone_id] = _ThinnedCamera(self, self.inner.camera(drone_id))
        return self._cams[drone_id]

    def pose_source(self) -> Any:
        return self._poses


class _ThinnedCamera:
    def __init__(self, up: _Thinned, inner: Any) -> None:
        self.up, self.inner, self._held = up, inner, None

    def latest(self) -> Frame | None:
        k = self.up.tick()
        if not self.up.held(k) or self._held is None:
            self._held = self.inner.latest()
        kind, stamp = self.up.bad.get(k, ("", 0.0))
        f = self._held
        return Frame(stamp, f.image, f.features, f.roi) if kind == "frame" and f is not None else f


class _ThinnedPoses:
    def __init__(self, up: _Thinned) -> None:
        self.up, self._held = up, {}  # body -> (tick read, pose)

    def latest(self, body: str) -> StampedPose | None:
        k = self.up.tick()
        held = self._held.get(body)
        if not body.startswith("drone"):
            return self.up.inner.pose_source().latest(body)
        if held is None or (not self.up.held(k) and held[0] != k):
            held = self._held[body] = (k, self.up.inner.pose_source().latest(body))
        kind, stamp = self.up.bad.get(k, ("", 0.0))
        p = held[1]
        return StampedPose(stamp, p.pose) if kind == "pose" and p is not None else p


def test_a_flight_with_bad_stamps_records_what_the_clean_one_does_but_the_counts() -> None:
    """paper_experiment on lab-sim under the Tello's links, compensated, 3 s of mode none: frames and own
    poses stamped 1e9, inf and NaN in place of repeats during pursuit. Every array, every event and every
    fact of the recording equals the clean run's, but the rejection counts, which have each bad sample
    once per drone that read it, and the safety layer's one `pose_error` per drone for the pose stamped
    ahead of the clock."""
    from flightstack.config.compensation import CompensationSpec
    from flightstack.config.links import LinksSpec
    from flightstack.config.mission import load_mission
    from flightstack.recording.fingerprint import EVENTS, META, fingerprints, meta_canonical
    from tests.conftest import fly_mode
    from tests.test_delay_compensation import _flight_events

    m = load_mission("paper_experiment", {"duration_s": 3.0}, rig="lab-sim")
    render = m.sim.render.model_copy(update={"model": "centres"})
    m = m.model_copy(
        update={
            "links": LinksSpec(profile="tello"),
            "sim": m.sim.model_copy(update={"render": render}),
            "compensation": CompensationSpec(enabled=True),
        }
    )
    dt = m.dt_s
    start = round(2.5 / dt)  # sources thinned in pursuit (it starts at ≈ 2.05 s), not during the takeoff
    k0 = round(3.0 / dt) + 1  # odd ticks: repeats
    bad = {k0: ("frame", 1e9), k0 + 4: ("pose", 1e9), k0 + 8: ("frame", math.inf)}
    bad |= {k0 + 12: ("pose", math.nan), k0 + 16: ("frame", math.nan), k0 + 20: ("pose", math.inf)}
    clean = fly_mode(m, "none", wrap_backend=lambda b: _Thinned(b, dt, {}, start))
    flown = fly_mode(m, "none", wrap_backend=lambda b: _Thinned(b, dt, bad, start))
    assert flown.ticks_done == clean.ticks_done == m.n_ticks
    a, b = fingerprints(flown), fingerprints(clean)
    assert {k: v for k, v in a.items() if k not in (EVENTS, META)} == {
        k: v for k, v in b.items() if k not in (EVENTS, META)
    }
    # the safety layer does not take an own pose stamped ahead of the clock either, and says so once
    ahead = [e for e in _flight_events(flown) if e.get("kind") == "pose_error" and "ahead" in e["detail"]]
    assert sorted(e["drone"] for e in ahead) == [1, 2], ahead
    assert [e for e in _flight_events(flown) if e not in ahead] == _flight_events(clean)
    meta_a, meta_b = meta_canonical(flown), meta_canonical(clean)
    rej_a, rej_b = meta_a.pop("vision_rejections"), meta_b.pop("vision_rejections")
    assert meta_a == meta_b
    extra = {
        i: {r: n - rej_b.get(i, {}).get(r, 0) for r, n in c.items() if n != rej_b.get(i, {}).get(r, 0)}
        for i, c in rej_a.items()
    }
    per_drone = {FRAME_AHEAD: 1, FRAME_NOT_FINITE: 2, POSE_AHEAD: 1, POSE_NOT_FINITE: 2}
    assert extra == {"1": per_drone, "2": per_drone}, (rej_a, rej_b)
    assert all(rej_b.get(i, {}).get(r, 0) <= rej_a[i][r] for i in rej_b for r in rej_b[i])


# ---- the horizon at validation ----------------------------------------------------------------------


def test_the_rc_link_standing_in_for_the_command_delay_is_bounded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rc latency 3600 s (the links schema's bound) with compensation on and command_delay_s unset: exit 2
    naming links.rc.latency_s, through --set on lab-sim, through an included links file, and on the
    emulated lab (compensation on by default there), before anything flies. Within the bound, or with
    command_delay_s given, or with compensation off, the same link is accepted."""
    from flightstack.config.mission import MissionError, load_mission
    from flightstack.config.rig import MISSION_CONFIGS

    out = tmp_path / "run"
    base = ["run", "paper_experiment", "--duration", "3", "--modes", "none", "--out", str(out)]
    lab = [*base, "--rig", "lab-sim", "--set", "compensation.enabled=true"]
    cases = {
        "--set on lab-sim": [*lab, "--set", "links.rc.latency_s=3600"],
        "--set jitter on lab-sim": [*lab, "--set", "links.rc.jitter_s=20.5"],
        "--set on emulated-lab": [*base, "--rig", "emulated-lab", "--set", "links.rc.latency_s=3600"],
    }
    rig = yaml.safe_load((MISSION_CONFIGS / "rigs" / "lab-sim.yaml").read_text())
    for name in ("cameras",):
        rig[name] = {k: str((MISSION_CONFIGS / "rigs" / v).resolve()) for k, v in rig[name].items()}
    (tmp_path / "measured.yaml").write_text(yaml.safe_dump({"links": {"rc": {"latency_s": 3600.0}}}))
    rig |= {"rig": "lab-measured", "links": {"include": "measured.yaml"}, "compensation": {"enabled": True}}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    cases["an included links file"] = [*base, "--rig", str(tmp_path / "rig.yaml")]
    for what, argv in cases.items():
        assert cli.main(argv) == 2, what
        err = capsys.readouterr().err
        assert "links.rc.latency_s:" in err and f"must be <= {MAX_DELAY_S:g} s" in err, (what, err)
        assert "Traceback" not in err and not out.exists(), what
    with pytest.raises(MissionError, match=r"links\.rc\.latency_s"):
        load_mission("paper_experiment", rig=tmp_path / "rig.yaml")
    # within the bound, command_delay_s given, or compensation off: the same link is accepted
    rig["compensation"] = {"enabled": True, "command_delay_s": 0.05}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    assert load_mission("paper_experiment", rig=tmp_path / "rig.yaml").delay_compensation() == Compensation(
        0.05, 0.1
    )
    rig["compensation"] = {"enabled": False}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    assert load_mission("paper_experiment", rig=tmp_path / "rig.yaml").delay_compensation() is None
    (tmp_path / "measured.yaml").write_text(yaml.safe_dump({"links": {"rc": {"latency_s": MAX_DELAY_S}}}))
    rig["compensation"] = {"enabled": True}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    c = load_mission("paper_experiment", rig=tmp_path / "rig.yaml").delay_compensation()
    assert c is not None and c.command_delay_s == MAX_DELAY_S
