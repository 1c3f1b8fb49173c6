"""The arrays and codes the smoothers' kernels take and hand each other, named once.

The kernels of `gn` and `gd` (`fusion.estimators._compiled_smoother` and the modules it names)
take a `SmootherProblem` as one namedtuple of arrays (`SmootherArrays`, built by `problem_arrays`)
and the constants of the maths as another (`SmootherConstants`): one compiled signature serves
every problem, and nothing that decides the result is frozen into a cached kernel. The kernels
and the Python that calls them import what is defined here; nothing here imports numba.

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

from .smoother_cost import LOSSES, SmootherProblem

# Modes of `linearize`.
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

