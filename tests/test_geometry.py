"""Planar SE(3) against 4×4 homogeneous matrices and scipy's matrix exponential (independent references)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from flightstack.paper.geometry import (
    Pose,
    ad_g,
    ad_R,
    compose,
    compose_arrays,
    exp_twist,
    hat,
    integrate_body_velocity,
    inverse,
    inverse_arrays,
    relative,
    rot_z,
    vec,
    vec_arrays,
    wrap_angle,
)
from tests.conftest import poses, twists


def close(a: Pose, b: Pose, tol: float = 1e-9) -> bool:
    return np.allclose(a.matrix(), b.matrix(), atol=tol)


@given(poses(), poses())
def test_compose_is_matrix_product(a: Pose, b: Pose) -> None:
    assert np.allclose(compose(a, b).matrix(), a.matrix() @ b.matrix(), atol=1e-9)


@given(poses(), poses(), poses())
def test_compose_is_associative(a: Pose, b: Pose, c: Pose) -> None:
    assert close(compose(compose(a, b), c), compose(a, compose(b, c)))


@given(poses())
def test_inverse_is_matrix_inverse(g: Pose) -> None:
    assert np.allclose(inverse(g).matrix(), np.linalg.inv(g.matrix()), atol=1e-9)
    assert close(compose(g, inverse(g)), Pose.identity())


@given(poses(), poses())
def test_relative(a: Pose, b: Pose) -> None:
    assert np.allclose(relative(a, b).matrix(), np.linalg.inv(a.matrix()) @ b.matrix(), atol=1e-9)


@given(poses())
def test_vec_and_matrix_round_trip(g: Pose) -> None:
    v = vec(g)
    assert np.allclose(v[:3], g.p) and math.isclose(v[3], math.sin(g.theta), abs_tol=1e-12)
    assert close(Pose.from_matrix(g.matrix()), g)
    assert close(Pose.from_vector(g.as_vector()), g)


@given(poses(), twists())
def test_ad_g_is_conjugation(g: Pose, V: np.ndarray) -> None:
    """(g V̂ g⁻¹)^∨ = Ad_g V (DESIGN §3)."""
    G = g.matrix()
    conj = G @ hat(V) @ np.linalg.inv(G)
    assert np.allclose(conj, hat(ad_g(g) @ V), atol=1e-9)


@given(st.floats(-10, 10), twists())
def test_ad_R_is_conjugation_by_rotation(theta: float, V: np.ndarray) -> None:
    g = Pose.make([0, 0, 0], theta)
    assert np.allclose(ad_R(theta) @ V, ad_g(g) @ V, atol=1e-12)


@given(twists(), st.floats(1e-4, 2.0))
@settings(max_examples=200)
def test_exp_twist_matches_expm(V: np.ndarray, dt: float) -> None:
    ref = expm(hat(V) * dt)
    assert np.allclose(exp_twist(V, dt).matrix(), ref, atol=1e-9)


@pytest.mark.parametrize("w", [0.0, 1e-9, -1e-7, 1e-6, 2e-6])
def test_exp_twist_near_zero_rotation(w: float) -> None:
    V = np.array([0.3, -0.2, 0.1, w])
    assert np.allclose(exp_twist(V, 0.5).matrix(), expm(hat(V) * 0.5), atol=1e-13)


@given(poses(), twists())
def test_integration_is_right_multiplication(g: Pose, V: np.ndarray) -> None:
    """ġ = g V̂: one step with a held V equals g·expm(V̂ dt)."""
    assert np.allclose(
        integrate_body_velocity(g, V, 0.1).matrix(), g.matrix() @ expm(hat(V) * 0.1), atol=1e-9
    )


@given(st.floats(-100, 100))
def test_wrap_angle_range_and_equivalence(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9)
    assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)


def test_wrap_angle_boundary() -> None:
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi


def test_rot_z_is_rotation() -> None:
    R = rot_z(0.7)
    assert np.allclose(R.T @ R, np.eye(3)) and math.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ [1, 0, 0], [math.cos(0.7), math.sin(0.7), 0])


def test_pose_rejects_non_finite() -> None:
    with pytest.raises(ValueError, match="finite"):
        Pose.make([0, float("nan"), 0], 0.0)


@given(st.lists(poses(), min_size=2, max_size=2), st.lists(poses(), min_size=2, max_size=2))
def test_batched_ops_match_scalar_ops(A: list[Pose], B: list[Pose]) -> None:
    a = np.array([g.as_vector() for g in A])
    b = np.array([g.as_vector() for g in B])
    comp = compose_arrays(a, b)
    for k in range(2):
        assert close(Pose.from_vector(comp[k]), compose(A[k], B[k]))
        assert close(Pose.from_vector(inverse_arrays(a)[k]), inverse(A[k]))
        assert np.allclose(vec_arrays(a)[k], vec(A[k]))


def test_yaw_quaternions_are_the_rotations_rot_z() -> None:
    """The quaternion (x, y, z, w) of yaw θ, turned back into a matrix by the standard formula, is R(θ)."""
    from flightstack.paper.geometry import rot_z, yaw_quaternions

    thetas = np.linspace(-3 * np.pi, 3 * np.pi, 37)
    q = yaw_quaternions(thetas)
    assert q.shape == (37, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-15)
    for th, (x, y, z, w) in zip(thetas, q, strict=True):
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        np.testing.assert_allclose(R, rot_z(float(th)), rtol=0, atol=1e-12)
