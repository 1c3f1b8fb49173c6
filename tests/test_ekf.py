"""Tests of the multiplicative error-state EKF (`ekf`)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.estimators import ESTIMATORS, build
from fusion.estimators.dr import DeadReckoning
from fusion.estimators.filters.ekf import EKF, EKFParams
from fusion import quaternion as quat

from motion_helpers import turning_body
from test_ukf import inclination_deg, synthetic


def test_registry():
    assert ESTIMATORS["ekf"] is EKF


@pytest.mark.parametrize("impl", ["compiled", "numpy"])
@pytest.mark.parametrize("bias", [True, False])
def test_without_accelerometer_and_noise_equals_dead_reckoning(bias, impl):
    imu, _ = synthetic(400)
    valid = np.ones(len(imu), bool)
    valid[100:130] = False
    imu = imu.replace(gyr_valid=valid)
    q0 = quat.normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    params = EKFParams(use_acc=False, process_noise_rad2_s=0.0, init_var_rad2=0.0, estimate_bias=bias,
                       estimate_scale=bias, impl=impl)
    est = EKF(params).estimate(imu, q0)
    ref = DeadReckoning().estimate(imu, q0)
    assert np.max(np.abs(quat.canonical(est.quat_wxyz) - quat.canonical(ref.quat_wxyz))) < 1e-9


def test_measurement_jacobian_matches_finite_differences():
    # h(q exp(e/2)) ~ h(q) + [h]x e, the H the update uses
    q = quat.normalize(np.array([0.8, 0.3, -0.4, 0.2]))
    h = quat.gravity_in_body(q)
    H = np.array([[0.0, -h[2], h[1]], [h[2], 0.0, -h[0]], [-h[1], h[0], 0.0]])
    eps = 1e-7
    num = np.stack([(quat.gravity_in_body(quat.multiply(q, quat.from_rotvec(eps * np.eye(3)[i]))) - h) / eps for i in range(3)], axis=1)
    assert np.allclose(H, num, atol=1e-6)


# Inclination RMSE bounds: measured 1.03 deg (ekf, gate=skip, gate=off: the gate never acts on this
# noise) and 1.11 (no bias or scale states), + 15 % (was 1.5 for all).
@pytest.mark.parametrize("spec,bound", [("ekf", 1.19), ("ekf:bias=false,scale=false", 1.28), ("ekf:gate=skip", 1.19),
                                        ("ekf:gate=off", 1.19)])
def test_tracks_synthetic_motion(spec, bound):
    imu, truth = synthetic(1500, noise=0.01, bias=(0.02, -0.01, 0.03), seed=5)
    est = build(spec).estimate(imu, truth[0])
    assert np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2)) < bound
    assert np.allclose(np.linalg.norm(est.quat_wxyz, axis=1), 1.0, atol=1e-12)
    cov = est.diagnostics["cov"]
    assert np.allclose(cov, np.swapaxes(cov, 1, 2))
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)


def test_ekf_and_ukf_bias_agree_closely():
    imu, truth = synthetic(1500, noise=0.01, bias=(0.02, -0.01, 0.03), seed=8)
    a = build("ekf").estimate(imu, truth[0])
    b = build("ukf-bias").estimate(imu, truth[0])
    angle = np.degrees(np.linalg.norm(quat.relative_rotvec(a.quat_wxyz, b.quat_wxyz), axis=1))
    # The same model and densities, covariance propagated by Jacobians or sigma points: 0.016 deg
    # apart at most (measured), + 25 % (was 0.5 deg).
    assert angle.max() < 0.02


def test_recovers_after_nan_and_saturated_stretch():
    imu, truth = synthetic(1500, noise=0.005, seed=7)
    gyr, acc = imu.gyr_rad_s.copy(), imu.acc_g.copy()
    gyr[500:600] = np.nan
    acc[520:560] = np.inf
    acc[560:600] = 8.0
    est = build("ekf").estimate(imu.replace(gyr_rad_s=gyr, acc_g=acc), truth[0])
    assert np.all(np.isfinite(est.quat_wxyz))
    # 0.351 deg measured over the last 300 samples, + 15 % (was 2.0); 0.345 with the slow external
    # acceleration (0.236 with tauslow=0; 1.30 if the low-pass's hold of the saturated samples counted as one)
    assert np.sqrt(np.mean(inclination_deg(truth[1200:], est.quat_wxyz[1200:]) ** 2)) < 0.41


@pytest.mark.parametrize("spec", ["ekf:Q=-1", "ekf:R=0", "ekf:Qb=-1e-6", "ekf:Pb0=inf", "ekf:gate=maybe", "ekf:gate_g=-1",
                                  "ekf:sigma=kraft", "ekf:tauslow=-1", "ekf:tauslow=inf"])
def test_bad_parameters_raise(spec):
    with pytest.raises(ValueError):
        build(spec)


@pytest.mark.parametrize(
    "spec,match",
    [("ekf:bias=false,scale=false,Qb=1e-6", "ekf: bias_walk_rad2_s3 applies only with estimate_bias=true; it is ignored with estimate_bias=false"),
     ("ekf:bias=false,scale=false,rest_time_s=2", "rest_time_s applies only with estimate_bias=true"),
     ("ekf:scale=false,Ps0=1e-3", "ekf: init_scale_var applies only with estimate_scale=true"),
     ("ekf:bias=false,scale=false,tauslow=3", "slow_disturbance_corr_s applies only with estimate_bias=true"),
     ("ekf:gate_g=0.5", "ekf: gate_g applies only with gate=skip or inflate")],
)
def test_parameter_ignored_by_the_chosen_option_raises(spec, match):
    with pytest.raises(ValueError, match=match):
        build(spec)
    build(spec.replace("gate_g", "gate=skip,gate_g") if "gate_g" in spec else spec.replace("bias=false,scale=false,", "").replace("scale=false,", ""))


def _fast_turning_with_translation(seconds=120.0, rate_hz=200.0, seed=1):
    """Turning at up to 7 rad/s about all axes while shaken at 0.3 g (velocity bounded), with an
    exactly calibrated gyro."""
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    w = 5.0 * np.stack([0.8 * np.sin(0.5 * t), -0.6 * np.cos(0.3 * t), 1.2 + 0.3 * np.sin(0.2 * t)], axis=1)
    q0 = quat.normalize(np.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0]))
    ext = np.stack([0.3 * np.sin(2 * np.pi * 1.5 * t), 0.3 * np.cos(2 * np.pi * 1.05 * t), np.zeros(len(t))], axis=1)
    return turning_body(t, w, q0, ext, gyr_std=0.005, acc_std=0.01, seed=seed, source="fast turning with translation")


@pytest.mark.parametrize("spec, scale_bound", [("ekf:lpcal=true", 8.4e-4), ("ukf-bias", 2.4e-4), ("ekf", 4.6e-4),
                                                   ("ekf:sprt=0", 1.1e-3)])
def test_fast_turning_with_translation_keeps_the_lowpass_and_the_scale(spec, scale_bound):
    # The raw samples carry 0.3 g of translation, so the filters take the low-passed one. Its lag
    # behind a drifting frame is modelled (`_accel.LowpassLag`), not added to its noise as
    # rate^2 x scale variance, so fast turning does not push the filters back to the raw samples,
    # and the low-passed sample shows that the gyro needs no scale correction (`ekf:lpcal=true`,
    # `ukf-bias`; the default `ekf` leaves its calibration to the velocity states, which show it, and
    # its scale test accepts the calibrated gyro).
    imu, truth = _fast_turning_with_translation()
    est = build(spec).estimate(imu, truth[0])
    second_half = slice(len(imu) // 2, None)
    # Measured: the low-passed sample on every update of the second half (1.0), 0.101 / 0.153 /
    # 0.082 / 0.102 deg inclination RMSE and a largest scale estimate of 7.3e-4 / 1.8e-4 / 4.0e-4 / 9.6e-4
    # (ekf:lpcal=true with its 2 s low-pass / ukf-bias with 1 s / ekf / ekf without the scale test;
    # ekf:lpcal=true with 1 s: 0.140 deg, 2.0e-4). The bounds add 15 % to the larger inclination and to
    # each scale (they were 0.22 deg and 2e-3).
    assert est.diagnostics["acc_lowpassed"][second_half].mean() > 0.9
    assert np.sqrt(np.mean(inclination_deg(truth[second_half], est.quat_wxyz[second_half]) ** 2)) < 0.18
    assert np.max(np.abs(est.diagnostics["gyr_scale"][-1])) < scale_bound


def test_the_scale_tests_likelihood_ratio_is_the_bayes_factor_of_the_two_priors():
    # A linear Gaussian model of two scale corrections, y = A s + noise: the ratio of the data's
    # marginal likelihoods under the priors N(0, P1 I) and N(0, P0 I), computed directly, equals
    # ScaleTest's expression in the P1 posterior; its update gives the P0 posterior.
    from fusion.estimators.filters.steps._scale_test import ScaleTest

    rng = np.random.default_rng(4)
    P1, P0, noise = 1e-2, 1e-4, 0.02
    A = rng.normal(0.0, 0.3, (40, 2))
    for s_true in ([0.0, 0.0], [-0.08, 0.05], [0.005, -0.01]):
        y = A @ s_true + rng.normal(0.0, noise, 40)

        def log_evidence(prior):
            C = A @ A.T * prior + np.eye(40) * noise**2
            return -0.5 * (y @ np.linalg.solve(C, y) + np.linalg.slogdet(C)[1])

        def posterior(prior):
            C = np.linalg.inv(A.T @ A / noise**2 + np.eye(2) / prior)
            return C @ A.T @ y / noise**2, C

        s1, C1 = posterior(P1)
        P = np.eye(11) * 0.3  # [attitude, bias, scale, velocity], the scale block of x and y from the model
        P[6:8, 6:8] = C1
        P[6:8, :3] = 1e-3  # correlated with the attitude
        P[:3, 6:8] = 1e-3
        test = ScaleTest(P1, P0, 0.1, np.array([True, True, False]))
        s = np.array([*s1, 0.0])
        assert test.log_likelihood_ratio(s, P) == pytest.approx(log_evidence(P1) - log_evidence(P0), abs=1e-9)
        dx, P_after = test.update(s, P, None)
        s0, C0 = posterior(P0)
        np.testing.assert_allclose(s1 + dx[6:8], s0, atol=1e-12)
        np.testing.assert_allclose(P_after[6:8, 6:8], C0, atol=1e-12)
        assert dx[8] == 0.0 and P_after[8, 8] == P[8, 8]  # the untested z axis is left alone


def _scale_test_motion(gyr_gain):
    """The fast turning of `_fast_turning_with_translation` for 60 s, the gyro's x and y reading gyr_gain times
    the rate (the axes `ekf` estimates the scale of by default)."""
    imu, truth = _fast_turning_with_translation(seconds=60.0)
    return imu.replace(gyr_rad_s=imu.gyr_rad_s * [gyr_gain, gyr_gain, 1.0]), truth


@pytest.mark.parametrize("name", ["ekf", "ukf-bias"])
def test_the_scale_test_keeps_a_scale_error_and_accepts_a_calibrated_gyro(name):
    # A gyro reading 8 % high (the course board's error): the test accepts H1 (scale error) and
    # the filter estimates the correction 1/1.08 - 1 = -7.4 % on the tested axes. An exactly
    # calibrated gyro: it accepts H0, and the scale posterior is within the calibrated prior's 1 %.
    # Measured (ekf): H1 after 3.1 s, -7.44 and -7.37 %; H0 after 5.6 s, 0.01 and -0.05 %, sigmas 0.5 and 0.8 %.
    # (The numpy step makes the same decisions: `tests/test_compiled.py`, `ekf:sprt=0.3`.)
    imu, truth = _scale_test_motion(1.08)
    d = build(name).estimate(imu, truth[0]).diagnostics
    assert d["scale_decision"] == 1 and d["scale_llr"][-1] >= np.log(9.0)
    np.testing.assert_allclose(d["gyr_scale"][-1, :2], 1 / 1.08 - 1, atol=0.01)
    imu, truth = _scale_test_motion(1.0)
    est = build(name).estimate(imu, truth[0])
    d = est.diagnostics
    decided = np.flatnonzero(d["scale_llr"] <= -np.log(9.0))
    assert d["scale_decision"] == -1 and len(decided) and decided[0] < len(imu) // 2
    assert np.all(np.sqrt(np.diagonal(d["cov"][-1])[6:8]) < 0.01)
    assert np.max(np.abs(d["gyr_scale"][-1])) < 2e-3
    # undecided, the filter is the one without the test
    off = build(f"{name}:sprt=0").estimate(imu, truth[0])
    np.testing.assert_array_equal(est.quat_wxyz[:decided[0]], off.quat_wxyz[:decided[0]])


@pytest.mark.parametrize("name", ["ekf", "ukf-bias"])
def test_with_a_magnetometer_the_scale_test_does_not_run(name):
    # The 9-D filter keeps the 10 % prior (module docstring): the test ends undecided at the first
    # magnetometer sample, and the filter is the one without the test, bit for bit.
    imu, truth = _scale_test_motion(1.0)
    field_enu_ut = np.array([0.0, 20.0, -40.0])
    imu = imu.replace(mag_ut=Rotation.from_quat(truth, scalar_first=True).inv().apply(field_enu_ut))
    with_test = build(name).estimate(imu, truth[0])
    without = build(f"{name}:sprt=0").estimate(imu, truth[0])
    assert with_test.diagnostics["mag_used"].any()
    assert with_test.diagnostics["scale_decision"] == 0 and np.isnan(with_test.diagnostics["scale_llr"][1:]).all()
    np.testing.assert_array_equal(with_test.quat_wxyz, without.quat_wxyz)
    # the same motion without the magnetometer decides (`test_the_scale_test_keeps_...` above)
    assert build(name).estimate(imu.replace(mag_ut=None), truth[0]).diagnostics["scale_decision"] == -1


@pytest.mark.parametrize("impl", ["compiled", "numpy"])
def test_the_velocity_states_follow_the_translation(impl):
    # Shaken at 0.3 g at 1.05 and 1.5 Hz, far above the bounded-velocity prior's time scale
    # (vb / (sv g), about 10 s): the velocity states carry the translation, to its amplitude.
    imu, truth = _fast_turning_with_translation(seconds=60.0)
    est = build(f"ekf:impl={impl}").estimate(imu, truth[0])
    f_world = Rotation.from_quat(np.array(truth), scalar_first=True).apply(np.array(imu.acc_g))[:, :2] * 9.80665
    v_true = np.concatenate([np.zeros((1, 2)), np.cumsum(f_world[1:] * imu.dt[:, None], axis=0)])
    half = slice(len(imu) // 2, None)
    for axis in range(2):
        est_v = est.diagnostics["velocity_m_s"][half, axis]
        true_v = v_true[half, axis]
        assert np.corrcoef(est_v, true_v)[0, 1] > 0.97
        assert abs(np.std(est_v) / np.std(true_v) - 1.0) < 0.05


@pytest.mark.parametrize("lpcal", [False, True])
def test_with_the_velocity_states_the_lowpassed_sample_corrects_the_attitude_only(monkeypatch, lpcal):
    # The velocity pseudo-measurement taken out (the states stay) and no rest update: the
    # accelerometer update is the only one that can move the bias and scale.
    monkeypatch.setattr(EKF, "_velocity_step", lambda self, q, P, acc_g, dt_s: (q, P))
    imu, truth = _fast_turning_with_translation(seconds=20.0)
    est = build(f"ekf:impl=numpy,rest_time_s=inf,lpcal={str(lpcal).lower()}").estimate(imu, truth[0])
    d = est.diagnostics
    lowpassed = d["acc_lowpassed"][1:]
    moved = np.abs(np.diff(np.concatenate([d["gyr_bias_rad_s"], d["gyr_scale"]], axis=1), axis=0)).max(axis=1)
    assert lowpassed.sum() > 1000 and (~lowpassed).sum() > 10
    assert moved[~lowpassed].max() > 0.0  # the raw samples correct the calibration either way
    if lpcal:
        assert moved[lowpassed].max() > 0.0
    else:
        assert moved[lowpassed].max() == 0.0


def test_without_the_velocity_model_there_are_no_velocity_states():
    imu, truth = _fast_turning_with_translation(seconds=5.0)
    for spec in ("ekf:Rv=inf", "ekf:acc=false"):
        est = build(spec).estimate(imu, truth[0])
        assert est.diagnostics["cov"].shape[1:] == (9, 9)
        np.testing.assert_array_equal(est.diagnostics["velocity_m_s"], 0.0)
    assert build("ekf").estimate(imu, truth[0]).diagnostics["cov"].shape[1:] == (11, 11)


def _slow_rocking_with_translation(seconds=150.0, rate_hz=200.0, seed=2):
    """A hand-held motion: the board rocks +-10 deg about x and +-20 deg about y (under 1 rad/s)
    while it is moved back and forth at 0.15 g (velocity bounded), with an exactly calibrated gyro."""
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    w = np.stack([0.6 * np.cos(2 * np.pi * 0.55 * t), 0.9 * np.cos(2 * np.pi * 0.4 * t), 0.1 * np.cos(2 * np.pi * 0.05 * t)],
                 axis=1)
    ext = np.stack([0.15 * np.sin(2 * np.pi * 0.5 * t), 0.15 * np.sin(2 * np.pi * 0.37 * t + 0.5), np.zeros(len(t))], axis=1)
    return turning_body(t, w, np.array([1.0, 0.0, 0.0, 0.0]), ext, gyr_std=0.005, acc_std=0.01, seed=seed,
                        source="slow rocking with translation")


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="the scale factors absorb translation that shares the frequencies of a "
                   "slow rocking motion: with the 10 % prior, ekf fits a scale error of 13 % to a calibrated "
                   "gyro and loses degrees of inclination (known limitation, see the ekf module docstring)")
@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_slow_rocking_with_translation_invents_no_scale(spec):
    imu, truth = _slow_rocking_with_translation()
    est = build(spec).estimate(imu, truth[0])
    assert np.max(np.abs(est.diagnostics["gyr_scale"][-1])) < 0.02
    assert np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2)) < 1.0


# Inclination RMSE measured 0.758 / 0.560 / 0.048 deg, + 15 % (was 1.0 for all); with scale
# states, above: 1.72 / 1.86 deg, and scale estimates of 9 / 15 %. ekf with a 1 s low-pass (its
# default before the cross-validated 2 s): 0.548 without scale states, 1.76 with them: the longer
# low-pass costs this simulated rocking 0.2 deg without scale states.
@pytest.mark.parametrize("spec,bound", [("ekf:scale=false", 0.87), ("ukf-bias:scale=false", 0.65), ("gd", 0.056)])
def test_slow_rocking_with_translation_without_scale_states(spec, bound):
    # The same motion without scale states in the filters: the limitation above is the scale's,
    # not the disturbance model's. The smoothers keep a scale error only where it lowers their
    # cost significantly (`BatchSmoother.significant_scales`), and here it does not.
    imu, truth = _slow_rocking_with_translation()
    est = build(spec).estimate(imu, truth[0])
    assert np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2)) < bound


def _slow_translation(seconds=90.0, rate_hz=100.0, peak_g=0.1, seed=4):
    """A body carried along straight horizontal lines by minimum-jerk moves of 3-6 s (Flash & Hogan
    1985: x(s) = D (10 s^3 - 15 s^4 + 6 s^5), peak acceleration 5.77 D / T^2 = peak_g), one after
    another in random directions, while it turns slowly (+-10 deg over tens of seconds); a gyro and
    an accelerometer with the course board's white noise (0.01 rad/s, 0.01 g per sample) and a bias."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    ext = np.zeros((len(t), 3))
    start = 3.0
    while start < seconds - 6.0:
        T = rng.uniform(3.0, 6.0)
        inside = (t >= start) & (t < start + T)
        s = (t[inside] - start) / T
        heading = rng.uniform(0.0, 2.0 * np.pi)
        profile = peak_g / 5.7735 * (60 * s - 180 * s**2 + 120 * s**3)
        ext[inside, :2] = np.outer(profile, [np.cos(heading), np.sin(heading)])
        start += T
    w = np.radians(10.0) * 2 * np.pi / 30.0 * np.stack([np.cos(2 * np.pi * t / 30.0), np.sin(2 * np.pi * t / 23.0),
                                                        0.5 * np.cos(2 * np.pi * t / 41.0)], axis=1)
    return turning_body(t, w, np.array([1.0, 0.0, 0.0, 0.0]), ext, gyr_std=0.01, acc_std=0.01,
                        bias=(0.004, -0.003, 0.002), seed=seed, source="slow translation")


@pytest.mark.parametrize("impl", ["compiled", "numpy"])
def test_a_sustained_acceleration_is_not_taken_for_tilt(impl):
    # A slow translation changes little within the 0.5 s disturbance window: without the slow
    # external acceleration (tauslow=0) the raw sample keeps a small noise and the attitude follows
    # the tilted specific force. Inclination RMSE measured 1.63 deg against 2.99 (VQF 3.59; seeds 1-3:
    # 1.36-1.43 against 2.57-2.64); bounds: the measured value + 15 %, and the ratio 0.55 + 0.1.
    imu, truth = _slow_translation()
    rmse = {}
    for spec in ("ekf:tauslow=2", "ekf:tauslow=0"):
        est = build(f"{spec},impl={impl}").estimate(imu, truth[0])
        rmse[spec] = np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2))
    assert rmse["ekf:tauslow=2"] < 1.88
    assert rmse["ekf:tauslow=2"] < 0.65 * rmse["ekf:tauslow=0"]
