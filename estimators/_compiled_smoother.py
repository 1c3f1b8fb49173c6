"""Compiled kernels of the batch smoothers `gn` and `gd` (numba).

What is compiled and why. A smoother iteration evaluates the cost of `smoother_cost` over the
whole recording, linearises it and solves the block-tridiagonal normal equations with their
calibration border. The numpy reference (`SmootherProblem.linearize`, `solve_normal_equations`,
`gd.Preconditioner`) does this in whole-array operations, each of which builds (T, 3, 3) or
(T, 5, 5) temporaries, writes the matrix to LAPACK's band storage and solves it there, with
the border as P extra right-hand sides. Here one pass over
the samples computes the cost, the gradient and the Gauss-Newton blocks of each sample from a
few registers' worth of local data and eliminates them at once, so nothing per sample is kept
but what the back-substitution needs.

The elimination is block Gaussian elimination of the symmetric positive definite
block-tridiagonal matrix with a dense border, forward over the samples (the block form of the
Thomas algorithm; Golub & Van Loan 2013, "Matrix Computations", 4th ed., sec. 4.5.1), with
the border eliminated by its Schur complement (ibid., sec. 3.2.10; Triggs et al. 2000, "Bundle
adjustment - a modern synthesis", sec. 6.1). With D_t, O_t = H[t, t+1] and C_t = H[t, theta]
the blocks of H (`Linearization.diag`, `off`, `cross`) and b the right-hand side:

    S_t  = D_t - O_{t-1}^T M_{t-1}            M_t = S_t^-1 O_t          (B x B)
    b'_t = b_t - O_{t-1}^T c_{t-1}            c_t = S_t^-1 b'_t          (B)
    C'_t = C_t - O_{t-1}^T N_{t-1}            N_t = S_t^-1 C'_t          (B x P)
    G'   = G - sum_t C'_t^T N_t,   b'_theta = b_theta - sum_t C'_t^T c_t,   x_theta = G'^-1 b'_theta
    x_t  = c_t - M_t x_{t+1} - N_t x_theta    (backwards from t = T - 1)

S_t is factorised as L D L^T (5 x 5; no square roots on the recursion's critical path:
Golub & Van Loan 2013, sec. 4.1.2) and never stored; a sample keeps M_t, c_t and N_t:
5 (5 + 1 + F) numbers for F free calibration variables. The blocks are those of the reference
(`SmootherProblem.linearize`, whose comments cite the Jacobians: Sola et al. 2018, "A micro Lie
theory", eqs. 143-146); without the velocity model the per-sample system is padded from 3 to 5
variables with an identity block, which gives the two padding variables an exact zero step and
the others the same arithmetic as a 3 x 3 system. Within the sweep, the blocks live in a few
small arrays that are filled in place, never reassigned (numba counts references on every
assignment of an array variable, which costs more than the arithmetic here).

The cost of a trial point (`cost_kernel`, a third of an iteration) needs no recursion over the
samples: on a recording of `SPLIT_MIN_SAMPLES` or more it runs as two ranges of samples on two
threads (`range_cost`; the kernels release the GIL), each writing its own rows, and their sums
are added in a fixed order. The split depends on the number of samples alone, so every result is
the same on any machine; it changes the wall time, not the CPU time. The linearisation's
elimination is a recursion; on a long recording (`linearize_ranges`) the Jacobian blocks of one
range of samples are computed (mode BLOCKS) while those of the range before are eliminated from
them (mode FROM_BLOCKS): the same arithmetic in the same order as the one fused pass, bit for bit
(`CompiledOps._eliminate_in_ranges`). On an hour at 100 Hz the two take a quarter off the
smoothers' wall time, for a sixth more CPU time.

The numpy code is the reference: every kernel line implements a line of `smoother_cost` (or of
`fusion.quaternion`), and `tests/test_compiled_smoother.py` checks the kernels against it
(cost, gradient, blocks, solves) and both solvers' iterations and final costs against their
`impl=numpy` runs on simulated and real recordings. The two paths differ only in rounding: the
summation order of the cost and the elimination order of the solve.

Like `_compiled`, the kernels are cached on disk next to this file (`_compiled._jit`), and the
constants that decide the maths (`fusion.quaternion`'s small-angle rules, 1 g) are passed in at
run time. The quaternion helpers are `fusion.quaternion`'s scalar path, compiled (one definition
for numpy, Python and the kernels); numba keys a cached kernel on its own file only, so
`_kernel_cache.forget_stale_kernels` drops this module's cache when `fusion.quaternion` changes.
The namedtuples the kernels take have names found nowhere
else (with a namedtuple of the same name in another compiled module, the kernels of whichever
module was loaded second ran markedly slower), and each is bound to its own name in this module:
numba's cache finds a kernel's signature again only if its types can be looked up by name.
"""
from __future__ import annotations

import math
import threading
import weakref
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from fusion import quaternion as quat
from fusion.types import STANDARD_GRAVITY_M_S2

from ._compiled import _jit
from ._kernel_cache import forget_stale_kernels
from .smoother_cost import LOSSES, Linearization, SmootherProblem

# Modes of `linearize_kernel`.
GRADIENT, BLOCKS, ELIMINATE, FROM_BLOCKS = 0, 1, 2, 3

# The problem as the kernels read it (`problem_arrays`), and the constants of the maths.
SmootherArrays = namedtuple("SmootherArrays", [
    "dt", "gyr", "valid", "acc",  # (T-1,), (T-1, 3), (T-1,) bool, (T, 3)
    "w_motion", "w_acc", "w_vel", "w_vzero", "w_rest",  # weights; w_vel, w_vzero, w_rest may be empty
    "init_quat", "w_prior",  # the anchor
    "w_theta", "theta_axis", "n_bias",  # calibration: prior weights, the gyro axis of each, how many are biases
    "loss", "loss_c",  # robust loss (index in LOSSES) and its scale, g
    "w_mag", "mag_ref", "mag_psi", "mag_loss", "mag_c",  # magnetometer heading term (w_mag empty: none)
])
forget_stale_kernels(__file__, [quat.__file__])  # the kernels compile fusion.quaternion's scalar path

SmootherConstants = namedtuple("SmootherConstants", ["small_angle", "series_rad", "jac_a", "jac_b", "jac_c", "gravity"])


def constants() -> SmootherConstants:
    """`fusion.quaternion`'s small-angle rules and series coefficients, and 1 g in m/s^2."""
    return SmootherConstants(float(quat.SMALL_ANGLE), float(quat.JACOBIAN_SERIES_RAD), tuple(float(c) for c in quat._A[1]),
                             tuple(float(c) for c in quat._B[1]), tuple(float(c) for c in quat._C[1]),
                             float(STANDARD_GRAVITY_M_S2))


def problem_arrays(problem: SmootherProblem) -> SmootherArrays:
    """The arrays of `problem` as contiguous float64 / bool / int64 arrays (one compiled signature)."""
    f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
    return SmootherArrays(
        f(problem.dt), f(problem.gyr), np.ascontiguousarray(problem.valid, dtype=bool), f(problem.acc),
        f(problem.w_motion), f(problem.w_acc), f(problem.w_vel), f(problem.w_vzero), f(problem.w_rest),
        f(problem.init_quat), float(problem.w_prior), f(problem.w_theta),
        np.ascontiguousarray(np.concatenate([problem.bias_idx, problem.scale_idx]), dtype=np.int64), int(len(problem.bias_idx)),
        LOSSES.index(problem.loss), float(problem.loss_c),
        f(problem.w_mag), f(problem.mag_ref), f(problem.mag_psi), LOSSES.index(problem.mag_loss), float(problem.mag_c),
    )


_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache: run each once on a two-sample
    problem (with velocity and calibration variables, the types every problem has). A compiled
    smoother calls this when it is built, so that its `estimate` is timed as the solver alone."""
    global _loaded
    if _loaded:
        return
    from fusion.types import ImuSamples

    from .smoother_cost import Weights

    imu = ImuSamples(np.array([0.0, 0.01]), np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)))
    weights = Weights(bias_axes="x", scale_axes="y", velocity_acc_noise_g2_s=1e-4, velocity_bound_m2_s=0.25)
    problem = SmootherProblem.from_imu(imu, quat.IDENTITY, weights, rest=np.ones(1, bool))
    ops = CompiledOps(problem, blocks=True)
    q, theta, v = np.tile(quat.IDENTITY, (2, 1)), np.zeros(2), np.zeros((2, 2))
    ops.linearize(q, theta, v)
    ops.blocks = False
    lin = ops.linearize(q, theta, v, shift=0.0)
    d_q, d_theta = ops.solve(lin, 0.0)
    ops.trial(q, v, theta, d_q, d_theta, 1.0)
    ops.theta_std(q, theta, v)
    ops.cost(q, theta, v)
    start = np.empty((2, 4))
    dead_reckoning(problem.gyr, problem.valid, problem.dt, quat.IDENTITY, 1e-12, start)
    levelled_kernel(imu.t, imu.acc_g, start, 1.0, 1e-12, np.empty((2, 4)))
    norm_error(start)
    five = np.zeros((2, 5))
    dot(five, five)
    dot(five[:, :3].copy(), five[:, :3])  # the step without velocities: a view of the (T, 5) storage
    _loaded = True


# ============================================================================ scalar helpers
# `fusion.quaternion`'s scalar path, compiled: one definition for numpy, Python and the kernels.
qmul = _jit(quat.multiply_floats)
qexp = _jit(quat.exp_floats)
qlog = _jit(quat.log_floats)
qnormalize = _jit(quat.normalize_floats)
rotation = _jit(quat.rotation_floats)  # R(q) as 9 scalars, row by row


@_jit
def load_quat(q, t):
    return (q[t, 0], q[t, 1], q[t, 2], q[t, 3])


@_jit
def right_jacobian_inv(x, y, z, o):
    """J_r^-1(v) = I + [v]x / 2 + C [v]x^2 as 9 scalars, row by row (`quaternion.right_jacobian_inv`)."""
    c = series(math.sqrt(x * x + y * y + z * z), 2, o)
    return (1.0 + c * (-z * z - y * y), -0.5 * z + c * (x * y), 0.5 * y + c * (x * z),
            0.5 * z + c * (x * y), 1.0 + c * (-z * z - x * x), -0.5 * x + c * (y * z),
            -0.5 * y + c * (x * z), 0.5 * x + c * (y * z), 1.0 + c * (-y * y - x * x))


@_jit
def right_jacobian(x, y, z, o):
    """J_r(v) = I - A [v]x + B [v]x^2 as 9 scalars, row by row (`quaternion.right_jacobian`)."""
    t = math.sqrt(x * x + y * y + z * z)
    a = series(t, 0, o)
    b = series(t, 1, o)
    return (1.0 + b * (-z * z - y * y), a * z + b * (x * y), -a * y + b * (x * z),
            -a * z + b * (x * y), 1.0 + b * (-z * z - x * x), a * x + b * (y * z),
            a * y + b * (x * z), -a * x + b * (y * z), 1.0 + b * (-y * y - x * x))


@_jit
def fill3(M, v):
    """M (3, 3) = the 9 scalars v, row by row."""
    for i in range(3):
        for j in range(3):
            M[i, j] = v[3 * i + j]


@_jit
def series(t, kind, o):
    """The coefficient `kind` (0: A, 1: B, 2: C of `quaternion._A/_B/_C`) at angle t: the closed
    form above `JACOBIAN_SERIES_RAD`, the Taylor series below (`quaternion._series`)."""
    if t > o.series_rad:
        if kind == 0:
            return (1.0 - math.cos(t)) / t**2
        if kind == 1:
            return (t - math.sin(t)) / t**3
        return 1.0 / t**2 - (1.0 + math.cos(t)) / (2.0 * t * math.sin(t))
    c = o.jac_a if kind == 0 else (o.jac_b if kind == 1 else o.jac_c)
    t2 = t * t
    return ((0.0 * t2 + c[2]) * t2 + c[1]) * t2 + c[0]


@_jit
def step_rotvec(p, b, k, t):
    """phi_t = ((1 + k) g_t - b) dt_t, zero on an invalid step (`SmootherProblem.step_rotvec`)."""
    if not p.valid[t]:
        return (0.0, 0.0, 0.0)
    dt = p.dt[t]
    return (((1.0 + k[0]) * p.gyr[t, 0] - b[0]) * dt, ((1.0 + k[1]) * p.gyr[t, 1] - b[1]) * dt,
            ((1.0 + k[2]) * p.gyr[t, 2] - b[2]) * dt)


@_jit
def motion_residual(qa, qb, u):
    """2 log(q_b^-1 q_a u) (`SmootherProblem.motion_residual`)."""
    return qlog(qmul(qmul((qb[0], -qb[1], -qb[2], -qb[3]), qa), u))


@_jit
def acc_term(sq, w, loss, c):
    """(cost term, IRLS weight) of one accelerometer residual of squared norm sq
    (`SmootherProblem.acc_terms`, `smoother_cost.robust_loss`)."""
    if loss == 0:
        return 0.5 * w * sq, w
    c2 = c * c
    s = sq / c2
    if loss == 1:  # huber
        root = math.sqrt(s)
        if root <= 1.0:
            rho, drho = s, 1.0
        else:
            rho, drho = 2.0 * root - 1.0, 1.0 / max(root, 1e-300)
    elif loss == 2:  # cauchy
        rho, drho = math.log1p(s), 1.0 / (1.0 + s)
    else:  # geman-mcclure
        rho, drho = s / (1.0 + s), 1.0 / (1.0 + s) ** 2
    return 0.5 * w * c2 * rho, w * drho


@_jit
def mag_residual(p, t, qt):
    """The magnetometer's heading residual at sample t, q_t = qt (`SmootherProblem.mag_residual`):
    (r_h rad, k0, k1, k2)."""
    d = qmul(qt, (p.mag_ref[t, 0], -p.mag_ref[t, 1], -p.mag_ref[t, 2], -p.mag_ref[t, 3]))
    dw, dx, dy, dz = d
    n2 = dw * dw + dz * dz
    x = p.mag_psi[t] + 2.0 * math.atan2(dz, dw)
    r = x - 2.0 * math.pi * math.floor((x + math.pi) / (2.0 * math.pi))
    safe = n2 if n2 > 0.0 else 1.0
    return r, (dw * dy + dz * dx) / safe, (dz * dy - dw * dx) / safe, 1.0


@_jit
def rest_residual(p, b, k, t, i):
    """Rest residual of step t on the i-th bias variable's axis, and that axis."""
    ax = p.theta_axis[i]
    return (1.0 + k[ax]) * p.gyr[t, ax] - b[ax], ax


@_jit
def calibration(p, theta):
    """theta -> (bias (3,), scale error (3,)) (`SmootherProblem.split_theta`)."""
    b = np.zeros(3)
    k = np.zeros(3)
    for i in range(len(theta)):
        if i < p.n_bias:
            b[p.theta_axis[i]] = theta[i]
        else:
            k[p.theta_axis[i]] = theta[i]
    return b, k


@_jit
def keep_step(keep, t, u, r):
    """Store step t's u_t (4) and motion residual r_m,t (3) in keep[t] (5 x 5: rows 0 and 1)."""
    for i in range(4):
        keep[t, 0, i] = u[i]
    for i in range(3):
        keep[t, 1, i] = r[i]


@_jit
def kept_step(kept, t):
    """(u_t, r_m,t) as `keep_step` stored them."""
    return (kept[t, 0, 0], kept[t, 0, 1], kept[t, 0, 2], kept[t, 0, 3]), (kept[t, 1, 0], kept[t, 1, 1], kept[t, 1, 2])


@_jit
def keep_mag(keep, t, m):
    """Store sample t's magnetometer residual and its Jacobian's factors (`mag_residual`: r_h, k0, k1,
    k2) and its (cost term, IRLS weight) (`acc_term`), 6 numbers, in keep[t] (row 2 and keep[t, 3, 0])."""
    for i in range(5):
        keep[t, 2, i] = m[i]
    keep[t, 3, 0] = m[5]


@_jit
def kept_mag(kept, t):
    """What `keep_mag` stored."""
    return kept[t, 2, 0], kept[t, 2, 1], kept[t, 2, 2], kept[t, 2, 3], kept[t, 2, 4], kept[t, 3, 0]


# ============================================================================ cost
@_jit
def total_cost(p, theta, V, acc, motion, prior_sq, vel, vzero, rest):
    """The cost from its terms' sums (`SmootherProblem.cost`): acc (with its 1/2), and the
    weighted squared residuals of motion, velocity, zero velocity and rest, the anchor's
    |r_0|^2; the calibration prior from theta."""
    prior = 0.0
    for i in range(len(theta)):
        prior += p.w_theta[i] * theta[i] ** 2
    total = acc + 0.5 * (motion + p.w_prior * prior_sq + prior)
    if V:
        total += 0.5 * (vel + vzero)
    return total + 0.5 * rest


@_jit
def cost_kernel(p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep, t0, t1, sums):
    """The cost's terms (`SmootherProblem.cost`) over the samples t0 <= t < t1 and their steps to
    t + 1, at q (T, 4), v (T, V) m/s, theta (P,); or, with kind 1 (geodesic) or 2 (normalise), at
    the point moved by alpha times the step x (T, B): q_out_t = retraction of q_t by alpha x_t[:3]
    (`gd.GradientDescentSmoother.retract`, `quaternion.retract`), v_out = v + alpha x[:, 3:], both
    written for t0 <= t < t1 (the step from t1 - 1 reads q_t1 moved, and leaves it to its own range).
    sums[:7] = the sums of the terms: acc (with its 1/2), motion, velocity, zero velocity, rest
    (weighted squares), magnetometer (with its 1/2), and the anchor's |r_0|^2 (0 unless t0 = 0):
    `total_cost` of them is the cost (`range_cost`). If keep (T, 5, 5) has rows, each step's
    u_t = exp(phi_t / 2) and motion residual r_m,t (`keep_step`), each sample's accelerometer cost
    term and IRLS weight (keep[t, 1, 3:5]) and magnetometer residual (`keep_mag`) are written to
    it, for the linearisation at this point (`linearize_kernel`'s `kept`)."""
    T = q.shape[0]
    V = v.shape[1]
    b, k = calibration(p, theta)
    cost_acc = 0.0
    cost_motion = 0.0
    cost_vel = 0.0
    cost_vzero = 0.0
    cost_rest = 0.0
    cost_mag = 0.0
    R = np.empty((3, 3))
    Rn = np.empty((3, 3))
    qn = (0.0, 0.0, 0.0, 0.0)
    qt = (0.0, 0.0, 0.0, 0.0)
    for t in range(t0, t1):
        if t == t0:
            qt = moved(q, x, alpha, kind, t, o, q_out, True)
            if kind:
                for i in range(V):
                    v_out[t, i] = v[t, i] + alpha * x[t, 3 + i]
            fill3(R, rotation(qt))
        else:
            qt = qn
            for i in range(3):
                for j in range(3):
                    R[i, j] = Rn[i, j]
        vv = v_out if kind else v
        r0 = p.acc[t, 0] - R[2, 0]
        r1 = p.acc[t, 1] - R[2, 1]
        r2 = p.acc[t, 2] - R[2, 2]
        c, w = acc_term(r0 * r0 + r1 * r1 + r2 * r2, p.w_acc[t], p.loss, p.loss_c)
        cost_acc += c
        if keep.shape[0]:
            keep[t, 1, 3], keep[t, 1, 4] = c, w
        if len(p.w_mag) and p.w_mag[t] > 0.0:
            rh, k0, k1, k2 = mag_residual(p, t, qt)
            c, w = acc_term(rh * rh, p.w_mag[t], p.mag_loss, p.mag_c)
            cost_mag += c
            if keep.shape[0]:
                keep_mag(keep, t, (rh, k0, k1, k2, c, w))
        if V:
            cost_vzero += p.w_vzero[t] * (vv[t, 0] * vv[t, 0] + vv[t, 1] * vv[t, 1])
        if t == T - 1:
            break
        mine = t + 1 < t1  # sample t + 1 is in this range: written here
        qn = moved(q, x, alpha, kind, t + 1, o, q_out, mine)
        vn0, vn1 = 0.0, 0.0  # v_t+1 (V = 2)
        if V:
            vn0, vn1 = v[t + 1, 0], v[t + 1, 1]
            if kind:
                vn0, vn1 = vn0 + alpha * x[t + 1, 3], vn1 + alpha * x[t + 1, 4]
                if mine:
                    v_out[t + 1, 0], v_out[t + 1, 1] = vn0, vn1
        fill3(Rn, rotation(qn))
        phi = step_rotvec(p, b, k, t)
        u = qexp(phi[0], phi[1], phi[2], o.small_angle)
        r = motion_residual(qt, qn, u)
        if keep.shape[0]:
            keep_step(keep, t, u, r)
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
        r = qlog(qmul((p.init_quat[0], -p.init_quat[1], -p.init_quat[2], -p.init_quat[3]),
                      (q_out[0, 0], q_out[0, 1], q_out[0, 2], q_out[0, 3]) if kind else load_quat(q, 0)))
        prior_sq = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], sums[6] = \
        cost_acc, cost_motion, cost_vel, cost_vzero, cost_rest, cost_mag, prior_sq


@_jit
def cost_of_sums(p, theta, V, sums):
    """The cost from `cost_kernel`'s sums of its ranges (R, 7), added in the ranges' order."""
    total = np.zeros(7)
    for i in range(sums.shape[0]):
        for j in range(7):
            total[j] += sums[i, j]
    acc, motion, vel, vzero, rest, mag, prior_sq = total
    return total_cost(p, theta, V, acc, motion, prior_sq, vel, vzero, rest) + mag


# A long recording's cost is computed as two ranges of samples on two threads (the kernels release
# the GIL). Where it is split depends on the number of samples alone, so the sum, and every result
# that depends on it, is the same on any machine.
SPLIT_MIN_SAMPLES = 8192


def cost_ranges(T: int) -> tuple[int, ...]:
    """The bounds of `range_cost`'s ranges for T samples."""
    return (0, T) if T < SPLIT_MIN_SAMPLES else (0, T // 2, T)


def range_cost(p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep) -> float:
    """`cost_kernel` over the whole recording, in the one or two ranges of `cost_ranges` (the second
    on a thread of its own): the cost, with q_out, v_out and keep written as `cost_kernel` says."""
    bounds = cost_ranges(len(q))
    sums = np.zeros((len(bounds) - 1, 7))
    args = (p, o, q, v, theta, x, alpha, kind, q_out, v_out, keep)
    second = run_beside(cost_kernel, *args, bounds[1], bounds[2], sums[1]) if len(bounds) == 3 else None
    try:
        cost_kernel(*args, 0, bounds[1], sums[0])
    finally:  # the second range writes into the caller's arrays: never leave it running
        if second is not None:
            second()
    return cost_of_sums(p, theta, v.shape[1], sums)


def run_beside(work, *args):
    """Start work(*args) on a new thread; returns the function that waits for it and returns what
    it returned or re-raises what it raised. A thread per call, not a pool: a pool's thread does not
    survive a fork."""
    raised, returned = [], []

    def target():
        try:
            returned.append(work(*args))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            raised.append(exc)

    thread = threading.Thread(target=target, name="fusion-smoother-range", daemon=True)
    thread.start()

    def join():
        thread.join()
        if raised:
            raise raised[0]
        return returned[0]

    return join


# The linearisation of a long recording in ranges on two threads (`CompiledOps._eliminate_in_ranges`).
RANGE_SAMPLES = (8192, 12288)  # the smallest and the largest range


def linearize_ranges(T: int) -> list[int]:
    """The bounds of `CompiledOps._eliminate_in_ranges`'s ranges for T samples: eight or more ranges
    of 8,192 to 12,288 samples (`RANGE_SAMPLES`; two ranges' blocks take less memory than the
    trial's trajectory), or one range below 8 x 8,192 samples. Writing and reading the blocks takes
    about a quarter more CPU time than the one fused pass; only on long recordings does the overlap
    gain more wall time than that: one hour at 100 Hz, 27 % less wall time for the whole estimate
    (`bench_long.py` against `--one-thread`); BROAD trial 15, 52,556 samples in ranges of 6,569
    (measured while choosing this bound), 6 % less wall time for 25 % more CPU time. The results do
    not depend on the ranges."""
    size = min(max(T // 8, RANGE_SAMPLES[0]), RANGE_SAMPLES[1])
    return [0, T] if T < 8 * RANGE_SAMPLES[0] else [*range(0, T, size), T]


@_jit
def moved(q, x, alpha, kind, t, o, q_out, write):
    """q_t (kind 0), or q_t retracted by alpha x_t[:3] (kind 1: q exp([0, alpha x / 2]); kind 2:
    normalise(q + q * [0, alpha x / 2])), then written to q_out[t] if `write`."""
    qt = load_quat(q, t)
    if kind == 0:
        return qt
    dx, dy, dz = alpha * x[t, 0], alpha * x[t, 1], alpha * x[t, 2]
    if kind == 1:
        m = qnormalize(qmul(qt, qexp(dx, dy, dz, o.small_angle)))
    else:
        d = qmul(qt, (0.0, dx, dy, dz))
        m = qnormalize((qt[0] + 0.5 * d[0], qt[1] + 0.5 * d[1], qt[2] + 0.5 * d[2], qt[3] + 0.5 * d[3]))
    if write:
        for i in range(4):
            q_out[t, i] = m[i]
    return m


# ============================================================================ linearisation
@_jit
def ldl5(S):
    """S = L diag(d) L^T for the lower triangle of the 5 x 5 S, L unit lower triangular (no
    square roots: Golub & Van Loan 2013, sec. 4.1.2): (positive definite, L below the diagonal
    row by row (10 scalars), 1 / d (5 scalars))."""
    d0 = S[0, 0]
    r0 = 1.0 / d0
    e10, e20, e30, e40 = S[1, 0], S[2, 0], S[3, 0], S[4, 0]  # E = L diag(d), column 0
    l10, l20, l30, l40 = e10 * r0, e20 * r0, e30 * r0, e40 * r0
    d1 = S[1, 1] - l10 * e10
    r1 = 1.0 / d1
    e21, e31, e41 = S[2, 1] - l20 * e10, S[3, 1] - l30 * e10, S[4, 1] - l40 * e10
    l21, l31, l41 = e21 * r1, e31 * r1, e41 * r1
    d2 = S[2, 2] - l20 * e20 - l21 * e21
    r2 = 1.0 / d2
    e32, e42 = S[3, 2] - l30 * e20 - l31 * e21, S[4, 2] - l40 * e20 - l41 * e21
    l32, l42 = e32 * r2, e42 * r2
    d3 = S[3, 3] - l30 * e30 - l31 * e31 - l32 * e32
    r3 = 1.0 / d3
    e43 = S[4, 3] - l40 * e30 - l41 * e31 - l42 * e32
    l43 = e43 * r3
    d4 = S[4, 4] - l40 * e40 - l41 * e41 - l42 * e42 - l43 * e43
    r4 = 1.0 / d4
    ok = d0 > 0.0 and d1 > 0.0 and d2 > 0.0 and d3 > 0.0 and d4 > 0.0
    return ok, (l10, l20, l21, l30, l31, l32, l40, l41, l42, l43), (r0, r1, r2, r3, r4)


@_jit
def ldl_solve5(L, r, b0, b1, b2, b3, b4):
    """S^-1 b for S = L diag(1 / r) L^T (`ldl5`), five scalars in and out."""
    l10, l20, l21, l30, l31, l32, l40, l41, l42, l43 = L
    y1 = b1 - l10 * b0
    y2 = b2 - l20 * b0 - l21 * y1
    y3 = b3 - l30 * b0 - l31 * y1 - l32 * y2
    y4 = b4 - l40 * b0 - l41 * y1 - l42 * y2 - l43 * y3
    x4 = y4 * r[4]
    x3 = y3 * r[3] - l43 * x4
    x2 = y2 * r[2] - l32 * x3 - l42 * x4
    x1 = y1 * r[1] - l21 * x2 - l31 * x3 - l41 * x4
    x0 = b0 * r[0] - l10 * x1 - l20 * x2 - l30 * x3 - l40 * x4
    return x0, x1, x2, x3, x4


@_jit
def linearize_kernel(p, o, q, v, theta, mode, shift, free, rhs_q, rhs_theta,
                     grad_q, grad_theta, diag, off, cross, theta_block, M, c, N, schur, schur_rhs, quad, kept,
                     t0, t1, carry):
    """Cost, gradient and Gauss-Newton blocks at (q (T, 4), v (T, V), theta (P,))
    (`SmootherProblem.linearize`). Returns the cost, or nan if the matrix is not positive
    definite (mode ELIMINATE).

    Always: grad_theta (P,), and grad_q (T, B) unless it has no rows. mode BLOCKS: also the blocks diag (T, B, B),
    off (T-1, B, B), cross (T, B, P), theta_block (P, P) as the reference lays them out.
    mode ELIMINATE: eliminate (H + shift diag(H)) x = b on the fly (module docstring) for the
    calibration variables `free` (F,) (their indices; the others are held), with b = -grad or,
    if rhs_q has rows, b = -[rhs_q; rhs_theta]; writes M (R, 5, 5), c (R, 5), N (R, 5, F) (R = T
    rows, or 2 to keep only the running ones) and the Schur complement schur (F, F) with its
    right-hand side schur_rhs (F,), and quad[0] = sum_t b'_t^T S_t^-1 b'_t (with the Schur
    complement's part, b^T (H + shift diag(H))^-1 b: `CompiledOps.slope`).

    kept (T, 5, 5), if it has rows: each step's u_t and motion residual r_m,t, each sample's
    accelerometer term and magnetometer residual at this very point (q, theta), as `cost_kernel`
    computed them for a trial step here (`keep_step`, `keep_mag`): read, not computed again (the
    same numbers). It may be M itself: row t is read before M's row t is written.

    Ranges (`CompiledOps._eliminate_in_ranges`): the samples t0 <= t < t1 only. Mode BLOCKS over a
    range writes its blocks and gradient at rows t - t0 and, before T, returns 0 and leaves in carry
    (`range_carry_size`) what the next range continues from (what the last step adds to its next
    sample, the cost's sums, the calibration block and gradient); the range that ends at T returns
    the cost, theta_block and grad_theta. Mode FROM_BLOCKS eliminates those blocks (grad_q, diag,
    off, cross: the BLOCKS range's rows; theta_block, grad_theta: the last range's) as ELIMINATE
    would have, the same arithmetic in the same order, with H[t-1, t] in carry[:25] between ranges;
    returns 0 (nan: not positive definite). A whole pass is t0 = 0, t1 = T, carry without rows.
    """
    T = q.shape[0]
    V = v.shape[1]
    B = 3 + V
    P = len(theta)
    F = len(free)
    b, k = calibration(p, theta)
    rows = M.shape[0]
    external = rhs_q.shape[0] > 0
    ranged = carry.shape[0] > 0
    cost_acc = 0.0
    cost_motion = 0.0
    cost_vel = 0.0
    cost_vzero = 0.0
    cost_rest = 0.0
    cost_prior = 0.0
    cost_mag = 0.0
    R = np.empty((3, 3))
    Rn = np.empty((3, 3))
    A = np.empty((3, 3))
    Ru = np.empty((3, 3))
    J0 = np.empty((3, 3))
    Jr = np.empty((3, 3))
    D = np.zeros((5, 5))  # H[t, t], then S_t
    Dn = np.zeros((5, 5))  # what step t adds to H[t+1, t+1]
    O = np.zeros((5, 5))  # H[t, t+1]
    Op = np.zeros((5, 5))  # H[t-1, t]
    C = np.zeros((5, P))  # H[t, theta]
    Cn = np.zeros((5, P))
    g = np.zeros(5)
    gn = np.zeros(5)
    AJ = np.zeros((3, 3))  # column a: A J_r(phi) e_a, what a calibration variable on gyro axis a moves r_m by (per unit)
    J0AJ = np.zeros((3, 3))  # J0^T AJ
    AAJ = np.zeros((3, 3))  # A AJ
    JJ = np.zeros((3, 3))  # AJ^T AJ
    used = np.zeros(3, np.bool_)  # gyro axes with a calibration variable
    for m in range(P):
        used[p.theta_axis[m]] = True
    dm = np.zeros(P)
    gth = np.zeros(P)
    G = np.zeros((P, P))
    col = np.zeros(5)
    Cf = np.zeros((5, F))
    X0 = np.zeros((2, 3))
    X1 = np.zeros((2, 3))
    if t0 == 0:
        quad[0] = 0.0
        for i in range(F):
            schur_rhs[i] = 0.0
            for j in range(F):
                schur[i, j] = 0.0
    elif mode == FROM_BLOCKS:
        carry_block(carry, 0, Op, False)
    else:  # BLOCKS, continued from the range before
        sums = np.empty(7)
        carry_state(carry, False, Dn, gn, Cn, sums, gth, G)
        cost_acc, cost_motion, cost_vel, cost_vzero, cost_rest, cost_prior, cost_mag = sums
    qn = load_quat(q, t0)
    rn = rotation(qn)
    for t in range(t0, t1):
        if mode == FROM_BLOCKS:  # the blocks a BLOCKS pass over this range wrote (row t - t0)
            tr = t - t0
            for i in range(5):
                g[i] = grad_q[tr, i] if i < B else 0.0
                for j in range(i + 1):
                    D[i, j] = diag[tr, i, j] if i < B else 0.0
                for j in range(5):
                    O[i, j] = off[tr, i, j] if i < B and j < B and t < T - 1 else 0.0
                for m in range(P):
                    C[i, m] = cross[tr, i, m] if i < B else 0.0
        else:
            qt = qn
            rt = rn
            fill3(R, rt)
            # What step t-1 added to sample t becomes sample t's; only lower triangles of the symmetric
            # diagonal blocks are formed (mirrored for BLOCKS).
            for i in range(5):
                g[i] = gn[i]
                gn[i] = 0.0
                for j in range(i + 1):
                    D[i, j] = Dn[i, j]
                    Dn[i, j] = 0.0
                for j in range(5):
                    O[i, j] = 0.0
                for j in range(P):
                    C[i, j] = Cn[i, j]
                    Cn[i, j] = 0.0
            # Accelerometer: r_a = a - h, h = R^T e_z (row 2 of R); d r_a / d delta = -[h]x.
            h0, h1, h2 = R[2, 0], R[2, 1], R[2, 2]
            r0, r1, r2 = p.acc[t, 0] - h0, p.acc[t, 1] - h1, p.acc[t, 2] - h2
            if kept.shape[0]:
                ca, wa = kept[t, 1, 3], kept[t, 1, 4]
            else:
                ca, wa = acc_term(r0 * r0 + r1 * r1 + r2 * r2, p.w_acc[t], p.loss, p.loss_c)
            cost_acc += ca
            y0, y1, y2 = wa * r0, wa * r1, wa * r2
            g[0] += h1 * y2 - h2 * y1
            g[1] += h2 * y0 - h0 * y2
            g[2] += h0 * y1 - h1 * y0
            hh = (h0, h1, h2)
            for i in range(3):
                for j in range(i + 1):
                    D[i, j] += wa * ((1.0 if i == j else 0.0) - hh[i] * hh[j])
            if len(p.w_mag) and p.w_mag[t] > 0.0:
                # Magnetometer (heading only): d r_h / d delta = k^T R, the body-frame row R^T k.
                if kept.shape[0]:
                    rh, k0, k1, k2, cm, wh = kept_mag(kept, t)
                else:
                    rh, k0, k1, k2 = mag_residual(p, t, qt)
                    cm, wh = acc_term(rh * rh, p.w_mag[t], p.mag_loss, p.mag_c)
                cost_mag += cm
                jh = (R[0, 0] * k0 + R[1, 0] * k1 + R[2, 0] * k2, R[0, 1] * k0 + R[1, 1] * k1 + R[2, 1] * k2,
                      R[0, 2] * k0 + R[1, 2] * k1 + R[2, 2] * k2)
                for i in range(3):
                    g[i] += wh * rh * jh[i]
                    for j in range(i + 1):
                        D[i, j] += wh * jh[i] * jh[j]
            if t == 0:  # the anchor: d r_0 / d delta_0 = J_r^-1(r_0)
                r = qlog(qmul((p.init_quat[0], -p.init_quat[1], -p.init_quat[2], -p.init_quat[3]), qt))
                cost_prior = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
                fill3(A, right_jacobian_inv(r[0], r[1], r[2], o))
                for i in range(3):
                    g[i] += p.w_prior * (A[0, i] * r[0] + A[1, i] * r[1] + A[2, i] * r[2])
                    for j in range(i + 1):
                        D[i, j] += p.w_prior * (A[0, i] * A[0, j] + A[1, i] * A[1, j] + A[2, i] * A[2, j])
            if V:
                wz = p.w_vzero[t]
                cost_vzero += wz * (v[t, 0] * v[t, 0] + v[t, 1] * v[t, 1])
                for i in range(2):
                    g[3 + i] += wz * v[t, i]
                    D[3 + i, 3 + i] += wz
            if t < T - 1:
                qn = load_quat(q, t + 1)
                rn = rotation(qn)
                fill3(Rn, rn)
                # Motion: r_m = 2 log(q_{t+1}^-1 q_t u_t); d r / d delta_t = A R(u)^T, d r / d delta_{t+1} = -A^T.
                phi = step_rotvec(p, b, k, t)
                if kept.shape[0]:  # computed by the trial that reached this point
                    u, r = kept_step(kept, t)
                else:
                    u = qexp(phi[0], phi[1], phi[2], o.small_angle)
                    r = motion_residual(qt, qn, u)
                wm = p.w_motion[t]
                cost_motion += wm * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
                fill3(A, right_jacobian_inv(r[0], r[1], r[2], o))
                fill3(Ru, rotation(u))
                wr = (wm * r[0], wm * r[1], wm * r[2])
                atw = (A[0, 0] * wr[0] + A[1, 0] * wr[1] + A[2, 0] * wr[2],
                       A[0, 1] * wr[0] + A[1, 1] * wr[1] + A[2, 1] * wr[2],
                       A[0, 2] * wr[0] + A[1, 2] * wr[1] + A[2, 2] * wr[2])
                for i in range(3):
                    g[i] += Ru[i, 0] * atw[0] + Ru[i, 1] * atw[1] + Ru[i, 2] * atw[2]
                    gn[i] -= A[i, 0] * wr[0] + A[i, 1] * wr[1] + A[i, 2] * wr[2]
                    for j in range(3):
                        J0[i, j] = A[i, 0] * Ru[j, 0] + A[i, 1] * Ru[j, 1] + A[i, 2] * Ru[j, 2]
                for i in range(3):
                    for j in range(3):
                        if j <= i:
                            D[i, j] += wm * (J0[0, i] * J0[0, j] + J0[1, i] * J0[1, j] + J0[2, i] * J0[2, j])
                            Dn[i, j] += wm * (A[i, 0] * A[j, 0] + A[i, 1] * A[j, 1] + A[i, 2] * A[j, 2])
                        O[i, j] = -wm * (J0[0, i] * A[j, 0] + J0[1, i] * A[j, 1] + J0[2, i] * A[j, 2])
                if P:
                    # d r_m / d theta = A J_r(phi) d phi / d theta, d phi / d theta: -dt (bias), g dt (scale):
                    # column a of A J_r(phi) once per gyro axis, times each variable's d phi_a / d theta.
                    fill3(Jr, right_jacobian(phi[0], phi[1], phi[2], o))
                    for a in range(3):
                        if used[a]:
                            for i in range(3):
                                AJ[i, a] = A[i, 0] * Jr[0, a] + A[i, 1] * Jr[1, a] + A[i, 2] * Jr[2, a]
                            for i in range(3):
                                J0AJ[i, a] = J0[0, i] * AJ[0, a] + J0[1, i] * AJ[1, a] + J0[2, i] * AJ[2, a]
                                AAJ[i, a] = A[i, 0] * AJ[0, a] + A[i, 1] * AJ[1, a] + A[i, 2] * AJ[2, a]
                            for e in range(a + 1):
                                if used[e]:
                                    JJ[a, e] = JJ[e, a] = AJ[0, a] * AJ[0, e] + AJ[1, a] * AJ[1, e] + AJ[2, a] * AJ[2, e]
                    dt = p.dt[t]
                    for m in range(P):
                        ax = p.theta_axis[m]
                        d = 0.0
                        if p.valid[t]:
                            d = -dt if m < p.n_bias else p.gyr[t, ax] * dt
                        dm[m] = d
                        gth[m] += d * (AJ[0, ax] * wr[0] + AJ[1, ax] * wr[1] + AJ[2, ax] * wr[2])
                        wd = wm * d
                        for i in range(3):
                            C[i, m] += wd * J0AJ[i, ax]
                            Cn[i, m] -= wd * AAJ[i, ax]
                    for m in range(P):
                        wd = wm * dm[m]
                        for n in range(P):
                            G[m, n] += wd * dm[n] * JJ[p.theta_axis[m], p.theta_axis[n]]
                if V:
                    # Velocity increments: d r_v / d delta_t = X0 = G dt P R_t [a_t]x / 2 (rows: R_t,i x a_t),
                    # / d delta_{t+1} = X1 likewise, / d v_t = -I, / d v_{t+1} = I.
                    dt = p.dt[t]
                    half = 0.5 * o.gravity * dt
                    wv = p.w_vel[t]
                    a0x, a0y, a0z = p.acc[t, 0], p.acc[t, 1], p.acc[t, 2]
                    a1x, a1y, a1z = p.acc[t + 1, 0], p.acc[t + 1, 1], p.acc[t + 1, 2]
                    for i in range(2):
                        f0 = R[i, 0] * a0x + R[i, 1] * a0y + R[i, 2] * a0z
                        f1 = Rn[i, 0] * a1x + Rn[i, 1] * a1y + Rn[i, 2] * a1z
                        rv = v[t + 1, i] - v[t, i] - o.gravity * (0.5 * (f0 + f1)) * dt
                        cost_vel += wv * rv * rv
                        X0[i, 0] = half * (R[i, 1] * a0z - R[i, 2] * a0y)
                        X0[i, 1] = half * (R[i, 2] * a0x - R[i, 0] * a0z)
                        X0[i, 2] = half * (R[i, 0] * a0y - R[i, 1] * a0x)
                        X1[i, 0] = half * (Rn[i, 1] * a1z - Rn[i, 2] * a1y)
                        X1[i, 1] = half * (Rn[i, 2] * a1x - Rn[i, 0] * a1z)
                        X1[i, 2] = half * (Rn[i, 0] * a1y - Rn[i, 1] * a1x)
                        w = wv * rv
                        for j in range(3):
                            g[j] += X0[i, j] * w
                            gn[j] += X1[i, j] * w
                        g[3 + i] -= w
                        gn[3 + i] += w
                    for i in range(3):
                        for j in range(3):
                            if j <= i:
                                D[i, j] += wv * (X0[0, i] * X0[0, j] + X0[1, i] * X0[1, j])
                                Dn[i, j] += wv * (X1[0, i] * X1[0, j] + X1[1, i] * X1[1, j])
                            O[i, j] += wv * (X0[0, i] * X1[0, j] + X0[1, i] * X1[1, j])
                        for m in range(2):
                            D[3 + m, i] -= wv * X0[m, i]
                            Dn[3 + m, i] += wv * X1[m, i]
                            O[i, 3 + m] += wv * X0[m, i]
                            O[3 + m, i] -= wv * X1[m, i]
                    for m in range(2):
                        D[3 + m, 3 + m] += p.w_vel[t]
                        Dn[3 + m, 3 + m] += p.w_vel[t]
                        O[3 + m, 3 + m] -= p.w_vel[t]
                if len(p.w_rest) and p.w_rest[t] > 0:  # the rest term (`rest_terms`): theta only
                    w = p.w_rest[t]
                    for i in range(p.n_bias):
                        rr, ax = rest_residual(p, b, k, t, i)
                        cost_rest += w * rr * rr
                        for m in range(P):  # d r / d theta_m: -1 (this axis's bias), g_t (its scale)
                            jm = -1.0 if m == i else (p.gyr[t, ax] if m >= p.n_bias and p.theta_axis[m] == ax else 0.0)
                            if jm != 0.0:
                                gth[m] += w * rr * jm
                                for n in range(P):
                                    jn = -1.0 if n == i else (p.gyr[t, ax] if n >= p.n_bias and p.theta_axis[n] == ax else 0.0)
                                    G[m, n] += w * jm * jn
        if grad_q.shape[0] and mode != FROM_BLOCKS:
            for i in range(B):
                grad_q[t - t0, i] = g[i]
        if mode == BLOCKS:
            tr = t - t0
            for i in range(B):
                if ranged:  # for FROM_BLOCKS, which reads the lower triangle
                    for j in range(i + 1):
                        diag[tr, i, j] = D[i, j]
                else:
                    for j in range(B):
                        diag[tr, i, j] = D[i, j] if j <= i else D[j, i]
                if t < T - 1:
                    for j in range(B):
                        off[tr, i, j] = O[i, j]
                for m in range(P):
                    cross[tr, i, m] = C[i, m]
        elif mode == ELIMINATE or mode == FROM_BLOCKS:
            row, prev = (t, t - 1) if rows == T else (t & 1, (t - 1) & 1)
            for i in range(5):
                D[i, i] = D[i, i] * (1.0 + shift) if i < B else 1.0  # the padding variables: identity
                col[i] = -(rhs_q[t, i] if external else g[i]) if i < B else 0.0
                for m in range(F):
                    Cf[i, m] = C[i, free[m]]
            if t > 0:  # S_t = D_t - O^T M, b'_t = b_t - O^T c, C'_t = C_t - O^T N (O = H[t-1, t])
                for i in range(5):
                    for j in range(i + 1):
                        s = 0.0
                        for m in range(5):
                            s += Op[m, i] * M[prev, m, j]
                        D[i, j] -= s
                    s = 0.0
                    for m in range(5):
                        s += Op[m, i] * c[prev, m]
                    col[i] -= s
                    for n in range(F):
                        s = 0.0
                        for m in range(5):
                            s += Op[m, i] * N[prev, m, n]
                        Cf[i, n] -= s
            ok, Lt, rt = ldl5(D)
            if not ok:
                return math.nan
            x = ldl_solve5(Lt, rt, col[0], col[1], col[2], col[3], col[4])
            for i in range(5):
                c[row, i] = x[i]
                quad[0] += col[i] * x[i]
            for n in range(F):  # N_t = S^-1 C'_t; the Schur complement and its right-hand side
                x = ldl_solve5(Lt, rt, Cf[0, n], Cf[1, n], Cf[2, n], Cf[3, n], Cf[4, n])
                for i in range(5):
                    N[row, i, n] = x[i]
                s = 0.0
                for i in range(5):
                    s += Cf[i, n] * c[row, i]
                schur_rhs[n] += s
                for m in range(n + 1):
                    s = 0.0
                    for i in range(5):
                        s += Cf[i, m] * x[i]
                    schur[m, n] += s
            if t < T - 1:
                for j in range(5):  # M_t = S^-1 O_t
                    x = ldl_solve5(Lt, rt, O[0, j], O[1, j], O[2, j], O[3, j], O[4, j])
                    for i in range(5):
                        M[row, i, j] = x[i]
                for i in range(5):
                    for j in range(5):
                        Op[i, j] = O[i, j]
    if mode == FROM_BLOCKS:
        carry_block(carry, 0, Op, True)
        if t1 < T:
            return 0.0
        for m in range(P):  # the calibration block and gradient of the BLOCKS pass, prior included
            gth[m] = grad_theta[m]
            for n in range(P):
                G[m, n] = theta_block[m, n]
    elif t1 < T:  # BLOCKS: what the next range continues from
        sums = np.array([cost_acc, cost_motion, cost_vel, cost_vzero, cost_rest, cost_prior, cost_mag])
        carry_state(carry, True, Dn, gn, Cn, sums, gth, G)
        return 0.0
    else:
        for m in range(P):
            gth[m] += p.w_theta[m] * theta[m]
            G[m, m] += p.w_theta[m]
            grad_theta[m] = gth[m]
            if mode == BLOCKS:
                for n in range(P):
                    theta_block[m, n] = G[m, n]
    if mode == ELIMINATE or mode == FROM_BLOCKS:
        for n in range(F):
            for m in range(n):
                schur[n, m] = schur[m, n] = G[free[m], free[n]] - schur[m, n]
            schur[n, n] = G[free[n], free[n]] * (1.0 + shift) - schur[n, n]
            schur_rhs[n] = -(rhs_theta[free[n]] if external else gth[free[n]]) - schur_rhs[n]
    if mode == FROM_BLOCKS:
        return 0.0
    return total_cost(p, theta, V, cost_acc, cost_motion, cost_prior, cost_vel, cost_vzero, cost_rest) + cost_mag


@_jit
def carry_block(carry, at, block, store):
    """Copy the C-contiguous array `block` to carry[at:] (store) or from there; -> the offset after it."""
    flat = block.reshape(-1)
    for i in range(flat.size):
        if store:
            carry[at + i] = flat[i]
        else:
            flat[i] = carry[at + i]
    return at + flat.size


@_jit
def carry_state(carry, store, Dn, gn, Cn, sums, gth, G):
    """A BLOCKS range's state to its carry (store) or from it, in one layout: what the last step
    adds to the next sample (Dn 5 x 5, gn 5, Cn 5 x P), the cost's seven sums, the calibration
    gradient gth (P) and block G (P x P): `range_carry_size` numbers."""
    at = carry_block(carry, 0, Dn, store)
    at = carry_block(carry, at, gn, store)
    at = carry_block(carry, at, Cn, store)
    at = carry_block(carry, at, sums, store)
    at = carry_block(carry, at, gth, store)
    carry_block(carry, at, G, store)


def range_carry_size(P: int) -> int:
    """The length of `linearize_kernel`'s carry (`carry_state`) with P calibration variables; at
    least the 25 of FROM_BLOCKS's H[t-1, t]."""
    return 25 + 5 + 5 * P + 7 + P + P * P


@_jit
def back_substitute(M, c, N, x_theta):
    """x_t = c_t - M_t x_{t+1} - N_t x_theta, backwards (module docstring), into c (T, 5)."""
    T = c.shape[0]
    F = len(x_theta)
    nxt = np.zeros(5)
    for t in range(T - 1, -1, -1):
        for i in range(5):
            s = c[t, i]
            for n in range(F):
                s -= N[t, i, n] * x_theta[n]
            if t < T - 1:
                for j in range(5):
                    s -= M[t, i, j] * nxt[j]
            c[t, i] = s
        for i in range(5):
            nxt[i] = c[t, i]


# ============================================================================ the start and the log
@_jit
def dead_reckoning(gyr, valid, dt, q0, small, out):
    """out (T, 4): q_0 = q0, q_{k+1} = q_k exp([0, w_k dt_k / 2]) (0 where invalid), each row
    normalised (`dr.DeadReckoning`, whose parallel scan gives the same products in another
    order, and `smoother.initial_trajectory`, which normalises)."""
    q = qnormalize((q0[0], q0[1], q0[2], q0[3]))
    for i in range(4):
        out[0, i] = q[i]
    for k in range(len(dt)):
        if valid[k]:
            u = qexp(gyr[k, 0] * dt[k], gyr[k, 1] * dt[k], gyr[k, 2] * dt[k], small)
        else:
            u = (1.0, 0.0, 0.0, 0.0)
        q = qnormalize(qmul(q, u))
        for i in range(4):
            out[k + 1, i] = q[i]


@_jit
def levelled_kernel(t, acc, q, window_s, small, out):
    """out (T, 4): q (T, 4) turned window by window so that the mean world-frame specific force
    of each window points up (`smoother.levelled`, line by line; the first window is q)."""
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
        fill3(R, rotation(load_quat(q, k)))
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
            c = qexp(uy * f, -ux * f, 0.0, small)
        for i in range(4):
            corr[j, i] = c[i]
    for k in range(T):
        j = int(math.floor((t[k] - t[0]) / window_s))
        m = load_quat(q, k) if j == 0 else qnormalize(qmul((corr[j, 0], corr[j, 1], corr[j, 2], corr[j, 3]), load_quat(q, k)))
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


@_jit
def norm_error(q):
    """max |(|q_t|) - 1| (`smoother.SolverLog`)."""
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


def levelled(imu, quat_wxyz: np.ndarray, window_s: float) -> np.ndarray:
    """(T, 4) `smoother.levelled` by the kernel (`levelled_kernel`)."""
    out = np.empty((len(imu), 4))
    levelled_kernel(np.ascontiguousarray(imu.t, float), np.ascontiguousarray(imu.acc_g, float),
                    np.ascontiguousarray(quat_wxyz, float), float(window_s), float(quat.SMALL_ANGLE), out)
    return out


# ============================================================================ the solvers' operations
@dataclass(frozen=True, eq=False)
class CompiledLinearization(Linearization):
    """A `Linearization` from the kernels: cost and gradient, the blocks only if asked for
    (`CompiledOps(blocks=True)`), and the point it was taken at, to eliminate there again."""

    point: tuple = ()


class CompiledOps:
    """What `gn` and `gd` do with the cost, by the kernels: the interface of
    `smoother.ReferenceOps`, whose numpy code is the reference.

    The elimination's per-sample storage (M, c, N: `linearize_kernel`) is allocated once and
    holds one system at a time: `linearize` with a `shift` eliminates the system at its point
    in the same pass (what the next `solve` needs), and `solve` eliminates again if asked for
    another shift, another set of free calibration variables or another right-hand side. The
    step `solve` returns is written over c: it is valid until the next elimination (the solvers
    use it before they linearise again). blocks: linearisations with a Hessian also carry the
    reference's blocks (`Linearization`: for `gd`'s "block" preconditioner).

    Between a `solve` and the next elimination M is not needed: a `trial` writes there each step's
    u_t = exp(phi_t / 2) and motion residual r_m,t, each sample's robust accelerometer term and
    magnetometer residual at the point it tries (their sines, cosines, arctangents and square
    roots are most of a sample's transcendental functions), and the linearisation at that point,
    if the solver accepts it, reads them instead of computing them again: the same numbers, no
    extra memory.
    """

    def __init__(self, problem: SmootherProblem, blocks: bool = False):
        self.problem = problem
        self.arrays = problem_arrays(problem)
        self.consts = constants()
        self.T, self.P = len(problem.acc), problem.n_theta
        self.B = 3 + problem.n_vel
        self.blocks = blocks
        self.norm_error = norm_error
        self._storage = None  # (M, c, N) of the system `_held` (lin, shift, free indices as bytes)
        self._held = None
        self._schur = None
        self._slope = None  # (lin, g.p) of the last solve with lin's own gradient
        self._kept = None  # (weak reference to q, theta) of the trial whose per-sample terms M holds (`trial`)

    # ---------------------------------------------------------------- cost
    def cost(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray) -> float:
        """The cost at (q (T, 4), theta (P,), v (T, V) m/s)."""
        none = np.zeros((0, 5))
        return range_cost(self.arrays, self.consts, q, v, np.asarray(theta, float), none, 0.0, 0, none, none, _NO_STORAGE[0])

    def trial(self, q, v, theta, d_q, d_theta, alpha: float, update: str = "geodesic"):
        """(q, v, theta) moved by alpha times the step (d_q (T, B), d_theta (P,)), retracted
        on the sphere by `update` ("geodesic" or "normalise"), and its cost:
        (q_new, v_new, theta_new, cost)."""
        q_new, v_new = np.empty_like(q), np.empty_like(v)
        theta_new = theta + alpha * d_theta
        if self._storage is not None and d_q.base is self._storage[1]:
            d_q = self._storage[1]  # the step `solve` returned: its (T, 5) storage, handed over whole
        # With no eliminated system waiting for its `solve`, M is free until the next elimination: the
        # trial keeps its per-sample terms there (`cost_kernel`'s keep), for `linearize` at q_new (if accepted).
        keep = self._storage[0] if self._storage is not None and self._held is None else _NO_STORAGE[0]
        self._kept = None
        cost = range_cost(self.arrays, self.consts, q, v, theta_new, np.ascontiguousarray(d_q), float(alpha),
                          1 if update == "geodesic" else 2, q_new, v_new, keep)
        if keep.shape[0]:
            self._kept = (weakref.ref(q_new), theta_new.copy())
        return q_new, v_new, theta_new, cost

    def slope(self, lin: Linearization, d_q, d_theta) -> float:
        """g.p: lin's gradient along the step (d_q (T, B), d_theta (P,)). If lin keeps no
        per-sample gradient, the step must be the last `solve` of lin's own system, p = -H^-1 g,
        and g.p = -g^T H^-1 g comes from its elimination."""
        if len(lin.grad_q):
            return dot(lin.grad_q, d_q) + float(lin.grad_theta @ d_theta)
        if self._slope is None or self._slope[0] is not lin:
            raise ValueError("slope: the step is not the last solve of this linearisation, whose gradient is not kept")
        return self._slope[1]

    # ---------------------------------------------------------------- linearisation and solves
    def linearize(self, q, theta, v, hessian: bool = True, shift: float | None = None, free=None,
                  gradient: bool = True) -> Linearization:
        """Cost and gradient at (q, theta, v) (gradient=False: no per-sample gradient, grad_q
        has no rows). With `hessian`: the blocks if this object keeps them, else, given a
        `shift`, the system (H + shift diag(H)) x = -g for the free calibration variables `free`
        ((P,) bool; None: all) eliminated for `solve`."""
        theta = np.asarray(theta, float)
        T, B, P = self.T, self.B, self.P
        grad_q, grad_theta = np.empty((T if gradient or (hessian and self.blocks) else 0, B)), np.empty(P)
        if hessian and self.blocks:
            blocks = (np.zeros((T, B, B)), np.zeros((max(T - 1, 0), B, B)), np.zeros((T, B, P)), np.zeros((P, P)))
            cost = self._kernel(q, v, theta, BLOCKS, grad_q, grad_theta, blocks=blocks)
            return CompiledLinearization(cost, grad_q, grad_theta, *blocks, point=(q, theta, v))
        if hessian and shift is not None:
            index = self._free_index(free)
            cost = self._eliminate(q, v, theta, float(shift), index, None, grad_q, grad_theta)
        else:
            cost = self._kernel(q, v, theta, GRADIENT, grad_q, grad_theta)
        lin = CompiledLinearization(cost, grad_q, grad_theta, *_NO_BLOCKS, point=(q, theta, v))
        if hessian and shift is not None:
            self._held = (lin, float(shift), index.tobytes())
        return lin

    def solve(self, lin: Linearization, shift: float, free=None, grad=None) -> tuple[np.ndarray, np.ndarray]:
        """x = -(H + shift diag(H))^-1 g with H at lin's point, for the free calibration
        variables (`free` (P,) bool, None: all; the others get no step) and g lin's gradient or
        `grad` = (grad_q (T, B), grad_theta (P,)): ((T, B), (P,))."""
        index = self._free_index(free)
        held = self._held
        if grad is not None or held is None or held[0] is not lin or held[1] != shift or held[2] != index.tobytes():
            q, theta, v = lin.point
            self._eliminate(q, v, theta, float(shift), index, grad, np.empty((0, self.B)), np.empty(self.P))
        self._held = None  # the step overwrites c
        schur, schur_rhs, quad = self._schur
        x_theta = np.linalg.solve(schur, schur_rhs) if len(index) else np.zeros(0)
        # g.x = -b^T H^-1 b (b = -g): the sum over the samples from the sweep, then the Schur complement's.
        self._slope = None if grad is not None else (lin, -(float(quad[0]) + float(schur_rhs @ x_theta)))
        M, c, N = self._storage
        back_substitute(M, c, N, x_theta)
        d_theta = np.zeros(self.P)
        d_theta[index] = x_theta
        return c[:, :self.B], d_theta

    def theta_std(self, q, theta, v, lin: Linearization | None = None) -> np.ndarray:
        """(P,) the calibration variables' posterior std at (q, theta, v): sqrt(diag((G - C^T
        A^-1 C)^-1)) (`theta_posterior_std`), from lin's elimination if it was made there with
        no shift and every variable free, else from one of its own."""
        if self.P == 0:
            return np.zeros(0)
        P = self.P
        held = self._held
        if lin is not None and held is not None and held[0] is lin and held[1] == 0.0 \
                and held[2] == self._free_index(None).tobytes():
            return np.sqrt(np.diag(np.linalg.inv(self._schur[0])))
        theta = np.asarray(theta, float)
        storage = np.empty((2, 5, 5)), np.empty((2, 5)), np.empty((2, 5, P))  # the running rows only
        schur = np.empty((P, P)), np.empty(P), np.empty(1)
        cost = self._kernel(q, v, theta, ELIMINATE, np.empty((0, self.B)), np.empty(P),
                            index=np.arange(P, dtype=np.int64), storage=storage, schur=schur)
        self._check(cost)
        return np.sqrt(np.diag(np.linalg.inv(schur[0])))

    # ---------------------------------------------------------------- internals
    def _free_index(self, free) -> np.ndarray:
        return np.arange(self.P, dtype=np.int64) if free is None else np.flatnonzero(free).astype(np.int64)

    def _kernel(self, q, v, theta, mode, grad_q, grad_theta, shift=0.0, index=None, rhs=None, blocks=None,
                storage=None, schur=None, kept=None, span=None, carry=None) -> float:
        return linearize_kernel(
            self.arrays, self.consts, q, v, theta, mode, shift, _NO_INDEX if index is None else index,
            *(_NO_RHS if rhs is None else rhs), grad_q, grad_theta, *(blocks or _NO_BLOCKS), *(storage or _NO_STORAGE),
            *(schur or _NO_SCHUR), self._kept_at(q, theta) if kept is None else kept, *(span or (0, self.T)),
            _NO_CARRY if carry is None else carry)

    def _kept_at(self, q, theta) -> np.ndarray:
        """M, if it holds the per-sample terms of a trial at exactly (q, theta) (`trial`), else no rows."""
        kept = self._kept
        if kept is not None and kept[0]() is q and np.array_equal(kept[1], theta):
            return self._storage[0]
        return _NO_STORAGE[0]

    def _eliminate(self, q, v, theta, shift, index, rhs, grad_q, grad_theta) -> float:
        F = len(index)
        if self._storage is None or self._storage[2].shape[2] != F:  # N has a column per free variable
            M, c = (np.empty((self.T, 5, 5)), np.empty((self.T, 5))) if self._storage is None else self._storage[:2]
            self._storage = None  # the old N goes before the new one comes
            self._storage = M, c, np.empty((self.T, 5, F))
        self._schur = np.empty((F, F)), np.empty(F), np.empty(1)
        if rhs is not None:
            rhs = np.ascontiguousarray(rhs[0], float), np.ascontiguousarray(rhs[1], float)
        if len(linearize_ranges(self.T)) > 2:
            cost = self._eliminate_in_ranges(q, v, theta, shift, index, rhs, grad_q, grad_theta)
        else:
            cost = self._kernel(q, v, theta, ELIMINATE, grad_q, grad_theta, shift=shift, index=index, rhs=rhs,
                                storage=self._storage, schur=self._schur)
        self._kept = None  # M now holds the elimination
        self._check(cost)
        return cost

    def _eliminate_in_ranges(self, q, v, theta, shift, index, rhs, grad_q, grad_theta) -> float:
        """`_eliminate` on two threads: the blocks of one range of samples (`linearize_ranges`) are
        computed (mode BLOCKS) while those of the range before are eliminated (FROM_BLOCKS), in two
        buffers taken in turn. The same numbers as one ELIMINATE pass, bit for bit."""
        P = self.P
        bounds = linearize_ranges(self.T)
        buffers = self._range_buffers(max(b - a for a, b in zip(bounds, bounds[1:])))
        kept = self._kept_at(q, theta)  # read by the BLOCKS ranges only, before FROM_BLOCKS writes the same rows
        theta_block, carries = np.empty((P, P)), (np.zeros(range_carry_size(P)), np.zeros(range_carry_size(P)))

        def blocks(k):  # mode BLOCKS over range k, into buffer k % 2
            return self._kernel(q, v, theta, BLOCKS, buffers[k % 2][3], grad_theta,
                                blocks=(*buffers[k % 2][:3], theta_block), kept=kept,
                                span=(bounds[k], bounds[k + 1]), carry=carries[0])

        cost = blocks(0)
        for k in range(len(bounds) - 1):
            following = run_beside(blocks, k + 1) if k + 2 < len(bounds) else None
            try:
                diag, off, cross, grad = buffers[k % 2]
                done = self._kernel(q, v, theta, FROM_BLOCKS, grad, grad_theta, shift=shift, index=index, rhs=rhs,
                                    blocks=(diag, off, cross, theta_block), storage=self._storage, schur=self._schur,
                                    kept=_NO_STORAGE[0], span=(bounds[k], bounds[k + 1]), carry=carries[1])
                if len(grad_q):
                    grad_q[bounds[k]:bounds[k + 1]] = grad[:bounds[k + 1] - bounds[k]]
            finally:
                if following is not None:
                    cost = following()
            if math.isnan(done):
                return done
        return cost

    def _range_buffers(self, R: int) -> tuple:
        """Two sets of the blocks (diag, off, cross, grad) of a range of R samples, for
        `_eliminate_in_ranges`, every entry it reads written before. Allocated for each elimination
        and dropped after it, so that they never add to the trial's trajectories (the peak)."""
        B, P = self.B, self.P
        return tuple((np.empty((R, B, B)), np.empty((R, B, B)), np.empty((R, B, P)), np.empty((R, B))) for _ in range(2))

    def _check(self, cost: float) -> None:
        if math.isnan(cost):
            raise np.linalg.LinAlgError("smoother: the Gauss-Newton matrix is not positive definite")


_NO_INDEX = np.zeros(0, np.int64)
_NO_CARRY = np.zeros(0)
_NO_RHS = (np.zeros((0, 5)), np.zeros(0))
_NO_BLOCKS = (np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0)))
_NO_STORAGE = (np.zeros((0, 5, 5)), np.zeros((0, 5)), np.zeros((0, 5, 0)))
_NO_SCHUR = (np.zeros((0, 0)), np.zeros(0), np.zeros(1))
