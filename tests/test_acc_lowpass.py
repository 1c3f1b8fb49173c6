"""The accelerometer low-passed in the gyro-only frame (`_accel.AccDisturbance` with
`lowpass_s`) and the choice between it and the raw sample (`_accel.acc_measurement`)."""
import math

import numpy as np
import pytest

from fusion import quaternion as quat
from fusion.estimators.filters.steps._accel import (
    AccDisturbance,
    acc_measurement,
    lowpass_drift_density,
    lowpass_residual_density,
)


def _turning_body_with_translation(seconds=20.0, rate_hz=200.0, amp_g=0.5, freq_hz=2.0):
    """A body turning about a tilted axis while shaken back and forth along world x
    (velocity bounded: a sinusoidal acceleration). Returns per-sample rate increments
    (4-float quaternions), accelerometer samples (N, 3) g and the true gravity in the body."""
    dt = 1.0 / rate_hz
    n = int(seconds * rate_hz)
    w_body = np.array([0.6, -0.4, 1.5])  # rad/s
    q = (math.cos(0.2), math.sin(0.2), 0.0, 0.0)  # tilted start
    dq = quat.exp_floats(*(w_body * dt))
    incs, acc, grav = [], [], []
    for k in range(n):
        q = quat.normalize_floats(quat.multiply_floats(q, dq))
        t = (k + 1) * dt
        f_world = np.array([amp_g * math.sin(2 * math.pi * freq_hz * t), 0.0, 1.0])  # specific force, g
        w, x, y, z = q
        conj = (w, -x, -y, -z)
        acc.append(quat.rotate_floats(conj, tuple(f_world)))
        grav.append(quat.rotate_floats(conj, (0.0, 0.0, 1.0)))
        incs.append(dq)
    return dt, incs, np.array(acc), np.array(grav)


def test_lowpassed_direction_removes_bounded_translation():
    dt, incs, acc, grav = _turning_body_with_translation()
    dist = AccDisturbance(0.5, lowpass_s=1.0, lowpass_window_s=3.0)
    err_raw, err_lp = [], []
    for k, (dq, a) in enumerate(zip(incs, acc)):
        dist.update(dq, a, dt)
        if k * dt > 5.0:  # after the low-pass settled
            err_raw.append(math.degrees(math.acos(np.clip(a @ grav[k] / np.linalg.norm(a), -1, 1))))
            err_lp.append(math.degrees(math.acos(np.clip(dist.lowpass_body @ grav[k], -1, 1))))
    # raw: off by up to atan(0.5) = 27 deg; a first-order low-pass of 1 s passes 2 Hz at
    # 1 / sqrt(1 + (2 pi 2 Hz 1 s)^2) = 8 %, so the low-passed direction is off by ~2 deg
    assert max(err_raw) > 20.0
    assert np.sqrt(np.mean(np.square(err_lp))) < 0.15 * np.sqrt(np.mean(np.square(err_raw)))
    assert np.isclose(np.linalg.norm(dist.lowpass_body), 1.0)
    # what is left of the translation has a far smaller low-frequency density than the raw power
    assert 0.0 < dist.lowpass_density < 2 * 0.1 * 0.5**2 / 2


def test_lowpass_restarts_when_the_frame_is_lost():
    dist = AccDisturbance(0.5, lowpass_s=1.0)
    dist.update((1.0, 0.0, 0.0, 0.0), np.array([0.0, 0.0, 1.0]), 0.01)
    assert dist.lowpass_body is not None
    dist.lose_frame()
    assert dist.lowpass_body is None and dist.lowpass_density == math.inf


def test_without_lowpass_nothing_is_lowpassed():
    dist = AccDisturbance(0.5)
    dist.update((1.0, 0.0, 0.0, 0.0), np.array([0.0, 0.0, 1.0]), 0.01)
    assert dist.lowpass_body is None
    acc = np.array([0.1, 0.0, 1.0])
    meas, density, lowpassed = acc_measurement(acc, dist, 3e-5, 0.1, 0.2, 0.0, 3e-4)
    assert meas is acc and not lowpassed and density == pytest.approx(3e-5 + 2 * 0.1 * 0.2)


@pytest.mark.parametrize("raw_power,expect_lowpassed", [(0.0, False), (0.5, True)])
def test_the_measurement_with_the_smaller_density_is_chosen(raw_power, expect_lowpassed):
    dist = AccDisturbance(0.5, lowpass_s=1.0)
    for _ in range(100):
        dist.update((1.0, 0.0, 0.0, 0.0), np.array([0.0, 0.0, 1.0]), 0.01)
    drift = lowpass_drift_density(1.0, 3e-4)
    meas, density, lowpassed = acc_measurement(np.array([0.3, 0.0, 1.0]), dist, 3e-5, 0.1, raw_power, drift, 3e-4)
    assert lowpassed is expect_lowpassed
    raw = 3e-5 + 2 * 0.1 * raw_power
    residual = lowpass_residual_density(dist.lowpass_density, 1.0, 3e-4)
    assert density == pytest.approx(min(raw, 3e-5 + residual + drift))


def test_residual_density_of_a_bounded_velocity():
    tau, q = 1.0, 3e-4
    meet = tau * tau * q  # where the filter's time constant sqrt(L / Q) equals the low-pass's
    # below it, and without process noise, the Gauss-Markov density stands
    assert lowpass_residual_density(0.5 * meet, tau, q) == 0.5 * meet
    assert lowpass_residual_density(1e-2, tau, 0.0) == 1e-2
    # continuous where the two meet, then smaller and still increasing
    assert lowpass_residual_density(meet * (1 + 1e-9), tau, q) == pytest.approx(meet)
    densities = [lowpass_residual_density(d, tau, q) for d in (1e-3, 1e-2, 1e-1)]
    assert all(r < d for r, d in zip(densities, (1e-3, 1e-2, 1e-1))) and densities == sorted(densities)
    # self-consistent: L = L_gm tau / T with the time constant T = sqrt(L / Q) of that L
    for gm, r in zip((1e-3, 1e-2, 1e-1), densities):
        assert r == pytest.approx(gm * tau / math.sqrt(r / q))


@pytest.mark.parametrize("freq_hz", [0.5, 2.0])
def test_residual_density_is_still_conservative_for_a_bounded_velocity(freq_hz):
    # A sustained translation of 0.5 g (velocity bounded), low-passed with 1 s. A filter that
    # weighs the low-passed sample with the corrected density L corrects with the time
    # constant T = sqrt(L / Q); its error is the residual low-passed with T. The measured error
    # variance stays below what L predicts, L / (2 T), which in turn is below the
    # Gauss-Markov density's prediction at the same T.
    dt, tau, q = 0.01, 1.0, 3e-4
    dist = AccDisturbance(0.5, lowpass_s=tau)
    residual_x = []
    for tk in np.arange(0.0, 60.0, dt):
        dist.update((1.0, 0.0, 0.0, 0.0), np.array([0.5 * math.sin(2 * math.pi * freq_hz * tk), 0.0, 1.0]), dt)
        residual_x.append(dist.lp[0])
    density = lowpass_residual_density(dist.lowpass_density, tau, q)
    T = math.sqrt(density / q)
    alpha, error, errors = dt / T, 0.0, []
    for x in residual_x:
        error += alpha * (x - error)
        errors.append(error)
    measured = float(np.var(errors[len(errors) // 2:]))
    assert measured < density / (2 * T) < dist.lowpass_density / (2 * T)


def test_drift_density_is_the_rate_noise_random_walk_over_one_window():
    assert lowpass_drift_density(1.0, 3e-4) == pytest.approx(2 * 3e-4)
    assert lowpass_drift_density(2.0, 3e-4) == pytest.approx(2 * 2 * 2 * 3e-4)  # grows as lowpass_s^2
    assert lowpass_drift_density(0.0, 3e-4) == 0.0


def test_the_frame_follows_the_gyro_through_skipped_samples():
    # Every third accelerometer sample is missing (a filter skips its update): the frame must
    # still turn with those steps' rate increments, or the low-passed direction goes wrong.
    dt, incs, acc, grav = _turning_body_with_translation(seconds=10.0, amp_g=0.0)
    dist = AccDisturbance(0.5, lowpass_s=1.0)
    for k, (dq, a) in enumerate(zip(incs, acc)):
        if k % 3 == 2:
            dist.turn(dq)
        else:
            dist.update(dq, a, dt)
            last = k
    assert math.degrees(math.acos(min(1.0, dist.lowpass_body @ grav[last]))) < 0.1


def test_lowpass_lag_predicts_the_error_of_a_miscalibrated_gyro():
    # A body turning on all axes; the gyro has a bias and scale error the filter does not know
    # (estimates zero). The strapdown frame drifts, and the low-passed direction lags gravity by
    # what the Jacobians of the lag it carries (`LowpassLag`) predict from the errors (to first order).
    dt, tau = 0.005, 1.0
    ds = np.array([0.01, -0.015, 0.008])
    db = np.array([0.004, -0.003, 0.002])  # rad/s
    dist = AccDisturbance(0.5, lowpass_s=tau, lag=True)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for k in range(int(8.0 / dt)):
        t = (k + 0.5) * dt
        w = np.array([1.5 * math.sin(1.3 * t), 2.0 * math.cos(0.7 * t), 1.0 * math.sin(2.1 * t + 0.4)])
        q = quat.multiply(q, quat.from_rotvec(w * dt))  # the true orientation
        measured = w / (1.0 + ds) + db  # true rate = (1 + ds) (measured - db)
        # accelerometer: gravity only; the lag advances with the rate the frame turns with
        dist.update(quat.exp_floats(*(measured * dt)), quat.gravity_in_body(q), dt, measured, np.ones(3))
    g_body = quat.gravity_in_body(q)
    error = dist.lowpass_body - g_body
    H_b, H_s = dist.lag_jacobian(quat.skew(g_body))
    predicted = H_b @ db + H_s @ ds
    assert np.linalg.norm(error) > 2e-3  # a lag worth modelling (0.1 deg and more)
    assert np.linalg.norm(error - predicted) < 0.05 * np.linalg.norm(error)
