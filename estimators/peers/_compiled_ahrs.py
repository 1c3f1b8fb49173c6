"""Compiled twins of the `ahrs` package's Madgwick, Mahony and EKF filters (numba).

What was chosen and why. The `ahrs` filters (`ahrs.filters.Madgwick`, `Mahony`, `EKF`, version
0.4) are written in numpy, one call per sample: about 60 us a sample for Madgwick and Mahony and
over 100 us for the EKF, almost all of it the overhead of numpy calls on 3- and 4-vectors. Tuning
them over a grid of parameters and a benchmark's recordings would take hours. Here one
`numba.njit` function per filter runs the adapter's whole loop (`peers._marg_loop` in 9-D,
`RecursiveEstimator.estimate` with the adapter's `step` in 6-D) over a recording, with the
library's update written out in scalars. Numba, cached on disk, for the reasons `_compiled` gives
(`kernels._numba._jit`: the kernels are cached next to this file, IEEE division). The quaternion
product of the 9-D output turn (NWU -> ENU) is `fusion.quaternion`'s own scalar function, compiled
(`kernels._compiled_quaternion.multiply_floats`), as `peers` applies it with `quaternion.multiply`;
`_kernel_cache.forget_stale_kernels` drops this module's cache when `fusion/quaternion.py` changes.

The library is the reference. Every function below that implements a library method is declared
with it (`kernels._numba.mirrors`, as the filters' and the smoothers' kernels are: the twin of
`Madgwick.updateIMU` is `madgwick_updateIMU`, its name prefixed by the filter's, since one module
holds the three), the others are listed in `HELPERS`; each follows the library's arithmetic line
by line, in the same order where the order decides the rounding:
its normalisations (`ahrs.Quaternion(q)` divides by the norm on construction, so an update
normalises its input, and Madgwick's result is normalised twice: `Quaternion(q + qDot dt)` and
then `q_new /= norm(q_new)`), its branches (a zero gyro sample returns the normalised input
unchanged, skipping the correction and Mahony's bias update; a zero accelerometer sample skips
the correction; a zero magnetometer sample falls back to the IMU update), and its choice of
which quaternion enters which term (Madgwick's objective uses `q / |q|` again; the EKF's
measurement model normalises the predicted quaternion but its Jacobian does not).

Rounding, and why it matters here. Madgwick's filter steps along the *normalised* gradient, a
step of fixed length beta dt however small the error: at rest, once the estimate sits on the
accelerometer's inclination, it hops about it by about beta dt, and the direction of each hop is
decided by an error vector of about that size. There the filter is chaotic: a difference in the
last bit grows by orders of magnitude within a second (from 1e-16 to 1e-9 within 2 s of rest on a
course recording). So Madgwick's and Mahony's twins round as numpy does on its calls into BLAS, not
just as the formulas read: `np.linalg.norm` is the square root of `ddot`, a chain of fused
multiply-adds (`_norm3`, `_norm4`); `J.T @ f`, `R @ m` and `R.T @ v` are `dgemv`, whose
fused multiply-adds come in a fixed order for each shape (`_gemv3`, `_gemv6` and Mahony's
products). These orders are OpenBLAS's (the BLAS of numpy's wheels, its x86-64 kernels for
processors with FMA), read off by comparing bit for bit; with them the twins equal the library
bit for bit on the shared recordings, for the OpenBLAS build they were read from. With another BLAS,
build or processor the library's own last bits change, and the twins then agree with it to
rounding only (which, at rest, Madgwick's chaos can grow: with numpy 2.4's OpenBLAS 0.3.31, 8.7e-9
on a course recording, where the library itself moves 3.5e-8 when its accelerometer input moves by
one unit in the last place). The EKF contracts differences instead of growing them; its matrix products
are written as the library associates them (`(F P) F^T`, `(P H^T) S^-1`), with plain sums, and
its 3x3 or 6x6 inverse is an LU factorisation with partial pivoting solved against the
identity, as numpy's `inv` (LAPACK `gesv`) does: it agrees to 4e-13 on the shared recordings.
`tests/test_compiled_peers.py` checks the twins against the library to 1e-9 on every shared
recording and on simulated recordings with invalid gyro and magnetometer samples.

One departure from the library, made in the adapter for both paths: `updateMARG` falls back to
`updateIMU(q, gyr, acc)` on a zero magnetometer sample *without passing dt*, so that step would
integrate over the library's default 0.01 s instead of the real interval. The adapters call
`updateIMU(..., dt=dt)` themselves for such a sample (`peers.ahrs_filters.MadgwickPeer`), and the twins do
the same.

Inputs of every kernel, prepared by `peers` exactly as its library path prepares them per
sample: `gyr` (N-1, 3) the interval rates, rad/s, body frame, an invalid sample already
replaced by the adapter's stand-in; `acc` (N-1, 3) the accelerometer sample at each step's end,
m/s^2, body frame; `mag` (N-1, 3) uT, body frame, zero rows where there is none (or (0, 3): 6-D);
`dt` (N-1,) s; `out` (N, 4) receives rows 1..N-1, scalar-first quaternions.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from fusion import quaternion as quat

from ..kernels._compiled_quaternion import multiply_floats as qmul
from ..kernels._numba import _jit, mirrors
from ..kernels._kernel_cache import forget_stale_kernels

forget_stale_kernels(__file__, [quat.__file__])  # the 9-D output turn compiles fusion.quaternion's product

# Kernels without a library method of their own (`kernels._numba.mirrors`): BLAS's rounding (`_norm3`,
# `_norm4`, `_gemv3`, `_gemv6`), `ahrs.Quaternion(q)`'s normalisation (`_versor`), what Mahony's two
# updates share (`_mahony_step`), rows of `EKF.dhdq` (`_dhdq_rows`), `np.linalg.inv` (`_inv`), the
# output's frame (`_write`) and the adapters' loops (`*_kernel`).
HELPERS = ("_norm3", "_norm4", "_gemv3", "_gemv6", "_versor", "_mahony_step", "_dhdq_rows", "_inv", "_write",
           "madgwick_kernel", "mahony_kernel", "ekf_kernel")

_SQRT_HALF = math.sqrt(0.5)  # Rz(90 deg) = [sqrt(1/2), 0, 0, sqrt(1/2)]: NWU -> ENU, as `peers._RZ90`


# ================================================================= numpy's rounding
@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c with one rounding (LLVM's `llvm.fma.f64`; a library call where the processor
    has no fused multiply-add)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        fma = builder.module.declare_intrinsic("llvm.fma", [double], ir.FunctionType(double, [double] * 3))
        return builder.call(fma, args)

    return sig, codegen


@intrinsic
def _square(typingctx, x):
    """x ** 2 as numpy computes it for a float64 scalar: the C library's `pow(x, 2.0)` (not always
    x * x to the last bit). The call is marked `nobuiltin`, so that LLVM keeps it a call instead
    of turning it into x * x."""
    sig = types.float64(types.float64)

    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        pow_ = builder.module.globals.get("pow") or ir.Function(builder.module, ir.FunctionType(double, [double] * 2),
                                                                "pow")
        pow_.attributes.add("nobuiltin")
        return builder.call(pow_, [args[0], ir.Constant(double, 2.0)])

    return sig, codegen


@_jit
def _norm3(x, y, z):
    """`np.linalg.norm` of a 3-vector: the square root of BLAS `ddot(v, v)`, a chain of fused
    multiply-adds in OpenBLAS."""
    return math.sqrt(_fma(z, z, _fma(y, y, x * x)))


@_jit
def _norm4(w, x, y, z):
    """`np.linalg.norm` of a 4-vector (see `_norm3`)."""
    return math.sqrt(_fma(z, z, _fma(y, y, _fma(x, x, w * w))))


@_jit
def _gemv3(a0, a1, a2, x0, x1, x2):
    """Element i of numpy's `A.T @ x` for a C-ordered (3, 4) A: column i of A (a) times x (3,),
    rounded as OpenBLAS's `dgemv` does it for four outputs: two columns fused, then the third
    product added."""
    return _fma(a0, x0, a1 * x1) + a2 * x2


@_jit
def _gemv6(a0, a1, a2, a3, a4, a5, x0, x1, x2, x3, x4, x5):
    """Element i of numpy's `A.T @ x` for a C-ordered (6, 4) A (see `_gemv3`): a chain of four
    fused products plus a chain of two."""
    return _fma(a3, x3, _fma(a2, x2, _fma(a0, x0, a1 * x1))) + _fma(a4, x4, a5 * x5)


# ================================================================= ahrs.common.quaternion
@_jit
def _versor(w, x, y, z):
    """`ahrs.Quaternion(q)`: `q / ||q||` (the constructor normalises)."""
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@mirrors("ahrs.common.quaternion.Quaternion.product")
def _product(w, x, y, z, qw, qx, qy, qz):
    """`ahrs.Quaternion.product`: the Hamilton product p q (p = [w, x, y, z]), its terms in the
    library's order."""
    return (w * qw - x * qx - y * qy - z * qz,
            w * qx + x * qw + y * qz - z * qy,
            w * qy - x * qz + y * qw + z * qx,
            w * qz + x * qy - y * qx + z * qw)


@mirrors("ahrs.common.quaternion.Quaternion.to_DCM")
def _to_DCM(w, x, y, z):
    """`ahrs.Quaternion.to_DCM`: the rotation matrix of a unit quaternion, row-major 9-tuple."""
    x2, y2, z2 = _square(x), _square(y), _square(z)
    return (1.0 - 2.0 * (y2 + z2), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x2 + z2), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (w * x + y * z), 1.0 - 2.0 * (x2 + y2))


# ================================================================= ahrs.filters.Madgwick
@mirrors("ahrs.filters.madgwick.Madgwick.updateIMU")
def madgwick_updateIMU(qw, qx, qy, qz, gx, gy, gz, ax, ay, az, dt, gain):
    """`ahrs.filters.Madgwick.updateIMU`: one gyro + accelerometer step.

    Madgwick 2010 ("An efficient orientation filter for inertial and inertial/magnetic sensor
    arrays", report, x-io and University of Bristol; the equation numbers the library cites): the
    rate of change of the quaternion from the gyro, q_dot = 1/2 q (x) [0, w] (eq. 12); the
    objective function f_g and its Jacobian J_g for gravity (eqs. 25-26); the gradient J_g^T f_g
    (eq. 34), normalised and subtracted with gain beta (eq. 33); integrated over dt (eq. 13) and
    normalised.
    q: the quaternion before the step (normalised here, as the library does); g: rad/s;
    a: any unit (normalised); dt: s; gain: beta, rad/s. Returns the quaternion after the step.
    """
    qw, qx, qy, qz = _versor(qw, qx, qy, qz)
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz
    pw, px, py, pz = _product(qw, qx, qy, qz, 0.0, gx, gy, gz)
    dw, dx, dy, dz = 0.5 * pw, 0.5 * px, 0.5 * py, 0.5 * pz  # eq. 12
    a_norm = _norm3(ax, ay, az)
    if a_norm > 0.0:
        ax, ay, az = ax / a_norm, ay / a_norm, az / a_norm
        w, x, y, z = _versor(qw, qx, qy, qz)
        f0 = 2.0 * (x * z - w * y) - ax  # eq. 25
        f1 = 2.0 * (w * x + y * z) - ay
        f2 = 2.0 * (0.5 - _square(x) - _square(y)) - az
        if _norm3(f0, f1, f2) > 0.0:
            # J_g (eq. 26) = [[-2y, 2z, -2w, 2x], [2x, 2w, 2z, 2y], [0, -4x, -4y, 0]]; J_g^T f_g (eq. 34),
            # rounded as numpy's `J.T @ f` (`_gemv3`)
            s0 = _gemv3(-2.0 * y, 2.0 * x, 0.0, f0, f1, f2)
            s1 = _gemv3(2.0 * z, 2.0 * w, -4.0 * x, f0, f1, f2)
            s2 = _gemv3(-2.0 * w, 2.0 * z, -4.0 * y, f0, f1, f2)
            s3 = _gemv3(2.0 * x, 2.0 * y, 0.0, f0, f1, f2)
            n = _norm4(s0, s1, s2, s3)
            s0, s1, s2, s3 = s0 / n, s1 / n, s2 / n, s3 / n
            dw, dx, dy, dz = dw - gain * s0, dx - gain * s1, dy - gain * s2, dz - gain * s3  # eq. 33
    w, x, y, z = _versor(qw + dw * dt, qx + dx * dt, qy + dy * dt, qz + dz * dt)  # eq. 13: Quaternion(q + qDot dt)
    return _versor(w, x, y, z)  # q_new /= norm(q_new)


@mirrors("ahrs.filters.madgwick.Madgwick.updateMARG")
def madgwick_updateMARG(qw, qx, qy, qz, gx, gy, gz, ax, ay, az, mx, my, mz, dt, gain):
    """`ahrs.filters.Madgwick.updateMARG`: one gyro + accelerometer + magnetometer step, in the
    library's NWU world (x north, z up).

    Madgwick 2010: as `madgwick_updateIMU`, with the earth's field measured in the world frame,
    h = q (x) m (x) q* (eq. 45), its reference b = [0, sqrt(h_x^2 + h_y^2), 0, h_z] (eq. 46), and
    the stacked objective function and Jacobian of gravity and field (eqs. 31-32) in the gradient
    step (eqs. 33-34). A zero magnetometer sample is the IMU update (the caller routes it
    there, with the real dt: see the module docstring). Units as `madgwick_updateIMU`; m: any unit.
    """
    qw, qx, qy, qz = _versor(qw, qx, qy, qz)
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz
    pw, px, py, pz = _product(qw, qx, qy, qz, 0.0, gx, gy, gz)
    dw, dx, dy, dz = 0.5 * pw, 0.5 * px, 0.5 * py, 0.5 * pz  # eq. 12
    a_norm = _norm3(ax, ay, az)
    if a_norm > 0.0:
        ax, ay, az = ax / a_norm, ay / a_norm, az / a_norm
        m_norm = _norm3(mx, my, mz)
        mx, my, mz = mx / m_norm, my / m_norm, mz / m_norm
        uw, ux, uy, uz = _versor(0.0, mx, my, mz)  # Quaternion([0, *m]) (f below uses m itself)
        cw, cx, cy, cz = _product(uw, ux, uy, uz, qw, -qx, -qy, -qz)  # m (x) q*
        hw, hx, hy, hz = _product(qw, qx, qy, qz, cw, cx, cy, cz)  # eq. 45
        bx = math.sqrt(_fma(hy, hy, hx * hx))  # eq. 46: np.linalg.norm([h_x, h_y])
        bz = hz
        w, x, y, z = _versor(qw, qx, qy, qz)
        f0 = 2.0 * (x * z - w * y) - ax  # eq. 25
        f1 = 2.0 * (w * x + y * z) - ay
        f2 = 2.0 * (0.5 - _square(x) - _square(y)) - az
        f3 = 2.0 * bx * (0.5 - _square(y) - _square(z)) + 2.0 * bz * (x * z - w * y) - mx  # eq. 31
        f4 = 2.0 * bx * (x * y - w * z) + 2.0 * bz * (w * x + y * z) - my
        f5 = 2.0 * bx * (w * y + x * z) + 2.0 * bz * (0.5 - _square(x) - _square(y)) - mz
        if _fma(f5, f5, _fma(f4, f4, _fma(f3, f3, _fma(f2, f2, _fma(f1, f1, f0 * f0))))) > 0.0:  # |f| > 0
            # rows 3-5 of J (eq. 32); J^T f (eq. 34), rounded as numpy's `J.T @ f` (`_gemv6`)
            j30, j31 = -2.0 * bz * y, 2.0 * bz * z
            j32, j33 = -4.0 * bx * y - 2.0 * bz * w, -4.0 * bx * z + 2.0 * bz * x
            j40, j41 = -2.0 * bx * z + 2.0 * bz * x, 2.0 * bx * y + 2.0 * bz * w
            j42, j43 = 2.0 * bx * x + 2.0 * bz * z, -2.0 * bx * w + 2.0 * bz * y
            j50, j51 = 2.0 * bx * y, 2.0 * bx * z - 4.0 * bz * x
            j52, j53 = 2.0 * bx * w - 4.0 * bz * y, 2.0 * bx * x
            s0 = _gemv6(-2.0 * y, 2.0 * x, 0.0, j30, j40, j50, f0, f1, f2, f3, f4, f5)
            s1 = _gemv6(2.0 * z, 2.0 * w, -4.0 * x, j31, j41, j51, f0, f1, f2, f3, f4, f5)
            s2 = _gemv6(-2.0 * w, 2.0 * z, -4.0 * y, j32, j42, j52, f0, f1, f2, f3, f4, f5)
            s3 = _gemv6(2.0 * x, 2.0 * y, 0.0, j33, j43, j53, f0, f1, f2, f3, f4, f5)
            n = _norm4(s0, s1, s2, s3)
            s0, s1, s2, s3 = s0 / n, s1 / n, s2 / n, s3 / n
            dw, dx, dy, dz = dw - gain * s0, dx - gain * s1, dy - gain * s2, dz - gain * s3  # eq. 33
    w, x, y, z = _versor(qw + dw * dt, qx + dx * dt, qy + dy * dt, qz + dz * dt)  # eq. 13
    return _versor(w, x, y, z)


@_jit
def madgwick_kernel(gyr, acc, mag, dt, q0, gain, nwu, out):
    """The adapter's loop of `Madgwick.updateIMU` (6-D: `mag` (0, 3)) or `updateMARG` (9-D) over a
    recording (`MadgwickPeer.estimate`). q0: (4,) the quaternion before the first step, in the
    library's world (NWU when `nwu`: the adapter's seed turned by Rz(-90 deg)); nwu: write
    `Rz(90 deg) q` (ENU) instead of q. Writes out[1:]."""
    marg = mag.shape[0] > 0
    qw, qx, qy, qz = q0[0], q0[1], q0[2], q0[3]
    for k in range(dt.shape[0]):
        gx, gy, gz = gyr[k, 0], gyr[k, 1], gyr[k, 2]
        ax, ay, az = acc[k, 0], acc[k, 1], acc[k, 2]
        if marg and _norm3(mag[k, 0], mag[k, 1], mag[k, 2]) != 0.0:
            qw, qx, qy, qz = madgwick_updateMARG(qw, qx, qy, qz, gx, gy, gz, ax, ay, az,
                                                 mag[k, 0], mag[k, 1], mag[k, 2], dt[k], gain)
        else:
            qw, qx, qy, qz = madgwick_updateIMU(qw, qx, qy, qz, gx, gy, gz, ax, ay, az, dt[k], gain)
        _write(out, k + 1, qw, qx, qy, qz, nwu)


@_jit
def _write(out, row, qw, qx, qy, qz, nwu):
    """out[row] = q, or Rz(90 deg) q (`quaternion.multiply(peers._RZ90, q)`) when `nwu`."""
    if nwu:
        qw, qx, qy, qz = qmul((_SQRT_HALF, 0.0, 0.0, _SQRT_HALF), (qw, qx, qy, qz))
    out[row, 0], out[row, 1], out[row, 2], out[row, 3] = qw, qx, qy, qz


# ================================================================= ahrs.filters.Mahony
@_jit
def _mahony_step(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ex, ey, ez, corrected, dt, k_p, k_i):
    """What `Mahony.updateIMU` and `updateMARG` share once the correction omega_mes = (ex, ey, ez)
    is known: with it (`corrected`: the accelerometer sample was not zero) the bias update b_dot =
    -k_I omega_mes and the rate w - b + k_P omega_mes (Mahony et al. 2008, eq. 32), without it the
    gyro rate alone; then q_dot = 1/2 q (x) [0, rate] integrated over dt and normalised (eq. 48).
    Returns (q, b) after the step."""
    ox, oy, oz = gx, gy, gz
    if corrected:
        bx, by, bz = bx + (-k_i * ex) * dt, by + (-k_i * ey) * dt, bz + (-k_i * ez) * dt  # b_dot = -k_I omega_mes
        ox, oy, oz = ox - bx + k_p * ex, oy - by + k_p * ey, oz - bz + k_p * ez  # w - b + k_P omega_mes
    pw, px, py, pz = _product(qw, qx, qy, qz, 0.0, ox, oy, oz)
    w, x, y, z = qw + 0.5 * pw * dt, qx + 0.5 * px * dt, qy + 0.5 * py * dt, qz + 0.5 * pz * dt  # eq. 48: q_dot dt
    w, x, y, z = _versor(w, x, y, z)
    return w, x, y, z, bx, by, bz


@mirrors("ahrs.filters.mahony.Mahony.updateIMU")
def mahony_updateIMU(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ax, ay, az, dt, k_p, k_i):
    """`ahrs.filters.Mahony.updateIMU`: one gyro + accelerometer step of the explicit
    complementary filter with bias estimation.

    Mahony, Hamel & Pflimlin 2008 ("Nonlinear complementary filters on the special orthogonal
    group", IEEE TAC 53(5)), the explicit complementary filter with bias correction (eq. 32) in its
    quaternion form (eq. 48): the correction omega_mes = a x v_a with v_a = R^T e_3 the predicted
    gravity direction (one vector, weight 1), the bias b_dot = -k_I omega_mes integrated over dt,
    and q_dot = 1/2 q (x) [0, w - b + k_P omega_mes] integrated over dt and normalised.
    q: before the step (normalised here); b: the library's `b`, rad/s, body frame; g: rad/s, body
    frame; a: any unit, body frame; dt: s; k_p, k_i: the gains. Returns (q, b) after the step.
    A zero gyro sample returns the normalised q and b unchanged; a zero accelerometer sample
    integrates the gyro alone, without subtracting b (as the library does).
    """
    qw, qx, qy, qz = _versor(qw, qx, qy, qz)
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz, bx, by, bz
    ex = ey = ez = 0.0
    a_norm = _norm3(ax, ay, az)
    if a_norm > 0.0:
        r = _to_DCM(qw, qx, qy, qz)
        vx, vy, vz = r[6], r[7], r[8]  # R^T [0, 0, 1]
        ax, ay, az = ax / a_norm, ay / a_norm, az / a_norm
        ex, ey, ez = ay * vz - az * vy, az * vx - ax * vz, ax * vy - ay * vx  # omega_mes = a x v_a
    return _mahony_step(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ex, ey, ez, a_norm > 0.0, dt, k_p, k_i)


@mirrors("ahrs.filters.mahony.Mahony.updateMARG")
def mahony_updateMARG(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ax, ay, az, mx, my, mz, dt, k_p, k_i):
    """`ahrs.filters.Mahony.updateMARG`: as `mahony_updateIMU` with the magnetometer's error term,
    in the library's ENU world (y north).

    Mahony et al. 2008, eqs. 32 and 48 with two vectors: omega_mes = a x v_a + m x v_m, where v_m =
    R^T [0, |h_xy|, h_z] / |.| and h = R m is the measured field in the world frame (its
    horizontal part turned to north, so that the field corrects the heading only through its
    direction). Both error terms have weight 1, as in the library. m: any unit. A zero
    magnetometer sample is the IMU update (the caller routes it there, with the real dt: see the
    module docstring); a zero accelerometer sample integrates the gyro alone.
    """
    qw, qx, qy, qz = _versor(qw, qx, qy, qz)
    if _norm3(gx, gy, gz) == 0.0:
        return qw, qx, qy, qz, bx, by, bz
    ex = ey = ez = 0.0
    a_norm = _norm3(ax, ay, az)
    if a_norm > 0.0:
        m_norm = _norm3(mx, my, mz)
        ax, ay, az = ax / a_norm, ay / a_norm, az / a_norm
        mx, my, mz = mx / m_norm, my / m_norm, mz / m_norm
        r = _to_DCM(qw, qx, qy, qz)
        vx, vy, vz = r[6], r[7], r[8]  # R^T [0, 0, 1]
        # h = R m and v_m = R^T [0, |h_xy|, h_z], rounded as numpy's `R @ m` and `R.T @ v`
        hx = _fma(r[2], mz, _fma(r[0], mx, r[1] * my))
        hy = _fma(r[5], mz, _fma(r[3], mx, r[4] * my))
        hz = _fma(r[8], mz, _fma(r[6], mx, r[7] * my))
        h_xy = math.sqrt(_fma(hy, hy, hx * hx))
        wx = _fma(r[6], hz, _fma(r[3], h_xy, r[0] * 0.0))
        wy = _fma(r[7], hz, _fma(r[4], h_xy, r[1] * 0.0))
        wz = _fma(r[8], hz, _fma(r[5], h_xy, r[2] * 0.0))
        w_norm = _norm3(wx, wy, wz)
        wx, wy, wz = wx / w_norm, wy / w_norm, wz / w_norm
        ex = (ay * vz - az * vy) + (my * wz - mz * wy)  # omega_mes = a x v_a + m x v_m
        ey = (az * vx - ax * vz) + (mz * wx - mx * wz)
        ez = (ax * vy - ay * vx) + (mx * wy - my * wx)
    return _mahony_step(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ex, ey, ez, a_norm > 0.0, dt, k_p, k_i)


@_jit
def mahony_kernel(gyr, acc, mag, dt, q0, bias, k_p, k_i, out):
    """The adapter's loop of `Mahony.updateIMU` (6-D: `mag` (0, 3)) or `updateMARG` (9-D, ENU) over
    a recording (`MahonyPeer.estimate`). q0: (4,) the quaternion before the first step; bias: (3,)
    the library's `b` before it (rad/s), overwritten with its final value. Writes out[1:]."""
    marg = mag.shape[0] > 0
    qw, qx, qy, qz = q0[0], q0[1], q0[2], q0[3]
    bx, by, bz = bias[0], bias[1], bias[2]
    for k in range(dt.shape[0]):
        gx, gy, gz = gyr[k, 0], gyr[k, 1], gyr[k, 2]
        ax, ay, az = acc[k, 0], acc[k, 1], acc[k, 2]
        if marg and _norm3(mag[k, 0], mag[k, 1], mag[k, 2]) != 0.0:
            qw, qx, qy, qz, bx, by, bz = mahony_updateMARG(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ax, ay, az,
                                                           mag[k, 0], mag[k, 1], mag[k, 2], dt[k], k_p, k_i)
        else:
            qw, qx, qy, qz, bx, by, bz = mahony_updateIMU(qw, qx, qy, qz, bx, by, bz, gx, gy, gz, ax, ay, az,
                                                          dt[k], k_p, k_i)
        _write(out, k + 1, qw, qx, qy, qz, False)
    bias[0], bias[1], bias[2] = bx, by, bz


# ================================================================= ahrs.filters.EKF
@mirrors("ahrs.filters.ekf.EKF.f")
def ekf_f(q, g, dt, F, out):
    """`ahrs.filters.EKF.f` and `EKF.dfdq`: the process model q_t = (I_4 + dt/2 Omega(w)) q, the
    first-order integration of q_dot = 1/2 Omega(w) q, and its Jacobian F = I_4 + Omega(dt/2 w),
    which is the same matrix (the `ahrs` documentation, EKF, "Prediction Step", after Sabatini
    2011, "Estimating three-dimensional orientation of human body parts by inertial/magnetic
    sensing", Sensors 11(2)). q: (4,); g: (3,) rad/s; dt: s; F: (4, 4) written; out: (4,) written
    with q_t."""
    c = 0.5 * dt
    x0, x1, x2 = c * g[0], c * g[1], c * g[2]
    F[0, 0], F[0, 1], F[0, 2], F[0, 3] = 1.0, -x0, -x1, -x2
    F[1, 0], F[1, 1], F[1, 2], F[1, 3] = x0, 1.0, x2, -x1
    F[2, 0], F[2, 1], F[2, 2], F[2, 3] = x1, -x2, 1.0, x0
    F[3, 0], F[3, 1], F[3, 2], F[3, 3] = x2, x1, -x0, 1.0
    for i in range(4):
        out[i] = F[i, 0] * q[0] + F[i, 1] * q[1] + F[i, 2] * q[2] + F[i, 3] * q[3]


@_jit
def _dhdq_rows(H, row, v0, v1, v2, qw, qx, qy, qz):
    """Three rows of `EKF.dhdq` (mode "normal") for the reference vector v, times 2: the Jacobian
    of R(q)^T v with respect to q (the `ahrs` documentation, EKF, "Correction Step")."""
    H[row, 0] = 2.0 * (v0 * qw + v1 * qz - v2 * qy)
    H[row, 1] = 2.0 * (v0 * qx + v1 * qy + v2 * qz)
    H[row, 2] = 2.0 * (-v0 * qy + v1 * qx - v2 * qw)
    H[row, 3] = 2.0 * (-v0 * qz + v1 * qw + v2 * qx)
    H[row + 1, 0] = 2.0 * (-v0 * qz + v1 * qw + v2 * qx)
    H[row + 1, 1] = 2.0 * (v0 * qy - v1 * qx + v2 * qw)
    H[row + 1, 2] = 2.0 * (v0 * qx + v1 * qy + v2 * qz)
    H[row + 1, 3] = 2.0 * (-v0 * qw - v1 * qz + v2 * qy)
    H[row + 2, 0] = 2.0 * (v0 * qy - v1 * qx + v2 * qw)
    H[row + 2, 1] = 2.0 * (v0 * qz - v1 * qw - v2 * qx)
    H[row + 2, 2] = 2.0 * (v0 * qw + v1 * qz - v2 * qy)
    H[row + 2, 3] = 2.0 * (v0 * qx + v1 * qy + v2 * qz)


@_jit
def _inv(S, m, L, piv, out):
    """`np.linalg.inv` of the leading m x m block of S (LAPACK `gesv` against the identity): LU
    with partial pivoting (Golub & Van Loan 2013, "Matrix Computations", 4th ed., alg. 3.4.1),
    then forward and back substitution for each column. L: (6, 6) work; piv: (6,) int work;
    out: (6, 6), its m x m block written."""
    for i in range(m):
        piv[i] = i
        for j in range(m):
            L[i, j] = S[i, j]
    for k in range(m):
        p = k
        for i in range(k + 1, m):
            if abs(L[i, k]) > abs(L[p, k]):
                p = i
        if p != k:
            for j in range(m):
                L[k, j], L[p, j] = L[p, j], L[k, j]
            piv[k], piv[p] = piv[p], piv[k]
        for i in range(k + 1, m):
            L[i, k] = L[i, k] / L[k, k]
            for j in range(k + 1, m):
                L[i, j] = L[i, j] - L[i, k] * L[k, j]
    for c in range(m):
        for i in range(m):  # forward: L y = P e_c (unit lower triangle)
            s = 1.0 if piv[i] == c else 0.0
            for j in range(i):
                s -= L[i, j] * out[j, c]
            out[i, c] = s
        for i in range(m - 1, -1, -1):  # back: U x = y
            s = out[i, c]
            for j in range(i + 1, m):
                s -= L[i, j] * out[j, c]
            out[i, c] = s / L[i, i]


@mirrors("ahrs.filters.ekf.EKF.update")
def ekf_update(q, g, a, mag, use_mag, dt, P, var_gyr, var_acc, var_mag, m_ref, w, out):
    """`ahrs.filters.EKF.update` (frame "NED", the adapter's; mode "normal"): one prediction with
    the gyro as control input and one correction with the accelerometer (and magnetometer).

    The library's arithmetic (its documentation, EKF, "Prediction Step" and "Correction Step",
    after Sabatini 2011): prediction q_t = f(q, w) (`ekf_f`), P_t = F P F^T + Q_t with the gyro
    noise mapped into the quaternion, Q_t = var_gyr W W^T, W = dt/2 [[-q_v^T], [q_w I + [q_v]x]];
    measurement z = [a / |a|, m / |m|], its prediction y = R(q_t / |q_t|)^T [a_ref, m_ref] with
    a_ref = [0, 0, 1], Jacobian H = dh/dq at q_t (unnormalised), and the Kalman update
    S = H P_t H^T + R, K = P_t H^T S^-1, P = (I - K H) P_t, q = (q_t + K (z - y)) / |.|
    (Kalman 1960, in the extended form). q: (4,) a unit quaternion;
    g: (3,) rad/s; a: (3,) any unit, not zero (the caller's branches); mag: (3,) any unit, used
    when `use_mag`; P: (4, 4) updated in place; m_ref: (3,) the library's normalised `m_ref`;
    w: the kernel's work arrays; out: (4,) written with the new q.
    """
    F, FP, Pt, H, HP, S, Sinv, PHt, K, IKH, L, piv, qt, z = w
    m = 6 if use_mag else 3
    a_norm = _norm3(a[0], a[1], a[2])
    z[0], z[1], z[2] = a[0] / a_norm, a[1] / a_norm, a[2] / a_norm
    if use_mag:
        m_norm = _norm3(mag[0], mag[1], mag[2])
        z[3], z[4], z[5] = mag[0] / m_norm, mag[1] / m_norm, mag[2] / m_norm
    ekf_f(q, g, dt, F, qt)
    c = 0.5 * dt  # W
    W = ((c * -q[1], c * -q[2], c * -q[3]),
         (c * q[0], c * -q[3], c * q[2]),
         (c * q[3], c * q[0], c * -q[1]),
         (c * -q[2], c * q[1], c * q[0]))
    for i in range(4):  # F P
        for j in range(4):
            FP[i, j] = F[i, 0] * P[0, j] + F[i, 1] * P[1, j] + F[i, 2] * P[2, j] + F[i, 3] * P[3, j]
    for i in range(4):  # P_t = (F P) F^T + var_gyr W W^T
        wi = W[i]
        gi0, gi1, gi2 = var_gyr * wi[0], var_gyr * wi[1], var_gyr * wi[2]
        for j in range(4):
            wj = W[j]
            Pt[i, j] = (FP[i, 0] * F[j, 0] + FP[i, 1] * F[j, 1] + FP[i, 2] * F[j, 2] + FP[i, 3] * F[j, 3]
                        + (gi0 * wj[0] + gi1 * wj[1] + gi2 * wj[2]))
    # y = h(q_t): C = R(q_t / |q_t|)^T, C a_ref = third row of R, C m_ref
    tw, tx, ty, tz = _versor(qt[0], qt[1], qt[2], qt[3])
    r = _to_DCM(tw, tx, ty, tz)
    v = (z[0] - r[6], z[1] - r[7], z[2] - r[8])
    _dhdq_rows(H, 0, 0.0, 0.0, 1.0, qt[0], qt[1], qt[2], qt[3])
    if use_mag:
        y3 = r[0] * m_ref[0] + r[3] * m_ref[1] + r[6] * m_ref[2]
        y4 = r[1] * m_ref[0] + r[4] * m_ref[1] + r[7] * m_ref[2]
        y5 = r[2] * m_ref[0] + r[5] * m_ref[1] + r[8] * m_ref[2]
        vm = (z[3] - y3, z[4] - y4, z[5] - y5)
        _dhdq_rows(H, 3, m_ref[0], m_ref[1], m_ref[2], qt[0], qt[1], qt[2], qt[3])
    for i in range(m):  # H P_t
        for j in range(4):
            HP[i, j] = H[i, 0] * Pt[0, j] + H[i, 1] * Pt[1, j] + H[i, 2] * Pt[2, j] + H[i, 3] * Pt[3, j]
    for i in range(m):  # S = (H P_t) H^T + R
        for j in range(m):
            S[i, j] = HP[i, 0] * H[j, 0] + HP[i, 1] * H[j, 1] + HP[i, 2] * H[j, 2] + HP[i, 3] * H[j, 3]
        S[i, i] += var_acc if i < 3 else var_mag
    for i in range(4):  # P_t H^T
        for j in range(m):
            PHt[i, j] = Pt[i, 0] * H[j, 0] + Pt[i, 1] * H[j, 1] + Pt[i, 2] * H[j, 2] + Pt[i, 3] * H[j, 3]
    _inv(S, m, L, piv, Sinv)
    for i in range(4):  # K = (P_t H^T) S^-1
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += PHt[i, k] * Sinv[k, j]
            K[i, j] = s
    for i in range(4):  # I - K H
        for j in range(4):
            s = 0.0
            for k in range(m):
                s += K[i, k] * H[k, j]
            IKH[i, j] = (1.0 if i == j else 0.0) - s
    for i in range(4):  # P = (I - K H) P_t
        for j in range(4):
            P[i, j] = IKH[i, 0] * Pt[0, j] + IKH[i, 1] * Pt[1, j] + IKH[i, 2] * Pt[2, j] + IKH[i, 3] * Pt[3, j]
    for i in range(4):  # q = q_t + K v
        s = K[i, 0] * v[0] + K[i, 1] * v[1] + K[i, 2] * v[2]
        if use_mag:
            s += K[i, 3] * vm[0] + K[i, 4] * vm[1] + K[i, 5] * vm[2]
        out[i] = qt[i] + s
    n = _norm4(out[0], out[1], out[2], out[3])
    for i in range(4):
        out[i] = out[i] / n


@_jit
def ekf_kernel(gyr, acc, mag, mag_ok, dt, q0, P, var_gyr, var_acc, var_mag, m_ref, nine_d, out):
    """The adapter's loop of `EKF.update` over a recording (`AhrsEKFPeer.estimate`).

    6-D (`nine_d` False; `acc` in m/s^2 with NaN rows kept, as `AhrsEKFPeer.step` passes them): a
    finite sample is `EKF.update` (which returns q untouched on an all-zero sample); a non-finite
    one `EKF.f` alone, normalised. 9-D (NWU, written as ENU; `acc` with zero rows for non-finite
    samples): an all-zero sample is `EKF.f` alone, normalised; otherwise the update, with the
    magnetometer where `mag_ok`. q0: (4,) before the first step; P: (4, 4) the initial
    covariance, overwritten with the final one. Writes out[1:].
    """
    q = q0.copy()
    nxt = np.empty(4)
    w = (np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((6, 4)), np.empty((6, 4)),
         np.empty((6, 6)), np.empty((6, 6)), np.empty((4, 6)), np.empty((4, 6)), np.empty((4, 4)),
         np.empty((6, 6)), np.empty(6, dtype=np.int64), np.empty(4), np.empty(6))
    F = w[0]
    for k in range(dt.shape[0]):
        g, a = gyr[k], acc[k]
        finite = math.isfinite(a[0]) and math.isfinite(a[1]) and math.isfinite(a[2])
        zero = a[0] == 0.0 and a[1] == 0.0 and a[2] == 0.0
        if not finite or (nine_d and zero):  # the process model alone
            ekf_f(q, g, dt[k], F, nxt)
            n = _norm4(nxt[0], nxt[1], nxt[2], nxt[3])
            for i in range(4):
                q[i] = nxt[i] / n
        elif not zero:  # (6-D, all zero: `EKF.update` returns q as it is)
            if nine_d:
                ekf_update(q, g, a, mag[k], mag_ok[k], dt[k], P, var_gyr, var_acc, var_mag, m_ref, w, nxt)
            else:
                ekf_update(q, g, a, a, False, dt[k], P, var_gyr, var_acc, var_mag, m_ref, w, nxt)
            q[:] = nxt
        _write(out, k + 1, q[0], q[1], q[2], q[3], nine_d)


_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache (`_compiled.load` says why): run
    each once on a one-step recording, in 6-D and 9-D, with the argument types the adapters pass."""
    global _loaded
    if _loaded:
        return
    gyr = np.full((1, 3), 0.1)
    acc = np.array([[0.0, 0.0, 9.8]])
    mag = np.array([[20.0, 0.0, -40.0]])
    none = np.zeros((0, 3))
    dt = np.full(1, 0.01)
    unit = np.array([1.0, 0.0, 0.0, 0.0])
    out = np.empty((2, 4))
    for m in (none, mag):
        madgwick_kernel(gyr, acc, m, dt, unit, 0.1, m.shape[0] > 0, out)
        mahony_kernel(gyr, acc, m, dt, unit, np.zeros(3), 1.0, 0.1, out)
        ekf_kernel(gyr, acc, m, np.ones(m.shape[0], dtype=np.bool_), dt, unit, np.eye(4), 0.09, 0.25, 0.64,
                   np.array([1.0, 0.0, 0.0]), m.shape[0] > 0, out)
    _loaded = True
