"""What the Kalman filters `ekf`, `ukf` and `ukf-bias` share around their steps: the initial
error state and its noise (`initial_quaternion`, `error_state_covariances`), and `KalmanFilter`,
whose `estimate` runs either the base class's loop of the numpy `step` or one compiled kernel
(`_compiled_ekf`, `_compiled_ukf`) over the whole recording.

The error state is `[e, db, ds][:n]` (n = 3, 6 or 9): the body-frame attitude error (rad), the
gyro bias error (rad/s) and the gyro scale-factor error (dimensionless), as the module
docstrings of `ekf` and `ukf` define them.
"""
from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from fusion.types import ImuSamples, Trajectory

from ..base import RecursiveEstimator
from ._error_state import UNESTIMATED_VAR, axes_mask
from .steps._rest import REST_STATE
from .steps._stuck import STUCK_THRESHOLDS, stuck_gyro_update


def initial_quaternion(owner: str, init_quat_wxyz: Any) -> np.ndarray:
    """The (4,) unit quaternion a filter's `reset` starts from; a ValueError naming `owner` for
    anything that is not a finite non-zero (4,) quaternion."""
    q0 = np.asarray(init_quat_wxyz, dtype=float)
    if q0.shape != (4,) or not np.all(np.isfinite(q0)) or np.linalg.norm(q0) == 0.0:
        raise ValueError(f"{owner}: init_quat_wxyz must be a finite non-zero (4,) quaternion, got {q0!r}")
    return q0 / np.linalg.norm(q0)


def error_state_covariances(p: Any, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(P0, Q_rate, Q_invalid)`, each (n, n) and block diagonal, for parameters `p` (a
    `FilterParams`, a `BiasFilterParams` when n > 3) and error dimension n:

    P0: the initial covariance: `init_var_rad2` on the attitude, `init_bias_var_rad2_s2` on
        the bias, `init_scale_var` on the scale axes estimated (`scale_axes`; the others
        `UNESTIMATED_VAR`, so that they stay at their calibration).
    Q_rate: the process-noise densities (a step of dt adds `Q_rate dt`): gyro noise
        `process_noise_rad2_s`, bias walk `bias_walk_rad2_s3`, scale walk `scale_walk_1_s`.
    Q_invalid: what a step without a usable gyro reading adds per dt^2 on the attitude
        (`invalid_gyr_var_rad2_s2`).
    """
    P0, Q_rate, Q_invalid = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    P0[:3, :3] = np.eye(3) * p.init_var_rad2
    Q_rate[:3, :3] = np.eye(3) * p.process_noise_rad2_s
    Q_invalid[:3, :3] = np.eye(3) * p.invalid_gyr_var_rad2_s2
    if n > 3:
        P0[3:6, 3:6] = np.eye(3) * p.init_bias_var_rad2_s2
        Q_rate[3:6, 3:6] = np.eye(3) * p.bias_walk_rad2_s3
    if n > 6:
        on = axes_mask(p.scale_axes)
        P0[6:, 6:] = np.diag(np.where(on, p.init_scale_var, UNESTIMATED_VAR))
        Q_rate[6:, 6:] = np.diag(np.where(on, p.scale_walk_1_s, 0.0))
    return P0, Q_rate, Q_invalid


class KalmanFilter(RecursiveEstimator):
    """A recursive filter with a numpy `step` (the reference) and a compiled kernel of the same
    loop (`params.impl == "compiled"`).

    A subclass's `reset` sets `_dist` (its `AccDisturbance`) and `_rest` (its `RestDetector` or
    None), and its `current()` has the covariance "cov" (whose size sizes the kernel's outputs);
    it implements `_run_kernel`, and names in `LAST_ROW`
    the per-sample attributes of `current()` that the kernel records (diagnostics key ->
    attribute), so that after a compiled run the filter is in the state of the last sample, as
    after the loop of `step`. Its `step` takes the gyro reading through `_usable` (the online
    stuck-gyro check), which the compiled path applies to the whole recording first.
    """

    LAST_ROW: ClassVar[dict[str, str]] = {"acc_var_g2": "acc_var", "at_rest": "at_rest", "nis": "nis",
                                          "acc_lowpassed": "lowpassed"}

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        if self.params.impl == "compiled":
            from . import _compiled  # numba is imported when a compiled filter is built

            _compiled.load()  # compile or load the kernels here, not in the first (timed) estimate

    def _usable(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> bool:
        """Whether `step` integrates this gyro reading: `gyr_valid`, and with `stuck_gyro_check`
        not stuck (`_stuck.stuck_gyro_update`, whose state `reset` starts afresh)."""
        if not self.params.stuck_gyro_check:
            return gyr_valid
        return gyr_valid and not stuck_gyro_update(self._stuck, gyr_rad_s, acc_g, dt_s, gyr_valid, *STUCK_THRESHOLDS)

    def _unstuck(self, kernels: Any, imu: ImuSamples) -> ImuSamples:
        """`imu` with the readings `_usable` would refuse marked invalid (the compiled check over
        the whole recording, from the reset state, which it advances as `step` would)."""
        if not self.params.stuck_gyro_check:
            return imu
        gyr, valid = imu.interval_rates()
        stuck = kernels.stuck_intervals(gyr, imu.dt, np.ascontiguousarray(imu.acc_g[1:]), valid, self._stuck,
                                        *STUCK_THRESHOLDS)
        if not stuck.any():
            return imu
        first = 1 if imu.gyr_timing == "end" else 0
        gyr_valid = np.array(imu.gyr_valid)
        gyr_valid[first:first + len(stuck)] &= ~stuck
        return imu.replace(gyr_valid=gyr_valid)

    def _run_kernel(self, kernels: Any, imu: ImuSamples, out: Any, dist: np.ndarray, rest: np.ndarray) -> None:
        """Run the compiled kernel (`kernels` is the `_compiled` module) from the reset state over
        `imu`, filling `out` (`_compiled.Outputs`) and advancing the packed disturbance and rest
        states `dist` and `rest` in place; set the final state and the counts of `diagnostics`."""
        raise NotImplementedError

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """The base class's loop of `step` (any `impl` but "compiled"), or the same loop compiled
        (`_run_kernel`): the same trajectory and diagnostics either way."""
        if self.params.impl != "compiled":
            return super().estimate(imu, init_quat_wxyz)
        from . import _compiled  # numba is imported on first use

        self.reset_for(imu, np.asarray(init_quat_wxyz, dtype=float))
        imu = self._unstuck(_compiled, imu)
        out = _compiled.outputs(len(imu), len(self.current()["cov"]), init_quat_wxyz, self.current())
        dist = self._dist.state()
        rest = self._rest.state() if self._rest is not None else np.zeros(REST_STATE)
        self._run_kernel(_compiled, imu, out, dist, rest)
        self._dist.set_state(dist)
        if self._rest is not None:
            self._rest.set_state(rest)
        for key, attribute in self.LAST_ROW.items():
            setattr(self, attribute, getattr(out, key)[-1].item())
        history = {key: getattr(out, key) for key in self.current()}
        return Trajectory(imu.t, out.quat, diagnostics={**history, **self.diagnostics()})
