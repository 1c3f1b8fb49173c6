"""The batch quaternion helpers against SciPy, and their exact properties."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from fusion import quaternion as quat

RNG = np.random.default_rng(7)
ROTVECS = RNG.normal(size=(200, 3)) * 1.5


def as_rot(q):
    return Rotation.from_quat(q, scalar_first=True)


def test_from_rotvec_matches_scipy():
    expected = Rotation.from_rotvec(ROTVECS).as_quat(scalar_first=True)
    np.testing.assert_allclose(quat.canonical(quat.from_rotvec(ROTVECS)), quat.canonical(expected), atol=1e-15)


def test_multiply_matches_scipy_composition():
    p, q = quat.from_rotvec(ROTVECS), quat.from_rotvec(ROTVECS[::-1])
    angle = (as_rot(quat.multiply(p, q)).inv() * (as_rot(p) * as_rot(q))).magnitude()
    assert angle.max() < 1e-14


def test_gravity_in_body_matches_scipy():
    q = quat.from_rotvec(ROTVECS)
    np.testing.assert_allclose(quat.gravity_in_body(q), as_rot(q).inv().apply([0, 0, 1]), atol=1e-15)


@settings(max_examples=300, deadline=None)
@given(arrays(float, 3, elements=st.floats(-3.1, 3.1)))
def test_log_exp_roundtrip(v):
    """log(exp(v)) == v for rotation angles below pi."""
    if np.linalg.norm(v) >= np.pi - 1e-6:
        v = v / np.linalg.norm(v) * 3.0
    np.testing.assert_allclose(quat.to_rotvec(quat.from_rotvec(v)), v, atol=1e-12)


def test_to_rotvec_same_for_q_and_minus_q():
    q = quat.from_rotvec(ROTVECS)
    np.testing.assert_allclose(quat.to_rotvec(q), quat.to_rotvec(-q), atol=1e-15)


def test_exact_at_zero_angle():
    assert np.array_equal(quat.from_rotvec(np.zeros(3)), quat.IDENTITY)
    assert np.array_equal(quat.to_rotvec(quat.IDENTITY), np.zeros(3))
    tiny = np.array([1e-20, 0, 0])
    assert np.all(np.isfinite(quat.to_rotvec(quat.from_rotvec(tiny))))


@pytest.mark.parametrize("n", [1, 2, 3, 17, 1000])
def test_cumulative_product_equals_sequential_loop(n):
    q = quat.from_rotvec(RNG.normal(size=(n, 3)) * 0.3)
    expected = np.empty_like(q)
    acc = as_rot(q[0])
    expected[0] = acc.as_quat(scalar_first=True)
    for i in range(1, n):
        acc = acc * as_rot(q[i])
        expected[i] = acc.as_quat(scalar_first=True)
    angle = (as_rot(quat.cumulative_product(q)).inv() * as_rot(expected)).magnitude()
    assert angle.max() < 1e-12


# ---------------------------------------------------------------- properties
def test_q_and_minus_q_are_the_same_rotation_everywhere():
    q = quat.from_rotvec(ROTVECS)
    np.testing.assert_allclose(quat.gravity_in_body(-q), quat.gravity_in_body(q), atol=1e-15)
    np.testing.assert_allclose(quat.rotation_matrix(-q), quat.rotation_matrix(q), atol=1e-15)
    np.testing.assert_allclose(quat.relative_rotvec(-q, q[::-1]), quat.relative_rotvec(q, q[::-1]), atol=1e-12)


def test_product_is_associative():
    a, b, c = quat.from_rotvec(ROTVECS[:60]), quat.from_rotvec(ROTVECS[60:120]), quat.from_rotvec(ROTVECS[120:180])
    np.testing.assert_allclose(quat.multiply(quat.multiply(a, b), c), quat.multiply(a, quat.multiply(b, c)), atol=1e-15)


def test_rotation_matrix_is_orthonormal_and_matches_scipy():
    q = quat.from_rotvec(ROTVECS)
    R = quat.rotation_matrix(q)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R, as_rot(q).as_matrix(), atol=1e-15)


def test_skew_is_the_cross_product():
    a, b = ROTVECS[:100], ROTVECS[100:]
    np.testing.assert_allclose(np.einsum("tij,tj->ti", quat.skew(a), b), np.cross(a, b), atol=1e-15)


@pytest.mark.parametrize("scale", [1e-7, 1e-4, 2e-3, 0.5, 2.5])
def test_right_jacobian_and_its_inverse_match_finite_differences(scale):
    """exp(theta + d) ~ exp(theta) exp(J_r(theta) d) on both sides of the series threshold."""
    theta = np.array([0.6, -1.0, 0.4]) * scale
    J = quat.right_jacobian(theta)
    eps = 1e-7
    num = np.empty((3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        num[:, i] = (quat.relative_rotvec(quat.from_rotvec(theta), quat.from_rotvec(theta + d))
                     - quat.relative_rotvec(quat.from_rotvec(theta), quat.from_rotvec(theta - d))) / (2 * eps)
    np.testing.assert_allclose(J, num, atol=1e-8)
    np.testing.assert_allclose(quat.right_jacobian_inv(theta) @ J, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(quat.right_jacobian_floats(*theta), J, atol=1e-15)


# ---------------------------------------------------------------- scalar path == batch path
def test_scalar_path_matches_batch_path():
    rng = np.random.default_rng(1)
    ps, qs = quat.normalize(rng.normal(size=(2, 50, 4)))
    vs = rng.normal(size=(50, 3)) * 1.2
    vs[0] = 0.0
    vs[1] = [1e-13, -2e-13, 0.0]  # below SMALL_ANGLE
    for p, q, v in zip(ps, qs, vs):
        batch_pq = quat.multiply(p, q)
        np.testing.assert_allclose(quat.multiply_floats(tuple(p), tuple(q)), batch_pq, atol=1e-15)
        np.testing.assert_allclose(quat.right_matrix(*q) @ p, batch_pq, atol=1e-15)
        np.testing.assert_allclose(quat.left_matrix(*p) @ q, batch_pq, atol=1e-15)
        np.testing.assert_allclose(quat.exp_floats(*v), quat.from_rotvec(v), atol=1e-15)
        np.testing.assert_allclose(quat.gravity_in_body_floats(*q), quat.gravity_in_body(q), atol=1e-15)
        np.testing.assert_allclose(quat.rotation_matrix_floats(*q), quat.rotation_matrix(q), atol=1e-15)
        np.testing.assert_allclose(quat.rotate_floats(tuple(q), tuple(v)), as_rot(q).apply(v), atol=1e-14)
        np.testing.assert_allclose(quat.skew_floats(*v), quat.skew(v), atol=0)
        np.testing.assert_allclose(quat.right_jacobian_floats(*v), quat.right_jacobian(v), atol=1e-15)
        np.testing.assert_allclose(quat.unit_array(tuple(2.0 * q)), q, atol=1e-15)


def test_batch_path_broadcasts_over_leading_axes():
    v = (0.3 * ROTVECS[:24]).reshape(2, 3, 4, 3)
    q = quat.from_rotvec(v)
    assert q.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(q.reshape(-1, 4), quat.from_rotvec(0.3 * ROTVECS[:24]), atol=0)
    np.testing.assert_allclose(quat.to_rotvec(q), v, atol=1e-12)
    assert quat.gravity_in_body(q).shape == (2, 3, 4, 3)
    assert quat.right_jacobian(v).shape == (2, 3, 4, 3, 3)
    assert quat.from_rotvec(np.zeros(3)).shape == (4,)
