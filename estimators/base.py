"""The one interface every estimator implements.

Batch-first outside, streaming inside (VQF's `offlineVQF` + `update`, FilterPy's
`batch_filter`): `Estimator.estimate(imu, init_quat_wxyz) -> Trajectory` sees the whole
recording; recursive filters derive from `RecursiveEstimator` and only write `reset` (from the
initial orientation alone) and `step`, which the base class loops over the samples; a
streaming user calls them directly.

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
    `causal` is False for smoothers (they see the future); reports say so. `partial` is True for
    an estimate that may have no orientation (NaN rows) at some samples, which are then not scored
    (a trajectory read from a file covers its own time span only). `magnetometer` is True for an
    estimator that fuses the magnetometer where the recording has one (9-D estimation; its rows
    say so, and BROAD's protocol scores them without removing a heading offset).
    """

    Params: ClassVar[type] = NoParams
    causal: ClassVar[bool] = True
    partial: ClassVar[bool] = False
    magnetometer: ClassVar[bool] = False  # fuses `ImuSamples.mag_ut` when the recording has one (9-D)

    def __init__(self, params: Any = None) -> None:
        if params is None:
            params = self.Params()
        if not isinstance(params, self.Params):
            raise TypeError(f"{type(self).__name__} takes {self.Params.__name__}, got {type(params).__name__}")
        self.params = params

    def for_recording(self, recording_id: str) -> "Estimator":
        """The estimator to run on the recording `recording_id` (default: this one). An estimator
        read from files, one per recording (`fusion.estimators.adapters.trajectory_file`), picks its file here."""
        return self

    @abstractmethod
    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """Orientation at every sample of `imu`.

        imu: calibrated samples (t (N,), gyr_rad_s (N, 3), acc_g (N, 3), gyr_valid (N,)).
        init_quat_wxyz: (4,) orientation at `imu.t[0]`, `R_world_body`.
        Returns a `Trajectory` on `imu.t`; its first row is `init_quat_wxyz` for causal
        estimators (a smoother may move it).
        """


class RecursiveEstimator(Estimator):
    """A streaming filter: `reset(init_quat_wxyz)` once, then `step(...)` per sample interval, forever.

    Neither needs the recording: `reset` takes the initial orientation only, and a step takes
    one gyro reading, its interval and one accelerometer sample. `estimate` (the batch
    interface) loops `step` over a recording: step k propagates with the gyro reading for the
    interval [t[k], t[k+1]] (`ImuSamples.interval_rates`: gyro sample k + 1 or k, as the
    recording's `gyr_timing` says) over `dt[k] = t[k+1] - t[k]`, corrects with the
    accelerometer sample k + 1, and returns the orientation at `t[k+1]`. A filter with
    `magnetometer = True` on a recording with one also gets the magnetometer sample k + 1
    (`step(..., mag_ut)`, None where it is not valid). After the reset and
    after every step it records `current()` (e.g. the covariance), so the trajectory's
    diagnostics hold one row per sample; the filter itself keeps no history.
    """

    @abstractmethod
    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        """Set the initial state. init_quat_wxyz: (4,) orientation, `R_world_body`."""

    @abstractmethod
    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        """Advance by one sample interval; return the (4,) quaternion at its end.

        gyr_rad_s: (3,) gyro reading for the interval, rad/s, body. dt_s: its length, s.
        acc_g: (3,) accelerometer sample at its end, g, body. gyr_valid: whether that gyro
        reading is usable.
        """

    def reset_for(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> None:
        """The reset `estimate` makes: `reset(init_quat_wxyz)`. A filter that needs a per-recording
        constant (e.g. a nominal sample rate) overrides this to pass it to its `reset` explicitly."""
        self.reset(init_quat_wxyz)

    def current(self) -> dict[str, Any]:
        """Per-sample quantities of the current state (e.g. `{"cov": P}`), recorded by `estimate`
        after the reset and after every step into (N, ...) diagnostics arrays."""
        return {}

    def diagnostics(self) -> dict[str, Any]:
        """Extras for the trajectory that are not per sample (e.g. counts), after the loop."""
        return {}

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        n = len(imu)
        out = np.empty((n, 4))
        out[0] = init_quat_wxyz
        self.reset_for(imu, np.asarray(init_quat_wxyz, dtype=float))
        history = {}
        for key, value in self.current().items():
            value = np.asarray(value)
            history[key] = np.empty((n,) + value.shape, value.dtype)
            history[key][0] = value
        (gyr, valid), acc, dt = imu.interval_rates(), imu.acc_g, imu.dt
        step, current = self.step, self.current
        if self.magnetometer and imu.has_mag:  # 9-D: the magnetometer sample at each step's end (None: invalid)
            mag, mag_valid = imu.mag_ut, imu.mag_valid
            for k in range(n - 1):
                out[k + 1] = step(gyr[k], dt[k], acc[k + 1], valid[k], mag[k + 1] if mag_valid[k + 1] else None)
                for key, value in current().items():
                    history[key][k + 1] = value
        elif history:
            for k in range(n - 1):
                out[k + 1] = step(gyr[k], dt[k], acc[k + 1], valid[k])
                for key, value in current().items():
                    history[key][k + 1] = value
        else:
            for k in range(n - 1):
                out[k + 1] = step(gyr[k], dt[k], acc[k + 1], valid[k])
        return Trajectory(imu.t, out, diagnostics={**history, **self.diagnostics()})
