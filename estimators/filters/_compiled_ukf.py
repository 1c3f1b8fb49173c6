"""`ukf` and `ukf-bias` compiled: the loop of `KalmanFilter.step` with `UKF`'s parts over a whole
recording (`estimate`).

Every line implements a line of `KalmanFilter.step`, `UKF`'s parts and `QuaternionUKF.predict_kraft`
/ `update_kraft` (`fusion.estimators.filters.kalman_base`, `fusion.estimators.filters.ukf`,
`fusion.estimators.filters.quaternion_ukf`, where the numbered steps and Kraft 2003 are), in the same
order where the order matters for rounding, and the sections of the loop are the sequence's;
the sensor concerns are the
kernels of `_compiled_accel`, `_compiled_rest`, `_compiled_magnetometer` and
`_compiled_scale_test`, called under their references' names. Organised differently, changing the
rounding only (`tests/test_compiled.py` checks 1e-10): the covariances are computed on their upper
triangle and mirrored (`weighted_outer_sum`, `weighted_cross3`: the numpy step's weighted matrix
products, summed in the same order); the sigma points take the attitude exponential only where
the Cholesky factor has an attitude part (step 3); the general-gain covariance of `heading_free`
is `_compiled_linalg.joseph`.
"""
from __future__ import annotations

import math

import numpy as np

from ..kernels._compiled_linalg import KalmanUpdateWork, _nis, _project_heading, inv_sym3, joseph, repair_covariance, sqrt_psd
from ..kernels._compiled_quaternion import exp_floats, gravity_floats, log_floats, multiply_floats, normalize_floats
from ..kernels._numba import _clip, _jit_leaf, _sample, forget_stale, mirrors
from .steps import _compiled_accel as accel
from .steps import _compiled_magnetometer as magnetometer
from .steps import _compiled_rest as rest
from .steps import _compiled_scale_test as scale_test
from .steps._error_state import BIAS_AT, CALIBRATION_AT, SCALE_AT, X_BIAS_AT, X_SCALE_AT
from .steps._scale_test import TEST_DECISION, TEST_LLR, TEST_ON

forget_stale(__file__)

# No numpy reference of their own: `QuaternionUKF` writes them as weighted matrix products.
HELPERS = ("weighted_outer_sum", "weighted_cross3")


@_jit_leaf
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


@_jit_leaf
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


@mirrors("fusion.estimators.filters.ukf.UKF.estimate")
def estimate(inp, x, P, Qrate, Qbad, Wm, Wc, st, o, out):
    """`UKF.estimate` with impl=numpy: the loop of `KalmanFilter.step` (`QuaternionUKF.predict_kraft`,
    `update_kraft`; steps 1-9 of the `ukf` module docstring) over a recording.

    inp: the recording (`_numba.Inputs`; the magnetometer for ukf-bias only, as in
    `_compiled_ekf.estimate`). State in and out: x (n + 1,) `[q, b, s]`, P (n, n) and the packed
    states st (`_compiled.SensorStates`, as in `_compiled_ekf.estimate`). Qrate, Qbad (n, n) as
    built by `UKF.reset`; Wm, Wc (2n + 1,) the sigma-point weights, centre first; o:
    `_compiled.Settings`. Fills rows 1.. of the outputs `out` (`_compiled.Outputs`); returns
    (updates skipped, square-root recoveries, covariance repairs, mean-iteration cap hits).
    """
    n = o.n
    m = 2 * n + 1
    small = o.quat.small_angle
    A = np.empty((n, n))
    L = np.empty((n, n))
    off = np.zeros((m, n))
    sig = np.empty((m, n + 1))
    Ep = np.empty((2 * n, 4))  # q exp(+-e_i / 2), i < 3 (step 3)
    err = np.empty((m, 3))
    res = np.empty((m, n))
    Wres = np.empty((m, n))
    dZ = np.empty((m, 3))
    WdZ = np.empty((m, 3))
    S = np.empty((3, 3))
    Sinv = np.empty((3, 3))
    Pxz = np.empty((n, 3))
    K = np.empty((n, 3))
    KS = np.empty((n, 3))
    dx = np.empty(n)
    uw = KalmanUpdateWork(K, dx, S, Sinv, Pxz, KS)
    H = np.zeros((3, n))
    with_lag = o.acc.lag
    use_mag = inp.mag.shape[0] > 0
    hi_fit = np.empty(4)
    hi_work = np.empty((4, 5))
    Km = np.empty(n)
    Gm = np.empty(n)
    skipped = 0
    sqrt_recovered = 0
    repaired = 0
    capped = 0
    iters = 0
    # The arrays of the named tuples and the views the loop passes, taken out once: an array read
    # from a tuple or sliced inside the loop costs a reference count increment and decrement each time.
    dts, gyr, valid, acc, mag, mag_ok = inp.dt, inp.gyr, inp.valid, inp.acc, inp.mag, inp.mag_ok
    dist, rest_st, mag_st, hard_iron, test = st.dist, st.rest, st.mag, st.hard_iron, st.test
    (quat_out, cov_out, bias_out, scale_out, iter_out, var_out, rest_out, nis_out, lowpassed_out, mag_used_out,
     hard_iron_out, llr_out) = (out.quat, out.cov, out.gyr_bias_rad_s, out.gyr_scale, out.mean_iterations,
                                out.acc_var_g2, out.at_rest, out.nis, out.acc_lowpassed, out.mag_used,
                                out.mag_hard_iron, out.scale_llr)
    P_cal = P[BIAS_AT:n, BIAS_AT:n]  # the calibration block (a view)
    x_scale = x[X_SCALE_AT:X_SCALE_AT + 3]  # the scale (a view; with scale states)
    for k in range(dts.shape[0]):
        h = dts[k]
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
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
        # ---- predict (steps 1-5)
        recovered = sqrt_psd(A, L, n, o.cov.sqrt_floor)
        if recovered:  # step 2: +- columns of sqrt(c (P + Q))
            sqrt_recovered += 1
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
                bx, by, bz = (x[X_BIAS_AT] + off[i, BIAS_AT], x[X_BIAS_AT + 1] + off[i, BIAS_AT + 1],
                              x[X_BIAS_AT + 2] + off[i, BIAS_AT + 2])
                rx, ry, rz = gx - bx, gy - by, gz - bz
                if o.scale:
                    s0, s1, s2 = (x[X_SCALE_AT] + off[i, SCALE_AT], x[X_SCALE_AT + 1] + off[i, SCALE_AT + 1],
                                  x[X_SCALE_AT + 2] + off[i, SCALE_AT + 2])
                    rx, ry, rz = rx * (1.0 + s0), ry * (1.0 + s1), rz * (1.0 + s2)
                    sig[i, X_SCALE_AT], sig[i, X_SCALE_AT + 1], sig[i, X_SCALE_AT + 2] = s0, s1, s2
                Y = multiply_floats(X, exp_floats(rx * h, ry * h, rz * h, small))  # steps 1, 4, per point
                sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = Y
                sig[i, X_BIAS_AT], sig[i, X_BIAS_AT + 1], sig[i, X_BIAS_AT + 2] = bx, by, bz
            else:
                sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = multiply_floats(X, dq)  # steps 1, 4 (dq: exp(w dt / 2))
        # step 5: iterative quaternion mean (`ukf.quaternion_mean`)
        qt = (sig[0, 0], sig[0, 1], sig[0, 2], sig[0, 3])
        ex, ey, ez = 0.0, 0.0, 0.0
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
        if iters >= o.mean_max_iter:
            capped += 1
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
        # ---- rest update (ukf-bias)
        at_rest = False
        if o.bias and ok and o.rest_on and rest.update(rest_st, gx, gy, gz, ax, ay, az, h, o.rest):
            rest.bias_rest_update((x[X_BIAS_AT], x[X_BIAS_AT + 1], x[X_BIAS_AT + 2]), P, (gx, gy, gz), o.rest_noise / h,
                                  n, uw)
            qn4 = normalize_floats(multiply_floats((x[0], x[1], x[2], x[3]), exp_floats(dx[0], dx[1], dx[2], small)))
            x[0], x[1], x[2], x[3] = qn4
            for j in range(CALIBRATION_AT, n):
                x[j + 1] = x[j + 1] + dx[j]
            at_rest = True
        # ---- accelerometer update (steps 6-9)
        var = math.nan
        nis = math.nan
        lowpassed = False
        scale = accel.acc_variance_scale(ax, ay, az, o.acc.gate, o.acc.gate_g) if o.use_acc else math.inf
        u, gain = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)  # the lag's inputs (`UKF._lag_rate`)
        if with_lag:
            u = (gx - x[X_BIAS_AT], gy - x[X_BIAS_AT + 1], gz - x[X_BIAS_AT + 2])
            if o.scale:
                gain = (1.0 + x[X_SCALE_AT], 1.0 + x[X_SCALE_AT + 1], 1.0 + x[X_SCALE_AT + 2])
        if scale < math.inf:
            q_rate = o.process_noise  # ukf: plus the scale noise Qs w_i^2, a rate noise density too
            if ok and o.scale_noise > 0.0:
                q_rate += o.scale_noise * max(gx * gx, gy * gy, gz * gz)
            step = accel.AccStep(dq, h, scale, q_rate, u, gain)
            slow = accel.SlowDisturbance(0.0, (0.0, 0.0, 0.0), P_cal, 0.0)  # no slow component
            mx, my, mz, r, lowpassed = accel.accelerometer_update_input(dist, (ax, ay, az), step, slow, o.acc, H)
            var = r
            lagged = with_lag and lowpassed
            if lagged:  # the low-passed sample's lag (`AccDisturbance.lag_jacobian`)
                hx, hy, hz = gravity_floats((x[0], x[1], x[2], x[3]))
                accel.gravity_jacobian(H, hx, hy, hz, n)
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
                joseph(P, K, Pxz, S, n, KS)
            else:
                for a in range(n):  # step 9: P - K P_zz K^T = P - P_xz K^T (upper triangle, mirrored)
                    for c in range(a, n):
                        v = P[a, c] - (Pxz[a, 0] * K[c, 0] + Pxz[a, 1] * K[c, 1] + Pxz[a, 2] * K[c, 2])
                        P[a, c] = v
                        P[c, a] = v
            yx, yy, yz = mx - zx, my - zy, mz - zz
            for a in range(n):
                dx[a] = K[a, 0] * yx + K[a, 1] * yy + K[a, 2] * yz
            qn4 = normalize_floats(multiply_floats((x[0], x[1], x[2], x[3]), exp_floats(dx[0], dx[1], dx[2], small)))  # step 9
            x[0], x[1], x[2], x[3] = qn4
            for j in range(CALIBRATION_AT, n):
                x[j + 1] = x[j + 1] + dx[j]
            nis = _nis(yx, yy, yz, Sinv)
        else:
            skipped += 1
            if o.acc.corr_s > 0.0:
                accel.turn(dist, dq, h, u, gain, o.acc)
        mag_used = False
        hi_used = False
        if use_mag and mag_ok[k + 1]:  # 9-D (ukf-bias): the gated heading-only update (`UKF.step`)
            mx, my, mz = mag[k + 1, 0], mag[k + 1, 1], mag[k + 1, 2]
            if math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz):
                if test[TEST_DECISION] == 0.0:  # 9-D: no scale test (`ScaleTest.stop`)
                    test[TEST_ON], test[TEST_LLR] = 0.0, math.nan
                q4 = (x[0], x[1], x[2], x[3])
                usable, east, north, hi_used = magnetometer.magnetometer_input(q4, P, mx, my, mz, mag_st, hard_iron,
                                                                               o.mag, h, hi_fit, hi_work)
                if usable:
                    r_mag = magnetometer.heading_variance(q4, wx * h, wy * h, wz * h, h, o.mag)
                    magnetometer.heading_update(P, n, n, q4, east, north, r_mag, Km, Gm, dx)
                    qn4 = normalize_floats(multiply_floats(q4, exp_floats(dx[0], dx[1], dx[2], small)))
                    x[0], x[1], x[2], x[3] = qn4
                    for j in range(CALIBRATION_AT, n):
                        x[j + 1] = x[j + 1] + dx[j]
                    mag_used = True
        # Wald's test on the scale (`_scale_test.ScaleTest`, as in `_compiled_ekf.estimate`)
        if o.test.axes and test[TEST_ON] == 1.0 and test[TEST_DECISION] == 0.0:
            q4 = (x[0], x[1], x[2], x[3])
            if scale_test.step(P, x_scale, test, q4, o.test, o.heading_free, n, uw):
                x[0], x[1], x[2], x[3] = normalize_floats(multiply_floats(q4, exp_floats(dx[0], dx[1], dx[2], small)))
                for j in range(CALIBRATION_AT, n):
                    x[j + 1] = x[j + 1] + dx[j]
        if o.bias:
            for i in range(X_BIAS_AT, X_BIAS_AT + 3):
                x[i] = _clip(x[i], -o.bias_max, o.bias_max)
        if o.scale:
            for i in range(X_SCALE_AT, X_SCALE_AT + 3):
                x[i] = _clip(x[i], -o.scale_max, o.scale_max)
        if repair_covariance(P, n, o.cov, L):
            repaired += 1
        for i in range(4):  # element by element: a slice would be a view, counted as a reference
            quat_out[k + 1, i] = x[i]
        for i in range(n):
            for j in range(n):
                cov_out[k + 1, i, j] = P[i, j]
        if o.bias:
            for i in range(3):
                bias_out[k + 1, i] = x[X_BIAS_AT + i]
        if o.scale:
            for i in range(3):
                scale_out[k + 1, i] = x[X_SCALE_AT + i]
        iter_out[k + 1] = iters
        var_out[k + 1] = var
        rest_out[k + 1] = at_rest
        nis_out[k + 1] = nis
        lowpassed_out[k + 1] = lowpassed
        mag_used_out[k + 1] = mag_used
        hard_iron_out[k + 1] = hi_used
        llr_out[k + 1] = test[TEST_LLR]
    return skipped, sqrt_recovered, repaired, capped
