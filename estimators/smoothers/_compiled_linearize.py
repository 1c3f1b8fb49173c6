"""The linearisation of the smoothers' cost and the elimination of its normal equations, compiled.

What is compiled and why. A smoother iteration evaluates the cost of `smoothers.cost` over the
whole recording, linearises it and solves the block-tridiagonal normal equations with their
calibration border. The numpy reference (`SmootherProblem.linearize`, `smoothers.solve`,
`gd.Preconditioner`) does this in whole-array operations, each of which builds (T, 3, 3) or
(T, 5, 5) temporaries, writes the matrix to LAPACK's band storage and solves it there, with
the border as P extra right-hand sides. Here one pass over the samples (`linearize`)
computes the cost, the gradient and the Gauss-Newton blocks of each sample from a few registers'
worth of local data and eliminates them at once, so nothing per sample is kept but what the
back-substitution (`back_substitute`) needs.

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
Golub & Van Loan 2013, sec. 4.1.2; `ldl5`) and never stored; a sample keeps M_t, c_t and N_t:
5 (5 + 1 + F) numbers for F free calibration variables. The blocks are those of the reference
(`SmootherProblem.linearize`, whose comments cite the Jacobians: Sola et al. 2018, "A micro Lie
theory", eqs. 143-146; the robust term's Gauss-Newton weight: Triggs et al. 2000, sec. 3.3);
without the velocity model the per-sample system is padded from 3 to 5 variables with an
identity block, which gives the two padding variables an exact zero step and the others the same
arithmetic as a 3 x 3 system. Within the sweep, the blocks live in a few small arrays that are
filled in place, never reassigned (numba counts references on every assignment of an array
variable, which costs more than the arithmetic here).

Three kernels, one per use: `linearize` (cost, gradient and, if asked, the blocks as the
reference lays them out), `linearize_eliminate` (the same with the elimination in the pass) and
`eliminate_blocks` (the elimination from the blocks a `linearize` range left), each one call of
the one loop over the samples (`_pass`), whose per-sample arithmetic the three share. Their inputs travel as small records (`SmootherPoint`, `SmootherGradient`,
`SmootherBlocks`, `SmootherSystem`, `SmootherElimination`, `SmootherSpan`). On a long recording
the pass runs in ranges of samples on two threads (`linearize` over one range while
`eliminate_blocks` eliminates the range before, `smoothers._compiled_ranges`): a range's state is
handed to the next in its carry (`carry_state`).

numba keys a cached kernel on its own file only: `_kernel_cache.forget_stale_kernels` drops this
module's cache when a file whose kernels it compiles changes.
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from fusion import quaternion as quat

from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _jit, compiled, mirrors
from . import _compiled_layout as layout
from . import _compiled_terms as terms
from ._compiled_layout import (CARRY_OFF_BLOCK, N_SUMS, SUM_ACC, SUM_MAG, SUM_MOTION, SUM_PRIOR, SUM_REST, SUM_VEL,
                               SUM_VZERO)
from ._compiled_terms import (exp_floats, fill3, kept_acc, kept_mag, kept_step, load_quat, log_floats, mag_residual,
                                       motion_residual, multiply_floats, rest_residual, right_jacobian, right_jacobian_inv,
                                       robust_terms, rotation_floats, split_theta, step_rotvec, total_cost)

forget_stale_kernels(__file__, [quat.__file__, layout.__file__, terms.__file__])

# Kernels without a numpy reference of their own (`kernels._numba.mirrors`), and why:
#   ldl5, ldl_solve5: the elimination's pivot block; the reference solves with LAPACK's banded Cholesky
#   _pass: the one loop behind linearize, linearize_eliminate and eliminate_blocks
#   _no_system, _no_elimination: the empty records of a pass that eliminates nothing
#   linearize_eliminate: `SmootherProblem.linearize` and the reference's banded solve, fused in one pass
#   eliminate_blocks: the elimination of `linearize_eliminate`, from stored blocks
#   carry_block, carry_state: the hand-over between ranges
#   back_substitute: the back-substitution of the elimination; the reference solves with LAPACK
HELPERS = ("ldl5", "ldl_solve5", "_pass", "_no_system", "_no_elimination", "linearize_eliminate", "eliminate_blocks",
           "carry_block", "carry_state", "back_substitute")

# `smoothers._compiled_layout.carry_offsets`, compiled under its name: one definition for the kernels and Python.
carry_offsets = compiled(layout.carry_offsets, __name__)


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


# The records the three kernels take (namedtuples of names found nowhere else, bound to their own
# names: `smoothers._compiled_layout`'s docstring says why).
SmootherPoint = namedtuple("SmootherPoint", ["q", "v", "theta"])  # (T, 4), (T, V) m/s, (P,)
SmootherGradient = namedtuple("SmootherGradient", ["q", "theta"])  # (T or R rows or none, B), (P,)
SmootherBlocks = namedtuple("SmootherBlocks", ["diag", "off", "cross", "theta"])  # as `Linearization`'s (theta: theta_block)
SmootherSystem = namedtuple("SmootherSystem", ["shift", "free", "rhs_q", "rhs_theta"])  # (H + shift diag(H)) x = b
SmootherElimination = namedtuple("SmootherElimination", ["M", "c", "N", "schur", "schur_rhs", "quad"])
SmootherSpan = namedtuple("SmootherSpan", ["t0", "t1", "carry"])  # samples t0 <= t < t1, and the hand-over
# The modes of `_pass`.
_GRADIENT, _BLOCKS, _ELIMINATE, _FROM_BLOCKS = 0, 1, 2, 3


@_jit
def _pass(p, o, point, mode, grad, blocks, system, elim, kept, span):
    """The one pass over the samples behind `linearize`, `linearize_eliminate` and
    `eliminate_blocks` (their docstrings): each sample's cost terms, gradient and Gauss-Newton
    blocks, then, by `mode`, the gradient alone (`_GRADIENT`), the blocks as the reference lays
    them out (`_BLOCKS`), their elimination in the same pass (`_ELIMINATE`), or the elimination
    of the blocks a `linearize` range left (`_FROM_BLOCKS`). One loop: the per-sample arithmetic is
    the same for the three uses, and a loop per use would repeat it; the records are unpacked once
    per pass (split into parts called per sample, the loop ran at half the speed: numba counts the
    references of every array a part binds anew)."""
    q, v, theta = point
    grad_q, grad_theta = grad
    diag, off, cross, theta_block = blocks
    shift, free, rhs_q, rhs_theta = system
    M, c, N, schur, schur_rhs, quad = elim
    t0, t1, carry = span
    T = q.shape[0]
    V = v.shape[1]
    B = 3 + V
    P = len(theta)
    F = len(free)
    b, k = split_theta(p, theta)
    rows = M.shape[0]
    external = rhs_q.shape[0] > 0
    ranged = carry.shape[0] > 0
    cost_acc = cost_motion = cost_vel = cost_vzero = cost_rest = cost_prior = cost_mag = 0.0  # the sums of the terms
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
    elif mode == _FROM_BLOCKS:
        carry_block(carry, CARRY_OFF_BLOCK, Op, False)
    else:  # BLOCKS, continued from the range before
        sums = np.empty(N_SUMS)
        carry_state(carry, False, Dn, gn, Cn, sums, gth, G)
        cost_acc, cost_motion, cost_vel, cost_vzero = sums[SUM_ACC], sums[SUM_MOTION], sums[SUM_VEL], sums[SUM_VZERO]
        cost_rest, cost_prior, cost_mag = sums[SUM_REST], sums[SUM_PRIOR], sums[SUM_MAG]
    qn = load_quat(q, t0)
    rn = rotation_floats(qn)
    for t in range(t0, t1):
        if mode == _FROM_BLOCKS:  # the blocks a BLOCKS pass over this range wrote (row t - t0)
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
                ca, wa = kept_acc(kept, t)
            else:
                ca, wa = robust_terms(p.loss, p.loss_c, p.w_acc[t], r0 * r0 + r1 * r1 + r2 * r2)
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
                    cm, wh = robust_terms(p.mag_loss, p.mag_c, p.w_mag[t], rh * rh)
                cost_mag += cm
                jh = (R[0, 0] * k0 + R[1, 0] * k1 + R[2, 0] * k2, R[0, 1] * k0 + R[1, 1] * k1 + R[2, 1] * k2,
                      R[0, 2] * k0 + R[1, 2] * k1 + R[2, 2] * k2)
                for i in range(3):
                    g[i] += wh * rh * jh[i]
                    for j in range(i + 1):
                        D[i, j] += wh * jh[i] * jh[j]
            if t == 0:  # the anchor: d r_0 / d delta_0 = J_r^-1(r_0)
                r = log_floats(multiply_floats((p.init_quat[0], -p.init_quat[1], -p.init_quat[2], -p.init_quat[3]), qt))
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
                rn = rotation_floats(qn)
                fill3(Rn, rn)
                # Motion: r_m = 2 log(q_{t+1}^-1 q_t u_t); d r / d delta_t = A R(u)^T, d r / d delta_{t+1} = -A^T.
                phi = step_rotvec(p, b, k, t)
                if kept.shape[0]:  # computed by the trial that reached this point
                    u, r = kept_step(kept, t)
                else:
                    u = exp_floats(phi[0], phi[1], phi[2], o.small_angle)
                    r = motion_residual(qt, qn, u)
                wm = p.w_motion[t]
                cost_motion += wm * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
                fill3(A, right_jacobian_inv(r[0], r[1], r[2], o))
                fill3(Ru, rotation_floats(u))
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
        if grad_q.shape[0] and mode != _FROM_BLOCKS:
            for i in range(B):
                grad_q[t - t0, i] = g[i]
        if mode == _BLOCKS:
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
        elif mode == _ELIMINATE or mode == _FROM_BLOCKS:
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
    sums = np.empty(N_SUMS)
    sums[SUM_ACC], sums[SUM_MOTION], sums[SUM_VEL], sums[SUM_VZERO] = cost_acc, cost_motion, cost_vel, cost_vzero
    sums[SUM_REST], sums[SUM_PRIOR], sums[SUM_MAG] = cost_rest, cost_prior, cost_mag
    if mode == _FROM_BLOCKS:
        carry_block(carry, CARRY_OFF_BLOCK, Op, True)
        if t1 < T:
            return 0.0
        for m in range(P):  # the calibration block and gradient of the BLOCKS pass, prior included
            gth[m] = grad_theta[m]
            for n in range(P):
                G[m, n] = theta_block[m, n]
    elif t1 < T:  # BLOCKS: what the next range continues from
        carry_state(carry, True, Dn, gn, Cn, sums, gth, G)
        return 0.0
    else:
        for m in range(P):
            gth[m] += p.w_theta[m] * theta[m]
            G[m, m] += p.w_theta[m]
            grad_theta[m] = gth[m]
            if mode == _BLOCKS:
                for n in range(P):
                    theta_block[m, n] = G[m, n]
    if mode == _ELIMINATE or mode == _FROM_BLOCKS:
        for n in range(F):
            for m in range(n):
                schur[n, m] = schur[m, n] = G[free[m], free[n]] - schur[m, n]
            schur[n, n] = G[free[n], free[n]] * (1.0 + shift) - schur[n, n]
            schur_rhs[n] = -(rhs_theta[free[n]] if external else gth[free[n]]) - schur_rhs[n]
    if mode == _FROM_BLOCKS:
        return 0.0
    return total_cost(p, theta, V, sums)


@_jit
def _no_system(B):
    """The `SmootherSystem` of a pass that eliminates nothing."""
    return SmootherSystem(0.0, np.zeros(0, np.int64), np.zeros((0, B)), np.zeros(0))


@_jit
def _no_elimination():
    """The `SmootherElimination` of a pass that eliminates nothing."""
    return SmootherElimination(np.zeros((0, 5, 5)), np.zeros((0, 5)), np.zeros((0, 5, 0)), np.zeros((0, 0)),
                               np.zeros(0), np.zeros(1))


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.linearize")
def linearize(p, o, point, grad, blocks, kept, span):
    """Cost, gradient and Gauss-Newton blocks at the point (q (T, 4), v (T, V), theta (P,))
    (`SmootherProblem.linearize`): the use that keeps the blocks (the others: `linearize_eliminate`,
    `eliminate_blocks`). Returns the cost.

    Always grad.theta (P,), and grad.q (T, B) unless it has no rows; if blocks.diag has rows, the
    blocks diag (T, B, B), off (T-1, B, B), cross (T, B, P), theta (P, P) as the reference lays them
    out. kept (T, 5, 5), if it has rows: each step's u_t and motion residual r_m,t, each sample's
    accelerometer term and magnetometer residual at this very point, as `cost` computed them for a
    trial step here (`keep_floats`, the layout's KEEP_*): read, not computed again (the same numbers).

    Ranges (`CompiledOps._eliminate_in_ranges`): the samples span.t0 <= t < span.t1 only, their
    blocks and gradient at rows t - t0 (`smoothers._compiled_layout.range_blocks`, the diagonal
    blocks' lower triangles); before T, returns 0 and leaves in span.carry (`carry_state`) what the
    next range continues from (what the last step adds to its next sample, the cost's sums, the
    calibration block and gradient); the range that ends at T returns the cost, blocks.theta and
    grad.theta. A whole pass is t0 = 0, t1 = T, carry without rows."""
    mode = _BLOCKS if blocks.diag.shape[0] > 0 else _GRADIENT
    return _pass(p, o, point, mode, grad, blocks, _no_system(grad.q.shape[1]), _no_elimination(), kept, span)


@_jit
def linearize_eliminate(p, o, point, grad, system, elim, kept):
    """`linearize` with the system (H + shift diag(H)) x = b eliminated in the same pass (module
    docstring): for the calibration variables system.free (F,) (their indices; the others are
    held), with b = -grad or, if system.rhs_q has rows, b = -[rhs_q; rhs_theta]. Writes elim's M
    (R, 5, 5), c (R, 5), N (R, 5, F) (R = T rows, or 2 to keep only the running ones), the Schur
    complement schur (F, F) with its right-hand side schur_rhs (F,), and quad[0] = sum_t b'_t^T
    S_t^-1 b'_t (with the Schur complement's part, b^T (H + shift diag(H))^-1 b:
    `CompiledOps.slope`); grad and kept as in `linearize` (kept may be M itself: row t is read
    before M's row t is written). Returns the cost, or nan if the matrix is not positive definite."""
    blocks = SmootherBlocks(np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0)))
    return _pass(p, o, point, _ELIMINATE, grad, blocks, system, elim, kept,
                 SmootherSpan(0, point.q.shape[0], np.zeros(0)))


@_jit
def eliminate_blocks(p, o, point, grad, blocks, system, elim, span):
    """The elimination of `linearize_eliminate` from the blocks a `linearize` range left (grad.q,
    blocks.diag, off, cross: that range's rows; blocks.theta, grad.theta: the last range's), the same
    arithmetic in the same order, over the samples span.t0 <= t < span.t1, with H[t-1, t] in
    span.carry (at CARRY_OFF_BLOCK) between ranges. Returns 0 (nan: not positive definite)."""
    return _pass(p, o, point, _FROM_BLOCKS, grad, blocks, system, elim, np.zeros((0, 5, 5)), span)


@_jit
def carry_block(carry, at, block, store):
    """Copy the C-contiguous array `block` to carry[at:] (store) or from there."""
    flat = block.reshape(-1)
    for i in range(flat.size):
        if store:
            carry[at + i] = flat[i]
        else:
            flat[i] = carry[at + i]


@_jit
def carry_state(carry, store, Dn, gn, Cn, sums, gth, G):
    """A `linearize` range's state to its carry (store) or from it, at `carry_offsets`: what the last
    step adds to the next sample (Dn 5 x 5, gn 5, Cn 5 x P), the cost's sums (N_SUMS), the
    calibration gradient gth (P) and block G (P x P)."""
    next_diag, next_grad, next_cross, at_sums, grad_theta, theta_block, _ = carry_offsets(len(gth))
    carry_block(carry, next_diag, Dn, store)
    carry_block(carry, next_grad, gn, store)
    carry_block(carry, next_cross, Cn, store)
    carry_block(carry, at_sums, sums, store)
    carry_block(carry, grad_theta, gth, store)
    carry_block(carry, theta_block, G, store)


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

