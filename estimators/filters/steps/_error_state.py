"""What the filters' error states share: where each block of the error state lies (named once,
for the numpy steps and the kernels alike), the variance that stands for "not estimated", and
which body axes a parameter's axis list names (`scale_axes`, the smoothers' bias and scale axes).

The error state of `ekf`, `ukf` and `ukf-bias` is `dx = [e, db, ds, dv][:N]`: the body-frame
attitude error e (rad), the gyro bias error db (rad/s), the gyro scale-factor error ds
(dimensionless) and, for `ekf`, the horizontal velocity error dv (m/s, world x and y); a filter
without bias (or scale, or velocity) states has the blocks before it only. The rows of P, of a
gain K and the entries of dx follow it: `P[BIAS, BIAS]` is the bias block, `dx[SCALE]` the scale
correction, `K[layout.velocity]` the velocity rows. The UKFs' nominal state is
`x = [q_wxyz, b, s][:n + 1]`: `x[X_QUAT]`, `x[X_BIAS]`, `x[X_SCALE]`. The kernels read the
blocks' first rows (`BIAS_AT`, `SCALE_AT`, `X_BIAS_AT`, `X_SCALE_AT`).

A leaf module (numpy only), so that the parameter classes (`filter_params`, `smoother`) and the
filters (`kalman_base`) import it without importing each other.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

# The error state's blocks: first rows, and the rows as slices.
ATTITUDE_AT, BIAS_AT, SCALE_AT = 0, 3, 6
CALIBRATION_AT = BIAS_AT  # the calibration (bias and scale, whichever the state has) follows the attitude
ATTITUDE = slice(ATTITUDE_AT, ATTITUDE_AT + 3)  # e, rad, body frame
BIAS = slice(BIAS_AT, BIAS_AT + 3)  # db, rad/s
SCALE = slice(SCALE_AT, SCALE_AT + 3)  # ds
# The UKFs' nominal state [q_wxyz, b, s]: first entries, and the entries as slices.
X_QUAT_AT, X_BIAS_AT, X_SCALE_AT = 0, 4, 7
X_QUAT = slice(X_QUAT_AT, X_QUAT_AT + 4)
X_BIAS = slice(X_BIAS_AT, X_BIAS_AT + 3)
X_SCALE = slice(X_SCALE_AT, X_SCALE_AT + 3)
X_CALIBRATION_AT = X_BIAS_AT
X_CALIBRATION = slice(X_CALIBRATION_AT, None)  # b and s, whichever the state has


class ErrorLayout(NamedTuple):
    """The blocks one filter's error state has (see the module docstring)."""

    bias: bool  # the gyro bias block, `BIAS`
    scale: bool  # the gyro scale block, `SCALE` (needs the bias block)
    velocity_states: int  # 2: the horizontal velocity block after the others (`ekf`), else 0

    @property
    def n(self) -> int:
        """The attitude and calibration rows: 3, 6 or 9."""
        return ATTITUDE_AT + 3 + 3 * self.bias + 3 * self.scale

    @property
    def N(self) -> int:
        """Every row, the velocity's included."""
        return self.n + self.velocity_states

    @property
    def calibration(self) -> slice:
        """The bias and scale rows (empty without them)."""
        return slice(BIAS_AT, self.n)

    @property
    def velocity(self) -> slice:
        """The velocity rows (empty without them)."""
        return slice(self.n, self.N)

    @classmethod
    def of(cls, n: int, velocity_states: int = 0) -> "ErrorLayout":
        """The layout of an error state of n = 3, 6 or 9 attitude and calibration rows."""
        if n not in (3, 6, 9):
            raise ValueError(f"error state: 3, 6 or 9 attitude and calibration rows, got {n}")
        return cls(bias=n > 3, scale=n > 6, velocity_states=velocity_states)


# Variance standing for "not estimated" in a filter's state: small enough that the state stays
# at its initial value, large enough to keep the covariance positive definite.
UNESTIMATED_VAR = 1e-12


def axes_mask(axes: str, name: str = "scale_axes") -> np.ndarray:
    """(3,) bool: which body axes an axis list names ("xy", "xyz", "" for none), e.g. the gyro
    scale factors or biases an estimator estimates. `name` is the parameter, for the error."""
    axes = "" if axes == "none" else axes
    if any(a not in "xyz" for a in axes) or len(set(axes)) != len(axes):
        raise ValueError(f"{name}={axes!r}: expected distinct letters from 'xyz' (or 'none')")
    return np.array([a in axes for a in "xyz"])
