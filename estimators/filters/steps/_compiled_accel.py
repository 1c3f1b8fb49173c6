"""`_accel` compiled: the accelerometer's gating, disturbance estimate, low-pass and lag.

Each kernel carries the name of the `_accel` function or method it implements (`update` is
`AccDisturbance.update`, `step` is `LowpassLag.step`), on the packed state of
`AccDisturbance.state()` laid out by `_accel`'s `DIST_*` offsets; the equations and their papers
are in `_accel`. `gravity_jacobian` (H = [[h]x, 0]) has no reference of its own: the numpy steps
fill H inline.
"""
from __future__ import annotations

import math
from typing import NamedTuple

from ...kernels._compiled_quaternion import multiply_floats, normalize_floats, rotate_floats, rotation_floats
from ...kernels._numba import _jit, _jit_leaf, forget_stale, mirrors
from ._accel import models_lag
from ._error_state import BIAS_AT
from ._accel import (DIST_AGE, DIST_BODY, DIST_DENSITY, DIST_FRAME, DIST_HAS_BODY, DIST_HAS_LOWPASS, DIST_HAS_MEAN,
                     DIST_LAG_B, DIST_LAG_S, DIST_LOWPASS, DIST_LOWPASS_MEAN, DIST_LOWPASS_NORM, DIST_LOWPASS_VAR,
                     DIST_MEAN, DIST_STATE, DIST_VAR)

forget_stale(__file__)

HELPERS = ("gravity_jacobian", "_rotate")
_GATES = {"off": 0, "skip": 1, "inflate": 2}


class AccStep(NamedTuple):
    """`_accel.AccStep` as the kernels take it: the same fields in the same order."""

    dq: tuple  # the step's rate increment, 4 floats
    dt: float  # s
    scale: float  # the gate's factor
    rate_noise: float  # rad^2/s
    u: tuple  # the lag's bias-corrected rate, 3 floats, rad/s
    gain: tuple  # ... and 1 + s, 3 floats


class SlowDisturbance(NamedTuple):
    """`_accel.SlowDisturbance` as the kernels take it: the same fields in the same order."""

    corr_s: float  # s; 0: none
    h: tuple  # gravity's direction in the body frame, 3 floats
    P_cal: object  # (k, k) the covariance's calibration block (a view of P)
    scale_prior_var: float


class AccSettings(NamedTuple):
    """The accelerometer fields of a `FilterParams`, as the kernels read them."""

    gate: int  # 0 off, 1 skip, 2 inflate
    gate_g: float  # g
    noise: float  # R, g^2 s
    corr_s: float  # the disturbance's correlation time, s (0: no disturbance model)
    window: float  # the disturbance's variance window, s
    lowpass_s: float  # the low-pass's time constant, s (0: none)
    lowpass_window: float  # its variance window, s
    lag: bool  # the low-pass's lag is modelled (`_accel.models_lag`; `AccDisturbance.lag`)


def acc_settings(p, bias: bool) -> AccSettings:
    """The `AccSettings` of a filter's parameters `p` (a `FilterParams`), with bias states or not."""
    return AccSettings(gate=_GATES[p.gate], gate_g=float(p.gate_g), noise=float(p.acc_noise_g2_s),
                       corr_s=float(p.disturbance_corr_s), window=float(p.disturbance_window_s),
                       lowpass_s=float(p.acc_lowpass_s), lowpass_window=float(p.acc_lowpass_window_s),
                       lag=bool(models_lag(p, bias)))


@mirrors("fusion.estimators.filters.steps._accel.acc_variance_scale")
def acc_variance_scale(ax, ay, az, gate, gate_g):
    """`_accel.acc_variance_scale` (gate 0 off, 1 skip, 2 inflate)."""
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if not math.isfinite(norm):
        return math.inf
    if gate == 0:
        return 1.0
    dev = abs(norm - 1.0)
    if gate == 1:
        return math.inf if dev > gate_g else 1.0
    r = dev / gate_g
    return 1.0 + r * r


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance.lose_frame", leaf=True)
def lose_frame(st):
    """`AccDisturbance.lose_frame` on its packed state (`AccDisturbance.state`)."""
    st[DIST_HAS_MEAN] = 0.0  # no mean
    st[DIST_VAR] = 0.0  # v
    st[DIST_AGE] = 0.0  # age
    st[DIST_HAS_LOWPASS] = 0.0  # no low-pass
    st[DIST_LOWPASS_MEAN], st[DIST_LOWPASS_MEAN + 1], st[DIST_LOWPASS_MEAN + 2] = 0.0, 0.0, 0.0  # lp_mean
    st[DIST_LOWPASS_VAR] = 0.0  # lp_v
    st[DIST_HAS_BODY] = 0.0  # no lowpass_body
    st[DIST_DENSITY] = math.inf  # lowpass_density
    st[DIST_LOWPASS_NORM] = 0.0  # lp_norm


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance._turn", leaf=True)
def _turn(st, dq):
    f = DIST_FRAME
    qi = normalize_floats(multiply_floats((st[f], st[f + 1], st[f + 2], st[f + 3]), dq))
    st[f], st[f + 1], st[f + 2], st[f + 3] = qi
    return qi


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance.turn", leaf=True)
def turn(st, dq, dt, u, gain, o):
    """`AccDisturbance.turn` on its state array: the frame follows the rate increment dq; with
    the lag (o.lag), N_b and N_s follow it (`step`, u and gain as there)."""
    fresh = st[DIST_HAS_LOWPASS] == 0.0
    _turn(st, dq)
    if o.lag:
        step(st, u, gain, dt, fresh, False, o.lowpass_s)


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance.update", leaf=True)
def update(st, dq, acc, dt, u, gain, o):
    """`AccDisturbance.update` (and `_lowpass` with o.lowpass_s > 0, the lag with o.lag) on its
    state array, acc the sample (3 floats, g); -> d, g^2."""
    ax, ay, az = acc
    fresh = st[DIST_HAS_LOWPASS] == 0.0  # the low-pass (re)starts with this sample: no lag yet
    qi = _turn(st, dq)
    wx, wy, wz = rotate_floats(qi, ax, ay, az)
    norm_dev = math.sqrt(ax * ax + ay * ay + az * az) - 1.0
    nd2 = norm_dev * norm_dev
    m = DIST_MEAN
    if st[DIST_HAS_MEAN] == 0.0:
        st[DIST_HAS_MEAN], st[m], st[m + 1], st[m + 2] = 1.0, wx, wy, wz
    ex, ey, ez = wx - st[m], wy - st[m + 1], wz - st[m + 2]
    inst = ex * ex + ey * ey + ez * ez
    alpha = -math.expm1(-dt / o.window)
    st[m], st[m + 1], st[m + 2] = st[m] + alpha * ex, st[m + 1] + alpha * ey, st[m + 2] + alpha * ez
    st[DIST_VAR] += alpha * (inst - st[DIST_VAR])
    st[DIST_AGE] += dt
    seen = -math.expm1(-st[DIST_AGE] / o.window)
    if o.lowpass_s > 0.0:
        _lowpass(st, qi, wx, wy, wz, abs(norm_dev), dt, o)
    if o.lag:
        step(st, u, gain, dt, fresh, True, o.lowpass_s)
    d = st[DIST_VAR] / seen  # max(v / seen, inst, nd2) with Python's max semantics
    if inst > d:
        d = inst
    if nd2 > d:
        d = nd2
    return d


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance._lowpass", leaf=True)
def _lowpass(st, qi, wx, wy, wz, norm_dev, dt, o):
    """`AccDisturbance._lowpass`: a_I low-passed, its density, its direction in the body frame, the
    norm deviation low-passed."""
    lp, lm = DIST_LOWPASS, DIST_LOWPASS_MEAN
    if st[DIST_HAS_LOWPASS] == 0.0:
        st[DIST_HAS_LOWPASS], st[lp], st[lp + 1], st[lp + 2] = 1.0, wx, wy, wz
        st[lm], st[lm + 1], st[lm + 2] = wx, wy, wz
        st[DIST_LOWPASS_NORM] = norm_dev
    beta = -math.expm1(-dt / o.lowpass_s)
    gamma = -math.expm1(-dt / o.lowpass_window)
    lx = st[lp] + beta * (wx - st[lp])
    ly = st[lp + 1] + beta * (wy - st[lp + 1])
    lz = st[lp + 2] + beta * (wz - st[lp + 2])
    st[lp], st[lp + 1], st[lp + 2] = lx, ly, lz
    st[DIST_LOWPASS_NORM] += beta * (norm_dev - st[DIST_LOWPASS_NORM])
    ex, ey, ez = lx - st[lm], ly - st[lm + 1], lz - st[lm + 2]
    st[lm], st[lm + 1], st[lm + 2] = st[lm] + gamma * ex, st[lm + 1] + gamma * ey, st[lm + 2] + gamma * ez
    st[DIST_LOWPASS_VAR] += gamma * (ex * ex + ey * ey + ez * ez - st[DIST_LOWPASS_VAR])
    seen = -math.expm1(-st[DIST_AGE] / o.lowpass_window)
    st[DIST_DENSITY] = 2.0 * o.lowpass_s * st[DIST_LOWPASS_VAR] / seen
    bx, by, bz = rotate_floats((qi[0], -qi[1], -qi[2], -qi[3]), lx, ly, lz)  # back into the body frame
    norm = math.sqrt(bx * bx + by * by + bz * bz)
    if norm > 0.0:
        st[DIST_HAS_BODY], st[DIST_BODY], st[DIST_BODY + 1], st[DIST_BODY + 2] = 1.0, bx / norm, by / norm, bz / norm
    else:
        st[DIST_HAS_BODY] = 0.0


@mirrors("fusion.estimators.filters.steps._accel.LowpassLag.step", leaf=True)
def step(st, u, gain, h, fresh, updated, lowpass_s):
    """`_accel.LowpassLag.step` on the disturbance state `st`: N_b and N_s advanced with its
    strapdown frame (q_I at DIST_FRAME); u, gain (3 floats each): the bias-corrected rate and the
    gain 1 + s (a step that was not integrated restarts the low-pass: fresh); h: the step, s."""
    if fresh:
        for c in range(DIST_LAG_B, DIST_STATE):
            st[c] = 0.0
        return
    f = DIST_FRAME
    R = rotation_floats((st[f], st[f + 1], st[f + 2], st[f + 3]))  # R_I, row by row
    for j in range(3):  # column j of R_I, times diag(1 + s) dt and diag(u) dt
        cx, cy, cz = R[j], R[3 + j], R[6 + j]
        gj = gain[j] * h
        uj = u[j] * h
        st[DIST_LAG_B + j] += cx * gj
        st[DIST_LAG_B + 3 + j] += cy * gj
        st[DIST_LAG_B + 6 + j] += cz * gj
        st[DIST_LAG_S + j] += cx * uj
        st[DIST_LAG_S + 3 + j] += cy * uj
        st[DIST_LAG_S + 6 + j] += cz * uj
    if updated:
        decay = math.exp(-h / lowpass_s)
        for c in range(DIST_LAG_B, DIST_STATE):
            st[c] *= decay


@_jit_leaf
def _rotate(r, vx, vy, vz):
    """R v for R given as its nine entries, row by row (`rotation_floats`): `rotate_floats` with
    the matrix computed once for several vectors, the same products and sums."""
    return (r[0] * vx + r[1] * vy + r[2] * vz, r[3] * vx + r[4] * vy + r[5] * vz, r[6] * vx + r[7] * vy + r[8] * vz)


@_jit_leaf
def gravity_jacobian(H, hx, hy, hz, n):
    """H (3 x n) <- [[h]x, 0]: the accelerometer's Jacobian `[h]x` for the raw sample."""
    H[0, 0], H[0, 1], H[0, 2] = 0.0, -hz, hy
    H[1, 0], H[1, 1], H[1, 2] = hz, 0.0, -hx
    H[2, 0], H[2, 1], H[2, 2] = -hy, hx, 0.0
    for i in range(3):
        for j in range(BIAS_AT, n):
            H[i, j] = 0.0


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance.lag_jacobian", leaf=True)
def lag_jacobian(H, st, scale):
    """`AccDisturbance.lag_jacobian` into H (3 x n) holding `[h]x` in its first three columns:
    H[:, BIAS] = A N_b, and with scale states H[:, SCALE] = -A N_s, with A = [h]x R_I^T (N_b, N_s
    in the state `st`)."""
    f = DIST_FRAME
    r = rotation_floats((st[f], -st[f + 1], -st[f + 2], -st[f + 3]))  # R_I^T, once for the columns
    for m in range(2 if scale else 1):
        sign = 1.0 if m == 0 else -1.0
        for j in range(3):
            c = (DIST_LAG_B if m == 0 else DIST_LAG_S) + j
            vx, vy, vz = _rotate(r, st[c], st[c + 3], st[c + 6])
            for i in range(3):
                H[i, BIAS_AT + 3 * m + j] = sign * (H[i, 0] * vx + H[i, 1] * vy + H[i, 2] * vz)


@mirrors("fusion.estimators.filters.steps._accel.AccDisturbance.slow_power", leaf=True)
def slow_power(st, h, P_cal, scale_prior_var, lowpass_s, Hc):
    """`AccDisturbance.slow_power` on the disturbance state `st`, for the gravity direction h
    (3 floats, body) and the filter's calibration covariance P_cal ((3, 3) bias or (6, 6) bias and
    scale); -> g^2. Hc: (3, >= 6) scratch, [H_b, H_s] in its first six columns."""
    hx, hy, hz = h
    if st[DIST_HAS_LOWPASS] == 0.0 or st[DIST_HAS_MEAN] == 0.0 or st[DIST_AGE] < lowpass_s:
        return 0.0
    m, lp = DIST_MEAN, DIST_LOWPASS
    ex, ey, ez = st[m] - st[lp], st[m + 1] - st[lp + 1], st[m + 2] - st[lp + 2]
    dev = ex * ex + ey * ey + ez * ez
    f = DIST_FRAME
    r = rotation_floats((st[f], -st[f + 1], -st[f + 2], -st[f + 3]))  # R_I^T, once for the six columns
    for c in range(6):  # [H_b, H_s] = [A N_b, -A N_s], A = [h]x R_I^T (`LowpassLag.jacobian`)
        sign = 1.0 if c < 3 else -1.0
        o = (DIST_LAG_B if c < 3 else DIST_LAG_S) + c % 3
        vx, vy, vz = _rotate(r, st[o], st[o + 3], st[o + 6])
        Hc[0, c] = sign * (-hz * vy + hy * vz)  # [h]x v
        Hc[1, c] = sign * (hz * vx - hx * vz)
        Hc[2, c] = sign * (-hy * vx + hx * vy)
    k = P_cal.shape[0]  # 3 (bias) or 6 (bias and scale)
    explained = 0.0
    for i in range(k):  # trace(H_c P_cal H_c^T)
        for j in range(k):
            explained += (Hc[0, i] * Hc[0, j] + Hc[1, i] * Hc[1, j] + Hc[2, i] * Hc[2, j]) * P_cal[i, j]
    hs2 = 0.0
    for i in range(3):
        for j in range(3, 6):
            hs2 += Hc[i, j] * Hc[i, j]
    explained += scale_prior_var * hs2
    explained += st[DIST_LOWPASS_NORM] * st[DIST_LOWPASS_NORM]
    return max(0.0, dev - explained)


@mirrors("fusion.estimators.filters.steps._accel.lowpass_drift_density")
def lowpass_drift_density(lowpass_s, rate_noise):
    """`_accel.lowpass_drift_density`."""
    return 2.0 * lowpass_s * (lowpass_s * rate_noise)


@mirrors("fusion.estimators.filters.steps._accel.lowpass_residual_density")
def lowpass_residual_density(density, lowpass_s, rate_noise):
    """`_accel.lowpass_residual_density`."""
    if rate_noise <= 0.0 or not density > lowpass_s * lowpass_s * rate_noise:
        return density
    return (density * lowpass_s * math.sqrt(rate_noise)) ** (2.0 / 3.0)


@mirrors("fusion.estimators.filters.steps._accel.acc_measurement", leaf=True)
def acc_measurement(st, ax, ay, az, o, d, drift, rate_noise):
    """`_accel.acc_measurement`: the raw sample or the low-passed direction, whichever has the
    smaller noise density; -> (z (3 floats), density g^2 s, low-passed)."""
    raw = o.noise + 2.0 * o.corr_s * d
    if st[DIST_HAS_BODY] != 0.0:
        lowpassed = o.noise + lowpass_residual_density(st[DIST_DENSITY], o.lowpass_s, rate_noise) + drift
        if lowpassed < raw:
            return st[DIST_BODY], st[DIST_BODY + 1], st[DIST_BODY + 2], lowpassed, True
    return ax, ay, az, raw, False


@mirrors("fusion.estimators.filters.steps._accel.accelerometer_update_input", leaf=True)
def accelerometer_update_input(dist, acc, step, slow, o, work):
    """`_accel.accelerometer_update_input`: the measurement and variance of one accelerometer
    update, as the filters' steps choose them, for the sample acc (3 floats, g) with the step's
    `AccStep` and the `SlowDisturbance` (work: `slow_power`'s (3, >= 6) scratch); o: `AccSettings`.
    -> (z (3 floats), r g^2, low-passed)."""
    ax, ay, az = acc
    if o.corr_s > 0.0:
        d = update(dist, step.dq, acc, step.dt, step.u, step.gain, o)
        if slow.corr_s > 0.0:  # as the power of the fast process with the same density
            d = max(d, slow_power(dist, slow.h, slow.P_cal, slow.scale_prior_var, o.lowpass_s, work)
                    * (slow.corr_s / o.corr_s))
        drift = lowpass_drift_density(o.lowpass_s, step.rate_noise)
        mx, my, mz, density, lowpassed = acc_measurement(dist, ax, ay, az, o, d, drift, step.rate_noise)
        return mx, my, mz, density / step.dt * step.scale, lowpassed
    return ax, ay, az, o.noise / step.dt * step.scale, False
