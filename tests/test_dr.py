"""Dead reckoning: quaternion kinematics integrated exactly."""
import numpy as np
from scipy.spatial.transform import Rotation

from fusion.estimators import build
from fusion.types import ImuSamples


def constant_rate_imu(rate, seconds, n, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, seconds, n)
    t[1:-1] += rng.uniform(-jitter, jitter, n - 2)
    gyr = np.tile(rate, (n, 1))
    acc = np.tile([0.0, 0.0, 1.0], (n, 1))
    return ImuSamples(t, gyr, acc)


def test_constant_rate_rotates_by_rate_times_duration():
    """A constant rate w for T seconds rotates by w * T about w, to 1e-9, with jittery dt."""
    rate = np.array([0.3, -0.2, 0.5])
    seconds = 7.3
    imu = constant_rate_imu(rate, seconds, 5001, jitter=2e-4)
    q0 = Rotation.from_euler("ZYX", [40, 10, -20], degrees=True)
    traj = build("dr").estimate(imu, q0.as_quat(scalar_first=True))
    expected = q0 * Rotation.from_rotvec(rate * seconds)
    assert (Rotation.from_quat(traj.quat_wxyz[-1], scalar_first=True).inv() * expected).magnitude() < 1e-9
    # and at every intermediate sample
    inter = q0 * Rotation.from_rotvec(np.outer(imu.t - imu.t[0], rate))
    assert (traj.rotation().inv() * inter).magnitude().max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(traj.quat_wxyz, axis=1), 1.0, atol=1e-12)


def test_invalid_gyro_samples_are_not_integrated():
    imu = constant_rate_imu([0.0, 0.0, 1.0], 2.0, 201)
    valid = np.ones(201, bool)
    valid[50:150] = False
    traj = build("dr").estimate(imu.replace(gyr_valid=valid), np.array([1.0, 0, 0, 0]))
    yaw = traj.rotation()[-1].as_rotvec()[2]
    np.testing.assert_allclose(yaw, 1.0, atol=1e-9)  # only half of the 2 s counted


def test_input_not_modified():
    imu = constant_rate_imu([0.1, 0.2, 0.3], 1.0, 11)
    before = imu.gyr_rad_s.copy()
    build("dr").estimate(imu, np.array([1.0, 0, 0, 0]))
    assert np.array_equal(imu.gyr_rad_s, before)
    assert not imu.gyr_rad_s.flags.writeable
