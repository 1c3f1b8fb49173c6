"""The smoothers' cost over a range of samples, and at a trial point, compiled (numba).

`cost` is `SmootherProblem.cost` (`fusion.estimators.smoothers.cost`) in one pass over the
samples t0 <= t < t1 and their steps, optionally at the point moved by a step (`retract`: the
retraction of `smoother.retract`, the exponential map or the normalised step; Absil, Mahony &
Sepulchre 2008, "Optimization Algorithms on Matrix Manifolds", sec. 4.1). It returns the sums of
the cost's terms, which `cost_of_sums` weights and adds in the ranges' order; `range_cost` runs
it over the ranges of `smoothers._compiled_ranges.cost_ranges`, the second on a thread of its own.
A trial may keep each sample's transcendental results for the linearisation at its point
(`keep`, read back by `smoothers._compiled_linearize.linearize`).

numba keys a cached kernel on its own file only: `_kernel_cache.forget_stale_kernels` drops this
module's cache when a file whose kernels it compiles changes.
"""
from __future__ import annotations

import numpy as np

from fusion import quaternion as quat

from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _jit, mirrors
from . import _compiled_layout as layout
from . import _compiled_terms as terms
from ._compiled_layout import (GEODESIC, KEEP_ACC, KEEP_MAG, KEEP_MOTION, KEEP_STEP, N_SUMS, POINT, SUM_ACC,
                                        SUM_MAG, SUM_MOTION, SUM_PRIOR, SUM_REST, SUM_VEL, SUM_VZERO)
from ._compiled_ranges import cost_ranges, run_beside
from ._compiled_terms import (exp_floats, fill3, keep_floats, load_quat, log_floats, mag_residual,
                                       motion_residual, multiply_floats, normalize_floats, rest_residual, robust_terms,
                                       rotation_floats, split_theta, step_rotvec, total_cost)

forget_stale_kernels(__file__, [quat.__file__, layout.__file__, terms.__file__])

# Kernels without a numpy reference of their own (`kernels._numba.mirrors`), and why:
#   cost_of_sums: the ranges' sums added, then `total_cost`
HELPERS = ("cost_of_sums",)


@mirrors("fusion.estimators.smoothers.smoother.retract")
def retract(q, x, alpha, kind, t, o, q_out, write):
    """q_t (kind POINT), or q_t retracted by alpha x_t[:3] (GEODESIC: q exp([0, alpha x / 2]);
    NORMALISE: normalise(q + q * [0, alpha x / 2]); Absil et al. 2008, sec. 4.1), then written to
    q_out[t] if `write`."""
    qt = load_quat(q, t)
    if kind == POINT:
        return qt
    dx, dy, dz = alpha * x[t, 0], alpha * x[t, 1], alpha * x[t, 2]
    if kind == GEODESIC:
        m = normalize_floats(multiply_floats(qt, exp_floats(dx, dy, dz, o.small_angle)))
    else:
        d = multiply_floats(qt, (0.0, dx, dy, dz))
        m = normalize_floats((qt[0] + 0.5 * d[0], qt[1] + 0.5 * d[1], qt[2] + 0.5 * d[2], qt[3] + 0.5 * d[3]))
    if write:
        for i in range(4):
            q_out[t, i] = m[i]
    return m


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.cost")
def cost(p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep, t0, t1, sums):
    """The cost's terms (`SmootherProblem.cost`) over the samples t0 <= t < t1 and their steps to
    t + 1, at q (T, 4), v (T, V) m/s, theta (P,); or, with kind GEODESIC or NORMALISE (not POINT), at
    the point moved by alpha times the step x (T, B): q_out_t = retraction of q_t by alpha x_t[:3]
    (`retract`), v_out = v + alpha x[:, 3:], both
    written for t0 <= t < t1 (the step from t1 - 1 reads q_t1 moved, and leaves it to its own range).
    sums (N_SUMS,) = the sums of the terms (`smoothers._compiled_layout`'s SUM_*; the anchor's is 0
    unless t0 = 0): `total_cost` of them is the cost (`range_cost`). If keep (T, 5, 5) has rows,
    each step's u_t = exp(phi_t / 2) and motion residual r_m,t, each sample's accelerometer cost
    term and IRLS weight and magnetometer residual are written to it (`keep_floats`, at the
    layout's KEEP_* offsets), for the linearisation at this point (`linearize`'s `kept`)."""
    T = q.shape[0]
    V = v.shape[1]
    b, k = split_theta(p, theta)
    cost_acc = cost_motion = cost_vel = cost_vzero = cost_rest = cost_mag = 0.0  # the sums of the terms
    R = np.empty((3, 3))
    Rn = np.empty((3, 3))
    qn = (0.0, 0.0, 0.0, 0.0)
    qt = (0.0, 0.0, 0.0, 0.0)
    for t in range(t0, t1):
        if t == t0:
            qt = retract(q, x, alpha, kind, t, o, q_out, True)
            if kind != POINT:
                for i in range(V):
                    v_out[t, i] = v[t, i] + alpha * x[t, 3 + i]
            fill3(R, rotation_floats(qt))
        else:
            qt = qn
            for i in range(3):
                for j in range(3):
                    R[i, j] = Rn[i, j]
        vv = v_out if kind != POINT else v
        r0 = p.acc[t, 0] - R[2, 0]
        r1 = p.acc[t, 1] - R[2, 1]
        r2 = p.acc[t, 2] - R[2, 2]
        c, w = robust_terms(p.loss, p.loss_c, p.w_acc[t], r0 * r0 + r1 * r1 + r2 * r2)
        cost_acc += c
        if keep.shape[0]:
            keep_floats(keep, t, KEEP_ACC, (c, w))
        if len(p.w_mag) and p.w_mag[t] > 0.0:
            rh, k0, k1, k2 = mag_residual(p, t, qt)
            c, w = robust_terms(p.mag_loss, p.mag_c, p.w_mag[t], rh * rh)
            cost_mag += c
            if keep.shape[0]:
                keep_floats(keep, t, KEEP_MAG, (rh, k0, k1, k2, c, w))
        if V:
            cost_vzero += p.w_vzero[t] * (vv[t, 0] * vv[t, 0] + vv[t, 1] * vv[t, 1])
        if t == T - 1:
            break
        mine = t + 1 < t1  # sample t + 1 is in this range: written here
        qn = retract(q, x, alpha, kind, t + 1, o, q_out, mine)
        vn0, vn1 = 0.0, 0.0  # v_t+1 (V = 2)
        if V:
            vn0, vn1 = v[t + 1, 0], v[t + 1, 1]
            if kind != POINT:
                vn0, vn1 = vn0 + alpha * x[t + 1, 3], vn1 + alpha * x[t + 1, 4]
                if mine:
                    v_out[t + 1, 0], v_out[t + 1, 1] = vn0, vn1
        fill3(Rn, rotation_floats(qn))
        phi = step_rotvec(p, b, k, t)
        u = exp_floats(phi[0], phi[1], phi[2], o.small_angle)
        r = motion_residual(qt, qn, u)
        if keep.shape[0]:
            keep_floats(keep, t, KEEP_STEP, u)
            keep_floats(keep, t, KEEP_MOTION, r)
        cost_motion += p.w_motion[t] * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        if V:
            dt = p.dt[t]
            a0 = p.acc[t]
            a1 = p.acc[t + 1]
            for i in range(2):
                f0 = R[i, 0] * a0[0] + R[i, 1] * a0[1] + R[i, 2] * a0[2]
                f1 = Rn[i, 0] * a1[0] + Rn[i, 1] * a1[1] + Rn[i, 2] * a1[2]
                rv = (vn0 if i == 0 else vn1) - vv[t, i] - o.gravity * (0.5 * (f0 + f1)) * dt
                cost_vel += p.w_vel[t] * rv * rv
        if len(p.w_rest) and p.w_rest[t] > 0:
            s = 0.0
            for i in range(p.n_bias):
                rr, _ = rest_residual(p, b, k, t, i)
                s += rr * rr
            cost_rest += p.w_rest[t] * s
    prior_sq = 0.0
    if t0 == 0:
        r = log_floats(multiply_floats((p.init_quat[0], -p.init_quat[1], -p.init_quat[2], -p.init_quat[3]),
                      (q_out[0, 0], q_out[0, 1], q_out[0, 2], q_out[0, 3]) if kind != POINT else load_quat(q, 0)))
        prior_sq = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    sums[SUM_ACC], sums[SUM_MOTION], sums[SUM_VEL], sums[SUM_VZERO], sums[SUM_REST], sums[SUM_MAG], sums[SUM_PRIOR] = \
        cost_acc, cost_motion, cost_vel, cost_vzero, cost_rest, cost_mag, prior_sq


@_jit
def cost_of_sums(p, theta, V, sums):
    """The cost from `cost`'s sums of its ranges (R, N_SUMS), added in the ranges' order."""
    total = np.zeros(N_SUMS)
    for i in range(sums.shape[0]):
        for j in range(N_SUMS):
            total[j] += sums[i, j]
    return total_cost(p, theta, V, total)


def range_cost(p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep) -> float:
    """`cost` over the whole recording, in the one or two ranges of `cost_ranges` (the second
    on a thread of its own): the cost, with q_out, v_out and keep written as `cost` says."""
    bounds = cost_ranges(len(q))
    sums = np.zeros((len(bounds) - 1, N_SUMS))
    args = (p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep)
    second = run_beside(cost, *args, bounds[1], bounds[2], sums[1]) if len(bounds) == 3 else None
    try:
        cost(*args, 0, bounds[1], sums[0])
    finally:  # the second range writes into the caller's arrays: never leave it running
        if second is not None:
            second()
    return cost_of_sums(p, theta, v.shape[1], sums)

