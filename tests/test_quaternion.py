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
