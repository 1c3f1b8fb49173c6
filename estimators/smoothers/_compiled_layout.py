"""The arrays and codes the smoothers' kernels take and hand each other, each layout named once.

The kernels of `gn` and `gd` (`fusion.estimators.smoothers._compiled` and the modules it names)
pass what one kernel leaves for another, and what Python allocates for them, as flat float64
arrays and small integer codes rather than objects (numba compiles a kernel once per combination
of argument types). Every such layout is defined here and nowhere else; the kernels and the
Python that allocates and reads the arrays (`CompiledOps`) import these names. Nothing here
imports numba: numba freezes a module's constants into a kernel that reads them, and every kernel
module lists this file among those whose change drops its disk cache (`_kernel_cache`).

- the problem: `SmootherArrays` (built by `problem_arrays` from a `SmootherProblem`), the constants
  of the maths `SmootherConstants` (`constants`), the loss codes (`LOSS_*`: an index in
  `smoothers.cost.LOSSES`);
- the per-sample variables: x_t = [delta_t (3), v_t (V)] as in `smoothers.cost.Linearization`,
  padded to `B_MAX` = 5 in the elimination's storage (M (T, 5, 5), c (T, 5), N (T, 5, F));
- the retractions of `smoothers._compiled_cost.cost` (`POINT`, or the `RETRACTIONS` of
  `smoother.retract`);
- the cost's partial sums (`SUM_*`, `N_SUMS`), from a range of samples to `total_cost`;
- what a trial keeps of each sample for the linearisation at its point (`KEEP_*`, in M's rows);
- what a range of `linearize` hands the next one (`carry_offsets`, `carry_size`), and the blocks
  it leaves for `eliminate_blocks` (`range_blocks`).

The namedtuples have names found nowhere else (with a namedtuple of the same name in another
compiled module, the kernels of whichever module was loaded second ran markedly slower), and each
is bound to its own name in this module: numba's cache finds a kernel's signature again only if
its types can be looked up by name.
"""
from __future__ import annotations

from collections import namedtuple

import numpy as np

from fusion import quaternion as quat
from fusion.types import STANDARD_GRAVITY_M_S2

from .cost import LOSSES, SmootherProblem

# The per-sample variables in the elimination's storage: [delta_t (3), v_t (2)], padded to 5 without
# the velocity model (an identity block: the padding variables get an exact zero step).
B_MAX = 5


# The retraction of `smoothers._compiled_cost.cost`'s trial point: none (the cost at q), or one of
# `smoother.retract`'s, by its `update` name.
POINT, GEODESIC, NORMALISE = 0, 1, 2
RETRACTIONS = {"geodesic": GEODESIC, "normalise": NORMALISE}

# The robust losses of `smoothers.cost.robust_loss`, by their index in LOSSES.
LOSS_NONE, LOSS_HUBER, LOSS_CAUCHY, LOSS_GEMAN_MCCLURE = (LOSSES.index(name) for name in
                                                          ("none", "huber", "cauchy", "geman-mcclure"))

# The cost's partial sums over a range of samples (`cost`'s `sums`, `linearize`'s carry), weighted
# and added by `total_cost`: the accelerometer's and the magnetometer's terms with their 1/2, the
# motion, velocity, zero-velocity and rest terms' weighted squares, the anchor's |r_0|^2.
SUM_ACC, SUM_MOTION, SUM_VEL, SUM_VZERO, SUM_REST, SUM_MAG, SUM_PRIOR = range(7)
N_SUMS = 7

# What a trial keeps of each sample at its point (`cost`'s keep) for `linearize` there (its kept):
# in keep[t], M's row t (B_MAX x B_MAX), read as B_MAX^2 numbers row by row, from these offsets:
KEEP_STEP = 0  # u_t = exp(phi_t / 2), 4 numbers
KEEP_MOTION = 5  # the motion residual r_m,t, 3
KEEP_ACC = 8  # the accelerometer's (cost term, IRLS weight), 2
KEEP_MAG = 10  # the magnetometer's (r_h, k0, k1, k2, cost term, IRLS weight), 6: 16 numbers in all


# `eliminate_blocks` hands the next range H[t1 - 1, t1] (B_MAX x B_MAX) in a carry of its own, from here.
CARRY_OFF_BLOCK = 0


def carry_offsets(P):
    """Where each part of a `linearize` range's carry starts, for P calibration variables: what its last
    step adds to the next sample's diagonal block (B_MAX x B_MAX), gradient (B_MAX) and cross block
    (B_MAX x P), the cost's sums (N_SUMS), the calibration gradient (P) and block (P x P), and the
    end (at least CARRY_OFF_BLOCK + B_MAX * B_MAX: a carry serves `eliminate_blocks` too)."""
    next_diag = 0
    next_grad = next_diag + B_MAX * B_MAX
    next_cross = next_grad + B_MAX
    sums = next_cross + B_MAX * P
    grad_theta = sums + N_SUMS
    theta_block = grad_theta + P
    return next_diag, next_grad, next_cross, sums, grad_theta, theta_block, theta_block + P * P


def carry_size(P: int) -> int:
    """The length of a carry (`carry_offsets`) with P calibration variables."""
    return carry_offsets(P)[-1]


def range_blocks(R: int, B: int, P: int) -> tuple:
    """The blocks a `linearize` range of at most R samples leaves for `eliminate_blocks`, row t - t0 for sample
    t, with B variables per sample and P calibration variables: diag (R, B, B) (its lower triangle),
    off (R, B, B), cross (R, B, P), grad_q (R, B); every entry `eliminate_blocks` reads is written first."""
    return np.empty((R, B, B)), np.empty((R, B, B)), np.empty((R, B, P)), np.empty((R, B))

# The problem as the kernels read it (`problem_arrays`), and the constants of the maths.
SmootherArrays = namedtuple("SmootherArrays", [
    "dt", "gyr", "valid", "acc",  # (T-1,), (T-1, 3), (T-1,) bool, (T, 3)
    "w_motion", "w_acc", "w_vel", "w_vzero", "w_rest",  # weights; w_vel, w_vzero, w_rest may be empty
    "init_quat", "w_prior",  # the anchor
    "w_theta", "theta_axis", "n_bias",  # calibration: prior weights, the gyro axis of each, how many are biases
    "loss", "loss_c",  # robust loss (index in LOSSES) and its scale, g
    "w_mag", "mag_ref", "mag_psi", "mag_loss", "mag_c",  # magnetometer heading term (w_mag empty: none)
])

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

