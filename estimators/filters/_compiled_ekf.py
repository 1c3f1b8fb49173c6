"""`ekf` compiled: the parts of `KalmanFilter.step` that are `EKF`'s own (`_predict`,
`_acc_correct`, `_velocity_step`, `_correct`), which the one compiled loop
(`_compiled_kalman.estimate`) calls for `ekf`.

Every line implements a line of `EKF`'s methods (`fusion.estimators.filters.ekf`, where the equations
and their papers are), in the same order where the order matters for rounding. Organised
differently, changing the rounding only (1e-14
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

from ..kernels._compiled_linalg import _nis, _project_heading, inv_sym3, joseph, joseph2
from ..kernels._compiled_quaternion import exp_floats, gravity_floats, multiply_floats, right_jacobian_dt, rotation_floats
from ..kernels._numba import _jit, forget_stale, mirrors
from .steps import _compiled_accel as accel
from .steps._error_state import BIAS_AT, SCALE_AT, X_BIAS_AT, X_SCALE_AT

forget_stale(__file__)

# No numpy reference of their own: `EKF._predict` writes it as `F @ P @ F.T + Q`.
HELPERS = ("predict_covariance",)


@_jit
def predict_covariance(P, F, Qrate, Qbad, h, ok, n, N, T):
    """P <- F P F^T + Q (`EKF._predict`, Sola 2017, Sec. 5.4) for F = [[A, B, 0], [0, I]]: A (3 x 3) and
    B (3 x (n - 3)) in F's first three rows, the velocity columns zero, the identity below (only
    F[:3, :n] is read), and Q = Qrate dt (+ Qbad dt^2 without a usable gyro) with Qrate, Qbad
    symmetric. With T = F[:3] P (3 x N): the block [:3, :3] is T F[:3]^T, the block [:3, 3:]
    is T[:, 3:] (and its mirror [3:, :3]), the block [3:, 3:] is P's own (T: 3 x N scratch).
    The dense product costs 2 N^3 multiplications, this one 3 n N + 6 n."""
    for c in range(N):  # T = F[ATTITUDE, :n] P[:n]
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


@mirrors("fusion.estimators.filters.ekf.EKF._correct")
def _correct(x, v, dx, o):
    """`EKF._correct`: inject an error-state correction dx (N,) into x = [q, b, s] (10,) and v (2,)
    in place: q exp(dx_e / 2) (not renormalised: `_finish` does), b + dx_b, s + dx_s, v + dx_v."""
    n = o.n
    for i in range(3):
        if o.bias:
            x[X_BIAS_AT + i] = x[X_BIAS_AT + i] + dx[BIAS_AT + i]
        if o.scale:
            x[X_SCALE_AT + i] = x[X_SCALE_AT + i] + dx[SCALE_AT + i]
    for i in range(o.nv):
        v[i] = v[i] + dx[n + i]
    x[0], x[1], x[2], x[3] = multiply_floats((x[0], x[1], x[2], x[3]),
                                             exp_floats(dx[0], dx[1], dx[2], o.quat.small_angle))


@mirrors("fusion.estimators.filters.ekf.EKF._predict")
def _predict(x, P, gyr, ok, h, noise, dist, o, w):
    """`EKF._predict`: q <- q exp(theta / 2) in x (10,) = [q, b, s], P <- F P F^T + Q, for the gyro
    reading gyr (3 floats, rad/s; ok: usable) over the step h (s); noise: `_compiled_kalman.Noise`;
    dist: the disturbance state (its frame is lost without a usable reading). -> (dq, theta, u, 0,
    False): the step's rotation, its rotation vector and the bias-corrected rate (the UKF's mean
    iterations and square-root recovery have no counterpart here)."""
    n = o.n
    N = n + o.nv
    F, J = w.F, w.J
    gx, gy, gz = gyr
    ux, uy, uz = gx, gy, gz
    sx, sy, sz = 1.0, 1.0, 1.0
    if ok:
        if o.bias:
            ux, uy, uz = gx - x[X_BIAS_AT], gy - x[X_BIAS_AT + 1], gz - x[X_BIAS_AT + 2]
        if o.scale:
            sx, sy, sz = 1.0 + x[X_SCALE_AT], 1.0 + x[X_SCALE_AT + 1], 1.0 + x[X_SCALE_AT + 2]
            tx, ty, tz = ux * sx * h, uy * sy * h, uz * sz * h  # w_true = diag(1 + s) (w_meas - b)
        else:
            tx, ty, tz = ux * h, uy * h, uz * h
    else:  # no rate integration; the attitude noise is inflated below
        tx, ty, tz = 0.0, 0.0, 0.0
        accel.lose_frame(dist)
    d = exp_floats(tx, ty, tz, o.quat.small_angle)
    x[0], x[1], x[2], x[3] = multiply_floats((x[0], x[1], x[2], x[3]), d)
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
    predict_covariance(P, F, noise.Qrate, noise.Qbad, h, ok, n, N, w.T)  # P <- F P F^T + Q
    return d, (tx, ty, tz), (ux, uy, uz), 0, False


@mirrors("fusion.estimators.filters.ekf.EKF._velocity_step")
def _velocity_step(P, x, v, acc, h, o, w):
    """`EKF._velocity_step`: the horizontal world velocity v (2,) integrates the specific force acc
    (3 floats, g) at the attitude q = x[:4], P <- V P V^T with V = I but V[velocity, ATTITUDE] =
    -(R [a]x)_xy g dt, then the pseudo-measurement v = 0 (variance Rv / dt, H = [0, I], so that
    P H^T = P[:, velocity] and H P H^T = P[velocity, velocity]) in Joseph form (`joseph2`); the
    correction into w.dx (N,) (w.K, w.PHt, w.D: N x 3 scratch, two columns used; w.S: 3 x 3
    scratch, its upper-left 2 x 2 used)."""
    n = o.n
    N = n + o.nv
    K, dx, PHt, S = w.K, w.dx, w.PHt, w.S
    ax, ay, az = acc
    q = (x[0], x[1], x[2], x[3])
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


@mirrors("fusion.estimators.filters.ekf.EKF._acc_correct")
def _acc_correct(P, x, v, meas, r, h, lowpassed, dist, o, w):
    """`EKF._acc_correct`: the accelerometer update with the measurement meas (3 floats, g) of
    variance r per axis and the gravity direction h (3 floats) at the estimate: H = [[h]x, H_b,
    H_s, 0], the heading-free gain, the chi-square guard, the Joseph form (`joseph`); the state x,
    v and P updated in place. -> (NIS, guarded)."""
    n = o.n
    N = n + o.nv
    H, PHt, S, Sinv, K, dx = w.H, w.PHt, w.S, w.Sinv, w.K, w.dx
    hx, hy, hz = h
    mx, my, mz = meas
    accel.gravity_jacobian(H, hx, hy, hz, N)  # H = [[h]x, 0, 0]
    lagged = o.acc.lag and lowpassed
    if lagged:  # the low-pass's lag: H = [[h]x, A N_b, -A N_s] (`_accel.LowpassLag`)
        accel.lag_jacobian(H, dist, o.scale)
    nh = n if lagged else 3  # H's columns nh.. are zero
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
    _correct(x, v, dx, o)
    joseph(P, K, PHt, S, N, w.D)  # Joseph form
    return nis, guarded


@mirrors("fusion.estimators.filters.ekf.EKF._lag_rate")
def _lag_rate(x, u, o):
    """`EKF._lag_rate`: the rate u (3 floats) the prediction integrated and `1 + s` now."""
    if o.scale:
        return u, (1.0 + x[X_SCALE_AT], 1.0 + x[X_SCALE_AT + 1], 1.0 + x[X_SCALE_AT + 2])
    return u, (1.0, 1.0, 1.0)
