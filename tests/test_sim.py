"""The built-in simulated recording: exact truth, deterministic, through the real path."""
import numpy as np
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion.sim import SimSettings, _Motion, simulate


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


def test_dead_reckoning_on_exact_rates_tracks_the_truth():
    """With no scale errors, integrating the simulated gyro follows the truth; what remains is
    discretisation, quantisation and the bias estimated from the first rest."""
    raw, truth = simulate(SimSettings(duration_s=30, gyro_sensitivity_ratio=(1, 1, 1)))
    from fusion.calibration import calibrate
    from estimators import build
    from evaluation.metrics import score

    imu = calibrate(raw).apply(raw)
    q0, _ = truth.interpolate(imu.t[:1])
    est = build("dr").estimate(imu, q0.as_quat(scalar_first=True)[0])
    assert score(truth, est).rmse_deg["total"] < 1.5  # 0.7 deg measured
