"""The filters' rest detection (`_rest.RestDetector`) and its tilt test: a turn slower than the gyro
threshold is not a rest, so the zero-rate update does not read its rate as gyro bias."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fusion import quaternion as quat
from fusion.estimators import build
from fusion.estimators.filters.steps._rest import RestDetector

from motion_helpers import turning_body

RATE_HZ = 285.7
SLOW_RAD_S = math.radians(1.0)  # under the 2 deg/s gyro threshold


def still_then_slow_turn(gyr_std: float = 0.002, acc_std: float = 0.006, bias=(0.0, 0.0, 0.0)):
    """10 s still, then 20 s turning at 1 deg/s about the body x axis (horizontal: the turn tilts
    gravity in the body frame), with BROAD's noise per sample."""
    t = np.arange(int(30 * RATE_HZ)) / RATE_HZ
    w = np.zeros((len(t), 3))
    w[t >= 10.0, 0] = SLOW_RAD_S
    return turning_body(t, w, quat.IDENTITY.copy(), None, gyr_std, acc_std, bias, seed=3)


def test_without_the_tilt_test_a_slow_turn_is_a_rest():
    """What the test is for: the detector without it calls the slow turn a rest."""
    imu, _ = still_then_slow_turn()
    for tilt, turning_rest in ((math.inf, True), (math.radians(0.3), False)):
        rest = RestDetector(0.035, 0.05, 1.5, tilt_rad=tilt)
        flags = np.array([rest.update(g, a, 1 / RATE_HZ) for g, a in zip(imu.gyr_rad_s[1:], imu.acc_g[1:])])
        still, turning = imu.t[1:] < 10.0, imu.t[1:] > 12.0
        assert flags[still & (imu.t[1:] > 2.0)].all()  # the still start is a rest either way
        assert flags[turning].any() == turning_rest


def test_tilt_test_angle_is_exact():
    """A still stretch ends on the step where the low-pass has turned by more than the angle."""
    angle = math.radians(1.0)
    rest = RestDetector(1.0, 1.0, 0.0, window_s=1e-9, tilt_rad=angle)  # low-pass = the sample
    for a in (0.0, 0.5, 0.99):  # the stretch begins at 0 deg; within the angle: still
        assert rest.update(np.zeros(3), np.array([0.0, math.sin(math.radians(a)), math.cos(math.radians(a))]), 0.01)
    assert not rest.update(np.zeros(3), np.array([0.0, math.sin(math.radians(1.01)), math.cos(math.radians(1.01))]), 0.01)
    assert rest.time_still == 0.0
    # the next sample starts a new stretch from where the turn has got to
    assert rest.update(np.zeros(3), np.array([0.0, math.sin(math.radians(1.02)), math.cos(math.radians(1.02))]), 0.01)
    assert np.allclose(rest.lp0, [0.0, math.sin(math.radians(1.02)), math.cos(math.radians(1.02))])


@pytest.mark.parametrize("name", ["ekf", "ukf-bias"])
def test_a_slow_turn_does_not_become_gyro_bias(name):
    """The filters: with the tilt test (0.3 deg) the bias estimate stays near the true zero through the
    slow turn; without it (rtilt=inf, the default) the rest update takes most of the turn's 1 deg/s for
    bias."""
    imu, truth = still_then_slow_turn()
    biases = {}
    for spec in (f"{name}:rtilt=0.0052", name):
        est = build(spec).estimate(imu, truth[0])
        biases[spec] = np.degrees(np.abs(est.diagnostics["gyr_bias_rad_s"][-1, 0]))
    assert biases[name] > 0.5
    assert biases[f"{name}:rtilt=0.0052"] < 0.1


def test_a_true_rest_with_a_bias_is_still_read():
    """At true rest with a gyro bias, the tilt test leaves the rest update alone: `ekf` reads the bias."""
    t = np.arange(int(20 * RATE_HZ)) / RATE_HZ
    bias = np.radians([0.5, -0.3, 0.2])
    imu, truth = turning_body(t, np.zeros((len(t), 3)), quat.IDENTITY.copy(), None, 0.002, 0.006, bias, seed=4)
    est = build("ekf:rtilt=0.0052").estimate(imu, truth[0])
    # at rest throughout once the detector's low-pass (0.5 s) has settled and a stretch has lasted 1.5 s: the
    # first stretch, begun from the unsettled low-pass, may end once on the way
    assert est.diagnostics["at_rest"][t > 3.5].all()
    np.testing.assert_allclose(est.diagnostics["gyr_bias_rad_s"][-1], bias, atol=math.radians(0.02))
