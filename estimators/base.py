"""The one interface every estimator implements.

Batch-first outside, streaming inside (VQF's `offlineVQF` + `update`, FilterPy's
`batch_filter`): `Estimator.estimate(imu, init_quat_wxyz) -> Trajectory` sees the whole
recording; recursive filters derive from `RecursiveEstimator` and only write `reset` and
`step`, which the base class loops over the samples.

Parameters are a frozen dataclass per estimator (`Params`), with units in the field names
(VQF). `fusion.estimators.params` builds them from command-line text and rejects unknown names.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from fusion.types import ImuSamples, Trajectory


@dataclass(frozen=True)
class NoParams:
    """For estimators without parameters."""


class Estimator(ABC):
    """Estimates `R_world_body` for every IMU sample.

    Subclasses set `Params` (a frozen dataclass) and implement `estimate`.
    `causal` is False for smoothers (they see the future); reports say so.
    """

    Params: ClassVar[type] = NoParams
    causal: ClassVar[bool] = True

    def __init__(self, params: Any = None) -> None:
        if params is None:
            params = self.Params()
        if not isinstance(params, self.Params):
            raise TypeError(f"{type(self).__name__} takes {self.Params.__name__}, got {type(params).__name__}")
        self.params = params

    @abstractmethod
    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """Orientation at every sample of `imu`.

        imu: calibrated samples (t (N,), gyr_rad_s (N, 3), acc_g (N, 3), gyr_valid (N,)).
        init_quat_wxyz: (4,) orientation at `imu.t[0]`, `R_world_body`.
        Returns a `Trajectory` on `imu.t`; its first row is `init_quat_wxyz` for causal
        estimators (a smoother may move it).
        """


class RecursiveEstimator(Estimator):
    """A filter: `reset` once, then one `step` per sample interval.

    `estimate` calls `step(k)` for k = 0 .. N-2; step k propagates with the gyro reading for
    the interval [t[k], t[k+1]] (`ImuSamples.interval_rates`: gyro sample k + 1 or k, as the
    recording's `gyr_timing` says) over `dt[k] = t[k+1] - t[k]`, corrects with the
    accelerometer sample k + 1, and returns the orientation at `t[k+1]`. Subclasses keep the step lean: state in
    preallocated arrays, no per-step object construction.
    """

    @abstractmethod
    def reset(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> None:
        """Set the initial state (and precompute whatever the steps share)."""

    @abstractmethod
    def step(self, k: int, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        """Advance from t[k] to t[k+1]; return the (4,) quaternion at t[k+1].

        gyr_rad_s: (3,) gyro reading for [t[k], t[k+1]], rad/s. dt_s: t[k+1] - t[k].
        acc_g: (3,) accelerometer sample k + 1, g. gyr_valid: whether that gyro reading is usable.
        """

    def diagnostics(self) -> dict[str, Any]:
        """Extras for the trajectory (e.g. covariance traces), collected after the loop."""
        return {}

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        n = len(imu)
        out = np.empty((n, 4))
        out[0] = init_quat_wxyz
        self.reset(imu, np.asarray(init_quat_wxyz, dtype=float))
        (gyr, valid), acc, dt = imu.interval_rates(), imu.acc_g, imu.dt
        step = self.step
        for k in range(n - 1):
            out[k + 1] = step(k, gyr[k], dt[k], acc[k + 1], valid[k])
        return Trajectory(imu.t, out, diagnostics=self.diagnostics())
