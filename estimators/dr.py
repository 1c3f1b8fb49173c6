"""Dead reckoning: integrate the gyro, ignore the accelerometer.

Quaternion kinematics, `q_{k+1} = q_k * exp([0, w_k dt_k / 2])` with the real
per-sample `dt_k` and `w_k` the gyro reading for [t_k, t_{k+1}] (`ImuSamples.interval_rates`), evaluated for the whole recording at once: the increments are one
vectorised `from_rotvec`, their running product a parallel scan
(`fusion.quaternion.cumulative_product`). Gyro samples marked invalid contribute no rotation.
"""
from __future__ import annotations

import numpy as np

from fusion import quaternion as quat
from fusion.types import ImuSamples, Trajectory

from .base import Estimator


class DeadReckoning(Estimator):
    """Gyro integration from the initial orientation; drifts, but is exact for exact rates."""

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        rate, valid = imu.interval_rates()
        rotvec = rate * imu.dt[:, None]  # body-frame increments, rad
        rotvec[~valid] = 0.0
        steps = np.concatenate([np.asarray(init_quat_wxyz, dtype=float)[None], quat.from_rotvec(rotvec)])
        return Trajectory(imu.t, quat.cumulative_product(steps))
