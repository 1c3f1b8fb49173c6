"""The smoothers' start trajectory and their log's measures, compiled (numba).

`dead_reckoning` integrates the gyro as `fusion.estimators.dr.DeadReckoning` does (a sequential
product where the reference takes a parallel scan: the same products in another order),
`levelled` re-levels it window by window as `smoother.levelled`; `dead_reckoned` and
`levelled_trajectory` call them on an `ImuSamples`. `norm_error` is `SolverLog`'s measure of the
retraction's drift off the unit sphere, `dot` the slope g.p of `ReferenceOps.slope` without a
temporary.

numba keys a cached kernel on its own file only: `_kernel_cache.forget_stale_kernels` drops this
module's cache when a file whose kernels it compiles changes.
"""
from __future__ import annotations

import math

import numpy as np

from fusion import quaternion as quat

from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _jit, mirrors
from . import _compiled_terms as terms
from ._compiled_terms import fill3, load_quat, exp_floats, multiply_floats, normalize_floats, rotation_floats

forget_stale_kernels(__file__, [quat.__file__, terms.__file__])

# Kernels without a numpy reference of their own (`kernels._numba.mirrors`), and why:
#   dead_reckoning: `fusion.estimators.dr.DeadReckoning`'s scan, as a sequential product
#   dot: `ReferenceOps.slope`'s np.sum(grad_q * d_q
HELPERS = ("dead_reckoning", "dot")


@_jit
def dead_reckoning(gyr, valid, dt, q0, small, out):
    """out (T, 4): q_0 = q0, q_{k+1} = q_k exp([0, w_k dt_k / 2]) (0 where invalid), each row
    normalised (`dr.DeadReckoning`, whose parallel scan gives the same products in another
    order, and `smoother.initial_trajectory`, which normalises)."""
    q = normalize_floats((q0[0], q0[1], q0[2], q0[3]))
    for i in range(4):
        out[0, i] = q[i]
    for k in range(len(dt)):
        if valid[k]:
            u = exp_floats(gyr[k, 0] * dt[k], gyr[k, 1] * dt[k], gyr[k, 2] * dt[k], small)
        else:
            u = (1.0, 0.0, 0.0, 0.0)
        q = normalize_floats(multiply_floats(q, u))
        for i in range(4):
            out[k + 1, i] = q[i]


@mirrors("fusion.estimators.smoothers.smoother.levelled")
def levelled(t, acc, q, window_s, small, out):
    """out (T, 4): q (T, 4) turned window by window so that the mean world-frame specific force
    of each window points up (line by line; the first window is q). t (T,) s, acc (T, 3) g."""
    T = len(t)
    n = int(math.floor((t[T - 1] - t[0]) / window_s)) + 1
    mean = np.zeros((n, 3))
    R = np.empty((3, 3))
    for k in range(T):
        a0, a1, a2 = acc[k, 0], acc[k, 1], acc[k, 2]
        if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2)):
            continue  # weight 0 (numpy: 0 * the zeroed sample)
        w = 0.5 * (t[k + 1] - t[k]) if k < T - 1 else 0.0  # `sample_durations`
        if k > 0:
            w += 0.5 * (t[k] - t[k - 1])
        fill3(R, rotation_floats(load_quat(q, k)))
        j = int(math.floor((t[k] - t[0]) / window_s))
        for i in range(3):
            mean[j, i] += w * (R[i, 0] * a0 + R[i, 1] * a1 + R[i, 2] * a2)
    corr = np.empty((n, 4))
    for j in range(n):
        norm = math.sqrt(mean[j, 0] ** 2 + mean[j, 1] ** 2 + mean[j, 2] ** 2)
        d = norm if norm > 0 else 1.0
        ux, uy, uz = mean[j, 0] / d, mean[j, 1] / d, mean[j, 2] / d
        sin = math.sqrt(uy * uy + ux * ux)  # |up x e_z|
        if norm == 0 or sin == 0:
            c = (1.0, 0.0, 0.0, 0.0)
        else:
            f = math.atan2(sin, uz) / sin
            c = exp_floats(uy * f, -ux * f, 0.0, small)
        for i in range(4):
            corr[j, i] = c[i]
    for k in range(T):
        j = int(math.floor((t[k] - t[0]) / window_s))
        m = load_quat(q, k) if j == 0 else normalize_floats(multiply_floats((corr[j, 0], corr[j, 1], corr[j, 2], corr[j, 3]), load_quat(q, k)))
        for i in range(4):
            out[k, i] = m[i]


@_jit
def dot(a, b):
    """sum of a * b over (T, B) arrays, without a temporary."""
    s = 0.0
    for t in range(a.shape[0]):
        for i in range(a.shape[1]):
            s += a[t, i] * b[t, i]
    return s


@mirrors("fusion.estimators.smoothers.smoother.norm_error")
def norm_error(q):
    """max |(|q_t|) - 1| over q (T, 4) (`smoother.SolverLog`)."""
    worst = 0.0
    for t in range(q.shape[0]):
        e = abs(math.sqrt(q[t, 0] ** 2 + q[t, 1] ** 2 + q[t, 2] ** 2 + q[t, 3] ** 2) - 1.0)
        if e > worst:
            worst = e
    return worst


def dead_reckoned(imu, init_quat_wxyz: np.ndarray) -> np.ndarray:
    """(T, 4) dead reckoning of `imu` from init_quat_wxyz (4,), rows normalised (`dead_reckoning`)."""
    gyr, valid = imu.interval_rates()
    q = np.empty((len(imu), 4))
    dead_reckoning(np.ascontiguousarray(gyr, float), np.ascontiguousarray(valid, bool), np.ascontiguousarray(imu.dt, float),
                   np.array(init_quat_wxyz, float), float(quat.SMALL_ANGLE), q)  # a writable copy: `load`'s signature
    return q


def levelled_trajectory(imu, quat_wxyz: np.ndarray, window_s: float) -> np.ndarray:
    """(T, 4) `smoother.levelled(imu, quat_wxyz, window_s)` by the kernel (`levelled`)."""
    out = np.empty((len(imu), 4))
    levelled(np.ascontiguousarray(imu.t, float), np.ascontiguousarray(imu.acc_g, float),
                    np.ascontiguousarray(quat_wxyz, float), float(window_s), float(quat.SMALL_ANGLE), out)
    return out

