"""The compiled kernels (flightstack.paper.kernels) against independent references, and numba's rules:
nothing compiles during a run after warm-up."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightstack.config.mission import load_mission
from flightstack.paper import kernels as kern
from flightstack.paper.fusion import FUSION_RULES, fuse, fusion_weights
from flightstack.paper.geometry import Pose
from flightstack.paper.kernels_warmup import dispatchers, signature_counts, warm_up
from flightstack.paper.observer import estimation_error
from flightstack.paper.projection import CameraModel
from tests.conftest import fly_mode
from tests.test_compiled_loop import _experts  # the same experts as the guard test


def _remainder_wrap(theta: float) -> float:
    """The reference: math.remainder, −π mapped to π (what geometry.wrap_angle did before the kernels)."""
    w = math.remainder(theta, 2.0 * math.pi)
    return w + 2.0 * math.pi if w <= -math.pi else w


def test_wrap_angle_is_bit_equal_to_math_remainder():
    rng = np.random.default_rng(1)
    edge = [math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 3 * math.pi, 0.0, 1e-300, -1e-300]
    edge += [np.nextafter(math.pi, 4.0), np.nextafter(-math.pi, -4.0), 7.0 * math.pi, 1e15, -1e15]
    vals = np.concatenate([rng.uniform(-20, 20, 20000), rng.uniform(-1e7, 1e7, 20000), edge])
    got = np.array([kern.wrap_angle(float(v)) for v in vals])
    ref = np.array([_remainder_wrap(float(v)) for v in vals])
    assert np.array_equal(got, ref)
    assert np.all((got > -math.pi) & (got <= math.pi))


def test_geometry_wrap_angle_is_the_kernels_code_without_the_compiler():
    """geometry.wrap_angle runs kernels.wrap_angle's Python code: bit-equal to the compiled kernel, and a
    process that only builds poses never dispatches (so never starts numba's compiler)."""
    import subprocess
    import sys

    from flightstack.paper.geometry import wrap_angle

    rng = np.random.default_rng(3)
    edge = [math.pi, -math.pi, 2 * math.pi, -3 * math.pi, 0.0, -0.0, np.nextafter(-math.pi, 0.0), 1e15]
    vals = np.concatenate([rng.uniform(-50, 50, 5000), rng.uniform(-1e9, 1e9, 5000), edge])
    got = np.array([wrap_angle(float(v)) for v in vals])
    assert np.array_equal(got, np.array([kern.wrap_angle(float(v)) for v in vals]))
    probe = (
        "from flightstack.paper import kernels as kern\n"
        "from flightstack.paper.geometry import Pose\n"
        "Pose.make([1.0, 2.0, 0.5], 7.0); Pose.from_vector([0.0, 0.0, 1.0, -4.0])\n"
        "print(len(kern.wrap_angle.signatures))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "0"


def test_solve4_against_numpy_and_singular():
    rng = np.random.default_rng(2)
    for _ in range(200):
        A = rng.normal(size=(4, 4)) + 4 * np.eye(4)
        b = rng.normal(size=4)
        x = np.empty(4)
        assert kern.solve4(A, b, x)
        np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-12, atol=1e-12)
    A = rng.normal(size=(4, 4))
    A[:, 2] = 0.0
    assert not kern.solve4(A, np.ones(4), np.empty(4))


def test_degenerate_feature_points_raise_instead_of_returning_garbage():
    P0 = np.zeros((4, 3))  # every point at the target's origin: θ is unobservable, JᵀJ singular
    g = Pose.make([0.0, 0.0, 1.5], 0.1)
    f = np.zeros(8)
    with pytest.raises(np.linalg.LinAlgError):
        estimation_error(f, g, P0, CameraModel())


@pytest.mark.parametrize("rule", FUSION_RULES)
def test_fuse_kernel_equals_the_numpy_weights(rule):
    """fuse (kernel) against fusion_weights (numpy expressions of the same rules): μ = Σ_k w_k μ_k."""
    rng = np.random.default_rng(3)
    for K in (1, 2, 5):
        var = rng.uniform(0.01, 0.9, size=(K, 4))
        mu = rng.normal(size=(K, 4))
        prior = np.ones((K, 4))
        mu_f, var_f = fuse(mu, var, rule, prior)
        w = fusion_weights(var, rule, prior)
        np.testing.assert_allclose(mu_f, (w * mu).sum(axis=0), rtol=1e-12, atol=1e-15)
        if rule == "poe":
            np.testing.assert_allclose(var_f, 1.0 / (1.0 / var).sum(axis=0), rtol=1e-14)


def test_division_by_zero_is_ieee_not_an_exception():
    mu, var = np.zeros(4), np.zeros(4)
    kern.fuse(np.ones((1, 4)), np.zeros((1, 4)), kern.RULE_POE, np.ones((1, 4)), 1, mu, var)
    assert np.all(var == 0.0) and np.all(np.isnan(mu))  # 1/0 = inf, 1/inf = 0, 0·inf = nan: caught downstream


def test_nothing_compiles_during_a_run_after_warm_up():
    """numba compiles on a new argument type; a compile mid-flight holds the GIL for seconds. After
    warm_up, flying every mode on the ideal rig (compiled and Agent paths) and on the simulated lab
    (image pipeline, safety layer, robot) adds no signature to any kernel."""
    warm_up(loop=True)
    before = signature_counts()
    assert set(before) == set(dispatchers()) and all(v >= 1 for v in before.values())
    sim = load_mission("paper_sim", {"duration_s": 0.1})
    experts = _experts(sim, {1: 10, 2: 8, 3: 12})
    for mode in ("none", "local", "dgp"):
        for compiled in (True, False):
            rec = fly_mode(sim, mode, None if mode == "none" else experts, compiled=compiled)
            assert rec.ticks_done == 50 and rec.error is None
    lab = load_mission("paper_experiment", {"duration_s": 0.5}, rig="lab-sim")
    rec = fly_mode(lab, "none", None)
    assert rec.ticks_done > 0 and rec.error is None and rec.visible.any()
    assert signature_counts() == before
