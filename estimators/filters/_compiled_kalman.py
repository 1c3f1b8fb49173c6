"""The one compiled loop of `KalmanFilter.step` (`ekf`, `ukf`, `ukf-bias`) over a whole recording:
`estimate`, the sequence of the step written once for the kernels, as `KalmanFilter.step` is for
the numpy filters:

    predict           `_compiled_ekf._predict` or `_compiled_ukf._predict` (`Settings.unscented`)
    before updates    `ekf`: `_compiled_ekf._velocity_step`
    rest              `_compiled_rest` (`update`, `bias_rest_update`)
    accelerometer     `_compiled_accel` (`acc_variance_scale`, `accelerometer_update_input`), then
                      `_compiled_ekf._acc_correct` or `_compiled_ukf._acc_correct`
    magnetometer      `_compiled_magnetometer` (`magnetometer_input`, `heading_variance`, `heading_update`)
    scale test        `_compiled_scale_test.step`
    finish            clip the calibration (`ekf`: renormalise q), repair the covariance, record

The state is `x = [q_wxyz, b, s]` (10,; the blocks a filter lacks stay zero), the velocity `v`
(2,; `ekf`) and the error covariance `P` (N, N), laid out as `_error_state` says; a correction
enters through `_inject` (`_compiled_ekf._correct` or `_compiled_ukf._inject`). Each line
implements a line of `KalmanFilter.step` and its parts, in the same order where the order matters
for rounding (`tests/test_compiled.py`: the numpy steps to 1e-10).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..kernels._compiled_linalg import repair_covariance
from ..kernels._compiled_quaternion import gravity_floats, normalize_floats
from ..kernels._numba import _clip, _jit, _sample, forget_stale, mirrors
from . import _compiled_ekf as ekf
from . import _compiled_ukf as ukf
from .steps import _compiled_accel as accel
from .steps import _compiled_magnetometer as magnetometer
from .steps import _compiled_rest as rest
from .steps import _compiled_scale_test as scale_test
from .steps._error_state import BIAS_AT, X_BIAS_AT, X_SCALE_AT
from .steps._scale_test import TEST_DECISION, TEST_LLR, TEST_ON

forget_stale(__file__)

# No numpy reference of their own: the work arrays of a run, and the recording of a step's row.
HELPERS = ("work", "_record")


class FilterState(NamedTuple):
    """A filter's state as the loop advances it in place."""

    x: np.ndarray  # (10,) [q_wxyz, b rad/s, s]; the blocks the filter lacks stay zero
    v: np.ndarray  # (2,) ekf's horizontal velocity, m/s, world x and y (zeros for the UKFs)
    P: np.ndarray  # (N, N) the error covariance


class Noise(NamedTuple):
    """A filter's noise and, for the UKFs, its sigma points' weights."""

    Qrate: np.ndarray  # (N, N) process-noise densities (`kalman_base.error_state_covariances`)
    Qbad: np.ndarray  # (N, N) what a step without a usable gyro reading adds per dt^2
    Wm: np.ndarray  # UKF: (2n + 1,) mean weights, centre first (ekf: unused)
    Wc: np.ndarray  # UKF: (2n + 1,) covariance weights


class Work(NamedTuple):
    """The work arrays of a run, allocated once (`work`); N rows for the error state, m = 2n + 1
    sigma points (the UKFs; none for `ekf`)."""

    F: np.ndarray  # (3, N) ekf: the first rows of the transition
    T: np.ndarray  # (3, N) ekf: F P scratch
    J: np.ndarray  # (3, 3) ekf: the right Jacobian times dt
    H: np.ndarray  # (3, N) the accelerometer's Jacobian (and `slow_power`'s scratch)
    PHt: np.ndarray  # (N, 3) P H^T (the UKFs' P_xz)
    S: np.ndarray  # (3, 3) the innovation covariance
    Sinv: np.ndarray  # (3, 3)
    K: np.ndarray  # (N, 3) the gain
    D: np.ndarray  # (N, 3) the Joseph form's scratch
    dx: np.ndarray  # (N,) an error-state correction
    L: np.ndarray  # (N, N) the covariance repair's (and the UKFs' square root's) scratch
    hi_fit: np.ndarray  # (4,) the hard-iron fit
    hi_work: np.ndarray  # (4, 5) its elimination
    Km: np.ndarray  # (N,) the heading update's gain
    Gm: np.ndarray  # (N,) ... and P H^T
    A: np.ndarray  # (n, n) UKF: P + Q
    off: np.ndarray  # (m, n) UKF: the sigma points' offsets
    sig: np.ndarray  # (m, n + 1) UKF: the propagated points
    Ep: np.ndarray  # (2n, 4) UKF: q exp(+-e_i / 2)
    err: np.ndarray  # (m, 3) UKF: the points' attitude errors about the mean
    res: np.ndarray  # (m, n) UKF: their error-state residuals
    Wres: np.ndarray  # (m, n) UKF: Wc res
    dZ: np.ndarray  # (m, 3) UKF: predicted measurements about their mean
    WdZ: np.ndarray  # (m, 3) UKF: Wc dZ


@_jit
def work(n, N, m):
    """The `Work` of a filter with n attitude and calibration rows, N rows and m sigma points."""
    return Work(F=np.zeros((3, N)), T=np.empty((3, N)), J=np.empty((3, 3)), H=np.zeros((3, N)), PHt=np.empty((N, 3)),
                S=np.empty((3, 3)), Sinv=np.empty((3, 3)), K=np.empty((N, 3)), D=np.empty((N, 3)), dx=np.empty(N),
                L=np.empty((N, N)), hi_fit=np.empty(4), hi_work=np.empty((4, 5)), Km=np.empty(N), Gm=np.empty(N),
                A=np.empty((n, n)), off=np.zeros((m, n)), sig=np.empty((m, n + 1)), Ep=np.empty((2 * n, 4)),
                err=np.empty((m, 3)), res=np.empty((m, n)), Wres=np.empty((m, n)), dZ=np.empty((m, 3)),
                WdZ=np.empty((m, 3)))


@mirrors("fusion.estimators.filters.kalman_base.KalmanFilter._inject")
def _inject(state, dx, o):
    """`KalmanFilter._inject`: the filter's own (`_compiled_ekf._correct`, `_compiled_ukf._inject`)."""
    if o.unscented:
        ukf._inject(state.x, dx, o)
    else:
        ekf._correct(state.x, state.v, dx, o)


@mirrors("fusion.estimators.filters.kalman_base.KalmanFilter.estimate")
def estimate(inp, state, noise, st, o, out):
    """`KalmanFilter.estimate` with impl=numpy: the loop of `KalmanFilter.step` over a recording.

    inp: the recording (`_numba.Inputs`: the interval rates and steps, the accelerometer, the
    magnetometer or none). state: the `FilterState`, advanced in place; noise: its `Noise`; st:
    the packed sensor states (`_compiled.SensorStates`: the disturbance estimator with its lag,
    the rest detector, the magnetometer's reference and sphere fit, the scale test), advanced in
    place; o: `_compiled.Settings`. Fills rows 1.. of the outputs `out` (`_compiled.Outputs`);
    returns (updates skipped, square-root recoveries, covariance repairs, mean-iteration cap hits).
    """
    x, v, P = state.x, state.v, state.P
    n = o.n
    N = n + o.nv
    w = work(n, N, 2 * n + 1 if o.unscented else 0)
    use_mag = inp.mag.shape[0] > 0
    skipped = 0
    sqrt_recovered = 0
    repaired = 0
    capped = 0
    for k in range(inp.dt.shape[0]):
        h = inp.dt[k]
        gx, gy, gz, ax, ay, az, ok = _sample(inp.gyr, inp.valid, inp.acc, k)
        gyr = (gx, gy, gz)
        acc = (ax, ay, az)
        # ---- predict (the filter's own), and what comes before the updates
        if o.unscented:
            dq, theta, u, iters, recovered = ukf._predict(x, P, gyr, ok, h, noise, st.dist, o, w)
            if recovered:
                sqrt_recovered += 1
            if iters >= o.mean_max_iter:
                capped += 1
        else:
            dq, theta, u, iters, recovered = ekf._predict(x, P, gyr, ok, h, noise, st.dist, o, w)
            if o.nv:  # the velocity model (`EKF._velocity_step`)
                ekf._velocity_step(P, x, v, acc, h, o, w)
                _inject(state, w.dx, o)
        # ---- rest (`KalmanFilter._rest_update`)
        at_rest = False
        if o.bias and ok and o.rest_on and rest.update(st.rest, gx, gy, gz, ax, ay, az, h, o.rest):
            # Zero-rate update at rest (VQF, Sec. 3.4): the gyro reads the bias.
            b = (x[X_BIAS_AT], x[X_BIAS_AT + 1], x[X_BIAS_AT + 2])
            rest.bias_rest_update(b, P, gyr, o.rest_noise / h, N, w)
            _inject(state, w.dx, o)
            at_rest = True
        # ---- accelerometer (`KalmanFilter._acc_update`)
        var = math.nan
        nis = math.nan
        guarded = False
        lowpassed = False
        scale = accel.acc_variance_scale(ax, ay, az, o.acc.gate, o.acc.gate_g) if o.use_acc else math.inf
        if o.unscented:  # the lag's inputs
            u, gain = ukf._lag_rate(x, gyr, o)
        else:
            u, gain = ekf._lag_rate(x, u, o)
        if scale < math.inf:
            hq = gravity_floats((x[0], x[1], x[2], x[3]))  # gravity in the body frame at the estimate
            rate_noise = o.process_noise  # ukf: plus the scale noise Qs w_i^2, a rate noise density too
            if ok and o.scale_noise > 0.0:
                rate_noise += o.scale_noise * max(gx * gx, gy * gy, gz * gz)
            step = accel.AccStep(dq, h, scale, rate_noise, u, gain)
            slow = accel.SlowDisturbance(o.slow_corr, hq, P[BIAS_AT:n, BIAS_AT:n], o.slow_scale_var)
            mx, my, mz, r, lowpassed = accel.accelerometer_update_input(st.dist, acc, step, slow, o.acc, w.H)
            var = r
            if o.unscented:
                nis = ukf._acc_correct(P, x, (mx, my, mz), r, hq, lowpassed, st.dist, noise, o, w)
            else:
                nis, guarded = ekf._acc_correct(P, x, v, (mx, my, mz), r, hq, lowpassed, st.dist, o, w)
        else:
            skipped += 1
            if o.acc.corr_s > 0.0:  # the strapdown frame follows the gyro through skipped updates
                accel.turn(st.dist, dq, h, u, gain, o.acc)
        # ---- magnetometer (`KalmanFilter._mag_update`; 9-D)
        mag_used = False
        hi_used = False
        if use_mag and inp.mag_ok[k + 1]:
            mx, my, mz = inp.mag[k + 1, 0], inp.mag[k + 1, 1], inp.mag[k + 1, 2]
            if math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz):
                if st.test[TEST_DECISION] == 0.0:  # 9-D: no scale test (`ScaleTest.stop`)
                    st.test[TEST_ON], st.test[TEST_LLR] = 0.0, math.nan
                q = (x[0], x[1], x[2], x[3])
                usable, east, north, hi_used = magnetometer.magnetometer_input(q, P, mx, my, mz, st.mag, st.hard_iron,
                                                                               o.mag, h, w.hi_fit, w.hi_work)
                if usable:
                    r_mag = magnetometer.heading_variance(q, theta[0], theta[1], theta[2], h, o.mag)
                    magnetometer.heading_update(P, n, N, q, east, north, r_mag, w.Km, w.Gm, w.dx)
                    _inject(state, w.dx, o)
                    mag_used = True
        # ---- Wald's test: a scale error, or a calibrated gyro? (`KalmanFilter._scale_test_update`)
        if o.test.axes and st.test[TEST_ON] == 1.0 and st.test[TEST_DECISION] == 0.0:
            q = (x[0], x[1], x[2], x[3])
            if scale_test.step(P, x[X_SCALE_AT:X_SCALE_AT + 3], st.test, q, o.test, o.heading_free, N, w):
                _inject(state, w.dx, o)
        # ---- finish (the filter's `_finish`)
        if o.bias:
            for i in range(X_BIAS_AT, X_BIAS_AT + 3):
                x[i] = _clip(x[i], -o.bias_max, o.bias_max)
        if o.scale:
            for i in range(X_SCALE_AT, X_SCALE_AT + 3):
                x[i] = _clip(x[i], -o.scale_max, o.scale_max)
        if not o.unscented:  # ekf renormalises once per step
            x[0], x[1], x[2], x[3] = normalize_floats((x[0], x[1], x[2], x[3]))
        if repair_covariance(P, N, o.cov, w.L):
            repaired += 1
        _record(out, k + 1, state, iters, (var, nis, st.test[TEST_LLR]), (at_rest, guarded, lowpassed, mag_used, hi_used))
    return skipped, sqrt_recovered, repaired, capped


@_jit
def _record(out, row, state, iters, values, flags):
    """Row `row` of the outputs (`_compiled.Outputs`): the state, the mean iterations, (acc_var,
    nis, scale_llr) and the flags (at_rest, bias_guarded, acc_lowpassed, mag_used, mag_hard_iron)."""
    x = state.x
    for i in range(4):
        out.quat[row, i] = x[i]
    out.cov[row, :, :] = state.P
    for i in range(3):
        out.gyr_bias_rad_s[row, i] = x[X_BIAS_AT + i]
        out.gyr_scale[row, i] = x[X_SCALE_AT + i]
    out.velocity_m_s[row, :] = state.v
    out.mean_iterations[row] = iters
    out.acc_var_g2[row], out.nis[row], out.scale_llr[row] = values
    out.at_rest[row], out.bias_guarded[row], out.acc_lowpassed[row], out.mag_used[row], out.mag_hard_iron[row] = flags
