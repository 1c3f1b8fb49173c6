"""Rate invariance and disturbance robustness of the recursive filters (continuous-time noise,
adaptive accelerometer noise)."""
from __future__ import annotations

import numpy as np
import pytest

from fusion.estimators import build
from fusion.estimators.params import EstimatorSpec
from fusion import quaternion as quat

from motion_helpers import turning_body
from optional_helpers import require_module
from test_ukf import inclination_deg


def motion(rate_hz: float, seconds: float = 30.0, seed: int = 0, shake_g: float = 0.0, bias=(0.0, 0.0, 0.0),
           same_sensor: bool = False):
    """The same smooth rotation sampled at `rate_hz`; optional 3 Hz linear shaking (g, world).

    White noise of std 0.003 rad/s (gyro) and 0.005 g (accelerometer) per sample; with
    `same_sensor`, those are the stds at 100 Hz and the noise densities (3e-4 rad/s/sqrt(Hz),
    5e-4 g/sqrt(Hz)) stay the same at any rate: the same sensor sampled faster, whose per-sample
    std grows with sqrt(rate) (Sola 2017, Sec. 5.4; `FilterParams`)."""
    n = int(seconds * rate_hz) + 1
    t = np.arange(n) / rate_hz
    w = np.stack([1.5 * np.sin(1.3 * t), 1.0 * np.cos(0.7 * t + 0.3), 0.8 * np.sin(0.9 * t + 1.0)], axis=1)
    q0 = quat.normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    ext_world = shake_g * np.stack([np.sin(2 * np.pi * 3.0 * t), np.cos(2 * np.pi * 2.3 * t), 0.5 * np.sin(2 * np.pi * 1.7 * t)], axis=1)
    k = np.sqrt(rate_hz / 100.0) if same_sensor else 1.0
    return turning_body(t, w, q0, ext_world, gyr_std=0.003 * k, acc_std=0.005 * k, bias=bias, seed=seed, source="synthetic")


def relative_difference_at_100_and_286_hz(spec: str) -> tuple[float, list[float]]:
    """(RMSE at 286 Hz - RMSE at 100 Hz) / the larger, inclination, for the same sensor and motion."""
    errs = []
    for rate in (100.0, 285.71):
        imu, truth = motion(rate, bias=(0.01, -0.01, 0.005), same_sensor=True)
        est = build(spec).estimate(imu, truth[0])
        errs.append(float(np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2))))
    return (errs[1] - errs[0]) / max(errs), errs


# The same sensor (noise densities) at 100 and 286 Hz must give the same error. The tolerance is
# what the noise alone makes of it: over seeds 0-4 the relative difference scatters with a
# standard deviation of 0.032 (ekf:tauc=0, ukf-bias:tauc=0) and 0.014 (ukf:tauc=0) about +0.016
# and +0.013 (seed 0, used here: -0.002, -0.003 and +0.004); 0.10 is three of the larger. Noise
# densities read as per-sample variances move it by 0.35 (ukf:tauc=0 fed the same per-sample
# stds at both rates). The old test fed the same per-sample stds (a quieter sensor at 286 Hz) and
# allowed 25 % + 0.05 deg.
RATE_TOLERANCE = 0.10


@pytest.mark.parametrize("spec", ["ekf:tauc=0", "ukf-bias:tauc=0", "ukf:tauc=0"])
def test_same_sensor_at_100_and_286_hz_gives_the_same_error(spec):
    rel, errs = relative_difference_at_100_and_286_hz(spec)
    assert abs(rel) < RATE_TOLERANCE, errs


# With the disturbance model (the defaults), the running variance `d` of the accelerometer
# (`_accel.AccDisturbance`) includes the sensor's white noise, whose per-sample variance grows
# with the rate, and the filters read it as an external acceleration of density `2 tauc d`: the
# median accelerometer density the filters use (`acc_var_g2 * dt`) is 5.1e-5 g^2 s at 100 Hz and
# 8.0e-5 at 286 Hz (ekf, ukf-bias; ukf 1.5e-4 and 2.9e-4) for the same sensor. Measured over seeds
# 0-9: the inclination RMSE is 21 +- 2 % higher at 286 Hz (ekf, ukf-bias; ukf 20 +- 3 %); seed 0:
# +0.209 (ekf, ukf-bias), +0.198 (ukf).
@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="the adaptive accelerometer noise counts the sensor's white noise as disturbance, "
                          "which grows with the rate: 21 % higher inclination RMSE at 286 Hz with the same sensor")
@pytest.mark.parametrize("spec", ["ekf", "ukf-bias", "ukf"])
def test_same_sensor_at_100_and_286_hz_gives_the_same_error_with_the_disturbance_model(spec):
    rel, errs = relative_difference_at_100_and_286_hz(spec)
    assert abs(rel) < RATE_TOLERANCE, errs


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_steady_state_acc_variance_scales_with_rate(spec):
    # R is a density: the per-step variance times dt is the same at both rates.
    r = []
    for rate in (100.0, 285.71):
        imu, truth = motion(rate, seconds=5.0)
        est = build(spec + ":tauc=0").estimate(imu, truth[0])
        r.append(np.nanmedian(est.diagnostics["acc_var_g2"]) / rate)
    assert np.isclose(r[0], r[1], rtol=1e-6)


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias", "ukf"])
def test_large_linear_acceleration_stays_below_gyro_integration(spec):
    imu, truth = motion(285.71, seconds=60.0, shake_g=0.5, bias=(0.0035, -0.0035, 0.002))
    est = build(spec).estimate(imu, truth[0])
    dr = build("dr").estimate(imu, truth[0])
    e_f = np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2))
    e_dr = np.sqrt(np.mean(inclination_deg(truth, dr.quat_wxyz) ** 2))
    assert e_f < e_dr, (e_f, e_dr)


# Regression on the hardest BROAD trials (fast rotation, fast translation, fast combined):
# measured ekf 0.793 / 0.547 / 1.290 deg inclination RMSE (BROAD protocol; the README's table),
# dr 2.62 / 10.45 / 11.06; the bounds add 15 % to ekf's (they were 1.8 / 3.5 / 6.2, from the
# first ekf's 1.60 / 3.11 / 5.56).
@pytest.mark.parametrize("trial,bound", [("06_undisturbed_fast_rotation_A", 0.92),
                                         ("15_undisturbed_fast_translation_A", 0.63),
                                         ("21_undisturbed_fast_combined", 1.49)])
def test_ekf_on_broad_trials_beats_gyro_integration(data_dir, trial, bound):
    from fusion.evaluation.compare import run_one
    from fusion import datasets

    path = data_dir / "broad"
    if not path.is_dir():
        pytest.fail(f"FUSION_DATA={data_dir} holds no broad/ folder")
    if (path / f"{trial}.hdf5").is_file():
        require_module("h5py")
    rec = datasets.load(f"broad/{trial}", data_dir)
    ekf = run_one(rec, EstimatorSpec("ekf"))
    dr = run_one(rec, EstimatorSpec("dr"))
    assert ekf.rmse_deg["inclination"] <= bound
    assert ekf.rmse_deg["inclination"] < dr.rmse_deg["inclination"]
