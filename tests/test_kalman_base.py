"""The shared skeleton of `ekf`, `ukf` and `ukf-bias` (`fusion.estimators.filters.kalman_base`): the
initial quaternion's check and the error state's covariances, as their docstrings state them.
That the compiled run ends in the state of the reference loop is tested in test_compiled.py."""
from __future__ import annotations

import numpy as np
import pytest

from fusion import quaternion as quat
from fusion.estimators import build
from fusion.estimators.filters.steps._error_state import UNESTIMATED_VAR
from fusion.estimators.filters.kalman_base import error_state_covariances, initial_quaternion


@pytest.mark.parametrize("bad", [[np.nan, 0, 0, 1], [0, 0, 0, 0], [1, 0, 0], [[1, 0, 0, 0]]])
@pytest.mark.parametrize("spec", ["ekf", "ukf", "ukf-bias"])
def test_a_bad_initial_quaternion_is_one_clear_error(spec, bad):
    f = build(spec)
    with pytest.raises(ValueError, match="init_quat_wxyz must be a finite non-zero"):
        f.reset(np.array(bad, dtype=float))


def test_the_initial_quaternion_is_normalised():
    np.testing.assert_allclose(initial_quaternion("x", [2.0, 0.0, 0.0, 0.0]), quat.IDENTITY)


@pytest.mark.parametrize("spec, n", [("ekf", 9), ("ekf:scale=false", 6), ("ekf:bias=false,scale=false", 3),
                                     ("ukf", 3), ("ukf-bias", 9), ("ukf-bias:saxes=z", 9)])
def test_error_state_covariances_are_the_documented_blocks(spec, n):
    p = build(spec).params
    P0, Q, Qbad = error_state_covariances(p, n)
    assert P0.shape == Q.shape == Qbad.shape == (n, n)
    for m in (P0, Q, Qbad):
        np.testing.assert_array_equal(m, np.diag(np.diag(m)))  # block diagonal, diagonal blocks
    np.testing.assert_array_equal(np.diag(P0)[:3], p.init_var_rad2)
    np.testing.assert_array_equal(np.diag(Q)[:3], p.process_noise_rad2_s)
    np.testing.assert_array_equal(np.diag(Qbad), [p.invalid_gyr_var_rad2_s2] * 3 + [0.0] * (n - 3))
    if n > 3:
        np.testing.assert_array_equal(np.diag(P0)[3:6], p.init_bias_var_rad2_s2)
        np.testing.assert_array_equal(np.diag(Q)[3:6], p.bias_walk_rad2_s3)
    if n > 6:
        on = np.array([a in p.scale_axes for a in "xyz"])
        np.testing.assert_array_equal(np.diag(P0)[6:], np.where(on, p.init_scale_var, UNESTIMATED_VAR))
        np.testing.assert_array_equal(np.diag(Q)[6:], np.where(on, p.scale_walk_1_s, 0.0))
