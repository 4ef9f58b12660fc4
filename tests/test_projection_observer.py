"""Pinhole projection, image Jacobian (finite differences) and the visual motion observer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from flightstack.paper.geometry import Pose, compose, exp_twist, hat, inverse, vec
from flightstack.paper.observer import estimation_error, observer_step
from flightstack.paper.projection import (
    CameraModel,
    TargetNotVisibleError,
    features_and_jacobian,
    image_jacobian,
    measure,
)

P0 = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.15, 0.05]])
DOWN = CameraModel(
    focal_length=0.9,
    R_ic=Rotation.from_euler("x", 180, degrees=True).as_matrix(),
    t_ic=np.array([0.02, 0.0, -0.01]),
)


def test_projection_closed_form() -> None:
    g = Pose.make([0.2, -0.1, 1.5], 0.3)
    cam = CameraModel(focal_length=2.0)
    f = measure(g, P0, cam)
    for j, p0 in enumerate(P0):
        p = g.matrix() @ np.append(p0, 1.0)
        assert np.allclose(f[2 * j : 2 * j + 2], 2.0 * p[:2] / p[2])


def test_projection_with_downward_extrinsic_closed_form() -> None:
    """The target below a z-up drone is seen by a camera flipped about x (Tello's downward camera)."""
    g = Pose.make([0.1, 0.2, -1.2], -0.4)  # target 1.2 m below the drone frame's origin
    f = measure(g, P0, DOWN)
    for j, p0 in enumerate(P0):
        p_i = (g.matrix() @ np.append(p0, 1.0))[:3]
        p_c = DOWN.R_ic.T @ (p_i - DOWN.t_ic)
        assert p_c[2] > 0
        assert np.allclose(f[2 * j : 2 * j + 2], 0.9 * p_c[:2] / p_c[2])


def test_behind_camera_is_not_visible() -> None:
    with pytest.raises(TargetNotVisibleError):
        measure(Pose.make([0, 0, -1.0], 0.0), P0, CameraModel())


@st.composite
def estimates(draw: st.DrawFn) -> Pose:
    xy = st.floats(-0.4, 0.4)
    return Pose.make([draw(xy), draw(xy), draw(st.floats(0.8, 3.0))], draw(st.floats(-1.5, 1.5)))


@pytest.mark.parametrize("cam", [CameraModel(focal_length=1.3), None], ids=["forward", "downward"])
@given(g=estimates())
@settings(max_examples=40, deadline=None)
def test_image_jacobian_matches_finite_differences(cam: CameraModel | None, g: Pose) -> None:
    """J ξ = d/dε f(ḡ exp(ε ξ̂)) with central differences, via scipy's expm (independent of our exp)."""
    if cam is None:  # downward camera: mirror the estimate below the drone
        cam = DOWN
        g = Pose.make([g.p[0], g.p[1], -g.p[2]], g.theta)
    J = image_jacobian(g, P0, cam)
    h = 1e-6
    for k in range(4):
        xi = np.zeros(4)
        xi[k] = 1.0
        plus = Pose.from_matrix(g.matrix() @ expm(hat(xi) * h))
        minus = Pose.from_matrix(g.matrix() @ expm(hat(-xi) * h))
        fd = (measure(plus, P0, cam) - measure(minus, P0, cam)) / (2 * h)
        assert np.allclose(J[:, k], fd, rtol=1e-5, atol=1e-7)
    f_bar, J2 = features_and_jacobian(g, P0, cam)
    assert np.allclose(f_bar, measure(g, P0, cam)) and np.allclose(J2, J)


def test_jacobian_has_full_column_rank_for_four_points() -> None:
    J = image_jacobian(Pose.make([0.1, 0, 1.5], 0.2), P0[:4], CameraModel())
    assert np.linalg.matrix_rank(J) == 4


@given(g=estimates(), err=st.tuples(*[st.floats(-1e-3, 1e-3)] * 4))
@settings(max_examples=50, deadline=None)
def test_estimation_error_recovers_small_errors(g: Pose, err: tuple[float, ...]) -> None:
    """e_e = J⁺(f − f̄) ≈ vec(ḡ⁻¹ g) to first order: residual O(‖e‖²)."""
    g_e = Pose.make(err[:3], err[3])
    g_true = compose(g, g_e)
    f = measure(g_true, P0, CameraModel())
    xi = estimation_error(f, g, P0, CameraModel())
    e_true = vec(compose(inverse(g), g_true))
    assert np.allclose(xi[:3], e_true[:3], atol=5e-6)
    assert math.isclose(math.sin(xi[3]), e_true[3], abs_tol=5e-6)


def test_estimation_error_zero_when_estimate_exact() -> None:
    g = Pose.make([0.05, -0.02, 1.4], 0.6)
    assert np.allclose(estimation_error(measure(g, P0, CameraModel()), g, P0, CameraModel()), 0.0, atol=1e-14)


def test_observer_step_is_exact_flow() -> None:
    """ḡ_w(t+dt) = ḡ_w expm(−û_e dt), and ḡ_i0 = g_wi⁻¹ ḡ_w obeys dḡ_i0/dt = −V̂_wi ḡ_i0 − ḡ_i0 û_e."""
    g_bar_w = Pose.make([0.3, -0.2, 0.1], 0.4)
    u_e = np.array([0.2, -0.1, 0.05, 0.3])
    out = observer_step(g_bar_w, u_e, 0.05)
    assert np.allclose(out.matrix(), g_bar_w.matrix() @ expm(-hat(u_e) * 0.05), atol=1e-12)
    # the paper's observer in the drone frame, by finite differences
    g_wi = Pose.make([1.0, 2.0, -1.0], -0.7)
    V_wi = np.array([0.4, 0.1, -0.2, 0.5])
    h = 1e-6
    G0 = inverse(g_wi).matrix() @ g_bar_w.matrix()
    g_wi_h = compose(g_wi, exp_twist(V_wi, h))
    G1 = inverse(g_wi_h).matrix() @ observer_step(g_bar_w, u_e, h).matrix()
    paper_rate = -hat(V_wi) @ G0 - G0 @ hat(u_e)
    assert np.allclose((G1 - G0) / h, paper_rate, atol=1e-5)
