"""The online stuck-gyro check of the filters: the causal form of
`fusion.checks.detect_freezes`, for a gyro freeze nobody flagged.

Contract: `stuck_gyro_update` takes one step (gyro (3,) rad/s, accelerometer (3,) g, body frame,
the step dt s, the reading's validity) and the state of `stuck_gyro_state`, which it advances in
place, and says whether this gyro reading is stuck. The same Python function runs in the numpy
`step` and, compiled, in the batch path (`_compiled_stuck`), so the two cannot differ.

The thresholds are the offline detector's (`fusion.checks.FreezeDetector`); the criterion (a gyro
that stays within a few ADC counts while the accelerometer moves) is the project's own, no paper.

The state's layout is the `STUCK_*` offsets below.
"""
from __future__ import annotations

import math

import numpy as np

from fusion.checks import FreezeDetector

# The layout of the (STUCK_STATE,) float64 state of `stuck_gyro_update` (offsets; vectors of 3).
STUCK_RESOLUTION = 0  # per channel: the smallest non-zero change seen (rad/s; inf: none yet)
STUCK_PREVIOUS = 3  # the previous reading (3), rad/s
STUCK_HAS_PREVIOUS = 6  # flag
STUCK_GYR_LOW = 7  # the run's gyro low (3) and high (3), rad/s
STUCK_GYR_HIGH = 10
STUCK_ACC_LOW = 13  # the run's accelerometer low (3) and high (3), g
STUCK_ACC_HIGH = 16
STUCK_DURATION = 19  # the run's duration, s
STUCK_HAS_RUN = 20  # flag
STUCK_STATE = 21


# Its thresholds (window_s, steps, acc_p2p_g): the offline detector's (`FreezeDetector`).
STUCK_THRESHOLDS = (FreezeDetector.window_s, FreezeDetector.gyro_p2p_steps, FreezeDetector.acc_p2p_g)


def stuck_gyro_state() -> np.ndarray:
    """(STUCK_STATE,) float64, a fresh state of `stuck_gyro_update` (laid out by the `STUCK_*`
    offsets); the resolution starts unknown (inf)."""
    state = np.zeros(STUCK_STATE)
    state[STUCK_RESOLUTION:STUCK_RESOLUTION + 3] = np.inf
    return state


def stuck_gyro_update(s: np.ndarray, gyr: np.ndarray, acc: np.ndarray, dt_s: float, valid: bool,
                      window_s: float, steps: float, acc_p2p_g: float) -> bool:
    """One step of the online stuck-gyro check; -> whether this gyro reading is stuck.

    The causal form of `fusion.checks.detect_freezes` (the same thresholds,
    `STUCK_THRESHOLDS`), for a gyro freeze nobody flagged: a gyro whose three
    channels stay within `steps` steps of their resolution for `window_s` seconds while the
    accelerometer moves by more than `acc_p2p_g` (peak to peak, g) is not measuring the motion
    the accelerometer sees, since a real gyro's noise moves it by more than that in a moving
    hand. The resolution of each channel is the smallest non-zero change between two
    consecutive readings seen so far (one ADC count on the course board); until a channel has
    shown one, it is not judged (a gyro without noise, a simulation, is never called stuck).
    The run restarts at any reading that leaves the band, and at an invalid or non-finite one.
    s: the state (`stuck_gyro_state`), advanced in place; gyr (3,) rad/s, acc (3,) g.
    The same function runs in the numpy `step` and, compiled, in the batch path.
    """
    if not (valid and math.isfinite(gyr[0] + gyr[1] + gyr[2] + acc[0] + acc[1] + acc[2])):
        s[STUCK_HAS_RUN] = 0.0
        return False
    if s[STUCK_HAS_PREVIOUS] > 0.0:
        for c in range(3):
            d = abs(gyr[c] - s[STUCK_PREVIOUS + c])
            if 0.0 < d < s[STUCK_RESOLUTION + c]:
                s[STUCK_RESOLUTION + c] = d
    for c in range(3):
        s[STUCK_PREVIOUS + c] = gyr[c]
    s[STUCK_HAS_PREVIOUS] = 1.0
    extends = s[STUCK_HAS_RUN] > 0.0
    for c in range(3):
        if not extends:
            break
        band = max(s[STUCK_GYR_HIGH + c], gyr[c]) - min(s[STUCK_GYR_LOW + c], gyr[c])
        extends = math.isfinite(s[STUCK_RESOLUTION + c]) and band <= steps * s[STUCK_RESOLUTION + c] * (1.0 + 1e-9)
    if extends:
        for c in range(3):
            s[STUCK_GYR_LOW + c] = min(s[STUCK_GYR_LOW + c], gyr[c])
            s[STUCK_GYR_HIGH + c] = max(s[STUCK_GYR_HIGH + c], gyr[c])
            s[STUCK_ACC_LOW + c] = min(s[STUCK_ACC_LOW + c], acc[c])
            s[STUCK_ACC_HIGH + c] = max(s[STUCK_ACC_HIGH + c], acc[c])
        s[STUCK_DURATION] += dt_s
    else:
        for c in range(3):
            s[STUCK_GYR_LOW + c] = s[STUCK_GYR_HIGH + c] = gyr[c]
            s[STUCK_ACC_LOW + c] = s[STUCK_ACC_HIGH + c] = acc[c]
        s[STUCK_DURATION] = 0.0
        s[STUCK_HAS_RUN] = 1.0
    moved = max(s[STUCK_ACC_HIGH] - s[STUCK_ACC_LOW], s[STUCK_ACC_HIGH + 1] - s[STUCK_ACC_LOW + 1],
                s[STUCK_ACC_HIGH + 2] - s[STUCK_ACC_LOW + 2])
    return s[STUCK_DURATION] >= window_s and moved > acc_p2p_g
