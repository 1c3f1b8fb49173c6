"""What the filters' error states share: the variance that stands for "not estimated", and which
body axes a parameter's axis list names (`scale_axes`, the smoothers' bias and scale axes).

A leaf module (numpy only), so that the parameter classes (`filter_params`, `smoother`) and the
filters (`kalman_base`) import it without importing each other.
"""
from __future__ import annotations

import numpy as np


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
