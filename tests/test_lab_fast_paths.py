"""The simulated lab's cheaper paths give the very numbers of the plain ones (bit for bit): noise drawn in
blocks, motion-capture frames computed when read, poses integrated as vectors."""

from __future__ import annotations

import math

import numpy as np

from flightstack.config.links import LinkDelays, LinkSpec
from flightstack.paper.geometry import Pose, integrate_body_velocity
from flightstack.sim_backend.lab import MocapParams, MocapSim, NormalStream, PoseState

PARAMS = MocapParams(rate_hz=120.0, noise_pos_m=0.0005, noise_yaw_rad=0.002)


def bits(x: np.ndarray | float) -> bytes:
    return np.asarray(x, dtype=float).tobytes()


def test_normals_in_blocks_are_the_numbers_drawn_one_call_at_a_time() -> None:
    one, blocks = np.random.default_rng(3), NormalStream(np.random.default_rng(3))
    for n in [4, 12, 1, 4095, 12, 9000, 3]:  # across block ends
        z, at = blocks.take(n)
        assert bits(z[at : at + n]) == bits([one.normal(0.0, 1.0) for _ in range(n)])


def reference_samples(rng: np.random.Generator, truth: list[dict[str, Pose]]) -> list[dict[str, Pose]]:
    """Each frame's noisy poses as the plain path draws them: per body 3 normals, then 1."""
    out = []
    for bodies in truth:
        out.append(
            {
                name: Pose.make(
                    g.p + rng.normal(0.0, PARAMS.noise_pos_m, 3),
                    g.theta + rng.normal(0.0, PARAMS.noise_yaw_rad),
                )
                for name, g in bodies.items()
            }
        )
    return out


def moving_bodies(n: int) -> list[dict[str, Pose]]:
    return [
        {
            "drone1": Pose.make([0.01 * k, 1.0, 1.2], 0.001 * k),
            "drone2": Pose.make([-0.02 * k, 0.5, 0.9], math.pi - 0.002 * k),
            "target": Pose.make([0.3, 0.003 * k, 0.0], -0.5),
        }
        for k in range(n)
    ]


def test_frames_computed_when_read_are_the_frames_drawn_when_taken() -> None:
    truth = moving_bodies(3000)  # 25 s at 120 Hz: several noise blocks
    want = reference_samples(np.random.default_rng(9), truth)
    m = MocapSim(PARAMS, np.random.default_rng(9))
    for k, bodies in enumerate(truth):
        m.capture(k / PARAMS.rate_hz, bodies)
        if k % 7 in (0, 3):  # read now and then, as the agents do
            for name in bodies:
                s = m.latest(name)
                assert s is not None and s.stamp == k / PARAMS.rate_hz
                assert bits(s.pose.p) == bits(want[k][name].p)
                assert bits(s.pose.theta) == bits(want[k][name].theta)


def test_late_frames_carry_the_same_noise() -> None:
    truth = moving_bodies(600)
    want = reference_samples(np.random.default_rng(2), truth)
    now = [0.0]
    link = LinkDelays(LinkSpec(latency_s=0.02), None)
    m = MocapSim(PARAMS, np.random.default_rng(2), link, lambda: now[0])
    for k, bodies in enumerate(truth):
        now[0] = k / PARAMS.rate_hz
        m.capture(now[0], bodies)
        s = m.latest("drone2")
        if k >= 3:  # 20 ms late: the frame taken 3 frames ago (25 ms) has arrived, the one 2 ago not
            j = round(s.stamp * PARAMS.rate_hz)
            assert j == k - 3
            assert bits(s.pose.p) == bits(want[j]["drone2"].p)


def test_a_pose_integrated_as_a_vector_is_the_pose_integrated_as_poses() -> None:
    rng = np.random.default_rng(1)
    g = Pose.make([0.2, -0.1, 1.0], 3.0)
    state = PoseState(g)
    for _ in range(2000):
        V = rng.normal(0.0, 1.0, 4)
        g = integrate_body_velocity(g, V, 0.005)
        state.integrate(V, 0.005)
    assert bits(state.pose.p) == bits(g.p) and bits(state.pose.theta) == bits(g.theta)
    assert state.z == g.p[2]


def test_a_lagged_step_is_the_numpy_update_then_the_integration() -> None:
    rng = np.random.default_rng(4)
    g = Pose.make([0.0, 0.5, 1.0], -2.0)
    state, V, V_fast = PoseState(g), np.zeros(4), np.zeros(4)
    for _ in range(1000):
        target = rng.normal(0.0, 1.0, 4)
        a = 1.0 - math.exp(-0.005 / 0.1)
        V += a * (target - V)
        g = integrate_body_velocity(g, V, 0.005)
        state.lag_integrate(V_fast, target, a, 0.005)
    assert bits(V_fast) == bits(V)
    assert bits(state.pose.p) == bits(g.p) and bits(state.pose.theta) == bits(g.theta)
