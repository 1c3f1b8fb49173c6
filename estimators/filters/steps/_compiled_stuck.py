"""`_stuck` compiled: the online stuck-gyro check over a whole recording.

`stuck_gyro_update` is `_stuck.stuck_gyro_update` itself, compiled (one definition for the numpy
step and the batch path); `stuck_intervals` is its loop over a recording, which the compiled
filters run before their kernel (`KalmanFilter._unstuck`).
"""
from __future__ import annotations

import numpy as np

from ...kernels._numba import _jit, compiled, forget_stale
from . import _stuck

forget_stale(__file__)

HELPERS = ("stuck_intervals",)

stuck_gyro_update = compiled(_stuck.stuck_gyro_update, __name__)


@_jit
def stuck_intervals(gyr, dt, acc_end, valid, state, window_s, steps, acc_p2p_g):
    """(N - 1,) bool: `_stuck.stuck_gyro_update` over every step (gyro reading, interval,
    accelerometer sample at its end, validity), advancing `state` in place."""
    out = np.zeros(len(dt), dtype=np.bool_)
    for k in range(len(dt)):
        out[k] = stuck_gyro_update(state, gyr[k], acc_end[k], dt[k], valid[k], window_s, steps, acc_p2p_g)
    return out
