"""Compiled twins of the rest of the `ahrs` package's recursive filters (numba): AQUA, FKF,
Fourati's filter, ROLEQ, the UKF and AngularRate, as `peers.ahrs_recursive` runs them.

What was chosen and why. These filters of `ahrs` 0.4 are written in numpy, one call per sample:
50-1000 us a sample through the library (`python benchmarks/bench_peers.py --more`), so that their
grids over BROAD's fourteen trials would take hours. Here one `numba.njit` function per filter
(`*_kernel`) runs the adapter's whole loop (`peers.ahrs_recursive._loop` with the adapter's `step`)
over a recording, with the library's update written out in scalars. Numba, cached on disk, as for
`peers._compiled_ahrs`, whose helpers are shared: numpy's rounding of a norm (`_norm3`, `_norm4`,
BLAS `ddot`'s fused multiply-adds), `x ** 2` as numpy computes it for a float64 scalar (`_square`),
`ahrs.Quaternion`'s normalisation (`_versor`), product and `to_DCM`, and `np.linalg.inv` (`_inv`,
LAPACK `gesv` against the identity). Every function below names the library function or method it
mirrors in its docstring's first line and follows its arithmetic line by line, in the library's
order; the adapter's own lines (its virtual field, its stand-ins for a missing sample) are
mirrored where the adapter's `step` has them, and named so.

How close. AQUA, FKF, Fourati's filter, ROLEQ and AngularRate contract differences (the library
itself moves by 1e-15 when its accelerometer input moves by one unit in the last place): their
matrix products are written as sums in the library's association (a 4x4 matrix times a vector in
OpenBLAS's order, `_mat_vec4`; the others plain), and the twins agree with the library to 3e-15 on
windows of BROAD's, the course's and simulated recordings. The UKF does not: with the library's
alpha = 1e-3, its sigma points' mean weight is about -1e6 against 1.25e5 for the others, so that a
last-bit difference of one sigma point moves the mean by some 1e-10, and the library itself moves
by 1e-8 within 1500 samples when its input moves by one unit in the last place. Its twin therefore
rounds as numpy does where numpy's order is known: the weighted sums over the nine sigma points
(`np.sum(..., axis=1)`) in numpy's pairwise order (`_sum9`), the products with a rotation matrix's
transpose as OpenBLAS's `dgemv` (`_rt_times`, as `peers._compiled_ahrs.mahony_updateMARG`'s
`R.T @ v`). `tests/test_compiled_peers.py` checks every twin against the library to 1e-9, or ten
times the library's own rounding sensitivity where that is larger (the UKF).

Inputs of every kernel, prepared by `peers.ahrs_recursive` as its library path prepares them per
step (`_inputs`): `gyr` (N-1, 3) the interval rates, rad/s, body frame, an invalid sample already
replaced by the adapter's stand-in; `dt` (N-1,) s; `acc` (N-1, 3) the accelerometer sample at each
step's end, m/s^2, zero where not finite, `acc_ok` (N-1,) where not all zero; `mag` (N-1, 3) mT,
zero where invalid, `mag_ok` (N-1,) where valid and not all zero (all False in 6-D); `q0` (4,) the
seed in the library's convention; `out` (N-1, 4) receives the library's quaternion after each step,
in its own convention (the adapter turns the rows into ENU, as on its library path).
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from fusion import quaternion as quat

from ..kernels._compiled_quaternion import rotation_floats
from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _clip, _jit
from . import _compiled_ahrs
from ._compiled_ahrs import _fma, _inv, _norm3, _norm4, _product, _square, _to_DCM, _versor

# the kernels compile in `fusion.quaternion`'s rotation matrix and `_compiled_ahrs`' helpers
forget_stale_kernels(__file__, [quat.__file__, _compiled_ahrs.__file__])


# ================================================================= shared
@intrinsic
def _pow(typingctx, x, y):
    """x ** y as numpy computes it for float64 arrays and scalars: the C library's `pow` (marked
    `nobuiltin`, so that LLVM keeps the call, as `_compiled_ahrs._square` does)."""
    sig = types.float64(types.float64, types.float64)

    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        pow_ = builder.module.globals.get("pow") or ir.Function(builder.module, ir.FunctionType(double, [double] * 2),
                                                                "pow")
        pow_.attributes.add("nobuiltin")
        return builder.call(pow_, args)

    return sig, codegen


@_jit
def _rt_times(r, v0, v1, v2):
    """`R.T @ v` for a C-ordered 3x3 R (row-major 9-tuple r), rounded as OpenBLAS's `dgemv`
    does for this shape: a chain of fused multiply-adds (as `_compiled_ahrs.mahony_updateMARG`)."""
    return (_fma(r[6], v2, _fma(r[3], v1, r[0] * v0)),
            _fma(r[7], v2, _fma(r[4], v1, r[1] * v0)),
            _fma(r[8], v2, _fma(r[5], v1, r[2] * v0)))


@_jit
def _in_body(qw, qx, qy, qz, v0, v1, v2):
    """`peers.ahrs_recursive._in_body`: `R(q / |q|)^T v`, the body-frame reading of the world vector
    v at `R_world_body` = q (`quaternion.rotation_matrix`, then numpy's `R.T @ v`)."""
    n = _norm4(qw, qx, qy, qz)
    return _rt_times(rotation_floats((qw / n, qx / n, qy / n, qz / n)), v0, v1, v2)


@_jit
def _mat_vec4(M, qw, qx, qy, qz):
    """numpy's `M @ q` for a C-ordered (4, 4) M: OpenBLAS's `dgemv` for this shape sums each row's
    four products as (m_0 q_0 + m_2 q_2) + (m_1 q_1 + m_3 q_3) (read off by comparing bit for bit)."""
    return ((M[0, 0] * qw + M[0, 2] * qy) + (M[0, 1] * qx + M[0, 3] * qz),
            (M[1, 0] * qw + M[1, 2] * qy) + (M[1, 1] * qx + M[1, 3] * qz),
            (M[2, 0] * qw + M[2, 2] * qy) + (M[2, 1] * qx + M[2, 3] * qz),
            (M[3, 0] * qw + M[3, 2] * qy) + (M[3, 1] * qx + M[3, 3] * qz))


@_jit
def _omega(M, c, x0, x1, x2):
    """M = c Omega(x), the library's 4x4 rate matrix [[0, -x^T], [x, -[x]x]] (FKF's `Omega4`,
    ROLEQ's `Omega_t`, the UKF's and AngularRate's `Omega`), each element scaled by c."""
    M[0, 0], M[0, 1], M[0, 2], M[0, 3] = c * 0.0, c * -x0, c * -x1, c * -x2
    M[1, 0], M[1, 1], M[1, 2], M[1, 3] = c * x0, c * 0.0, c * x2, c * -x1
    M[2, 0], M[2, 1], M[2, 2], M[2, 3] = c * x1, c * -x2, c * 0.0, c * x0
    M[3, 0], M[3, 1], M[3, 2], M[3, 3] = c * x2, c * x1, c * -x0, c * 0.0


@_jit
def _write_row(out, k, q):
    out[k, 0], out[k, 1], out[k, 2], out[k, 3] = q[0], q[1], q[2], q[3]


# ================================================================= ahrs.filters.AQUA
@_jit
def slerp_I(w, x, y, z, ratio, t):
    """`ahrs.filters.aqua.slerp_I`: the interpolation of q towards the identity by `ratio`,
    linear (LERP) where q's scalar part exceeds the threshold t, spherical (SLERP) below it,
    normalised (Valenti et al. 2015, "Keeping a good attitude: a quaternion-based orientation filter
    for IMUs and MARGs", Sensors 15(8), eqs. 50-52)."""
    if w > t:
        c = 1.0 - ratio
        w, x, y, z = c * 1.0 + ratio * w, c * 0.0 + ratio * x, c * 0.0 + ratio * y, c * 0.0 + ratio * z
    else:
        angle = math.acos(w)
        s = math.sin(angle)
        s1 = math.sin(abs(1.0 - ratio) * angle)
        s2 = math.sin(ratio * angle)
        w, x, y, z = (1.0 * s1 / s + w * s2 / s, 0.0 * s1 / s + x * s2 / s, 0.0 * s1 / s + y * s2 / s,
                      0.0 * s1 / s + z * s2 / s)
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def adaptive_gain(ax, ay, az, alpha_bar, t1, t2, g):
    """`ahrs.filters.aqua.adaptive_gain`: alpha_bar f(e_m), e_m = | |a| - g | / g the
    acceleration's magnitude error, f falling linearly from 1 at e_m = t2 - t1 to 0 at t2
    (Valenti et al. 2015, eqs. 60-61)."""
    em = abs(_norm3(ax, ay, az) - g) / g
    return alpha_bar * _clip((t2 - em) / t1, 0.0, 1.0)


@_jit
def _aqua_predict(qw, qx, qy, qz, gx, gy, gz, dt):
    """AQUA's gyro step: q_dot = Omega(w) q with the library's Omega = 1/2 [[0, w^T], [-w, [w]x]]
    (Valenti et al. 2015, eq. 38, the inverse orientation's derivative), integrated over dt and
    normalised (`Quaternion(q + qDot * dt)`)."""
    o0, o1, o2 = 0.5 * gx, 0.5 * gy, 0.5 * gz
    dw = 0.5 * 0.0 * qw + o0 * qx + o1 * qy + o2 * qz
    dx = 0.5 * -gx * qw + 0.5 * 0.0 * qx + o2 * qy + 0.5 * -gy * qz
    dy = 0.5 * -gy * qw + 0.5 * -gz * qx + 0.5 * 0.0 * qy + o0 * qz
    dz = 0.5 * -gz * qw + o1 * qx + 0.5 * -gx * qy + 0.5 * 0.0 * qz
    return _versor(qw + dw * dt, qx + dx * dt, qy + dy * dt, qz + dz * dt)


@_jit
def _aqua_acc(qw, qx, qy, qz, ax, ay, az, a_norm, alpha, adaptive, threshold, gravity):
    """AQUA's accelerometer correction, shared by `updateIMU` and `updateMARG`: the gravity
    predicted by the prediction, the delta quaternion that turns it onto the measurement (Valenti
    et al. 2015, eq. 41 for a_z >= -1), interpolated towards the identity (eqs. 50-52, `slerp_I`;
    with `adaptive`, by `adaptive_gain`'s gain). Returns q_pred (x) delta, not normalised."""
    vx, vy, vz = ax / a_norm, ay / a_norm, az / a_norm
    gx, gy, gz = _rt_times(_to_DCM(qw, qx, qy, qz), vx, vy, vz)  # qInt.to_DCM().T @ a
    r = math.sqrt(2.0 * (gz + 1.0))
    cw, cx, cy, cz = math.sqrt((gz + 1.0) / 2.0), -gy / r, gx / r, 0.0
    if adaptive:
        alpha = adaptive_gain(ax, ay, az, 0.1, 0.1, 0.2, gravity)
    cw, cx, cy, cz = slerp_I(cw, cx, cy, cz, alpha, threshold)
    return _product(qw, qx, qy, qz, cw, cx, cy, cz)


@_jit
def aqua_updateIMU(qw, qx, qy, qz, gx, gy, gz, ax, ay, az, dt, alpha, adaptive, threshold, gravity):
    """`ahrs.filters.AQUA.updateIMU`: the gyro step and the accelerometer's correction (Valenti et
    al. 2015, sec. 5). A zero gyro sample returns q as given; a zero accelerometer sample the
    gyro step alone. q: the library's (the inverse of `R_world_body`); g: rad/s; a: any unit."""
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz
    qw, qx, qy, qz = _aqua_predict(qw, qx, qy, qz, gx, gy, gz, dt)
    a_norm = _norm3(ax, ay, az)
    if a_norm == 0.0:
        return qw, qx, qy, qz
    pw, px, py, pz = _aqua_acc(qw, qx, qy, qz, ax, ay, az, a_norm, alpha, adaptive, threshold, gravity)
    n = _norm4(pw, px, py, pz)
    return pw / n, px / n, py / n, pz / n


@_jit
def aqua_updateMARG(qw, qx, qy, qz, gx, gy, gz, ax, ay, az, mx, my, mz, dt, alpha, beta, adaptive, threshold,
                    gravity):
    """`ahrs.filters.AQUA.updateMARG`: `aqua_updateIMU`'s steps, then the magnetometer's
    correction, a rotation about the vertical only (Valenti et al. 2015, eqs. 44-47 and 59:
    the field's horizontal direction l_x, l_y in the corrected frame, interpolated with gain beta).
    A zero magnetometer sample skips it."""
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz
    qw, qx, qy, qz = _aqua_predict(qw, qx, qy, qz, gx, gy, gz, dt)
    a_norm = _norm3(ax, ay, az)
    if a_norm == 0.0:
        return qw, qx, qy, qz
    pw, px, py, pz = _versor(*_aqua_acc(qw, qx, qy, qz, ax, ay, az, a_norm, alpha, adaptive, threshold, gravity))
    m_norm = _norm3(mx, my, mz)
    if m_norm == 0.0:
        return pw, px, py, pz
    lx, ly, _ = _rt_times(_to_DCM(pw, px, py, pz), mx / m_norm, my / m_norm, mz / m_norm)
    gamma = _square(lx) + _square(ly)
    root = math.sqrt(gamma + lx * math.sqrt(gamma))
    cw, cx, cy, cz = root / math.sqrt(2.0 * gamma), 0.0, 0.0, ly / math.sqrt(2.0 * (gamma + lx * math.sqrt(gamma)))
    cw, cx, cy, cz = slerp_I(cw, cx, cy, cz, beta, threshold)
    w, x, y, z = _product(pw, px, py, pz, cw, cx, cy, cz)
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def aqua_kernel(gyr, acc, mag, dt, q0, alpha, beta, threshold, adaptive, gravity, marg, out):
    """The adapter's loop of `AQUA.updateIMU` (6-D) or `updateMARG` (9-D: `marg`) over a recording
    (`AQUAPeer.estimate`); the zero samples are the library's own "no sample" branches. gravity:
    the library's `aqua.GRAVITY` (m/s^2, for `adaptive_gain`). Writes out[0:N-1]."""
    qw, qx, qy, qz = q0[0], q0[1], q0[2], q0[3]
    for k in range(dt.shape[0]):
        if marg:
            qw, qx, qy, qz = aqua_updateMARG(qw, qx, qy, qz, gyr[k, 0], gyr[k, 1], gyr[k, 2], acc[k, 0], acc[k, 1],
                                             acc[k, 2], mag[k, 0], mag[k, 1], mag[k, 2], dt[k], alpha, beta, adaptive,
                                             threshold, gravity)
        else:
            qw, qx, qy, qz = aqua_updateIMU(qw, qx, qy, qz, gyr[k, 0], gyr[k, 1], gyr[k, 2], acc[k, 0], acc[k, 1],
                                            acc[k, 2], dt[k], alpha, adaptive, threshold, gravity)
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = qw, qx, qy, qz


# ================================================================= ahrs.filters.FKF
@_jit
def measurement_quaternion_acc_mag(q, acc, mag, q_new, J):
    """`ahrs.filters.FKF.measurement_quaternion_acc_mag`: the quaternion of the accelerometer and
    magnetometer in closed form, linear in the previous quaternion q, and its Jacobian with respect
    to the normalised readings (Guo et al. 2017, "A Novel Fast Linear Kalman Filter for Attitude
    Estimation", eqs. 27-37, as the library expands them). q: (4,); acc, mag: (3,) any unit;
    q_new: (4,) written (0.25 q_new / |q_new|, as the library scales it); J: (4, 6) written."""
    a_n = _norm3(acc[0], acc[1], acc[2])
    ax, ay, az = acc[0] / a_n, acc[1] / a_n, acc[2] / a_n
    m_n = _norm3(mag[0], mag[1], mag[2])
    mx, my, mz = mag[0] / m_n, mag[1] / m_n, mag[2] / m_n
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    mD = ax * mx + ay * my + az * mz
    mN = math.sqrt(1.0 - _square(mD))
    q_new[0] = (ay * mD * my + (1 + az) * (1 + mN * mx + mD * mz) + ax * (mD * mx - mN * mz)) * qw + (
        (mD + az * mD - ax * mN) * my + ay * (1 + mN * mx - mD * mz)) * qx + (
        ay * mN * my + ax * (-1 + mN * mx + mD * mz) + (1 + az) * (-(mD * mx) + mN * mz)) * qy + (
        -((ax * mD + mN + az * mN) * my) + ay * (mD * mx + mN * mz)) * qz
    q_new[1] = ((mD - az * mD - ax * mN) * my + ay * (1 + mN * mx + mD * mz)) * qw + (
        ay * mD * my - (-1 + az) * (1 + mN * mx - mD * mz) + ax * (mD * mx + mN * mz)) * qx + (
        (ax * mD + mN - az * mN) * my + ay * (-(mD * mx) + mN * mz)) * qy + (
        -(ay * mN * my) + ax * (1 - mN * mx + mD * mz) - (-1 + az) * (mD * mx + mN * mz)) * qz
    q_new[2] = (-(ay * mN * my) - ax * (1 + mN * mx + mD * mz) + (-1 + az) * (mD * mx - mN * mz)) * qw + (
        (-(ax * mD) + mN - az * mN) * my + ay * (mD * mx + mN * mz)) * qx + (
        ay * mD * my + (-1 + az) * (-1 + mN * mx + mD * mz) + ax * (mD * mx - mN * mz)) * qy + (
        (mD - az * mD + ax * mN) * my + ay * (1 - mN * mx + mD * mz)) * qz
    q_new[3] = ax * (qx + mN * mx * qx + mN * my * qy + mN * mz * qz + mD * (my * qw - mz * qx + mx * qz)) + (
        1 + az) * (mD * mx * qx + mD * my * qy + qz + mD * mz * qz - mN * (my * qw - mz * qx + mx * qz)) + ay * (
        mN * mz * qw + mN * my * qx + qy - mN * mx * qy - mD * (mx * qw + mz * qy - my * qz))
    n = _norm4(q_new[0], q_new[1], q_new[2], q_new[3])
    for i in range(4):
        q_new[i] = 0.25 * q_new[i] / n
    J[0, 0] = -qy - mN * (mz * qw + my * qx - mx * qy) + mD * (mx * qw + mz * qy - my * qz)
    J[0, 1] = qx + mN * mx * qx + mN * my * qy + mN * mz * qz + mD * (my * qw - mz * qx + mx * qz)
    J[0, 2] = qw + mN * mx * qw + mD * mz * qw + mD * my * qx - mD * mx * qy + mN * mz * qy - mN * my * qz
    J[0, 3] = (ax * mD + mN + az * mN) * qw + ay * mN * qx + (-((1 + az) * mD) + ax * mN) * qy + ay * mD * qz
    J[0, 4] = ay * mD * qw + (mD + az * mD - ax * mN) * qx + ay * mN * qy - (ax * mD + mN + az * mN) * qz
    J[0, 5] = mD * (qw + az * qw - ay * qx + ax * qy) + mN * (-(ax * qw) + qy + az * qy + ay * qz)
    J[1, 0] = qz - mN * (my * qw - mz * qx + mx * qz) + mD * (mx * qx + my * qy + mz * qz)
    J[1, 1] = qw + mN * mx * qw + mD * mz * qw + mD * my * qx - mD * mx * qy + mN * mz * qy - mN * my * qz
    J[1, 2] = -((1 + mN * mx) * qx) - mD * (my * qw - mz * qx + mx * qz) - mN * (my * qy + mz * qz)
    J[1, 3] = ay * (mN * qw - mD * qy) - (-1 + az) * (mN * qx + mD * qz) + ax * (mD * qx - mN * qz)
    J[1, 4] = mD * (qw - az * qw + ay * qx + ax * qy) - mN * (ax * qw + (-1 + az) * qy + ay * qz)
    J[1, 5] = ay * (mD * qw + mN * qy) + mD * ((-1 + az) * qx + ax * qz) + mN * (ax * qx + qz - az * qz)
    J[2, 0] = -((1 + mN * mx + mD * mz) * qw) - mD * my * qx + mD * mx * qy - mN * mz * qy + mN * my * qz
    J[2, 1] = qz - mN * (my * qw - mz * qx + mx * qz) + mD * (mx * qx + my * qy + mz * qz)
    J[2, 2] = -qy - mN * (mz * qw + my * qx - mx * qy) + mD * (mx * qw + mz * qy - my * qz)
    J[2, 3] = mD * ((-1 + az) * qw + ay * qx + ax * qy) - mN * (ax * qw + qy - az * qy + ay * qz)
    J[2, 4] = ay * (-(mN * qw) + mD * qy) - (-1 + az) * (mN * qx + mD * qz) + ax * (-(mD * qx) + mN * qz)
    J[2, 5] = mN * (qw - az * qw + ay * qx) - ax * (mD * qw + mN * qy) + mD * ((-1 + az) * qy + ay * qz)
    J[3, 0] = qx + mN * mx * qx + mN * my * qy + mN * mz * qz + mD * (my * qw - mz * qx + mx * qz)
    J[3, 1] = qy + mN * (mz * qw + my * qx - mx * qy) - mD * (mx * qw + mz * qy - my * qz)
    J[3, 2] = qz - mN * (my * qw - mz * qx + mx * qz) + mD * (mx * qx + my * qy + mz * qz)
    J[3, 3] = -(ay * (mD * qw + mN * qy)) + ax * (mN * qx + mD * qz) + (1 + az) * (mD * qx - mN * qz)
    J[3, 4] = (1 + az) * (-(mN * qw) + mD * qy) + ax * (mD * qw + mN * qy) + ay * (mN * qx + mD * qz)
    J[3, 5] = ay * (mN * qw - mD * qy) + (1 + az) * (mN * qx + mD * qz) + ax * (-(mD * qx) + mN * qz)


@_jit
def kalman_update(q_1, q_am, Pk, Phi, Sigma_eps, Sigma_v, w, q_out):
    """`ahrs.filters.FKF.kalman_update`: the linear Kalman filter's step with the measurement
    quaternion q_am (Guo et al. 2017, eqs. 38-42): q_ = Phi q, Sigma_q_ = Phi (P Phi^T) + Sigma_eps,
    G = Sigma_q_ (Sigma_q_ + Sigma_v)^-1, P = (I - G) Sigma_q_, q = q_ + G (q_am - q_).
    Pk: (4, 4) updated in place; w: work arrays; q_out: (4,) written (not normalised)."""
    PPt, Sq_, S, Sinv, G, L, piv = w
    q_ = _mat_vec4(Phi, q_1[0], q_1[1], q_1[2], q_1[3])
    for i in range(4):  # Pk_1 @ Phi.T
        for j in range(4):
            PPt[i, j] = Pk[i, 0] * Phi[j, 0] + Pk[i, 1] * Phi[j, 1] + Pk[i, 2] * Phi[j, 2] + Pk[i, 3] * Phi[j, 3]
    for i in range(4):  # Phi @ (.) + Sigma_eps
        for j in range(4):
            Sq_[i, j] = (Phi[i, 0] * PPt[0, j] + Phi[i, 1] * PPt[1, j] + Phi[i, 2] * PPt[2, j] + Phi[i, 3] * PPt[3, j]
                         + Sigma_eps[i, j])
            S[i, j] = Sq_[i, j] + Sigma_v[i, j]
    _inv(S, 4, L, piv, Sinv)
    for i in range(4):  # Gk = Sigma_q_ @ inv(.)
        for j in range(4):
            G[i, j] = Sq_[i, 0] * Sinv[0, j] + Sq_[i, 1] * Sinv[1, j] + Sq_[i, 2] * Sinv[2, j] + Sq_[i, 3] * Sinv[3, j]
    for i in range(4):  # (I - Gk) @ Sigma_q_
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += ((1.0 if i == k else 0.0) - G[i, k]) * Sq_[k, j]
            Pk[i, j] = s
    d0, d1, d2, d3 = q_am[0] - q_[0], q_am[1] - q_[1], q_am[2] - q_[2], q_am[3] - q_[3]
    for i in range(4):
        q_out[i] = q_[i] + (G[i, 0] * d0 + G[i, 1] * d1 + G[i, 2] * d2 + G[i, 3] * d3)


@_jit
def fkf_kernel(gyr, acc, acc_ok, mag, mag_ok, dt, q0, Pk, sigma_g, sigma_a, sigma_m, out):
    """The adapter's loop over a recording (`FKFPeer.estimate`'s `step`: the lines of
    `FKF._compute_all` with each step's dt, in NWU): Phi = I + dt/2 Omega4(w), the process noise
    Sigma_eps = (dt/2)^2 Xi Sigma_g Xi^T (Guo et al. 2017, eqs. 17-19), the measurement
    quaternion and its noise J Sigma_am J^T, the Kalman update. A missing accelerometer sample is
    the gravity the prediction Phi q expects, a missing magnetometer sample (all of them in 6-D) the
    horizontal northern field it expects (the adapter's virtual field). Pk: (4, 4) the initial
    covariance, overwritten with the final one. The state q is carried unnormalised, as the
    library carries it. Writes out[0:N-1]."""
    Phi, Xe, Sigma_eps, Jm, JS, Sigma_v = (np.empty((4, 4)), np.empty((4, 3)), np.empty((4, 4)), np.empty((4, 6)),
                                           np.empty((4, 6)), np.empty((4, 4)))
    w = (np.empty((4, 4)), np.empty((4, 4)), np.empty((6, 6)), np.empty((6, 6)), np.empty((4, 4)), np.empty((6, 6)),
         np.empty(6, dtype=np.int64))
    q, q_am, a, m, nxt = q0.copy(), np.empty(4), np.empty(3), np.empty(3), np.empty(4)
    am = (sigma_a, sigma_a, sigma_a, sigma_m, sigma_m, sigma_m)  # the diagonal of Sigma_am
    for k in range(dt.shape[0]):
        c = 0.5 * dt[k]
        _omega(Phi, c, gyr[k, 0], gyr[k, 1], gyr[k, 2])  # np.identity(4) + 0.5 * dt * Omega4(w)
        for i in range(4):
            Phi[i, i] = 1.0 + Phi[i, i]
        Xi = ((q[1], q[2], q[3]), (-q[0], -q[3], -q[2]), (q[2], -q[0], -q[1]), (-q[2], q[1], -q[0]))
        c2 = _square(dt[k] / 2.0)
        for i in range(4):  # ((dt/2)^2 Xi) @ Sigma_g, Sigma_g = sigma_g I_3
            for j in range(3):
                Xe[i, j] = (c2 * Xi[i][0]) * (sigma_g if j == 0 else 0.0) + (c2 * Xi[i][1]) * (
                    sigma_g if j == 1 else 0.0) + (c2 * Xi[i][2]) * (sigma_g if j == 2 else 0.0)
        for i in range(4):  # (.) @ Xi^T
            for j in range(4):
                Sigma_eps[i, j] = Xe[i, 0] * Xi[j][0] + Xe[i, 1] * Xi[j][1] + Xe[i, 2] * Xi[j][2]
        a[0], a[1], a[2] = acc[k, 0], acc[k, 1], acc[k, 2]
        m[0], m[1], m[2] = mag[k, 0], mag[k, 1], mag[k, 2]
        if not acc_ok[k] or not mag_ok[k]:
            pw, px, py, pz = _mat_vec4(Phi, q[0], q[1], q[2], q[3])  # the prediction Phi q
            if not acc_ok[k]:
                a[0], a[1], a[2] = _in_body(pw, px, py, pz, 0.0, 0.0, 1.0)
            if not mag_ok[k]:
                m[0], m[1], m[2] = _in_body(pw, px, py, pz, 1.0, 0.0, 0.0)
        measurement_quaternion_acc_mag(q, a, m, q_am, Jm)
        for i in range(4):  # (J @ Sigma_am) @ J^T
            for j in range(6):
                s = 0.0
                for l in range(6):
                    s += Jm[i, l] * (am[l] if l == j else 0.0)
                JS[i, j] = s
        for i in range(4):
            for j in range(4):
                s = 0.0
                for l in range(6):
                    s += JS[i, l] * Jm[j, l]
                Sigma_v[i, j] = s
        kalman_update(q, q_am, Pk, Phi, Sigma_eps, Sigma_v, w, nxt)
        q[:] = nxt
        _write_row(out, k, q)


# ================================================================= ahrs.filters.Fourati
@_jit
def _skew_T_rows(X, row, vx, vy, vz):
    """Rows row..row+2 of `-2 * np.c_[skew(f), skew(h)].T`: -2 skew(v)^T, skew(v) = [[0, -v_z, v_y],
    [v_z, 0, -v_x], [-v_y, v_x, 0]] (`ahrs.common.mathfuncs.skew`)."""
    S = ((0.0, -vz, vy), (vz, 0.0, -vx), (-vy, vx, 0.0))
    for i in range(3):
        for j in range(3):
            X[row + i, j] = -2.0 * S[j][i]


@_jit
def fourati_update(q, gx, gy, gz, ax, ay, az, mx, my, mz, dt, gain, g_q, m_q, w, out):
    """`ahrs.filters.Fourati.update`: the gyro's quaternion derivative, multiplied by the
    correction [1, eta] of a Levenberg-Marquardt step on the accelerometer's and magnetometer's
    errors (Fourati, Manamanni, Afilal & Handrich 2011, "A Nonlinear Filtering Approach for the
    Attitude and Dynamic Body Acceleration Estimation Based on Inertial and Magnetic Sensors:
    Bio-Logging Application", IEEE Sensors J. 11(1), eqs. 25-31 with lambda = 1e-5), integrated over
    dt and normalised. q: (4,) the quaternion before the step; g: rad/s; a, m: any unit, not zero
    (the adapter's stand-ins); g_q, m_q: the library's reference quaternions; w: work arrays; out:
    (4,) written. A zero gyro sample returns q as given (the library's first branch)."""
    X, XtX, Minv, L, piv, e = w
    if _norm3(gx, gy, gz) == 0.0:
        out[0], out[1], out[2], out[3] = q[0], q[1], q[2], q[3]
        return
    qw, qx, qy, qz = _versor(q[0], q[1], q[2], q[3])  # Quaternion(q)
    pw, px, py, pz = _product(qw, qx, qy, qz, 0.0, gx, gy, gz)
    dw, dx, dy, dz = 0.5 * pw, 0.5 * px, 0.5 * py, 0.5 * pz  # qDot = 0.5 q (x) [0, w] (eq. 25)
    a_norm = _norm3(ax, ay, az)
    m_norm = _norm3(mx, my, mz)
    cw, cx, cy, cz = _versor(qw, -qx, -qy, -qz)  # Quaternion(q.conj)
    f = _product(cw, cx, cy, cz, *_product(g_q[0], g_q[1], g_q[2], g_q[3], qw, qx, qy, qz))  # fhat (eq. 27)
    h = _product(cw, cx, cy, cz, *_product(m_q[0], m_q[1], m_q[2], m_q[3], qw, qx, qy, qz))  # hhat
    dq = (ax / a_norm - f[1], ay / a_norm - f[2], az / a_norm - f[3],
          mx / m_norm - h[1], my / m_norm - h[2], mz / m_norm - h[3])  # y - yhat
    _skew_T_rows(X, 0, f[1], f[2], f[3])  # X = -2 [skew(f) skew(h)]^T (eq. 30)
    _skew_T_rows(X, 3, h[1], h[2], h[3])
    for i in range(3):  # X^T X + lambda I
        for j in range(3):
            s = 0.0
            for k in range(6):
                s += X[k, i] * X[k, j]
            XtX[i, j] = s + 1e-05 * (1.0 if i == j else 0.0)
    _inv(XtX, 3, L, piv, Minv)
    for i in range(3):  # eta = ((gain (X^T X + lambda I)^-1) X^T) dq (eq. 31)
        s = 0.0
        for j in range(6):
            kij = (gain * Minv[i, 0]) * X[j, 0] + (gain * Minv[i, 1]) * X[j, 1] + (gain * Minv[i, 2]) * X[j, 2]
            s += kij * dq[j]
        e[i] = s
    dw, dx, dy, dz = _product(dw, dx, dy, dz, 1.0, e[0], e[1], e[2])  # qDot (x) [1, eta]
    w_, x_, y_, z_ = qw + dw * dt, qx + dx * dt, qy + dy * dt, qz + dz * dt
    n = _norm4(w_, x_, y_, z_)
    out[0], out[1], out[2], out[3] = w_ / n, x_ / n, y_ / n, z_ / n


@_jit
def fourati_kernel(gyr, acc, acc_ok, mag, mag_ok, dt, q0, gain, g_q, m_q, m_ref, out):
    """The adapter's loop of `Fourati.update` over a recording (`FouratiPeer.estimate`, ENU): a
    missing accelerometer sample is the gravity the current estimate expects, a missing
    magnetometer sample (all of them in 6-D) the reference field `m_ref` (3,) it expects (the
    adapter's virtual field). Writes out[0:N-1]."""
    w = (np.empty((6, 3)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)), np.empty(6, dtype=np.int64),
         np.empty(3))
    q, nxt = q0.copy(), np.empty(4)
    for k in range(dt.shape[0]):
        ax, ay, az = acc[k, 0], acc[k, 1], acc[k, 2]
        mx, my, mz = mag[k, 0], mag[k, 1], mag[k, 2]
        if not acc_ok[k]:
            ax, ay, az = _in_body(q[0], q[1], q[2], q[3], 0.0, 0.0, 1.0)
        if not mag_ok[k]:
            mx, my, mz = _in_body(q[0], q[1], q[2], q[3], m_ref[0], m_ref[1], m_ref[2])
        fourati_update(q, gyr[k, 0], gyr[k, 1], gyr[k, 2], ax, ay, az, mx, my, mz, dt[k], gain, g_q, m_q, w, nxt)
        q[:] = nxt
        _write_row(out, k, q)


# ================================================================= ahrs.filters.ROLEQ
@_jit
def attitude_propagation(q, gx, gy, gz, dt, M):
    """`ahrs.filters.ROLEQ.attitude_propagation`: q_omega = (I + dt/2 Omega(w)) q, normalised
    (Zhou et al. 2018, "Novel Optimal Linear Estimator of Quaternion from Gravity and Geomagnetic
    Vectors", eq. 34's first-order integration). M: (4, 4) work."""
    _omega(M, 0.5 * dt, gx, gy, gz)
    for i in range(4):
        M[i, i] = 1.0 + M[i, i]
    w, x, y, z = _mat_vec4(M, q[0], q[1], q[2], q[3])
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def WW(W, bx, by, bz, rx, ry, rz):
    """`ahrs.filters.ROLEQ.WW`: W = r_x M1(b) + r_y M2(b) + r_z M3(b), the matrix of one vector
    pair in OLEQ (Zhou et al. 2018, eqs. 17-19). W: (4, 4) written."""
    M1 = ((bx, 0.0, bz, -by), (0.0, bx, by, bz), (bz, by, -bx, 0.0), (-by, bz, 0.0, -bx))
    M2 = ((by, -bz, 0.0, bx), (-bz, -by, bx, 0.0), (0.0, bx, by, bz), (bx, 0.0, bz, -by))
    M3 = ((bz, by, -bx, 0.0), (by, -bz, 0.0, bx), (-bx, 0.0, -bz, by), (0.0, bx, by, bz))
    for i in range(4):
        for j in range(4):
            W[i, j] = rx * M1[i][j] + ry * M2[i][j] + rz * M3[i][j]


@_jit
def oleq(ax, ay, az, mx, my, mz, qw, qx, qy, qz, a0, a1, a_ref, m_ref, Wa, Wm):
    """`ahrs.filters.ROLEQ.oleq`: one step of OLEQ's power iteration from q_omega, q = R q_omega /
    |.| with R = 1/2 (I + a_1 W_a + a_2 W_m) (Zhou et al. 2018, eqs. 22 and 34). A zero sample
    returns q_omega. a_ref, m_ref: the library's references; Wa, Wm: (4, 4) work."""
    a_norm = _norm3(ax, ay, az)
    m_norm = _norm3(mx, my, mz)
    if not a_norm > 0.0 or not m_norm > 0.0:
        return qw, qx, qy, qz
    WW(Wa, ax / a_norm, ay / a_norm, az / a_norm, a_ref[0], a_ref[1], a_ref[2])
    WW(Wm, mx / m_norm, my / m_norm, mz / m_norm, m_ref[0], m_ref[1], m_ref[2])
    for i in range(4):
        for j in range(4):
            Wa[i, j] = 0.5 * ((1.0 if i == j else 0.0) + (a0 * Wa[i, j] + a1 * Wm[i, j]))
    w, x, y, z = _mat_vec4(Wa, qw, qx, qy, qz)
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def roleq_kernel(gyr, acc, acc_ok, mag, mag_ok, dt, q0, a0, a1, a_ref, m_ref, field, out):
    """The adapter's loop over a recording (`ROLEQPeer.estimate`'s `step`, ENU): the gyro step
    (`attitude_propagation`), then `oleq`; where the accelerometer sample is usable but the
    magnetometer's is not (all of them in 6-D), the magnetometer reads `field` (3,), the adapter's
    reference field, at the gyro step's estimate (its virtual field). Writes out[0:N-1]."""
    M, Wa, Wm = np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4))
    q = q0.copy()
    for k in range(dt.shape[0]):
        gw, gx, gy, gz = attitude_propagation(q, gyr[k, 0], gyr[k, 1], gyr[k, 2], dt[k], M)
        mx, my, mz = mag[k, 0], mag[k, 1], mag[k, 2]
        if acc_ok[k] and not mag_ok[k]:
            mx, my, mz = _in_body(gw, gx, gy, gz, field[0], field[1], field[2])
        q[0], q[1], q[2], q[3] = oleq(acc[k, 0], acc[k, 1], acc[k, 2], mx, my, mz, gw, gx, gy, gz, a0, a1, a_ref,
                                      m_ref, Wa, Wm)
        _write_row(out, k, q)


# ================================================================= ahrs.filters.UKF
@_jit
def _sum9(v0, v1, v2, v3, v4, v5, v6, v7, v8):
    """`np.sum` of nine floats along a contiguous axis: numpy's pairwise summation (eight
    partial sums paired, then the ninth added)."""
    return ((v0 + v1) + (v2 + v3)) + ((v4 + v5) + (v6 + v7)) + v8


@_jit
def _cholesky(A, L):
    """`np.linalg.cholesky` of a (4, 4) A: L lower triangular with L L^T = A (Golub & Van Loan
    2013, alg. 4.2.1, column by column), as OpenBLAS's unblocked `potf2` orders it: each pivot
    a_jj minus a dot product (a chain of fused multiply-adds, as `_norm3`), the column below it
    scaled by the pivot's reciprocal. Returns False where A is not positive definite (`potrf`
    reports a pivot that is not positive, or NaN)."""
    for j in range(4):
        dot = 0.0
        for k in range(j):
            dot = _fma(L[j, k], L[j, k], dot)
        s = A[j, j] - dot
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        r = 1.0 / d
        for i in range(j + 1, 4):
            dot = 0.0
            for k in range(j):
                dot = _fma(L[i, k], L[j, k], dot)
            L[i, j] = (A[i, j] - dot) * r
        for i in range(j):
            L[i, j] = 0.0
    return True


@_jit
def compute_sigma_points(q, P, c, sp, A, L):
    """`ahrs.filters.UKF.compute_sigma_points`: the 2n + 1 sigma points q, q +- the columns of
    sqrt((n + lambda) |P|) (Wan & van der Merwe 2000, "The unscented Kalman filter for nonlinear
    estimation", eq. 15; the library takes |P| elementwise, and regularises P by 1e-8 I where
    that is not positive definite). c: n + lambda; sp: (4, 9) written; A, L: (4, 4) work. Returns
    False where the regularised P is not positive definite either (where the library raises
    numpy's LinAlgError)."""
    for i in range(4):
        for j in range(4):
            A[i, j] = c * abs(P[i, j])
    if not _cholesky(A, L):
        for i in range(4):
            for j in range(4):
                A[i, j] = c * (P[i, j] + (1e-08 if i == j else 0.0))
        if not _cholesky(A, L):
            return False
    for i in range(4):
        sp[i, 0] = q[i]
        for j in range(4):
            sp[i, j + 1] = q[i] + L[i, j]
            sp[i, 4 + j + 1] = q[i] - L[i, j]
    return True


@_jit
def ukf_update(q, gx, gy, gz, acc, mag, use_mag, dt, P, wm, wc, c, Q_t, R_var, a_ref, m_ref, w, out):
    """`ahrs.filters.UKF.update`: one step of the library's quaternion UKF (Wan & van der Merwe
    2000): sigma points of (q, P); each propagated by (I + dt/2 Omega(w)) and normalised; their
    weighted mean (normalised) and covariance plus Q_t; their predicted gravity (and field)
    R(s)^T a_ref (R(s)^T m_ref); the measurement mean and covariance plus R, the cross covariance,
    the gain K = P_xz P_zz^-1; q = (mean + K (z - z_mean)) / |.|, P = P_pred - (K P_zz) K^T.
    q: (4,); g: rad/s; acc, mag: (3,) normalised (the adapter's); P: (4, 4) updated in place;
    wm, wc: (9,) the library's weights; c: n + lambda; Q_t: the process variance (Q_t = Q_t I_4);
    R_var: the measurement variance (R = R_var I); w: work arrays; out: (4,) written. Returns False
    (and writes nothing) where the library raises: P not positive definite (`compute_sigma_points`)."""
    sp, prop, meas, A, L, Pp, Pzz, Pxz, Sinv, K, KP, Lw, piv = w
    m = 6 if use_mag else 3
    if not compute_sigma_points(q, P, c, sp, A, L):
        return False
    _omega(A, 0.5, gx, gy, gz)  # rotation_operator = np.eye(4) + 0.5 * Omega(w) * dt
    for i in range(4):
        for j in range(4):
            A[i, j] = (1.0 if i == j else 0.0) + A[i, j] * dt
    for s in range(9):
        pw, px, py, pz = _versor(*_mat_vec4(A, sp[0, s], sp[1, s], sp[2, s], sp[3, s]))
        prop[0, s], prop[1, s], prop[2, s], prop[3, s] = pw, px, py, pz
    mean = np.empty(4)
    for i in range(4):
        mean[i] = _sum9(prop[i, 0] * wm[0], prop[i, 1] * wm[1], prop[i, 2] * wm[2], prop[i, 3] * wm[3],
                        prop[i, 4] * wm[4], prop[i, 5] * wm[5], prop[i, 6] * wm[6], prop[i, 7] * wm[7],
                        prop[i, 8] * wm[8])
    mean[0], mean[1], mean[2], mean[3] = _versor(mean[0], mean[1], mean[2], mean[3])
    Pp[:, :] = 0.0
    for s in range(9):
        for i in range(4):
            di = prop[i, s] - mean[i]
            for j in range(4):
                Pp[i, j] += wc[s] * (di * (prop[j, s] - mean[j]))
    for i in range(4):
        for j in range(4):
            Pp[i, j] += Q_t if i == j else 0.0
    for s in range(9):
        r = _to_DCM(*_versor(prop[0, s], prop[1, s], prop[2, s], prop[3, s]))
        meas[0, s], meas[1, s], meas[2, s] = _rt_times(r, a_ref[0], a_ref[1], a_ref[2])
        if use_mag:
            meas[3, s], meas[4, s], meas[5, s] = _rt_times(r, m_ref[0], m_ref[1], m_ref[2])
    zmean = np.empty(6)
    for i in range(m):
        zmean[i] = _sum9(meas[i, 0] * wm[0], meas[i, 1] * wm[1], meas[i, 2] * wm[2], meas[i, 3] * wm[3],
                         meas[i, 4] * wm[4], meas[i, 5] * wm[5], meas[i, 6] * wm[6], meas[i, 7] * wm[7],
                         meas[i, 8] * wm[8])
    Pzz[:, :] = 0.0
    Pxz[:, :] = 0.0
    for s in range(9):
        for i in range(m):
            dz = meas[i, s] - zmean[i]
            for j in range(m):
                Pzz[i, j] += wc[s] * (dz * (meas[j, s] - zmean[j]))
        for i in range(4):
            dx = prop[i, s] - mean[i]
            for j in range(m):
                Pxz[i, j] += wc[s] * (dx * (meas[j, s] - zmean[j]))
    for i in range(m):
        for j in range(m):
            Pzz[i, j] += R_var if i == j else 0.0
    _inv(Pzz, m, Lw, piv, Sinv)
    for i in range(4):  # K = P_xz @ inv(P_zz)
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += Pxz[i, k] * Sinv[k, j]
            K[i, j] = s
    z = (acc[0], acc[1], acc[2], mag[0], mag[1], mag[2])
    for i in range(4):  # mean + K (z - z_mean)
        s = 0.0
        for k in range(m):
            s += K[i, k] * (z[k] - zmean[k])
        out[i] = mean[i] + s
    # Quaternion(mean + correction): `Quaternion.__add__` normalises, and so does the constructor
    out[0], out[1], out[2], out[3] = _versor(*_versor(out[0], out[1], out[2], out[3]))
    for i in range(4):  # K @ P_zz
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += K[i, k] * Pzz[k, j]
            KP[i, j] = s
    for i in range(4):  # P = P_pred - (K P_zz) K^T
        for j in range(4):
            s = 0.0
            for k in range(m):
                s += KP[i, k] * K[j, k]
            P[i, j] = Pp[i, j] - s
    return True


@_jit
def ukf_kernel(gyr, acc, acc_ok, mag, mag_ok, dt, q0, P, wm, wc, c, Q_t, R_var, a_ref, m_ref, nine_d, out):
    """The adapter's loop of `UKF.update` over a recording (`AhrsUKFPeer.estimate`'s `step`, ENU):
    the accelerometer normalised, or, where missing, the gravity the current estimate expects; in
    9-D (`nine_d`) likewise the magnetometer, or the reference field `m_ref` it expects. P: (4, 4)
    the initial covariance, overwritten with the final one. Writes out[0:N-1]; returns -1, or the
    step at which the library would raise (`ukf_update`), where it stops."""
    w = (np.empty((4, 9)), np.empty((4, 9)), np.empty((6, 9)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)),
         np.empty((6, 6)), np.empty((4, 6)), np.empty((6, 6)), np.empty((4, 6)), np.empty((4, 6)), np.empty((6, 6)),
         np.empty(6, dtype=np.int64))
    q, nxt, a, m = q0.copy(), np.empty(4), np.empty(3), np.zeros(3)
    for k in range(dt.shape[0]):
        if acc_ok[k]:
            n = _norm3(acc[k, 0], acc[k, 1], acc[k, 2])
            a[0], a[1], a[2] = acc[k, 0] / n, acc[k, 1] / n, acc[k, 2] / n
        else:
            a[0], a[1], a[2] = _in_body(q[0], q[1], q[2], q[3], a_ref[0], a_ref[1], a_ref[2])
        if nine_d:
            if mag_ok[k]:
                n = _norm3(mag[k, 0], mag[k, 1], mag[k, 2])
                m[0], m[1], m[2] = mag[k, 0] / n, mag[k, 1] / n, mag[k, 2] / n
            else:
                m[0], m[1], m[2] = _in_body(q[0], q[1], q[2], q[3], m_ref[0], m_ref[1], m_ref[2])
        if not ukf_update(q, gyr[k, 0], gyr[k, 1], gyr[k, 2], a, m, nine_d, dt[k], P, wm, wc, c, Q_t, R_var, a_ref,
                          m_ref, w, nxt):
            return k
        q[:] = nxt
        _write_row(out, k, q)
    return -1


# ================================================================= ahrs.filters.AngularRate
@_jit
def angular_update(qw, qx, qy, qz, gx, gy, gz, closed, order, dt, M, A):
    """`ahrs.filters.AngularRate.update`: q_new = A q, normalised, with A = cos(|w| dt/2) I +
    sin(|w| dt/2) Omega(w) / |w| (`closed`: the exponential of the rate over dt) or the library's
    series I + sum_i S**i / i! with S = dt/2 Omega(w) (the powers elementwise, as the library
    computes them). q is normalised first; a zero rate returns it. M, A: (4, 4) work."""
    qw, qx, qy, qz = _versor(qw, qx, qy, qz)
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz
    _omega(M, 1.0, gx, gy, gz)
    if closed:
        wn = _norm3(gx, gy, gz)
        co, si = math.cos(wn * dt / 2.0), math.sin(wn * dt / 2.0)
        for i in range(4):
            for j in range(4):
                A[i, j] = co * (1.0 if i == j else 0.0) + si * M[i, j] / wn
    else:
        c = 0.5 * dt
        for i in range(4):
            for j in range(4):
                A[i, j] = 1.0 if i == j else 0.0
        f = 1.0
        for p in range(1, order + 1):
            f *= p  # math.factorial(p)
            for i in range(4):
                for j in range(4):
                    s = c * M[i, j]
                    sp = s if p == 1 else (s * s if p == 2 else _pow(s, float(p)))
                    A[i, j] += sp / f
    return _versor(*_mat_vec4(A, qw, qx, qy, qz))


@_jit
def angular_kernel(gyr, dt, q0, closed, order, out):
    """The adapter's loop of `AngularRate.update` over a recording (`AngularRatePeer.estimate`).
    Writes out[0:N-1]."""
    M, A = np.empty((4, 4)), np.empty((4, 4))
    qw, qx, qy, qz = q0[0], q0[1], q0[2], q0[3]
    for k in range(dt.shape[0]):
        qw, qx, qy, qz = angular_update(qw, qx, qy, qz, gyr[k, 0], gyr[k, 1], gyr[k, 2], closed, order, dt[k], M, A)
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = qw, qx, qy, qz


_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache (`peers._compiled_ahrs.load`): run
    each once on a one-step recording, 6-D and 9-D, with the argument types the adapters pass."""
    global _loaded
    if _loaded:
        return
    gyr, dt = np.full((1, 3), 0.1), np.full(1, 0.01)
    acc, mag = np.array([[0.0, 0.0, 9.8]]), np.array([[0.02, 0.0, -0.04]])
    ok = np.ones(1, dtype=np.bool_)
    unit, out, ref = np.array([1.0, 0.0, 0.0, 0.0]), np.empty((1, 4)), np.array([0.0, 1.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    for marg in (False, True):
        aqua_kernel(gyr, acc, mag, dt, unit, 0.01, 0.01, 0.9, marg, 9.8, marg, out)
        ukf_kernel(gyr, acc, ok, mag, ok, dt, unit, np.eye(4) * 0.01, np.full(9, 0.1), np.full(9, 0.1), 4e-6, 1e-4,
                   1e-2, up, ref, marg, out)
    fkf_kernel(gyr, acc, ok, mag, ok, dt, unit, np.eye(4) * 0.01, 0.01, 0.01, 0.01, out)
    fourati_kernel(gyr, acc, ok, mag, ok, dt, unit, 0.1, np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0, 0.0]),
                   ref, out)
    roleq_kernel(gyr, acc, ok, mag, ok, dt, unit, 1.0, 1.0, up, ref, ref, out)
    angular_kernel(gyr, dt, unit, True, 1, out)
    _loaded = True
