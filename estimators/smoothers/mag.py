"""The smoothers' magnetometer (9-D): gated heading measurements, and a heading-only stage.

`gn` and `gd` solve the gyro + accelerometer cost (`fusion.estimators.smoothers.cost`) first; on
a recording with a magnetometer, its samples are turned into heading measurements at that 6-D
solution (`measurements`: eqs. 1-2, the gates and the hard-iron fit below). The magnetometer
corrects the heading, and only the heading (the accelerometer owns the inclination: Laidig &
Seel 2023, "VQF: Highly accurate IMU orientation estimation with bias estimation and magnetic
disturbance rejection", Information Fusion 91, Sec. 3.3, where the magnetometer's correction is
a rotation about the world's vertical), in one of two ways (`SmootherParams.mag_term`): as a
term of the batch cost, solved again from the 6-D solution (`smoothers.cost`, the magnetometer
term; the default), or in the stage of `heading_correction` below, a second, scalar smoothing
problem on the 6-D solution.

Measurement. With q_t the 6-D solution (`R_world_body`, ENU, z up) and m_t the magnetometer
sample (uT, body), the field in the world is m_w,t = R(q_t) m_t; its horizontal components
(east e_t, north n_t) give the heading error of q_t against magnetic north (the world's +y),

    psi_t = atan2(-e_t, n_t)                                                       (1)

(0 at the true attitude; turning the estimate by phi about the world vertical turns psi by phi,
as in the filters' `_magnetometer.heading_update`). Its variance is that of a white heading noise of
density Rm (rad^2 s) over the time dt_t the sample stands for, grown with the rate about the
vertical w_up,t = (R(q_t)^T e_z) . w_t (a magnetometer lagging the gyro errs by the angle turned
over its lag; the filters' `_magnetometer.heading_variance`):

    r_t = Rm / dt_t (1 + (w_up,t / mrate)^2)                                       (2)

Gates (the disturbance rejection of VQF, Laidig & Seel 2023, Sec. 3.3, made offline). A sample's
norm |m_t| and dip atan2(-m_w,z, |m_w,xy|) are compared with a reference learned from the
recording's own samples: the median norm and dip, then the median over the samples within the
gates of that (twice), which is robust to disturbances over less than half the recording. A
sample is in the gates when its norm is within `mag_norm_gate_frac` of the reference norm and
its dip within `mag_dip_gate_rad`; it counts (weight 1, else 0) only inside an uninterrupted run
of in-gate samples at least `mag_min_undisturbed_s` long (VQF's minimum undisturbed time,
looked at on both sides since the stage is offline).

A magnet carried with the sensor (hard iron: a constant body-frame offset o) moves the samples
out of the gates. Each disturbed stretch (out-of-gate samples, gaps shorter than the minimum
undisturbed time merged) is fitted with a sphere, |m - o|^2 = r^2, linear in [2 o, r^2 - |o|^2]
(the filters' `_magnetometer.hard_iron_fit`, after Vasconcelos et al. 2011, "Geometric approach to
strapdown magnetometer calibration in sensor frame", IEEE TAES 47(2), eqs. 4-6 without soft
iron), over the whole stretch and, if that is not trusted, over windows of
`mag_hard_iron_window_s`. A fit is trusted on the filters' terms (coverage of the sphere, RMS
residual, an offset above the residual) and when its radius is the reference norm; every sample
it covers is then used with o removed if that is in the gates, and not at all otherwise (a raw
sample that passes the gates by chance still carries the offset). Without a trusted fit the
stretch stays gated out.

Heading-error smoother (`heading_correction`). The 6-D heading error is modelled as a random
walk of density Qm (`mag_heading_walk_rad2_s`: the gyro's noise about the vertical and
what the 6-D cost leaves unmodelled there, the z gyro's scale error and its bias between rests):

    e_{t+1} = e_t + w_t,   w_t ~ N(0, Qm dt_t);   e_0 ~ N(0, P0)          (3)

(P0: the anchor variance of the 6-D cost, `init_var_rad2`: the given start is trusted as much as
there), observed by psi_t = e_t + v_t, v_t ~ N(0, r_t / (g_t k_t)), g_t the gate weight (0 or 1)
and k_t a robust weight. The posterior mean of e given all samples is the Kalman filter run
forward followed by the Rauch-Tung-Striebel backward pass (Rauch, Tung & Striebel 1965,
"Maximum likelihood estimates of linear dynamic systems", AIAA Journal 3(8), the smoother's
recursion; for a scalar random walk, with filtered mean/variance m_t, P_t and predicted
P_{t+1|t} = P_t + Qm dt_t: C_t = P_t / P_{t+1|t},
s_t = m_t + C_t (s_{t+1} - m_t), S_t = P_t + C_t^2 (S_{t+1} - P_{t+1|t})). Innovations are
wrapped to (-pi, pi]. The robust weights come from iteratively reweighted least squares with
the Huber loss on the residual wrap(psi_t - s_t) at scale `mag_loss_scale_rad` (`k_t` =
`smoothers.cost.robust_loss`'s rho', the same loss family as the accelerometer's term).
The minimised cost is therefore

    1/2 sum_t (e_{t+1} - e_t)^2 / (Qm dt_t) + 1/2 e_0^2 / P0
      + 1/2 sum_t g_t dt_t / (Rm (1 + (w_up,t / mrate)^2)) c^2 rho(|psi_t - e_t|^2 / c^2).

Correction (`heading_correction`). q_t <- Rz(-s_t) q_t: a rotation about the world vertical on
the left, so the inclination (R(q_t)^T e_z) is unchanged. A recording without a magnetometer
never reaches either (the 6-D result is returned as it is).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fusion import quaternion as quat
from fusion.checks import runs
from fusion.quaternion import rotation_matrix
from fusion.types import ImuSamples

from ..filters.steps._magnetometer import hard_iron_fit
from .cost import robust_loss, sample_durations

# IRLS passes of the heading-error smoother (the robust weights settle in a few).
IRLS_PASSES = 4


@dataclass(frozen=True)
class MagSettings:
    """The magnetometer stage's settings (`SmootherParams`' mag_* fields; see the module docstring).

    heading_noise_rad2_s: Rm, density of the heading measurement, rad^2 s.
    heading_walk_rad2_s: Qm, density of the 6-D heading error's random walk, rad^2/s.
    init_var_rad2: P0, variance of the heading error at the first sample, rad^2.
    rate_rad_s: mrate of eq. (2), rad/s (inf: constant variance).
    loss, loss_scale_rad: robust loss on the heading residual and its scale, rad.
    norm_gate_frac, dip_gate_rad, min_undisturbed_s: the gates.
    hard_iron: fit a carried magnet; hard_iron_window_s, hard_iron_residual_ut, hard_iron_coverage:
        the fit's windows (s), residual bound (uT) and coverage (fraction of the radius).
    """

    heading_noise_rad2_s: float
    heading_walk_rad2_s: float
    init_var_rad2: float
    rate_rad_s: float
    loss: str
    loss_scale_rad: float
    norm_gate_frac: float
    dip_gate_rad: float
    min_undisturbed_s: float
    hard_iron: bool
    hard_iron_window_s: float
    hard_iron_residual_ut: float
    hard_iron_coverage: float


def world_field(q: np.ndarray, mag_ut: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The samples mag_ut (T, 3) (uT, body) in the world of q (T, 4): (norm (T,) uT, dip (T,) rad
    positive down, east (T,) uT, north (T,) uT)."""
    m_w = (rotation_matrix(q) @ mag_ut[:, :, None])[:, :, 0]
    horizontal = np.hypot(m_w[:, 0], m_w[:, 1])
    return np.linalg.norm(m_w, axis=1), np.arctan2(-m_w[:, 2], horizontal), m_w[:, 0], m_w[:, 1]


def reference(norm: np.ndarray, dip: np.ndarray, s: MagSettings) -> tuple[float, float]:
    """(norm uT, dip rad) of the undisturbed field: the medians over the samples given, then
    twice over those within the gates of the previous reference."""
    ref_n, ref_d = float(np.median(norm)), float(np.median(dip))
    for _ in range(2):
        inside = in_gates(norm, dip, ref_n, ref_d, s)
        if not inside.any():
            break
        ref_n, ref_d = float(np.median(norm[inside])), float(np.median(dip[inside]))
    return ref_n, ref_d


def in_gates(norm: np.ndarray, dip: np.ndarray, ref_norm: float, ref_dip: float, s: MagSettings) -> np.ndarray:
    return (np.abs(norm - ref_norm) < s.norm_gate_frac * ref_norm) & (np.abs(dip - ref_dip) < s.dip_gate_rad)


def long_runs(mask: np.ndarray, t: np.ndarray, min_s: float) -> np.ndarray:
    """mask (T,) with the runs of True shorter than min_s seconds (first to last sample) cleared."""
    out = np.zeros_like(mask)
    for a, b in runs(mask):
        if t[b - 1] - t[a] >= min_s:
            out[a:b] = True
    return out


def sphere_fit(mag_ut: np.ndarray, s: MagSettings) -> tuple[float, float, float, float] | None:
    """The hard-iron sphere fit `(ox, oy, oz, r)` (uT) of the samples mag_ut (K, 3), uT, body,
    equally weighted (the sums of the filters' `_magnetometer.HardIron` as plain means over the
    samples), or None when it is not trusted (`_magnetometer.hard_iron_fit`)."""
    x = np.column_stack([mag_ut, np.ones(len(mag_ut))])  # [m, 1]
    y = np.sum(mag_ut**2, axis=1)  # |m|^2
    sums = np.concatenate([(x.T @ x).ravel(), x.T @ y, [y @ y, len(y)]]) / len(y)  # `HardIron`'s sums, as means
    return hard_iron_fit(sums, s.hard_iron_residual_ut, s.hard_iron_coverage)


def heading_smoother(psi: np.ndarray, info: np.ndarray, walk_var: np.ndarray, init_var: float
                     ) -> np.ndarray:
    """The RTS smoother of the scalar random walk of eq. (3).

    psi: (T,) measured heading errors, rad; info: (T,) their information 1 / variance, rad^-2
    (0: no measurement); walk_var: (T-1,) the walk's variance over each step, rad^2; init_var:
    the prior variance of e_0, rad^2 (prior mean 0). Returns the smoothed means (T,), rad.
    Innovations are wrapped to (-pi, pi].
    """
    T = len(psi)
    m = np.empty(T)
    P = np.empty(T)
    mean, var = 0.0, init_var
    psi_l, info_l, walk_l = psi.tolist(), info.tolist(), walk_var.tolist()
    for t in range(T):
        if t:
            var += walk_l[t - 1]
        w = info_l[t]
        if w > 0.0:
            gain = var * w / (1.0 + var * w)  # P / (P + r), r = 1 / w
            innovation = math.remainder(psi_l[t] - mean, 2.0 * math.pi)
            mean += gain * innovation
            var *= 1.0 - gain
        m[t], P[t] = mean, var
    s = m.copy()
    m_l, P_l = m.tolist(), P.tolist()
    nxt = m_l[-1]
    for t in range(T - 2, -1, -1):
        c = P_l[t] / (P_l[t] + walk_l[t])
        nxt = m_l[t] + c * (nxt - m_l[t])
        s[t] = nxt
    return s


def measurements(imu: ImuSamples, q: np.ndarray, s: MagSettings) -> tuple[np.ndarray, np.ndarray, dict]:
    """The gated heading measurements of the magnetometer at the 6-D solution q (T, 4) (module
    docstring, eqs. 1-2 and the gates): (psi (T,) rad, their information g_t / r_t (T,) rad^-2,
    0 where a sample is not used, diagnostics). Diagnostics: "mag_used" (T,) bool (gate weight
    1), "mag_hard_iron" (T,) bool (used with a fitted offset removed), "mag_reference" (norm uT,
    dip rad), "mag_hard_iron_fits" (list of (start, stop, ox, oy, oz, r)).
    imu: the samples, with a magnetometer (`imu.has_mag`); q: unit quaternions, `R_world_body`.
    """
    T = len(q)
    t = np.asarray(imu.t, float)
    valid = np.asarray(imu.mag_valid, bool) & np.all(np.isfinite(imu.mag_ut), axis=1)
    mag = np.where(valid[:, None], imu.mag_ut, 0.0)  # a new array: the input is not touched
    norm, dip, east, north = world_field(q, mag)
    used = np.zeros(T, bool)
    hard = np.zeros(T, bool)
    fits: list[tuple] = []
    ref_n = ref_d = math.nan
    if valid.any():
        ref_n, ref_d = reference(norm[valid], dip[valid], s)
        inside = valid & in_gates(norm, dip, ref_n, ref_d, s)
        if s.hard_iron:
            # Disturbed stretches: out of the gates, gaps shorter than the minimum undisturbed time merged.
            out = valid & ~inside
            calm = long_runs(~out, t, s.min_undisturbed_s)
            for a, b in runs(~calm):
                pieces = [(a, b)]
                fit = sphere_fit(mag[a:b][valid[a:b]], s) if valid[a:b].sum() >= 10 else None
                if fit is None:
                    edges = np.searchsorted(t[a:b], np.arange(t[a], t[b - 1], s.hard_iron_window_s)) + a
                    pieces = list(zip(edges.tolist(), edges[1:].tolist() + [b]))
                for c, d in pieces:
                    ok = valid[c:d]
                    if ok.sum() < 10:
                        continue
                    fit = sphere_fit(mag[c:d][ok], s) if len(pieces) > 1 else fit
                    if fit is None or not abs(fit[3] - ref_n) < s.norm_gate_frac * ref_n:
                        continue
                    fits.append((c, d) + tuple(fit))
                    corrected = mag[c:d] - np.array(fit[:3])
                    cn, cd, ce, cnn = world_field(q[c:d], corrected)
                    # The magnet is there over the whole piece: every sample of it is used with the
                    # offset removed if that is in the gates, and not at all otherwise (a raw sample
                    # that happens to pass the gates still carries the offset).
                    good = ok & in_gates(cn, cd, ref_n, ref_d, s)
                    idx = np.flatnonzero(good) + c
                    norm[idx], dip[idx], east[idx], north[idx] = cn[good], cd[good], ce[good], cnn[good]
                    inside[c:d] = good
                    hard[c:d] = good
        used = long_runs(inside & (east**2 + north**2 > 0.0), t, s.min_undisturbed_s)
    hard &= used
    diagnostics = {"mag_used": used, "mag_hard_iron": hard, "mag_reference": (ref_n, ref_d),
                   "mag_hard_iron_fits": fits}
    if not used.any():
        return np.zeros(T), np.zeros(T), diagnostics
    psi = np.arctan2(-east, north)  # eq. (1)
    # eq. (2): the rate about the vertical from the gyro (the interval rates; the last sample takes the last step's)
    rate, _ = imu.interval_rates()
    rate = np.concatenate([rate, rate[-1:]]) if len(rate) else np.zeros((T, 3))
    w_up = np.sum(quat.gravity_in_body(q) * np.nan_to_num(rate), axis=1)  # R(q)^T e_z: the vertical, body
    dt = sample_durations(t)
    base_info = np.where(used, dt / (s.heading_noise_rad2_s * (1.0 + (w_up / s.rate_rad_s) ** 2)), 0.0)
    return psi, base_info, diagnostics


def heading_correction(imu: ImuSamples, q: np.ndarray, s: MagSettings) -> tuple[np.ndarray, dict]:
    """The 9-D heading correction of the 6-D solution q (T, 4) (module docstring).

    imu: the samples, with a magnetometer (`imu.has_mag`); q: unit quaternions, `R_world_body`.
    Returns the corrected (T, 4) quaternions (a new array) and diagnostics: those of
    `measurements` and "mag_heading_correction_rad" (T,) (s_t: the heading error removed).
    """
    T = len(q)
    t = np.asarray(imu.t, float)
    psi, base_info, diagnostics = measurements(imu, q, s)
    if not diagnostics["mag_used"].any():
        diagnostics["mag_heading_correction_rad"] = np.zeros(T)
        return np.array(q, dtype=float), diagnostics
    walk_var = s.heading_walk_rad2_s * np.diff(t)
    init_var = s.init_var_rad2
    robust = np.ones(T)
    c2 = s.loss_scale_rad**2
    for _ in range(IRLS_PASSES if s.loss != "none" else 1):
        smoothed = heading_smoother(psi, base_info * robust, walk_var, init_var)
        if s.loss == "none":
            break
        residual = np.remainder(psi - smoothed + np.pi, 2.0 * np.pi) - np.pi
        _, robust = robust_loss(s.loss, residual**2 / c2)
    smoothed = heading_smoother(psi, base_info * robust, walk_var, init_var) if s.loss != "none" else smoothed
    diagnostics["mag_heading_correction_rad"] = smoothed
    turn = quat.from_rotvec(np.stack([np.zeros(T), np.zeros(T), -smoothed], axis=1))  # Rz(-s_t), world frame
    return quat.normalize(quat.multiply(turn, q)), diagnostics
