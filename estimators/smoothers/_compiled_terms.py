"""The terms of the smoothers' cost, one sample at a time, compiled (numba).

Each kernel here is a line or two of `fusion.estimators.smoothers.cost` for one sample or one step,
as scalars: the motion, accelerometer, magnetometer and rest residuals, the robust loss, the
calibrated step rotation, the calibration variables, the SO(3) Jacobians and the cost from its
terms' sums. The quaternion helpers are `fusion.quaternion`'s scalar path, compiled (one
definition for numpy, Python and the kernels).

The Jacobians are those of `fusion.quaternion` (Sola et al. 2018, "A micro Lie theory for state
estimation in robotics", arXiv:1812.01537: J_r eq. 143, J_r^-1 eq. 144, their coefficients'
series); the robust losses are Zhang 1997's M-estimators ("Parameter estimation techniques: a
tutorial with application to conic fitting", Image and Vision Computing 15), as
`smoothers.cost.robust_loss` says. The cost kernels (`smoothers._compiled_cost`) and the
linearisation (`smoothers._compiled_linearize`) are built from these.

numba keys a cached kernel on its own file only: `_kernel_cache.forget_stale_kernels` drops this
module's cache when `fusion.quaternion` or `smoothers._compiled_layout` changes.
"""
from __future__ import annotations

import math

import numpy as np

from fusion import quaternion as quat

from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _jit, compiled, mirrors
from . import _compiled_layout as layout
from ._compiled_layout import (B_MAX, KEEP_ACC, KEEP_MAG, KEEP_MOTION, KEEP_STEP, LOSS_CAUCHY, LOSS_HUBER,
                                        LOSS_NONE, SUM_ACC, SUM_MAG, SUM_MOTION, SUM_PRIOR, SUM_REST, SUM_VEL, SUM_VZERO)

# the kernels compile fusion.quaternion's scalar path and the layout's constants
forget_stale_kernels(__file__, [quat.__file__, layout.__file__])

# Kernels without a numpy reference of their own (`kernels._numba.mirrors`), and why:
#   load_quat: how the kernels read a row
#   fill3: how the kernels keep a 3 x 3 matrix
#   total_cost: the last lines of `SmootherProblem.cost`, which sums whole arrays
#   keep_floats: what a trial keeps for the linearisation at its point
#   kept_float: what a trial keeps for the linearisation at its point
#   kept_step: what a trial keeps for the linearisation at its point
#   kept_acc: what a trial keeps for the linearisation at its point
#   kept_mag: what a trial keeps for the linearisation at its point
HELPERS = ("load_quat", "fill3", "total_cost", "keep_floats", "kept_float", "kept_step", "kept_acc", "kept_mag")


# `fusion.quaternion`'s scalar path, compiled under its own names: one definition for numpy, Python
# and the kernels.
multiply_floats = compiled(quat.multiply_floats, __name__)
exp_floats = compiled(quat.exp_floats, __name__)
log_floats = compiled(quat.log_floats, __name__)
normalize_floats = compiled(quat.normalize_floats, __name__)
rotation_floats = compiled(quat.rotation_floats, __name__)  # R(q) as 9 scalars, row by row


@_jit
def load_quat(q, t):
    """q[t] (q (T, 4)) as 4 scalars."""
    return (q[t, 0], q[t, 1], q[t, 2], q[t, 3])


@_jit
def fill3(M, v):
    """M (3, 3) = the 9 scalars v, row by row."""
    for i in range(3):
        for j in range(3):
            M[i, j] = v[3 * i + j]


@mirrors("fusion.quaternion._series_float")
def _series_float(t, kind, o):
    """The coefficient `kind` (0: A, 1: B, 2: C of `quaternion._A/_B/_C`; Sola et al. 2018, eqs.
    143-146) at angle t: the closed form above `JACOBIAN_SERIES_RAD`, the Taylor series below."""
    if t > o.series_rad:
        if kind == 0:
            return (1.0 - math.cos(t)) / t**2
        if kind == 1:
            return (t - math.sin(t)) / t**3
        return 1.0 / t**2 - (1.0 + math.cos(t)) / (2.0 * t * math.sin(t))
    c = o.jac_a if kind == 0 else (o.jac_b if kind == 1 else o.jac_c)
    t2 = t * t
    return ((0.0 * t2 + c[2]) * t2 + c[1]) * t2 + c[0]


@mirrors("fusion.quaternion.right_jacobian_inv")
def right_jacobian_inv(x, y, z, o):
    """J_r^-1(v) = I + [v]x / 2 + C [v]x^2 (Sola et al. 2018, eq. 144) as 9 scalars, row by row."""
    c = _series_float(math.sqrt(x * x + y * y + z * z), 2, o)
    return (1.0 + c * (-z * z - y * y), -0.5 * z + c * (x * y), 0.5 * y + c * (x * z),
            0.5 * z + c * (x * y), 1.0 + c * (-z * z - x * x), -0.5 * x + c * (y * z),
            -0.5 * y + c * (x * z), 0.5 * x + c * (y * z), 1.0 + c * (-y * y - x * x))


@mirrors("fusion.quaternion.right_jacobian")
def right_jacobian(x, y, z, o):
    """J_r(v) = I - A [v]x + B [v]x^2 (Sola et al. 2018, eq. 143) as 9 scalars, row by row."""
    t = math.sqrt(x * x + y * y + z * z)
    a = _series_float(t, 0, o)
    b = _series_float(t, 1, o)
    return (1.0 + b * (-z * z - y * y), a * z + b * (x * y), -a * y + b * (x * z),
            -a * z + b * (x * y), 1.0 + b * (-z * z - x * x), a * x + b * (y * z),
            a * y + b * (x * z), -a * x + b * (y * z), 1.0 + b * (-y * y - x * x))


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.split_theta")
def split_theta(p, theta):
    """theta -> (bias (3,) rad/s, scale error (3,))."""
    b = np.zeros(3)
    k = np.zeros(3)
    for i in range(len(theta)):
        if i < p.n_bias:
            b[p.theta_axis[i]] = theta[i]
        else:
            k[p.theta_axis[i]] = theta[i]
    return b, k


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.step_rotvec")
def step_rotvec(p, b, k, t):
    """phi_t = ((1 + k) g_t - b) dt_t, zero on an invalid step."""
    if not p.valid[t]:
        return (0.0, 0.0, 0.0)
    dt = p.dt[t]
    return (((1.0 + k[0]) * p.gyr[t, 0] - b[0]) * dt, ((1.0 + k[1]) * p.gyr[t, 1] - b[1]) * dt,
            ((1.0 + k[2]) * p.gyr[t, 2] - b[2]) * dt)


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.motion_residual")
def motion_residual(qa, qb, u):
    """r_m = 2 log(q_b^-1 q_a u), rad."""
    return log_floats(multiply_floats(multiply_floats((qb[0], -qb[1], -qb[2], -qb[3]), qa), u))


@mirrors("fusion.estimators.smoothers.cost.robust_loss")
def robust_loss(kind, s):
    """(rho(s), rho'(s)) of the robust loss `kind` (its index in `smoothers.cost.LOSSES`) at the
    normalised squared residual s = |r|^2 / c^2."""
    if kind == LOSS_NONE:
        return s, 1.0
    if kind == LOSS_HUBER:
        root = math.sqrt(s)
        if root <= 1.0:
            return s, 1.0
        return 2.0 * root - 1.0, 1.0 / max(root, 1e-300)
    if kind == LOSS_CAUCHY:
        return math.log1p(s), 1.0 / (1.0 + s)
    return s / (1.0 + s), 1.0 / (1.0 + s) ** 2  # LOSS_GEMAN_MCCLURE


@mirrors("fusion.estimators.smoothers.cost.robust_terms")
def robust_terms(kind, c, w, sq):
    """(cost term 1/2 w c^2 rho(sq / c^2), IRLS weight w rho') of one residual of squared norm sq,
    information w and loss `kind` (index in `smoothers.cost.LOSSES`) of scale c: the accelerometer's
    (`SmootherProblem.acc_terms`) and the magnetometer's (`mag_terms`) term of one sample."""
    if kind == LOSS_NONE:
        return 0.5 * w * sq, w
    c2 = c * c
    rho, drho = robust_loss(kind, sq / c2)
    return 0.5 * w * c2 * rho, w * drho


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.mag_residual")
def mag_residual(p, t, qt):
    """The magnetometer's heading residual at sample t, q_t = qt: (r_h rad, k0, k1, k2)
    (`smoothers.cost`'s module docstring)."""
    d = multiply_floats(qt, (p.mag_ref[t, 0], -p.mag_ref[t, 1], -p.mag_ref[t, 2], -p.mag_ref[t, 3]))
    dw, dx, dy, dz = d
    n2 = dw * dw + dz * dz
    x = p.mag_psi[t] + 2.0 * math.atan2(dz, dw)
    r = x - 2.0 * math.pi * math.floor((x + math.pi) / (2.0 * math.pi))
    safe = n2 if n2 > 0.0 else 1.0
    return r, (dw * dy + dz * dx) / safe, (dz * dy - dw * dx) / safe, 1.0


@mirrors("fusion.estimators.smoothers.cost.SmootherProblem.rest_residual")
def rest_residual(p, b, k, t, i):
    """The rest residual of step t on the i-th bias variable's axis, rad/s, and that axis."""
    ax = p.theta_axis[i]
    return (1.0 + k[ax]) * p.gyr[t, ax] - b[ax], ax


@_jit
def total_cost(p, theta, V, sums):
    """The cost from its terms' sums (N_SUMS,) (`smoothers._compiled_layout`'s SUM_*: the
    accelerometer's and magnetometer's terms with their 1/2, the weighted squared residuals of
    motion, velocity, zero velocity and rest, the anchor's |r_0|^2); the calibration prior from theta."""
    prior = 0.0
    for i in range(len(theta)):
        prior += p.w_theta[i] * theta[i] ** 2
    total = sums[SUM_ACC] + 0.5 * (sums[SUM_MOTION] + p.w_prior * sums[SUM_PRIOR] + prior)
    if V:
        total += 0.5 * (sums[SUM_VEL] + sums[SUM_VZERO])
    return total + 0.5 * sums[SUM_REST] + sums[SUM_MAG]


# ============================================================================ what a trial keeps
@_jit
def keep_floats(keep, t, at, values):
    """Store the scalars `values` in keep[t] (B_MAX x B_MAX, read as one row of numbers) from number
    `at` on (`smoothers._compiled_layout`'s KEEP_* offsets)."""
    for i in range(len(values)):
        keep[t, (at + i) // B_MAX, (at + i) % B_MAX] = values[i]


@_jit
def kept_float(kept, t, at):
    """Number `at` of kept[t], as `keep_floats` stored it."""
    return kept[t, at // B_MAX, at % B_MAX]


@_jit
def kept_step(kept, t):
    """(u_t, r_m,t) as `keep_floats` stored them."""
    return ((kept_float(kept, t, KEEP_STEP), kept_float(kept, t, KEEP_STEP + 1), kept_float(kept, t, KEEP_STEP + 2),
             kept_float(kept, t, KEEP_STEP + 3)),
            (kept_float(kept, t, KEEP_MOTION), kept_float(kept, t, KEEP_MOTION + 1), kept_float(kept, t, KEEP_MOTION + 2)))


@_jit
def kept_acc(kept, t):
    """The accelerometer's (cost term, IRLS weight) as `keep_floats` stored them."""
    return kept_float(kept, t, KEEP_ACC), kept_float(kept, t, KEEP_ACC + 1)


@_jit
def kept_mag(kept, t):
    """The magnetometer's (r_h, k0, k1, k2, cost term, IRLS weight) as `keep_floats` stored them."""
    return (kept_float(kept, t, KEEP_MAG), kept_float(kept, t, KEEP_MAG + 1), kept_float(kept, t, KEEP_MAG + 2),
            kept_float(kept, t, KEEP_MAG + 3), kept_float(kept, t, KEEP_MAG + 4), kept_float(kept, t, KEEP_MAG + 5))
