"""`_rest` compiled: rest detection and the bias update at rest, and the rest steps of a whole
recording for the smoothers (`rest_steps`).

`update` is `RestDetector.update` on the packed state of `RestDetector.state()` (the `REST_*`
offsets), `bias_rest_update` the function of that name; the equations and their paper (VQF,
Laidig & Seel 2023, Sec. 3.4) are in `_rest`. `rest_kernel` is the batch loop behind
`rest_steps`, which has no numpy reference (the filters feed the detector step by step).
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ...kernels._compiled_linalg import inv_sym3, joseph
from ...kernels._numba import _jit, _sample, forget_stale, inputs, mirrors
from ._error_state import BIAS_AT
from ._rest import REST_HAS_LOWPASS, REST_LOWPASS, REST_START, REST_STATE, REST_TIME_STILL, REST_WINDOW_S

forget_stale(__file__)

HELPERS = ("rest_kernel",)


class RestSettings(NamedTuple):
    """A `RestDetector`'s thresholds, as the kernels read them."""

    gyr: float  # gyro norm, rad/s
    acc: float  # accelerometer deviation, g
    time: float  # minimum duration, s (inf: never at rest)
    window: float  # the accelerometer low-pass's time constant, s
    tilt: float  # the tilt test's angle, rad (inf: none)


def rest_settings(rest: Any) -> RestSettings:
    """The `RestSettings` of a `RestDetector`, or of none (never at rest)."""
    if rest is None:
        return RestSettings(gyr=0.0, acc=0.0, time=math.inf, window=1.0, tilt=math.inf)
    return RestSettings(gyr=float(rest.gyr_th), acc=float(rest.acc_th), time=float(rest.min_time),
                        window=float(rest.window_s), tilt=float(rest.tilt))


@mirrors("fusion.estimators.filters.steps._rest.RestDetector.update", leaf=True)
def update(st, gx, gy, gz, ax, ay, az, dt, o):
    """`RestDetector.update` on its packed state (`RestDetector.state`); -> at rest."""
    if not (math.isfinite(ax + ay + az) and math.isfinite(gx + gy + gz)):
        st[REST_TIME_STILL] = 0.0
        return False
    lp = REST_LOWPASS
    if st[REST_HAS_LOWPASS] == 0.0:
        st[REST_HAS_LOWPASS], st[lp], st[lp + 1], st[lp + 2] = 1.0, ax, ay, az
    alpha = -math.expm1(-dt / o.window)
    dx, dy, dz = ax - st[lp], ay - st[lp + 1], az - st[lp + 2]
    st[lp], st[lp + 1], st[lp + 2] = st[lp] + alpha * dx, st[lp + 1] + alpha * dy, st[lp + 2] + alpha * dz
    g = gx * gx + gy * gy + gz * gz
    a = ax * ax + ay * ay + az * az
    still = (g < o.gyr * o.gyr and dx * dx + dy * dy + dz * dz < o.acc * o.acc
             and abs(math.sqrt(a) - 1.0) < o.acc)
    if still and o.tilt < math.inf:  # the tilt test: has the low-pass turned within the stretch?
        s0 = REST_START
        if st[REST_TIME_STILL] == 0.0:
            st[s0], st[s0 + 1], st[s0 + 2] = st[lp], st[lp + 1], st[lp + 2]
        elif _turned(st[s0], st[s0 + 1], st[s0 + 2], st[lp], st[lp + 1], st[lp + 2], o.tilt):
            st[REST_TIME_STILL] = 0.0  # a turn, not a rest: a new stretch begins next
            return False
    st[REST_TIME_STILL] = st[REST_TIME_STILL] + dt if still else 0.0
    return st[REST_TIME_STILL] >= o.time


@mirrors("fusion.estimators.filters.steps._rest._turned")
def _turned(ax, ay, az, bx, by, bz, angle):
    """`_rest._turned` on two directions of 3 floats each."""
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    s = math.sin(angle)
    return (ax * bx + ay * by + az * bz <= 0.0
            or cx * cx + cy * cy + cz * cz > s * s * (ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz))


@_jit
def rest_kernel(gyr, valid, dt, acc, o, out):
    """out[k] (N-1,): whether step k ends at rest, as the filters' rest updates see it (the
    detector is fed step k's gyro reading and the accelerometer sample at its end, only on
    steps whose gyro is usable)."""
    st = np.zeros(REST_STATE)
    for k in range(len(dt)):
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
        out[k] = ok and update(st, gx, gy, gz, ax, ay, az, dt[k], o)


def rest_steps(imu: Any, gyr_th_rad_s: float, acc_th_g: float, min_time_s: float,
               window_s: float = REST_WINDOW_S, tilt_rad: float = math.inf) -> np.ndarray:
    """(N-1,) bool: the steps of `imu` (`ImuSamples`) that end at rest by `_rest.RestDetector`
    with these thresholds, run causally over the recording (the samples the `ekf` and `ukf-bias`
    rest updates use, with their `tilt_rad`). A batch smoother reads its gyro bias there (without
    the tilt test: inf)."""
    inp = inputs(imu)
    out = np.zeros(len(inp.dt), dtype=bool)
    if math.isfinite(min_time_s):
        o = RestSettings(gyr=float(gyr_th_rad_s), acc=float(acc_th_g), time=float(min_time_s), window=float(window_s),
                         tilt=float(tilt_rad))
        rest_kernel(inp.gyr, inp.valid, inp.dt, inp.acc, o, out)
    return out


@mirrors("fusion.estimators.filters.steps._rest.bias_rest_update", leaf=True)
def bias_rest_update(b, P, gyr, r, n, w):
    """`_rest.bias_rest_update`: the zero-rate update gyr = b + noise (b, gyr: 3 floats, rad/s),
    H = [0, I, 0] (3 x n), so that P H^T = P[:, BIAS] and H P H^T = P[BIAS, BIAS]; P updated in
    place (Joseph form, `joseph`), the correction into w.dx (n,) (w: the filter's work arrays, K,
    PHt, D: n x 3, S, Sinv: 3 x 3)."""
    K, dx, S, Sinv, PHt = w.K, w.dx, w.S, w.Sinv, w.PHt
    c = BIAS_AT
    for i in range(n):
        PHt[i, 0], PHt[i, 1], PHt[i, 2] = P[i, c], P[i, c + 1], P[i, c + 2]
    for i in range(3):
        for j in range(3):
            S[i, j] = P[c + i, c + j] + (r if i == j else 0.0)
    inv_sym3(S, Sinv)
    yx, yy, yz = gyr[0] - b[0], gyr[1] - b[1], gyr[2] - b[2]
    for i in range(n):
        for j in range(3):
            K[i, j] = P[i, c] * Sinv[0, j] + P[i, c + 1] * Sinv[1, j] + P[i, c + 2] * Sinv[2, j]
        dx[i] = K[i, 0] * yx + K[i, 1] * yy + K[i, 2] * yz
    joseph(P, K, PHt, S, n, w.D)
