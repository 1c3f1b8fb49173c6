"""What the Kalman filters `ekf`, `ukf` and `ukf-bias` share: the initial error state and its
noise (`initial_quaternion`, `error_state_covariances`), and `KalmanFilter`, whose `step` is the
one sequence of every filter's step and whose `estimate` runs either the base class's loop of
that `step` or the compiled loop of the same sequence (`_compiled_ekf.estimate`,
`_compiled_ukf.estimate`) over the whole recording.

The step, written once here (`KalmanFilter.step`), for `ekf` and the UKFs alike:

    predict           the filter's own (`_predict`: Jacobians for `ekf`, sigma points for the UKFs)
    before updates    the filter's own (`_before_updates`: `ekf`'s velocity model)
    rest              `_rest`: the zero-rate bias update (filters with bias states)
    accelerometer     `_accel`: the gate, the disturbance model and the sample (raw or low-passed),
                      then the filter's own correction (`_acc_correct`)
    magnetometer      `_magnetometer`: gates, hard-iron fit, the heading-only update (9-D)
    scale test        `_scale_test`: Wald's test on the gyro scale (6-D, filters with scale states)
    finish            the filter's own (`_finish`: clip the calibration, repair the covariance)

A correction of the error state enters through the filter's `_inject`. The error state is
`[e, db, ds, dv][:N]`, its blocks named once in `_error_state` (`ErrorLayout`, `BIAS`, `SCALE`).
"""
from __future__ import annotations

import math
from typing import Any, ClassVar, NamedTuple

import numpy as np

from fusion.types import ImuSamples, Trajectory

from ..base import RecursiveEstimator
from .steps._error_state import ATTITUDE, BIAS, SCALE, UNESTIMATED_VAR, ErrorLayout, axes_mask
from .steps._accel import AccStep, SlowDisturbance, acc_variance_scale, accelerometer_update_input
from .steps._magnetometer import heading_update, heading_variance, magnetometer_input
from .steps._rest import REST_STATE, bias_rest_update
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
    layout = ErrorLayout.of(n)
    P0, Q_rate, Q_invalid = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    P0[ATTITUDE, ATTITUDE] = np.eye(3) * p.init_var_rad2
    Q_rate[ATTITUDE, ATTITUDE] = np.eye(3) * p.process_noise_rad2_s
    Q_invalid[ATTITUDE, ATTITUDE] = np.eye(3) * p.invalid_gyr_var_rad2_s2
    if layout.bias:
        P0[BIAS, BIAS] = np.eye(3) * p.init_bias_var_rad2_s2
        Q_rate[BIAS, BIAS] = np.eye(3) * p.bias_walk_rad2_s3
    if layout.scale:
        on = axes_mask(p.scale_axes)
        P0[SCALE, SCALE] = np.diag(np.where(on, p.init_scale_var, UNESTIMATED_VAR))
        Q_rate[SCALE, SCALE] = np.diag(np.where(on, p.scale_walk_1_s, 0.0))
    return P0, Q_rate, Q_invalid


class Motion(NamedTuple):
    """What a filter's prediction (`KalmanFilter._predict`) tells the updates after it."""

    valid: bool  # the gyro reading was integrated (usable and finite)
    dq: tuple  # the step's rotation exp(theta / 2), 4 floats, body frame
    theta: tuple  # theta, the step's rotation vector (3 floats, rad, body; zeros when not integrated)
    u: Any  # `ekf`: the bias-corrected rate (3,) rad/s the prediction integrated (None: not integrated)


class KalmanFilter(RecursiveEstimator):
    """A recursive filter with a numpy `step` (the reference) and a compiled kernel of the same
    loop (`params.impl == "compiled"`).

    `step` is the sequence every filter runs (module docstring); a subclass supplies its parts:
    `_predict`, `_before_updates`, `_acc_correct`, `_finish`, and the access to its state the
    shared updates need (`_cov`, `_attitude`, `_bias`, `_scale`, `_vertical`, `_inject`,
    `_lag_rate`, `_rate_noise`, `_slow`). Its `reset` sets `layout` (its `ErrorLayout`), `_dist`
    (its `AccDisturbance`), `_rest` (its `RestDetector` or None), `_scale_test`, and with a
    magnetometer `_mag` and `_hard_iron`; its `current()` has the covariance "cov" (whose size
    sizes the kernel's outputs). It implements `_run_kernel`, and names in `LAST_ROW` the
    per-sample attributes of `current()` that the kernel records (diagnostics key -> attribute),
    so that after a compiled run the filter is in the state of the last sample, as after the loop
    of `step`. `step` takes the gyro reading through `_usable` (the online stuck-gyro check),
    which the compiled path applies to the whole recording first.
    """

    LAST_ROW: ClassVar[dict[str, str]] = {"acc_var_g2": "acc_var", "at_rest": "at_rest", "nis": "nis",
                                          "acc_lowpassed": "lowpassed"}

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        if self.params.impl == "compiled":
            from . import _compiled  # numba is imported when a compiled filter is built

            _compiled.load()  # compile or load the kernels here, not in the first (timed) estimate

    magnetometer = False  # 9-D where the recording has a magnetometer (the heading-only update)

    # ------------------------------------------------------------------ the step, once for every filter
    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool,
             mag_ut: np.ndarray | None = None) -> np.ndarray:
        """`RecursiveEstimator.step`, plus mag_ut: (3,) the magnetometer sample at the step's end,
        uT, body frame, or None (no magnetometer, or no valid sample): the heading update of a
        filter with `magnetometer` (the others ignore it). The sequence of the module docstring."""
        gyr_valid = self._usable(gyr_rad_s, dt_s, acc_g, gyr_valid)
        self.acc_var, self.at_rest, self.nis, self.guarded, self.lowpassed = math.nan, False, math.nan, False, False
        self.mag_used = self.hard_iron_used = False
        motion = self._predict(gyr_rad_s, dt_s, gyr_valid)
        self._before_updates(acc_g, dt_s)
        self._rest_update(gyr_rad_s, acc_g, dt_s, motion)
        self._acc_update(gyr_rad_s, acc_g, dt_s, motion)
        if (self.magnetometer and mag_ut is not None and math.isfinite(mag_ut[0]) and math.isfinite(mag_ut[1])
                and math.isfinite(mag_ut[2])):
            self._mag_update(mag_ut, dt_s, motion)
        self._scale_test_update()
        return self._finish()

    def _rest_update(self, gyr_rad_s: np.ndarray, acc_g: np.ndarray, dt_s: float, motion: Motion) -> None:
        """Zero-rate update at rest (VQF, Sec. 3.4; `_rest`): after `rest_time_s` still, the gyro
        reads the bias. H = [0, I, 0] is linear, so this is the exact Kalman update for every filter."""
        if self.layout.bias and motion.valid and self._rest is not None and self._rest.update(gyr_rad_s, acc_g, dt_s):
            dx, self._cov = bias_rest_update(self._bias(), self._cov, gyr_rad_s, self.params.rest_noise_rad2_s / dt_s)
            self._inject(dx)
            self.at_rest = True

    def _acc_update(self, gyr_rad_s: np.ndarray, acc_g: np.ndarray, dt_s: float, motion: Motion) -> None:
        """The accelerometer update (`_accel`): the gate's factor, then the sample and its variance
        (`accelerometer_update_input`: the disturbance model, raw or low-passed) and the filter's
        own correction (`_acc_correct`); a step without one (gated out, not finite, `acc=false`)
        still turns the disturbance model's strapdown frame."""
        p = self.params
        scale = acc_variance_scale(acc_g, p.gate, p.gate_g) if p.use_acc else math.inf
        u, gain = self._lag_rate(gyr_rad_s, motion)  # the lag's inputs (`AccDisturbance.update`)
        if scale < math.inf:
            h = self._vertical()  # gravity in the body frame at the estimate
            step = AccStep(dq=motion.dq, dt=dt_s, scale=scale, rate_noise=self._rate_noise(gyr_rad_s, motion),
                           u=u, gain=gain)
            meas, r, self.lowpassed = accelerometer_update_input(self._dist, acc_g, step, self._slow(h), p)
            self.acc_var = r
            self._acc_correct(meas, r, h)
        else:
            self.n_skipped += 1
            if p.disturbance_corr_s > 0.0:  # the strapdown frame follows the gyro through skipped updates
                self._dist.turn(motion.dq, dt_s, u, gain)

    def _mag_update(self, mag_ut: np.ndarray, dt_s: float, motion: Motion) -> None:
        """9-D: the heading-only magnetometer update (`_magnetometer`: the gates, the hard-iron fit,
        `heading_update`) with one finite sample (3,) uT, body frame. The first ends the scale test
        undecided ("Scale test" in `ekf`)."""
        p = self.params
        self._scale_test.stop()
        q = self._attitude()
        usable, east, north, self.hard_iron_used = magnetometer_input(p, self._mag, self._hard_iron, q, self._cov,
                                                                      mag_ut, dt_s)
        if usable:
            r = heading_variance(p, q, *motion.theta, dt_s)  # grown with the rate about the vertical
            dx, self._cov = heading_update(q, self._cov, self.layout.n, east, north, r)
            self._inject(dx)
            self.mag_used = True

    def _scale_test_update(self) -> None:
        """Wald's test: a scale error, or a calibrated gyro? (`_scale_test.ScaleTest`; off without
        scale states, and once decided)."""
        vertical = self._vertical() if self.params.heading_free else None
        dx, self._cov = self._scale_test.step(self._scale(), self._cov, vertical)
        if dx is not None:
            self._inject(dx)

    # ------------------------------------------------------------------ what each filter supplies
    def _predict(self, gyr_rad_s: np.ndarray, dt_s: float, gyr_valid: bool) -> Motion:
        """Propagate the state and its covariance over the step; -> what the updates need of it."""
        raise NotImplementedError

    def _before_updates(self, acc_g: np.ndarray, dt_s: float) -> None:
        """What the filter does between its prediction and the updates (nothing by default)."""

    def _acc_correct(self, meas: np.ndarray, r: float, h: np.ndarray) -> None:
        """The filter's accelerometer correction with the measurement meas (3,) g of variance r g^2
        per axis, h the gravity direction at the estimate (`_vertical`); sets `nis` (and `guarded`)."""
        raise NotImplementedError

    def _finish(self) -> np.ndarray:
        """The end of a step: clip the calibration, repair the covariance; -> the (4,) quaternion."""
        raise NotImplementedError

    def _inject(self, dx: np.ndarray) -> None:
        """Inject an error-state correction dx (N,) into the state."""
        raise NotImplementedError

    def _lag_rate(self, gyr_rad_s: np.ndarray, motion: Motion) -> tuple[Any, Any]:
        """The low-pass lag's inputs: the bias-corrected rate (3,) (None: not integrated) and the
        scale gain `1 + s` (3,) (`AccDisturbance.update`)."""
        raise NotImplementedError

    def _rate_noise(self, gyr_rad_s: np.ndarray, motion: Motion) -> float:
        """The rate noise density, rad^2/s, that the accelerometer's low-pass weighs (the gyro's Q)."""
        return self.params.process_noise_rad2_s

    def _slow(self, h: np.ndarray) -> SlowDisturbance:
        """The slow external acceleration's inputs (`SlowDisturbance`; none by default)."""
        return SlowDisturbance.none()

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
