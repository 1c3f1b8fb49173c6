"""`ukf` and `ukf-bias` compiled: the parts of `KalmanFilter.step` that are `UKF`'s own
(`_predict`, `_acc_correct`, `_inject`, `_lag_rate`), which the one compiled loop
(`_compiled_kalman.estimate`) calls for the UKFs.

Every line implements a line of `UKF`'s methods and `QuaternionUKF.predict_kraft` / `update_kraft`
(`fusion.estimators.filters.ukf`, `fusion.estimators.filters.quaternion_ukf`, where the numbered steps and Kraft
2003 are), in the same order where the order matters for rounding. Organised differently, changing the
rounding only (`tests/test_compiled.py` checks 1e-10): the covariances are computed on their upper
triangle and mirrored (`weighted_outer_sum`, `weighted_cross3`: the numpy step's weighted matrix
products, summed in the same order); the sigma points take the attitude exponential only where
the Cholesky factor has an attitude part (step 3); the general-gain covariance of `heading_free`
is `_compiled_linalg.joseph`.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernels._compiled_linalg import _nis, _project_heading, inv_sym3, joseph, sqrt_psd
from ..kernels._compiled_quaternion import exp_floats, gravity_floats, log_floats, multiply_floats, normalize_floats
from ..kernels._numba import _jit, forget_stale, mirrors
from .steps import _compiled_accel as accel
from .steps._error_state import BIAS_AT, CALIBRATION_AT, SCALE_AT, X_BIAS_AT, X_CALIBRATION_AT, X_SCALE_AT

forget_stale(__file__)

# No numpy reference of their own: `QuaternionUKF` writes them as weighted matrix products.
HELPERS = ("weighted_outer_sum", "weighted_cross3")


@_jit
def weighted_outer_sum(E, WE, P, m, n):
    """P = sum_i E[i]^T WE[i] (n x n) over the m rows of E and WE (= Wc E), symmetric: the upper
    triangle, mirrored. Four entries of a row at a time: each sums its terms in the rows' order
    (as one entry at a time would, to the bit), but the four chains of additions overlap."""
    for a in range(n):
        c = a
        while c + 3 < n:
            v0, v1, v2, v3 = 0.0, 0.0, 0.0, 0.0
            for i in range(m):
                ea = E[i, a]
                v0 += ea * WE[i, c]
                v1 += ea * WE[i, c + 1]
                v2 += ea * WE[i, c + 2]
                v3 += ea * WE[i, c + 3]
            P[a, c], P[a, c + 1], P[a, c + 2], P[a, c + 3] = v0, v1, v2, v3
            c += 4
        while c < n:
            v = 0.0
            for i in range(m):
                v += E[i, a] * WE[i, c]
            P[a, c] = v
            c += 1
        for c in range(a + 1, n):
            P[c, a] = P[a, c]


@_jit
def weighted_cross3(E, WZ, out, n, m):
    """out[:n, :3] = sum_i E[i, :n]^T WZ[i, :3] over the m rows (the UKF's P_zz and P_xz, step 8):
    the three entries of a row at a time, each summed in the rows' order."""
    for a in range(n):
        v0, v1, v2 = 0.0, 0.0, 0.0
        for i in range(m):
            ea = E[i, a]
            v0 += ea * WZ[i, 0]
            v1 += ea * WZ[i, 1]
            v2 += ea * WZ[i, 2]
        out[a, 0], out[a, 1], out[a, 2] = v0, v1, v2


@mirrors("fusion.estimators.filters.ukf.UKF._inject")
def _inject(x, dx, o):
    """`UKF._inject`: q <- q exp(dx_e / 2), renormalised, and b, s + their corrections, in x (10,)."""
    x[0], x[1], x[2], x[3] = normalize_floats(multiply_floats((x[0], x[1], x[2], x[3]),
                                                              exp_floats(dx[0], dx[1], dx[2], o.quat.small_angle)))
    for j in range(CALIBRATION_AT, o.n):
        x[X_CALIBRATION_AT + j - CALIBRATION_AT] = x[X_CALIBRATION_AT + j - CALIBRATION_AT] + dx[j]


@mirrors("fusion.estimators.filters.ukf.UKF._predict")
def _predict(x, P, gyr, ok, h, noise, dist, o, w):
    """`UKF._predict` (`QuaternionUKF.predict_kraft`, steps 1-5) on x (10,) = [q, b, s] and P (n, n)
    in place, for the gyro reading gyr (3 floats, rad/s; ok: usable) over the step h (s); noise:
    `_compiled_kalman.Noise` (Qrate, Qbad, the weights Wm, Wc (2n + 1,), centre first); dist: the
    disturbance state (its frame is lost without a usable reading). -> (dq, theta, (0, 0, 0),
    mean iterations, square root recovered)."""
    n = o.n
    m = 2 * n + 1
    small = o.quat.small_angle
    A, L, off, sig, Ep, err, res, Wres = w.A, w.L, w.off, w.sig, w.Ep, w.err, w.res, w.Wres
    Qrate, Qbad, Wm, Wc = noise.Qrate, noise.Qbad, noise.Wm, noise.Wc
    gx, gy, gz = gyr
    hh = h * h
    scale_noise = ok and o.scale_noise > 0.0  # ukf only: Qs w_i^2 dt added to the attitude noise
    for i in range(n):  # A = P + Q
        for c in range(n):
            qn = Qrate[i, c] * h
            if not ok:  # no rate integration; inflate the attitude noise instead
                qn = qn + Qbad[i, c] * hh
            elif scale_noise and i == c and i < 3:
                g = gx if i == 0 else gy if i == 1 else gz
                qn += o.scale_noise * g * g * h
            A[i, c] = P[i, c] + qn
    if ok:
        # The mean rate increment, for the disturbance estimator's strapdown frame.
        wx, wy, wz = gx, gy, gz
        if o.bias:
            wx, wy, wz = gx - x[X_BIAS_AT], gy - x[X_BIAS_AT + 1], gz - x[X_BIAS_AT + 2]
        if o.scale:
            wx, wy, wz = wx * (1.0 + x[X_SCALE_AT]), wy * (1.0 + x[X_SCALE_AT + 1]), wz * (1.0 + x[X_SCALE_AT + 2])
        dq = exp_floats(wx * h, wy * h, wz * h, small)
    else:
        wx, wy, wz = 0.0, 0.0, 0.0
        dq = (1.0, 0.0, 0.0, 0.0)
        accel.lose_frame(dist)
    recovered = sqrt_psd(A, L, n, o.cov.sqrt_floor)  # step 2: +- columns of sqrt(c (P + Q))
    for i in range(n):
        for j in range(n):
            v = L[j, i] * o.sqrt_c
            off[1 + i, j] = v
            off[1 + n + i, j] = -v
    xq = (x[0], x[1], x[2], x[3])
    # step 3: X_i = q exp(e_i / 2) for the attitude part e_i of offset i. Offset 0 is zero, and
    # a Cholesky factor is lower triangular: the columns 3.. of L have no attitude part, so
    # X_i = q there (exp(0) = 1 exactly); and exp(-e / 2) is the conjugate of exp(e / 2), so
    # only the first three columns need an exponential (all n after the eigen fallback).
    n_att = n if recovered else 3
    for i in range(n_att):
        E = exp_floats(off[1 + i, 0], off[1 + i, 1], off[1 + i, 2], small)
        Ep[i, 0], Ep[i, 1], Ep[i, 2], Ep[i, 3] = multiply_floats(xq, E)
        Ep[n + i, 0], Ep[n + i, 1], Ep[n + i, 2], Ep[n + i, 3] = multiply_floats(xq, (E[0], -E[1], -E[2], -E[3]))
    for i in range(m):
        if i == 0 or (i - 1) % n >= n_att:
            X = xq
        else:
            X = (Ep[i - 1, 0], Ep[i - 1, 1], Ep[i - 1, 2], Ep[i - 1, 3])
        if not ok:
            sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = X
            for j in range(CALIBRATION_AT, n):
                sig[i, j + 1] = x[j + 1] + off[i, j]
        elif o.bias:
            bx, by, bz = x[X_BIAS_AT] + off[i, BIAS_AT], x[X_BIAS_AT + 1] + off[i, BIAS_AT + 1], x[X_BIAS_AT + 2] + off[i, BIAS_AT + 2]
            rx, ry, rz = gx - bx, gy - by, gz - bz
            if o.scale:
                s0, s1, s2 = x[X_SCALE_AT] + off[i, SCALE_AT], x[X_SCALE_AT + 1] + off[i, SCALE_AT + 1], x[X_SCALE_AT + 2] + off[i, SCALE_AT + 2]
                rx, ry, rz = rx * (1.0 + s0), ry * (1.0 + s1), rz * (1.0 + s2)
                sig[i, X_SCALE_AT], sig[i, X_SCALE_AT + 1], sig[i, X_SCALE_AT + 2] = s0, s1, s2
            Y = multiply_floats(X, exp_floats(rx * h, ry * h, rz * h, small))  # steps 1, 4, per point
            sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = Y
            sig[i, X_BIAS_AT], sig[i, X_BIAS_AT + 1], sig[i, X_BIAS_AT + 2] = bx, by, bz
        else:
            sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = multiply_floats(X, dq)  # steps 1, 4 (dq: exp(w dt / 2))
    # step 5: iterative quaternion mean (`quaternion_ukf.quaternion_mean`)
    qt = (sig[0, 0], sig[0, 1], sig[0, 2], sig[0, 3])
    ex, ey, ez = 0.0, 0.0, 0.0
    iters = 0
    for it in range(1, o.mean_max_iter + 1):
        iters = it
        ci = (qt[0], -qt[1], -qt[2], -qt[3])
        ex, ey, ez = 0.0, 0.0, 0.0
        for i in range(m):
            e0, e1, e2 = log_floats(multiply_floats(ci, (sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3])))
            err[i, 0], err[i, 1], err[i, 2] = e0, e1, e2
            ex += Wm[i] * e0
            ey += Wm[i] * e1
            ez += Wm[i] * e2
        qt = normalize_floats(multiply_floats(qt, exp_floats(ex, ey, ez, small)))
        if math.sqrt(ex * ex + ey * ey + ez * ez) < o.mean_tol:
            break
    x[0], x[1], x[2], x[3] = qt
    for i in range(m):
        res[i, 0], res[i, 1], res[i, 2] = err[i, 0] - ex, err[i, 1] - ey, err[i, 2] - ez
    for j in range(CALIBRATION_AT, n):
        v = 0.0
        for i in range(m):
            v += Wm[i] * sig[i, j + 1]
        x[j + 1] = v
        for i in range(m):
            res[i, j] = sig[i, j + 1] - v
    # P_pred = sum Wc e_i e_i^T, symmetric: the upper triangle, mirrored (Wc e_i once per point)
    for i in range(m):
        for c in range(n):
            Wres[i, c] = Wc[i] * res[i, c]
    weighted_outer_sum(res, Wres, P, m, n)
    return dq, (wx * h, wy * h, wz * h), (0.0, 0.0, 0.0), iters, recovered


@mirrors("fusion.estimators.filters.ukf.UKF._acc_correct")
def _acc_correct(P, x, meas, r, h, lowpassed, dist, noise, o, w):
    """`UKF._acc_correct` (`QuaternionUKF.update_kraft`, steps 6-9) with the measurement meas (3
    floats, g) of variance r per axis, from the propagated points of `_predict` (w.sig, w.res),
    with the low-passed sample's lag per point where it is modelled (h: the gravity direction at
    the mean, 3 floats); x, P updated in place. -> NIS."""
    n = o.n
    m = 2 * n + 1
    H, dZ, WdZ, S, Sinv, Pxz, K, dx, sig, res = w.H, w.dZ, w.WdZ, w.S, w.Sinv, w.PHt, w.K, w.dx, w.sig, w.res
    Wm, Wc = noise.Wm, noise.Wc
    mx, my, mz = meas
    lagged = o.acc.lag and lowpassed
    if lagged:  # the low-passed sample's lag (`AccDisturbance.lag_jacobian`)
        accel.gravity_jacobian(H, h[0], h[1], h[2], n)
        accel.lag_jacobian(H, dist, o.scale)
    zx, zy, zz = 0.0, 0.0, 0.0
    for i in range(m):  # step 6
        g0, g1, g2 = gravity_floats((sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3]))
        if lagged:
            for c in range(CALIBRATION_AT, n):
                g0 += H[0, c] * res[i, c]
                g1 += H[1, c] * res[i, c]
                g2 += H[2, c] * res[i, c]
        dZ[i, 0], dZ[i, 1], dZ[i, 2] = g0, g1, g2
        zx += Wm[i] * g0  # step 7
        zy += Wm[i] * g1
        zz += Wm[i] * g2
    for i in range(m):
        dZ[i, 0] -= zx
        dZ[i, 1] -= zy
        dZ[i, 2] -= zz
        for j in range(3):
            WdZ[i, j] = Wc[i] * dZ[i, j]
    weighted_cross3(dZ, WdZ, S, 3, m)  # step 8: P_zz
    for a in range(3):
        S[a, a] = S[a, a] + r
    weighted_cross3(res, WdZ, Pxz, n, m)  # step 8: P_xz
    inv_sym3(S, Sinv)
    for a in range(n):  # step 9: K = P_xz P_zz^-1
        for c in range(3):
            K[a, c] = Pxz[a, 0] * Sinv[0, c] + Pxz[a, 1] * Sinv[1, c] + Pxz[a, 2] * Sinv[2, c]
    if o.heading_free:
        nz = math.sqrt(zx * zx + zy * zy + zz * zz)
        hx, hy, hz = zx / nz, zy / nz, zz / nz
        _project_heading(K, 0, hx, hy, hz)
        if o.bias:
            _project_heading(K, BIAS_AT, hx, hy, hz)
        # P - K Pxz^T - Pxz K^T + K S K^T (the covariance of a general gain: `joseph`)
        joseph(P, K, Pxz, S, n, w.D)
    else:
        for a in range(n):  # step 9: P - K P_zz K^T = P - P_xz K^T (upper triangle, mirrored)
            for c in range(a, n):
                v = P[a, c] - (Pxz[a, 0] * K[c, 0] + Pxz[a, 1] * K[c, 1] + Pxz[a, 2] * K[c, 2])
                P[a, c] = v
                P[c, a] = v
    yx, yy, yz = mx - zx, my - zy, mz - zz
    for a in range(n):
        dx[a] = K[a, 0] * yx + K[a, 1] * yy + K[a, 2] * yz
    _inject(x, dx, o)  # step 9
    return _nis(yx, yy, yz, Sinv)


@mirrors("fusion.estimators.filters.ukf.UKF._lag_rate")
def _lag_rate(x, gyr, o):
    """`UKF._lag_rate`: the lag's inputs from the current mean's calibration: the bias-corrected
    rate of the reading gyr (3 floats) and `1 + s` (3 floats)."""
    u = (gyr[0] - x[X_BIAS_AT], gyr[1] - x[X_BIAS_AT + 1], gyr[2] - x[X_BIAS_AT + 2])
    if o.scale:
        return u, (1.0 + x[X_SCALE_AT], 1.0 + x[X_SCALE_AT + 1], 1.0 + x[X_SCALE_AT + 2])
    return u, (1.0, 1.0, 1.0)
