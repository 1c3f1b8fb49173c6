"""`ekf` compiled: the loop of `KalmanFilter.step` with `EKF`'s parts over a whole recording
(`estimate`), and the kernels of `EKF`'s own helpers (`_correct`, `_velocity_step`).

Every line implements a line of `KalmanFilter.step` and `EKF`'s parts (`fusion.estimators.filters.kalman_base`,
`fusion.estimators.filters.ekf`, where the equations and their papers are), in the same order
where the order matters for rounding, and the sections of the loop are the sequence's (predict,
before updates, rest, accelerometer, magnetometer, scale test, finish); the sensor concerns are the
kernels of `_compiled_accel`, `_compiled_rest`, `_compiled_magnetometer` and `_compiled_scale_test`,
called under their references' names. Organised differently, changing the rounding only (1e-14
relative on the recordings; `tests/test_compiled.py` checks 1e-10): the covariance prediction
uses the block structure of F (`predict_covariance`: the reference multiplies the full matrices;
zero blocks contribute exact zeros, identity blocks copies), the accelerometer's P H^T only H's
non-zero columns; the Joseph form is expanded for a symmetric P (`_compiled_linalg.joseph`); the
covariances are computed on their upper triangle and mirrored (the reference symmetrises P at
the end of each step).
"""
from __future__ import annotations

import math

import numpy as np

from ..kernels._compiled_linalg import KalmanUpdateWork, _nis, _project_heading, inv_sym3, joseph, joseph2, repair_covariance
from ..kernels._compiled_quaternion import (exp_floats, gravity_floats, multiply_floats, normalize_floats, right_jacobian_dt,
                                   rotation_floats)
from ..kernels._numba import _clip, _jit_leaf, _sample, forget_stale, mirrors
from .steps import _compiled_accel as accel
from .steps import _compiled_magnetometer as magnetometer
from .steps import _compiled_rest as rest
from .steps import _compiled_scale_test as scale_test
from .steps._error_state import BIAS_AT, SCALE_AT
from .steps._scale_test import TEST_DECISION, TEST_LLR, TEST_ON

forget_stale(__file__)

# No numpy reference of their own: `EKF._predict` writes it as `F @ P @ F.T + Q`.
HELPERS = ("predict_covariance",)


@_jit_leaf
def predict_covariance(P, F, Qrate, Qbad, h, ok, n, N, T):
    """P <- F P F^T + Q (`EKF._predict`, Sola 2017, Sec. 5.4) for F = [[A, B, 0], [0, I]]: A (3 x 3) and
    B (3 x (n - 3)) in F's first three rows, the velocity columns zero, the identity below (only
    F[:3, :n] is read), and Q = Qrate dt (+ Qbad dt^2 without a usable gyro) with Qrate, Qbad
    symmetric. With T = F[:3] P (3 x N): the block [:3, :3] is T F[:3]^T, the block [:3, 3:]
    is T[:, 3:] (and its mirror [3:, :3]), the block [3:, 3:] is P's own (T: 3 x N scratch).
    The dense product costs 2 N^3 multiplications, this one 3 n N + 6 n."""
    for c in range(N):  # T = F[:3, :n] P[:n]
        v0, v1, v2 = 0.0, 0.0, 0.0
        for j in range(n):
            pj = P[j, c]
            v0 += F[0, j] * pj
            v1 += F[1, j] * pj
            v2 += F[2, j] * pj
        T[0, c], T[1, c], T[2, c] = v0, v1, v2
    hh = h * h
    for i in range(N):  # the upper triangle, mirrored
        for c in range(i, N):
            if c < 3:
                v = 0.0
                for j in range(n):
                    v += T[i, j] * F[c, j]
            elif i < 3:
                v = T[i, c]
            else:
                v = P[i, c]
            qn = Qrate[i, c] * h
            if not ok:  # no rate integration: the attitude noise is inflated
                qn = qn + Qbad[i, c] * hh
            v = v + qn
            P[i, c] = v
            P[c, i] = v


@mirrors("fusion.estimators.filters.ekf.EKF._correct", leaf=True)
def _correct(q, b, s, v, dx, n, N, small):
    """`EKF._correct`: inject an error-state correction dx (N,): q exp(dx_e / 2), b + dx_b, s + dx_s, v + dx_v (in place); -> the new q."""
    for i in range(3):
        if n > BIAS_AT:  # the bias block
            b[i] = b[i] + dx[BIAS_AT + i]
        if n > SCALE_AT:  # the scale block
            s[i] = s[i] + dx[SCALE_AT + i]
    for i in range(N - n):
        v[i] = v[i] + dx[n + i]
    return multiply_floats(q, exp_floats(dx[0], dx[1], dx[2], small))


@mirrors("fusion.estimators.filters.ekf.EKF._velocity_step", leaf=True)
def _velocity_step(P, n, N, q, v, acc, h, o, w):
    """`EKF._velocity_step`: the horizontal world velocity v (2,) integrates the specific force at
    the attitude q, P <- V P V^T with V = I but V[velocity, ATTITUDE] = -(R [a]x)_xy g dt, then the
    pseudo-measurement v = 0 (variance Rv / dt, H = [0, I], so that P H^T = P[:, n:] and
    H P H^T = P[n:, n:]) in Joseph form (`joseph2`); the correction into dx (N,) (K, PHt, D:
    N x 3 scratch, two columns used; S: 3 x 3 scratch, its upper-left 2 x 2 used; w: the
    `KalmanUpdateWork` holding them); acc: the accelerometer sample, 3 floats, g."""
    K, dx, PHt, S = w.K, w.dx, w.PHt, w.S
    ax, ay, az = acc
    r00, r01, r02, r10, r11, r12, _, _, _ = rotation_floats(q)  # the first two rows of R(q)
    if math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az):
        g = o.gravity * h
        v[0] += (r00 * ax + r01 * ay + r02 * az) * g
        v[1] += (r10 * ax + r11 * ay + r12 * az) * g
        a00, a01, a02 = -(r01 * az - r02 * ay) * g, -(r02 * ax - r00 * az) * g, -(r00 * ay - r01 * ax) * g
        a10, a11, a12 = -(r11 * az - r12 * ay) * g, -(r12 * ax - r10 * az) * g, -(r10 * ay - r11 * ax) * g
        for c in range(N):  # V P
            P[n, c] += a00 * P[0, c] + a01 * P[1, c] + a02 * P[2, c]
            P[n + 1, c] += a10 * P[0, c] + a11 * P[1, c] + a12 * P[2, c]
        for i in range(N):  # (V P) V^T
            P[i, n] += P[i, 0] * a00 + P[i, 1] * a01 + P[i, 2] * a02
            P[i, n + 1] += P[i, 0] * a10 + P[i, 1] * a11 + P[i, 2] * a12
    r = o.vel_bound / h
    s00, s01, s10, s11 = P[n, n] + r, P[n, n + 1], P[n + 1, n], P[n + 1, n + 1] + r
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    for i in range(N):
        K[i, 0] = P[i, n] * i00 + P[i, n + 1] * i10
        K[i, 1] = P[i, n] * i01 + P[i, n + 1] * i11
        K[i, 2] = 0.0
    if o.heading_free:
        hx, hy, hz = gravity_floats(q)
        _project_heading(K, 0, hx, hy, hz)
        if o.bias:
            _project_heading(K, BIAS_AT, hx, hy, hz)
    for i in range(N):
        dx[i] = -(K[i, 0] * v[0] + K[i, 1] * v[1])
    for i in range(N):  # P H^T
        PHt[i, 0], PHt[i, 1] = P[i, n], P[i, n + 1]
    S[0, 0], S[0, 1], S[1, 0], S[1, 1] = s00, s01, s10, s11  # H P H^T + r I
    joseph2(P, K, PHt, S, N, w.D)


@mirrors("fusion.estimators.filters.ekf.EKF.estimate")
def estimate(inp, qio, b, s, v, P, Qrate, Qbad, st, o, out):
    """`EKF.estimate`: the loop of `KalmanFilter.step` with `EKF`'s parts over a recording (see `ekf`
    for the equations).

    inp: the recording (`_numba.Inputs`: the interval rates and steps, the accelerometer, the
    magnetometer or none). State in and out: qio (4,), b (3,), s (3,), v (2,), P (N, N)
    (N = n + nv, the velocity last) and the packed states st (`_compiled.SensorStates`: the
    disturbance estimator with its lag, the rest detector, the magnetometer's reference and
    sphere fit, the scale test). Qrate, Qbad (N, N) as built by `EKF.reset`; o: `_compiled.Settings`.
    Fills rows 1.. of the outputs `out` (`_compiled.Outputs`); returns (updates skipped,
    covariance repairs).
    """
    n = o.n
    N = n + o.nv
    small = o.quat.small_angle
    # Work arrays, allocated once for the whole recording.
    F = np.zeros((3, N))  # the first three rows of F; the others are [0, I]
    T = np.empty((3, N))
    J = np.empty((3, 3))
    H = np.zeros((3, N))
    with_lag = o.acc.lag
    PHt = np.empty((N, 3))
    S = np.empty((3, 3))
    Sinv = np.empty((3, 3))
    K = np.empty((N, 3))
    D = np.empty((N, 3))
    dx = np.empty(N)
    uw = KalmanUpdateWork(K, dx, S, Sinv, PHt, D)
    L = np.empty((N, N))
    q = (qio[0], qio[1], qio[2], qio[3])
    use_mag = inp.mag.shape[0] > 0
    hi_fit = np.empty(4)
    hi_work = np.empty((4, 5))
    Km = np.empty(N)
    Gm = np.empty(N)
    skipped = 0
    repaired = 0
    # The arrays of the named tuples, taken out once: an array read from a tuple inside the loop
    # costs a reference count increment and decrement each time.
    dts, gyr, valid, acc, mag, mag_ok = inp.dt, inp.gyr, inp.valid, inp.acc, inp.mag, inp.mag_ok
    dist, rest_st, mag_st, hard_iron, test = st.dist, st.rest, st.mag, st.hard_iron, st.test
    (quat_out, cov_out, bias_out, scale_out, vel_out, var_out, rest_out, nis_out, guarded_out, lowpassed_out,
     mag_used_out, hard_iron_out, llr_out) = (out.quat, out.cov, out.gyr_bias_rad_s, out.gyr_scale, out.velocity_m_s,
                                              out.acc_var_g2, out.at_rest, out.nis, out.bias_guarded,
                                              out.acc_lowpassed, out.mag_used, out.mag_hard_iron, out.scale_llr)
    P_cal = P[BIAS_AT:n, BIAS_AT:n]  # the calibration block (a view, for the slow disturbance)
    for k in range(dts.shape[0]):
        h = dts[k]
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
        ux, uy, uz = gx, gy, gz
        sx, sy, sz = 1.0, 1.0, 1.0
        if ok:
            if o.bias:
                ux, uy, uz = gx - b[0], gy - b[1], gz - b[2]
            if o.scale:
                sx, sy, sz = 1.0 + s[0], 1.0 + s[1], 1.0 + s[2]
                tx, ty, tz = ux * sx * h, uy * sy * h, uz * sz * h  # w_true = diag(1 + s) (w_meas - b)
            else:
                tx, ty, tz = ux * h, uy * h, uz * h
        else:  # no rate integration; the attitude noise is inflated below
            tx, ty, tz = 0.0, 0.0, 0.0
            accel.lose_frame(dist)
        d = exp_floats(tx, ty, tz, small)
        q = multiply_floats(q, d)
        # F[ATTITUDE, ATTITUDE] = R(theta)^T; F[ATTITUDE, BIAS] = -J_r diag(1 + s) dt; F[ATTITUDE, SCALE] = J_r diag(w - b) dt
        dw, dxx, dyy, dzz = d
        F[0, 0] = 1 - 2 * (dyy * dyy + dzz * dzz)
        F[1, 0] = 2 * (dxx * dyy - dw * dzz)
        F[2, 0] = 2 * (dxx * dzz + dw * dyy)
        F[0, 1] = 2 * (dxx * dyy + dw * dzz)
        F[1, 1] = 1 - 2 * (dxx * dxx + dzz * dzz)
        F[2, 1] = 2 * (dyy * dzz - dw * dxx)
        F[0, 2] = 2 * (dxx * dzz - dw * dyy)
        F[1, 2] = 2 * (dyy * dzz + dw * dxx)
        F[2, 2] = 1 - 2 * (dxx * dxx + dyy * dyy)
        if o.bias:
            right_jacobian_dt(tx, ty, tz, h, o.quat, J)
            for i in range(3):
                for j in range(3):
                    if not ok:  # the rate was not integrated: no bias or scale enters
                        F[i, BIAS_AT + j] = 0.0
                        if o.scale:
                            F[i, SCALE_AT + j] = 0.0
                    elif o.scale:
                        F[i, BIAS_AT + j] = -J[i, j] * (sx if j == 0 else sy if j == 1 else sz)
                        F[i, SCALE_AT + j] = J[i, j] * (ux if j == 0 else uy if j == 1 else uz)
                    else:
                        F[i, BIAS_AT + j] = -J[i, j]
        predict_covariance(P, F, Qrate, Qbad, h, ok, n, N, T)  # P <- F P F^T + Q
        if N > n:  # before the updates: the velocity model (`EKF._before_updates`, `_velocity_step`)
            _velocity_step(P, n, N, q, v, (ax, ay, az), h, o, uw)
            q = _correct(q, b, s, v, dx, n, N, small)
        at_rest = False
        if o.bias and ok and o.rest_on and rest.update(rest_st, gx, gy, gz, ax, ay, az, h, o.rest):
            # Zero-rate update at rest (VQF, Sec. 3.4; `KalmanFilter._rest_update`): the gyro reads the bias.
            rest.bias_rest_update((b[0], b[1], b[2]), P, (gx, gy, gz), o.rest_noise / h, N, uw)
            q = _correct(q, b, s, v, dx, n, N, small)
            at_rest = True
        var = math.nan
        nis = math.nan
        guarded = False
        lowpassed = False
        scale = accel.acc_variance_scale(ax, ay, az, o.acc.gate, o.acc.gate_g) if o.use_acc else math.inf
        # the lag's inputs (`EKF._lag_rate`): the rate the prediction integrated and 1 + s now
        gain = (1.0 + s[0], 1.0 + s[1], 1.0 + s[2]) if o.scale else (1.0, 1.0, 1.0)
        if scale < math.inf:  # the accelerometer (`KalmanFilter._acc_update`, `EKF._acc_correct`)
            hx, hy, hz = gravity_floats(q)
            step = accel.AccStep(d, h, scale, o.process_noise, (ux, uy, uz), gain)
            slow = accel.SlowDisturbance(o.slow_corr, (hx, hy, hz), P_cal, o.slow_scale_var)
            mx, my, mz, r, lowpassed = accel.accelerometer_update_input(dist, (ax, ay, az), step, slow, o.acc,
                                                                        H)  # H: scratch until filled below
            var = r
            accel.gravity_jacobian(H, hx, hy, hz, N)  # H = [[h]x, 0, 0]
            if with_lag and lowpassed:  # the low-pass's lag: H = [[h]x, A N_b, -A N_s] (`_accel.LowpassLag`)
                accel.lag_jacobian(H, dist, o.scale)
            nh = n if with_lag and lowpassed else 3  # H's columns nh.. are zero
            for i in range(N):  # P H^T
                for j in range(3):
                    acc_ = 0.0
                    for c in range(nh):
                        acc_ += P[i, c] * H[j, c]
                    PHt[i, j] = acc_
            for i in range(3):  # H P H^T + R
                for j in range(3):
                    acc_ = 0.0
                    for c in range(nh):
                        acc_ += H[i, c] * PHt[c, j]
                    S[i, j] = acc_
                S[i, i] += r
            inv_sym3(S, Sinv)
            for i in range(N):
                for j in range(3):
                    K[i, j] = PHt[i, 0] * Sinv[0, j] + PHt[i, 1] * Sinv[1, j] + PHt[i, 2] * Sinv[2, j]
            if o.heading_free:  # K <- (I - h h^T) K on the attitude and bias rows
                _project_heading(K, 0, hx, hy, hz)
                if o.bias:
                    _project_heading(K, BIAS_AT, hx, hy, hz)
            yx, yy, yz = mx - hx, my - hy, mz - hz
            nis = _nis(yx, yy, yz, Sinv)
            guarded = o.bias and nis > o.chi2  # inconsistent innovation: correct the attitude only
            if guarded or (o.bias and lowpassed and not o.lowpass_calibration):  # ... or the velocity's to correct
                for i in range(BIAS_AT, n):
                    K[i, 0] = 0.0
                    K[i, 1] = 0.0
                    K[i, 2] = 0.0
            for i in range(N):
                dx[i] = K[i, 0] * yx + K[i, 1] * yy + K[i, 2] * yz
            q = _correct(q, b, s, v, dx, n, N, small)
            joseph(P, K, PHt, S, N, D)  # Joseph form
        else:
            skipped += 1
            if o.acc.corr_s > 0.0:  # the strapdown frame follows the gyro through skipped updates
                accel.turn(dist, d, h, (ux, uy, uz), gain, o.acc)
        mag_used = False
        hi_used = False
        if use_mag and mag_ok[k + 1]:  # 9-D: the gated heading-only update (`KalmanFilter._mag_update`)
            mx, my, mz = mag[k + 1, 0], mag[k + 1, 1], mag[k + 1, 2]
            if math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz):
                if test[TEST_DECISION] == 0.0:  # 9-D: no scale test (`ScaleTest.stop`)
                    test[TEST_ON], test[TEST_LLR] = 0.0, math.nan
                usable, east, north, hi_used = magnetometer.magnetometer_input(q, P, mx, my, mz, mag_st, hard_iron, o.mag,
                                                                               h, hi_fit, hi_work)
                if usable:
                    r_mag = magnetometer.heading_variance(q, tx, ty, tz, h, o.mag)
                    magnetometer.heading_update(P, n, N, q, east, north, r_mag, Km, Gm, dx)
                    q = _correct(q, b, s, v, dx, n, N, small)
                    mag_used = True
        # Wald's test: a scale error, or a calibrated gyro? (`KalmanFilter._scale_test_update`)
        if o.test.axes and test[TEST_ON] == 1.0 and test[TEST_DECISION] == 0.0:
            if scale_test.step(P, s, test, q, o.test, o.heading_free, N, uw):
                q = _correct(q, b, s, v, dx, n, N, small)
        if o.bias:  # finish (`EKF._finish`)
            for i in range(3):
                b[i] = _clip(b[i], -o.bias_max, o.bias_max)
        if o.scale:
            for i in range(3):
                s[i] = _clip(s[i], -o.scale_max, o.scale_max)
        q = normalize_floats(q)
        if repair_covariance(P, N, o.cov, L):
            repaired += 1
        quat_out[k + 1, 0], quat_out[k + 1, 1], quat_out[k + 1, 2], quat_out[k + 1, 3] = q
        for i in range(N):  # element by element: a slice would be a view, counted as a reference
            for j in range(N):
                cov_out[k + 1, i, j] = P[i, j]
        for i in range(3):
            bias_out[k + 1, i] = b[i]
            scale_out[k + 1, i] = s[i]
        vel_out[k + 1, 0], vel_out[k + 1, 1] = v[0], v[1]
        var_out[k + 1] = var
        rest_out[k + 1] = at_rest
        nis_out[k + 1] = nis
        guarded_out[k + 1] = guarded
        lowpassed_out[k + 1] = lowpassed
        mag_used_out[k + 1] = mag_used
        hard_iron_out[k + 1] = hi_used
        llr_out[k + 1] = test[TEST_LLR]
    qio[0], qio[1], qio[2], qio[3] = q
    return skipped, repaired
