"""The built-in simulated recording: exact truth, deterministic, through the real path."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.estimators import build
from fusion import datasets
from fusion.calibration import calibrate
from fusion.sim import T0_S, SimSettings, _Motion, simulate


def test_body_rate_is_the_derivative_of_the_truth():
    motion = _Motion(SimSettings())
    t = np.linspace(5, 170, 400)
    h = 1e-5
    r0, r1 = motion.rotation(t - h), motion.rotation(t + h)
    numeric = (r0.inv() * r1).as_rotvec() / (2 * h)  # body-frame rate
    # central differences lose ~1e-6 rad/s where the envelope's second derivative jumps
    np.testing.assert_allclose(motion.body_rate(t), numeric, atol=1e-5)


def test_deterministic_and_realistic():
    a, truth_a = simulate()
    b, _ = simulate()
    assert np.array_equal(a.counts, b.counts) and np.array_equal(a.t, b.t)
    rec = datasets.load("sim")
    assert rec.id == "sim" and len(rec.imu) == 18000
    rate = np.degrees(np.linalg.norm(rec.imu.gyr_rad_s, axis=1))
    assert 150 < rate.max() < 400  # hand-held: a few hundred deg/s
    assert np.all((a.counts >= 0) & (a.counts <= 1023)) and np.array_equal(a.counts, np.round(a.counts))
    dt = np.diff(a.t)
    assert dt.min() > 0.007 and dt.max() < 0.013 and dt.std() > 1e-4  # jittery stamps


@pytest.mark.parametrize("settings", [SimSettings(duration_s=20.0),
                                      SimSettings(duration_s=20.0, imu_rate_hz=286.0, truth_rate_hz=120.0, gyr_timing="end",
                                                  freezes_s=((5.0, 6.5),), truth_clock_offset_s=0.01)],
                         ids=["default", "286 Hz, end timing, a freeze, a clock offset"])
def test_the_recording_does_not_depend_on_the_block_size(settings, monkeypatch):
    """The signals are computed a block of samples at a time (bounded memory on long recordings):
    blocks of 7 samples give the recording of one block, bit for bit, at the edges too."""
    whole_raw, whole_truth = simulate(settings)
    monkeypatch.setattr("fusion.sim._BLOCK", 7)
    raw, truth = simulate(settings)
    for a, b in [(raw.t, whole_raw.t), (raw.counts, whole_raw.counts), (truth.t, whole_truth.t),
                 (truth.quat_wxyz, whole_truth.quat_wxyz)]:
        np.testing.assert_array_equal(a, b)


def test_dead_reckoning_on_exact_rates_tracks_the_truth():
    """With no scale errors, integrating the simulated gyro follows the truth; what remains is
    discretisation, quantisation and the bias estimated from the first rest."""
    raw, truth = simulate(SimSettings(duration_s=30, gyro_sensitivity_ratio=(1, 1, 1)))
    from fusion.calibration import calibrate
    from fusion.estimators import build
    from fusion.evaluation.scoring.metrics import score

    imu = calibrate(raw).apply(raw)
    q0, _ = truth.interpolate(imu.t[:1])
    est = build("dr").estimate(imu, q0.as_quat(scalar_first=True)[0])
    assert score(truth, est).rmse_deg["total"] < 0.82  # 0.716 deg measured, + 15 % (was 1.5)


def _exact(timing: str, duration_s: float = 30.0) -> SimSettings:
    """A noiseless, error-free board: no noise, no quantisation, datasheet sensitivities."""
    return SimSettings(duration_s=duration_s, gyr_timing=timing, gyro_sensitivity_ratio=(1, 1, 1),
                       acc_noise_counts=0.0, gyro_noise_counts=0.0, quantise=False)


@pytest.mark.parametrize("timing", ["start", "end"])
def test_gyro_sample_is_the_mean_rate_over_its_interval(timing):
    """Sample k is rotvec(R(t_a)^-1 R(t_b)) / (t_b - t_a) over [t_k, t_k+1] ("start") or
    [t_k-1, t_k] ("end"), and the recording says which."""
    s = _exact(timing, 20.0)
    raw, _ = simulate(s)
    assert raw.gyr_timing == timing
    imu = calibrate(raw).apply(raw)
    assert imu.gyr_timing == timing
    t = imu.t - T0_S
    r = _Motion(s).rotation(t)
    between = (r[:-1].inv() * r[1:]).as_rotvec() / np.diff(t)[:, None]
    rate, _ = imu.interval_rates()
    np.testing.assert_allclose(rate, between, atol=1e-12)
    # close to, but not, the instantaneous rate at the interval's midpoint
    mid = _Motion(s).body_rate(0.5 * (t[1:] + t[:-1]))
    assert 1e-6 < np.abs(rate - mid).max() < 1e-2  # rad/s; 1.3e-3 measured


@pytest.mark.parametrize("timing", ["start", "end"])
def test_dead_reckoning_is_exact_when_the_declared_timing_matches(timing):
    raw, _ = simulate(_exact(timing))
    imu = calibrate(raw).apply(raw)
    truth = _Motion(_exact(timing)).rotation(imu.t - T0_S)
    q0 = truth[0].as_quat(scalar_first=True)
    est = build("dr").estimate(imu, q0)
    # Rounding only: 3,000 steps of ~eps each, accumulated, make ~7e-13 rad; 1.04e-12 measured (was 1e-9)
    assert (truth.inv() * est.rotation()).magnitude().max() < 1e-11
    other = {"start": "end", "end": "start"}[timing]
    wrong = build("dr").estimate(imu.replace(gyr_timing=other), q0)
    assert np.degrees((truth.inv() * wrong.rotation()).magnitude().max()) > 1.0  # 1.9 deg measured


def test_unknown_timing_is_an_error():
    with pytest.raises(ValueError, match="gyr_timing"):
        SimSettings(gyr_timing="middle")
