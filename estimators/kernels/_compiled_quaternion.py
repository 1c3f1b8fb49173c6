"""`fusion.quaternion`'s scalar path, compiled for the kernels: one definition for numpy, Python
and the kernels.

The functions of `fusion.quaternion` that the kernels call are that module's own Python
functions compiled here, under their own names; `rotate_floats` is written out on
`rotation_floats` (the same products). `right_jacobian_dt` is the SO(3) right Jacobian times dt,
as `EKF.step` uses it. The small-angle constants that decide the series are passed in at run time
(`QuatSettings`), not frozen into the cached machine code.
"""
from __future__ import annotations

import math
from typing import NamedTuple

from fusion import quaternion as quat

from ._numba import _jit, _jit_leaf, compiled, forget_stale, mirrors

forget_stale(__file__)

# No numpy reference of their own: the right Jacobian times dt (`EKF.step` multiplies
# `quaternion.right_jacobian_floats` by dt).
HELPERS = ("right_jacobian_dt",)


class QuatSettings(NamedTuple):
    """`fusion.quaternion`'s small-angle rules, read at run time."""

    small_angle: float  # `quaternion.SMALL_ANGLE`: below it exp and log use their series
    series_rad: float  # `quaternion.JACOBIAN_SERIES_RAD`: below it the right Jacobian's series
    jac_a: tuple  # the series' coefficients (`quaternion._A[1]`, `_B[1]`), 3 floats each
    jac_b: tuple


def quat_settings() -> QuatSettings:
    return QuatSettings(small_angle=float(quat.SMALL_ANGLE), series_rad=float(quat.JACOBIAN_SERIES_RAD),
                        jac_a=tuple(float(c) for c in quat._A[1]), jac_b=tuple(float(c) for c in quat._B[1]))


multiply_floats = compiled(quat.multiply_floats, __name__)
exp_floats = compiled(quat.exp_floats, __name__)  # (vx, vy, vz, small): small is `quaternion.SMALL_ANGLE`
log_floats = compiled(quat.log_floats, __name__)
normalize_floats = compiled(quat.normalize_floats, __name__)
gravity_floats = compiled(quat.gravity_floats, __name__)  # R(q)^T e_z
rotation_floats = compiled(quat.rotation_floats, __name__)


@mirrors("fusion.quaternion.rotate_floats")
def rotate_floats(q, vx, vy, vz):
    """R(q) v (`quaternion.rotate_floats`, on `rotation_floats`)."""
    r = rotation_floats(q)
    return (r[0] * vx + r[1] * vy + r[2] * vz, r[3] * vx + r[4] * vy + r[5] * vz, r[6] * vx + r[7] * vy + r[8] * vz)


@_jit_leaf
def right_jacobian_dt(tx, ty, tz, dt, o, out):
    """out = J_r(t) dt, the SO(3) right Jacobian (`quaternion.right_jacobian_floats`) times dt."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    if t > o.series_rad:
        a = (1.0 - math.cos(t)) / (t * t)
        b = (t - math.sin(t)) / (t * t * t)
    else:
        t2 = t * t
        a = 0.0
        b = 0.0
        for i in range(2, -1, -1):
            a = a * t2 + o.jac_a[i]
            b = b * t2 + o.jac_b[i]
    S = ((0.0, -tz, ty), (tz, 0.0, -tx), (-ty, tx, 0.0))
    for i in range(3):
        for j in range(3):
            ss = S[i][0] * S[0][j] + S[i][1] * S[1][j] + S[i][2] * S[2][j]
            out[i, j] = ((1.0 if i == j else 0.0) - a * S[i][j] + b * ss) * dt
