"""A magnetometer for the simulated recording, and the disturbances the 9-D tests put on it
(`tests/test_mag_filters.py`, `tests/test_mag_smoothers.py`)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion.types import ImuSamples

FIELD_ENU_UT = np.array([0.0, 16.0, -41.0])  # 44 uT, dip 69 deg (BROAD's lab: 44 uT, 69 deg)
Z_BIAS_RAD_S = np.radians(0.2)  # an uncalibrated z gyro bias (BROAD: about 0.2 deg/s): the 6-D heading drifts


def sim_with_magnetometer() -> tuple[ImuSamples, Rotation]:
    """The built-in simulated recording (180 s, 100 Hz) with a 0.2 deg/s z gyro bias added after
    its calibration and a noisy (1 uT) magnetometer reading `FIELD_ENU_UT` along the truth; and
    the true rotation at each sample."""
    rec = datasets.load("sim")
    rot, inside = rec.truth.interpolate(rec.imu.t)
    assert inside.all()
    mag = rot.inv().apply(FIELD_ENU_UT) + np.random.default_rng(7).normal(0.0, 1.0, (len(rec.imu), 3))
    imu = rec.imu.replace(gyr_rad_s=rec.imu.gyr_rad_s + [0.0, 0.0, Z_BIAS_RAD_S], mag_ut=mag)
    return imu, rot


def q0(rot: Rotation) -> np.ndarray:
    """The true initial orientation, (4,) wxyz."""
    return rot[0].as_quat(scalar_first=True)


def with_magnet_carried(imu: ImuSamples, start: int, stop: int, offset_ut=(30.0, -25.0, 12.0)) -> ImuSamples:
    """A magnet fixed to the sensor over samples start..stop: a constant body-frame offset."""
    mag = np.array(imu.mag_ut)
    mag[start:stop] += offset_ut
    return imu.replace(mag_ut=mag)


def with_magnet_passed(imu: ImuSamples, rot: Rotation, centre: int, width: int,
                       peak_ut=(35.0, 10.0, 20.0)) -> ImuSamples:
    """The sensor carried past a magnet fixed in the room: a world-frame field that swells and
    fades (Gaussian in time, `width` samples), read in the body frame."""
    k = np.arange(len(imu))
    world = np.exp(-0.5 * ((k - centre) / width) ** 2)[:, None] * np.asarray(peak_ut)
    return imu.replace(mag_ut=np.array(imu.mag_ut) + rot.inv().apply(world))


def with_field_bent(imu: ImuSamples, rot: Rotation, degrees: float, start_s: float, stop_s: float,
                    ramp_s: float = 5.0) -> tuple[ImuSamples, np.ndarray]:
    """The field's direction turned about the vertical by up to `degrees` from start_s to stop_s
    (ramps of ramp_s at each end; s from the first sample), its norm and dip unchanged: steel or a
    magnet in the room that bends the field without changing its strength or dip; 1 uT noise.
    Returns the samples and the bend's fraction (0-1) at each sample."""
    t = imu.t - imu.t[0]
    bend = np.clip((t - start_s) / ramp_s, 0.0, 1.0) - np.clip((t - stop_s) / ramp_s, 0.0, 1.0)
    turn = Rotation.from_rotvec(np.radians(degrees) * bend[:, None] * [0.0, 0.0, 1.0])
    mag = rot.inv().apply(turn.apply(FIELD_ENU_UT)) + np.random.default_rng(7).normal(0.0, 1.0, (len(imu), 3))
    return imu.replace(mag_ut=mag), bend
