"""`_magnetometer` compiled: the reference field and its gates, the hard-iron sphere fit and the
heading-only update (9-D).

`update` and `in_gates` are `MagReference`'s methods on the packed state of
`MagReference.state()` (the `MAG_*` offsets); the sphere fit works on `HardIron.state()`'s sums
(the `HARD_IRON_*` offsets); the others carry their `_magnetometer` function's name. The
equations and their papers (VQF, Laidig & Seel 2023, Sec. 3.3; Vasconcelos et al. 2011, eqs. 4-6)
are in `_magnetometer`. `heading_update`'s Joseph form is expanded for a symmetric P as in
`_compiled_linalg.joseph`.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

from ...kernels._compiled_quaternion import gravity_floats, rotate_floats
from ...kernels._numba import forget_stale, mirrors
from ._error_state import BIAS_AT
from ._magnetometer import (HARD_IRON_A, HARD_IRON_B, HARD_IRON_W, HARD_IRON_YY, HEADING_GATE_CHI2, MAG_DIP,
                            MAG_HAS_REF, MAG_LEARNED, MAG_NORM, MAG_PSI, MAG_REJECTED, MAG_TIME_OK)

forget_stale(__file__)

HELPERS = ()


class MagSettings(NamedTuple):
    """The magnetometer fields of a `BiasFilterParams` (the mag_* fields), as the kernels read them."""

    noise: float  # Rm, rad^2 s
    norm_gate: float  # fraction of the reference norm
    dip_gate: float  # rad
    min_time: float  # s in the gates before a sample is used
    ref_s: float  # the reference's time constant, s
    rate: float  # rad/s of the rate term (inf: none)
    heading_gate: float  # the heading gate's tolerated deviation, rad (inf: no gate)
    heading_gate_s: float  # its innovation's low-pass time constant, s
    heading_gate_max_s: float  # its longest rejection, s
    hard_iron: bool  # the sphere fit is on
    hi_window: float  # its window, s
    hi_residual: float  # its residual bound, uT
    hi_coverage: float  # its coverage bound


def mag_settings(p: Any) -> MagSettings:
    """The `MagSettings` of a filter's parameters (zeros for a filter without a magnetometer)."""
    return MagSettings(
        noise=float(getattr(p, "mag_heading_noise_rad2_s", 0.0)), norm_gate=float(getattr(p, "mag_norm_gate_frac", 0.0)),
        dip_gate=float(getattr(p, "mag_dip_gate_rad", 0.0)), min_time=float(getattr(p, "mag_min_undisturbed_s", 0.0)),
        ref_s=float(getattr(p, "mag_ref_s", 1.0)), rate=float(getattr(p, "mag_rate_rad_s", math.inf)),
        heading_gate=float(getattr(p, "mag_heading_gate_rad", math.inf)),
        heading_gate_s=float(getattr(p, "mag_heading_gate_s", 1.0)),
        heading_gate_max_s=float(getattr(p, "mag_heading_gate_max_s", math.inf)),
        hard_iron=bool(getattr(p, "mag_hard_iron", False)), hi_window=float(getattr(p, "mag_hard_iron_window_s", 1.0)),
        hi_residual=float(getattr(p, "mag_hard_iron_residual_ut", 0.0)),
        hi_coverage=float(getattr(p, "mag_hard_iron_coverage", 0.0)))


@mirrors("fusion.estimators.filters.steps._magnetometer.MagReference.update", leaf=True)
def update(st, norm, dip, dt, o):
    """`MagReference.update` on its packed state st (`MagReference.state`);
    -> the sample may correct the heading."""
    if st[MAG_HAS_REF] == 0.0:
        st[MAG_HAS_REF], st[MAG_NORM], st[MAG_DIP] = 1.0, norm, dip
        st[MAG_LEARNED], st[MAG_TIME_OK] = dt, 0.0
        return False
    if abs(norm - st[MAG_NORM]) < o.norm_gate * st[MAG_NORM] and abs(dip - st[MAG_DIP]) < o.dip_gate:
        st[MAG_LEARNED] += dt
        alpha = dt / min(st[MAG_LEARNED], o.ref_s)
        st[MAG_NORM] += alpha * (norm - st[MAG_NORM])
        st[MAG_DIP] += alpha * (dip - st[MAG_DIP])
        st[MAG_TIME_OK] += dt
    else:
        st[MAG_TIME_OK] = 0.0
    return st[MAG_TIME_OK] >= o.min_time


@mirrors("fusion.estimators.filters.steps._magnetometer.MagReference.in_gates", leaf=True)
def in_gates(st, norm, dip, o):
    """`MagReference.in_gates` on its packed state st (`MagReference.state`)."""
    return (st[MAG_HAS_REF] != 0.0 and abs(norm - st[MAG_NORM]) < o.norm_gate * st[MAG_NORM]
            and abs(dip - st[MAG_DIP]) < o.dip_gate)


@mirrors("fusion.estimators.filters.steps._magnetometer.MagReference.heading_gate_update", leaf=True)
def heading_gate_update(st, psi, var, dt, o):
    """`MagReference.heading_gate_update` on its packed state st (`MagReference.state`);
    -> the sample may correct the heading."""
    st[MAG_PSI] += min(dt / o.heading_gate_s, 1.0) * (psi - st[MAG_PSI])
    if st[MAG_PSI] * st[MAG_PSI] < HEADING_GATE_CHI2 * (var + o.heading_gate * o.heading_gate):
        st[MAG_REJECTED] = 0.0
        return True
    st[MAG_REJECTED] += dt
    return st[MAG_REJECTED] > o.heading_gate_max_s


@mirrors("fusion.estimators.filters.steps._magnetometer.heading_innovation", leaf=True)
def heading_innovation(q, P, east, north):
    """`heading_innovation`: (psi, v^T P_attitude v) with v = R(q)^T e_z."""
    vx, vy, vz = gravity_floats(q)
    var = (vx * (P[0, 0] * vx + P[0, 1] * vy + P[0, 2] * vz) + vy * (P[1, 0] * vx + P[1, 1] * vy + P[1, 2] * vz)
           + vz * (P[2, 0] * vx + P[2, 1] * vy + P[2, 2] * vz))
    return math.atan2(-east, north), var


@mirrors("fusion.estimators.filters.steps._magnetometer.magnetometer_input", leaf=True)
def magnetometer_input(q, P, mx, my, mz, mag_ref, hard_iron, o, h, hi_fit, hi_work):
    """`magnetometer_input`: one finite sample (uT, body) through the sphere fit, the gates and the
    heading gate (the packed states mag_ref of `MagReference` and hard_iron of `HardIron`, advanced
    in place; P: the error covariance; o: `MagSettings`); -> (usable, east, north, hard iron used)."""
    east, north, up = rotate_floats(q, mx, my, mz)  # `_magnetometer.field_norm_dip`
    horizontal = math.hypot(east, north)
    norm = math.sqrt(east * east + north * north + up * up)
    dip = math.atan2(-up, horizontal)
    hi_used = False
    if o.hard_iron:
        hard_iron_add(hard_iron, mx, my, mz, min(h / o.hi_window, 1.0))
        if mag_ref[MAG_HAS_REF] != 0.0 and hard_iron_fit(hard_iron, o.hi_residual, o.hi_coverage, hi_fit, hi_work) \
                and abs(hi_fit[3] - mag_ref[MAG_NORM]) < o.norm_gate * mag_ref[MAG_NORM]:
            e2, n2, u2 = rotate_floats(q, mx - hi_fit[0], my - hi_fit[1], mz - hi_fit[2])
            horizontal2 = math.hypot(e2, n2)
            norm2 = math.sqrt(e2 * e2 + n2 * n2 + u2 * u2)
            dip2 = math.atan2(-u2, horizontal2)
            if in_gates(mag_ref, norm2, dip2, o):
                east, north, norm, dip = e2, n2, norm2, dip2
                hi_used = True
    usable = update(mag_ref, norm, dip, h, o) and east * east + north * north > 0.0
    if usable:
        psi, var = heading_innovation(q, P, east, north)
        usable = heading_gate_update(mag_ref, psi, var, h, o)
    return usable, east, north, hi_used


@mirrors("fusion.estimators.filters.steps._magnetometer.heading_variance")
def heading_variance(q, tx, ty, tz, h, o):
    """`heading_variance`: Rm / dt (1 + (w / mrate)^2), w the rate about the vertical."""
    vx, vy, vz = gravity_floats(q)
    w_up = (tx * vx + ty * vy + tz * vz) / h
    return o.noise / h * (1.0 + (w_up / o.rate) ** 2)


@mirrors("fusion.estimators.filters.steps._magnetometer.hard_iron_add", leaf=True)
def hard_iron_add(s, mx, my, mz, alpha):
    """`hard_iron_add`: the sphere fit's sums s (`HardIron.state`) <- (1 - alpha) s + alpha (the
    sample's terms)."""
    y = mx * mx + my * my + mz * mz
    keep = 1.0 - alpha
    for i in range(4):
        xi = mx if i == 0 else my if i == 1 else mz if i == 2 else 1.0
        for j in range(4):
            xj = mx if j == 0 else my if j == 1 else mz if j == 2 else 1.0
            s[HARD_IRON_A + 4 * i + j] = keep * s[HARD_IRON_A + 4 * i + j] + alpha * xi * xj
        s[HARD_IRON_B + i] = keep * s[HARD_IRON_B + i] + alpha * xi * y
    s[HARD_IRON_YY] = keep * s[HARD_IRON_YY] + alpha * y * y
    s[HARD_IRON_W] = keep * s[HARD_IRON_W] + alpha


@mirrors("fusion.estimators.filters.steps._magnetometer.hard_iron_fit", leaf=True)
def hard_iron_fit(s, residual_ut, coverage, out, a):
    """`hard_iron_fit` (with `solve4`): True and out (4,) = (ox, oy, oz, r) when the sphere fit is
    trusted (a: 4 x 5 scratch)."""
    w = s[HARD_IRON_W]
    if not w > 0.0:
        return False
    for i in range(4):
        for j in range(4):
            a[i, j] = s[HARD_IRON_A + 4 * i + j]
        a[i, 4] = s[HARD_IRON_B + i]
    for c in range(4):
        p = c
        for r in range(c + 1, 4):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if not abs(a[p, c]) > 0.0:
            return False
        if p != c:
            for j in range(5):
                a[c, j], a[p, j] = a[p, j], a[c, j]
        for r in range(c + 1, 4):
            f = a[r, c] / a[c, c]
            for j in range(c, 5):
                a[r, j] -= f * a[c, j]
    x0 = x1 = x2 = x3 = 0.0
    for r in range(3, -1, -1):
        v = a[r, 4]
        for j in range(r + 1, 4):
            v -= a[r, j] * (x0 if j == 0 else x1 if j == 1 else x2 if j == 2 else x3)
        if r == 3:
            x3 = v / a[r, r]
        elif r == 2:
            x2 = v / a[r, r]
        elif r == 1:
            x1 = v / a[r, r]
        else:
            x0 = v / a[r, r]
    ox, oy, oz = 0.5 * x0, 0.5 * x1, 0.5 * x2
    r2 = x3 + ox * ox + oy * oy + oz * oz
    if not r2 > 0.0:
        return False
    rad = math.sqrt(r2)
    xAx = 0.0
    xb = 0.0
    for i in range(4):
        xi = x0 if i == 0 else x1 if i == 1 else x2 if i == 2 else x3
        xb += xi * s[HARD_IRON_B + i]
        for j in range(4):
            xj = x0 if j == 0 else x1 if j == 1 else x2 if j == 2 else x3
            xAx += xi * s[HARD_IRON_A + 4 * i + j] * xj
    res = (s[HARD_IRON_YY] - 2.0 * xb + xAx) / w
    if not res < (2.0 * rad * residual_ut) ** 2:
        return False
    mx, my, mz = s[HARD_IRON_A + 3] / w, s[HARD_IRON_A + 7] / w, s[HARD_IRON_A + 11] / w
    cxx, cxy, cxz = s[HARD_IRON_A + 0] / w - mx * mx, s[HARD_IRON_A + 1] / w - mx * my, s[HARD_IRON_A + 2] / w - mx * mz
    cyy, cyz, czz = s[HARD_IRON_A + 5] / w - my * my, s[HARD_IRON_A + 6] / w - my * mz, s[HARD_IRON_A + 10] / w - mz * mz
    det = cxx * (cyy * czz - cyz * cyz) - cxy * (cxy * czz - cyz * cxz) + cxz * (cxy * cyz - cyy * cxz)
    if not det > (coverage * rad) ** 6:
        return False
    if not ox * ox + oy * oy + oz * oz > residual_ut * residual_ut:
        return False
    out[0], out[1], out[2], out[3] = ox, oy, oz, rad
    return True


@mirrors("fusion.estimators.filters.steps._magnetometer.heading_update", leaf=True)
def heading_update(P, n, N, q, east, north, r, K, G, dx):
    """`_magnetometer.heading_update`: the heading-only update with H = [v^T, 0] (v = R(q)^T e_z), the
    gain restricted to v on the attitude and bias rows and 0 on the velocity rows, Joseph form for a scalar
    measurement, expanded as in `joseph` for a symmetric P: with g = P H^T and s = H P H^T + r,
    P <- P - K g^T - g K^T + s K K^T = P - K g^T + (s K - g) K^T (upper triangle, mirrored); the
    correction into dx (N,) (K, G: (N,) scratch)."""
    vx, vy, vz = gravity_floats(q)
    psi = math.atan2(-east, north)
    for i in range(N):  # g = P H^T
        G[i] = P[i, 0] * vx + P[i, 1] * vy + P[i, 2] * vz
    S = vx * G[0] + vy * G[1] + vz * G[2] + r
    for i in range(N):
        K[i] = G[i] / S
    vk = vx * K[0] + vy * K[1] + vz * K[2]
    K[0], K[1], K[2] = vx * vk, vy * vk, vz * vk
    if n > BIAS_AT:  # the bias rows
        c = BIAS_AT
        vk = vx * K[c] + vy * K[c + 1] + vz * K[c + 2]
        K[c], K[c + 1], K[c + 2] = vx * vk, vy * vk, vz * vk
    for i in range(n, N):
        K[i] = 0.0
    for i in range(N):
        ka = K[i]
        da = S * ka - G[i]
        for c in range(i, N):
            v = P[i, c] - ka * G[c] + da * K[c]
            P[i, c] = v
            P[c, i] = v
    for i in range(N):
        dx[i] = -psi * K[i]
