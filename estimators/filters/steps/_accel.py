"""The accelerometer as a measurement of gravity: gating, the external-acceleration
(disturbance) estimate, the low-pass in a gyro-only frame and its lag, and the choice between the
raw and the low-passed sample (`ekf`, `ukf`, `ukf-bias`).

Contract: the accelerometer reads `R_world_body^T (e_z + a_ext)` in g (body frame); the filters
treat gravity's direction as the measurement and `a_ext` as noise whose density this module
estimates without the filter's attitude. `accelerometer_update_input` is what one update uses:
the sample (raw or low-passed, (3,) g, body) and its variance per axis (g^2).

Papers: Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation with bias
estimation and magnetic disturbance rejection", Information Fusion 91, Sec. 3.2 (the strapdown
frame `I` and the low-pass there, eq. 7) and Sec. 3.4 (the bias observed through the low-passed
signal); Sabatini 2006, IEEE Trans. Biomed. Eng. 53(7) (the |a| - g norm test); Suh 2010, IEEE
TIM 59(12) (R adapted to the external acceleration).

`AccDisturbance.state()` packs the estimator into one float64 array of `DIST_STATE` numbers, the
state the compiled filters carry (`_compiled_accel`); its layout is the `DIST_*` offsets below,
which both sides import.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from fusion import quaternion as quat

# The layout of `AccDisturbance.state()` (offsets into the (DIST_STATE,) float64 array; a flag is
# 1.0 or 0.0, a vector of 3 or 4 starts at its offset). Read and written by `AccDisturbance.state`,
# `set_state` and the kernels of `_compiled_accel`.
DIST_HAS_MEAN = 0  # flag: the running mean m exists (not after `lose_frame`)
DIST_MEAN = 1  # m (3), g, strapdown frame
DIST_VAR = 4  # v, g^2: running variance about m
DIST_FRAME = 5  # q_I (4, wxyz): the strapdown frame
DIST_AGE = 9  # s since the (re)start
DIST_HAS_LOWPASS = 10  # flag: the low-pass has started
DIST_LOWPASS = 11  # lp (3), g: a_I low-passed
DIST_LOWPASS_MEAN = 14  # its slower mean (3), g
DIST_LOWPASS_VAR = 17  # its running variance about that mean, g^2
DIST_HAS_BODY = 18  # flag: lowpass_body is available
DIST_BODY = 19  # lowpass_body (3), unit, body frame
DIST_DENSITY = 22  # lowpass_density, g^2 s
DIST_LOWPASS_NORM = 23  # lp_norm, g: | |a| - 1 | low-passed
DIST_LAG_B = 24  # LowpassLag.N[0] = N_b (3 x 3, row by row)
DIST_LAG_S = 33  # LowpassLag.N[1] = N_s (3 x 3, row by row)
DIST_STATE = 42  # the array's length


def acc_variance_scale(acc_g: np.ndarray, gate: str, gate_g: float) -> float:
    """How much to scale R for this accelerometer sample (accelerometer gating).

    `| |a| - 1 g |` measures how far the sample is from the gravity-only model.
    gate "off": 1 (always use). "skip": inf (skip the update) when the deviation exceeds
    `gate_g`, else 1. "inflate": `1 + (dev / gate_g)^2`, a smooth down-weighting that
    leaves near-static samples untouched. Non-finite samples always give inf (skip).
    """
    ax, ay, az = float(acc_g[0]), float(acc_g[1]), float(acc_g[2])
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if not math.isfinite(norm):
        return math.inf
    if gate == "off":
        return 1.0
    dev = abs(norm - 1.0)
    if gate == "skip":
        return math.inf if dev > gate_g else 1.0
    r = dev / gate_g
    return 1.0 + r * r


class AccDisturbance:
    """Running estimate of the external (non-gravitational) acceleration power, for adaptive R.

    The accelerometer measures `R^T (e_z + a_ext)` (g). The filters treat the gravity
    direction as the measurement and `a_ext` as noise, but `a_ext` of a moving hand is neither
    white nor small. This tracks, per step, its power `d` (g^2) from signals that do not
    depend on the filter's attitude estimate (so an attitude error, e.g. after a gyro
    freeze, is never mistaken for a disturbance and cannot lock the accelerometer out):

    * the variance of the accelerometer rotated into a gyro-only (strapdown) frame `I`, the
      frame of Laidig & Seel 2023 (VQF), Sec. 3.2, in which gravity is constant over a few
      seconds while linear, centripetal and tapping accelerations are not. `I` is propagated
      with the filter's rate increments (bias and scale corrected) and never corrected by the
      accelerometer. Exponential window of time constant `window_s`:
      `m <- m + alpha (a_I - m)`, `v <- v + alpha (|a_I - m_prev|^2 - v)`,
      `alpha = 1 - exp(-dt / window_s)`, so the window means the same at any rate;
    * the norm test `(|a| - 1)^2` of the current sample (Sabatini 2006's |a|-g criterion),
      which reacts in the first sample of a tap.

    `d = max(v / (1 - exp(-age / window_s)), |a_I - m_prev|^2, (|a| - 1)^2)`, where the
    divisor corrects the window's start at v = 0 (age: time since the start). On a gyro sample
    that cannot be integrated the frame `I` is lost and the window restarts.

    The filters model `a_ext` as a first-order Gauss-Markov process of variance `d` and
    correlation time `corr_s`, whose low-frequency spectral density is `2 corr_s d` (g^2 s);
    it adds to the accelerometer noise density (see `acc_measurement`).

    With `lowpass_s > 0` it also low-passes `a_I` (first order, time constant `lowpass_s`),
    as VQF does before its inclination correction (Laidig & Seel 2023, Sec. 3.2, eq. 7). The
    acceleration of a body whose velocity stays bounded averages out in `I`, while gravity,
    constant there, passes: `lowpass_body` is the low-passed direction rotated back into the
    body frame (a unit vector, a measurement of gravity's direction), and `lowpass_density`
    (g^2 s) the low-frequency density of what is left of `a_ext` in it, `2 lowpass_s v_lp`
    from the running variance `v_lp` of the low-passed signal about its own slower mean
    (time constant `lowpass_window_s`): a white noise of density S low-passed with time
    constant tau has the variance S / (2 tau). See `acc_measurement` for how a filter
    chooses between the raw sample and this one.

    With `lag=True` (and `lowpass_s > 0`) it also carries the low-pass's lag behind a frame that
    drifts with a gyro bias or scale error (`LowpassLag`), advanced with the frame: `update` and
    `turn` then take the step's bias-corrected rate `u` and scale gain `1 + s`, and
    `lag_jacobian` gives the low-passed sample's calibration Jacobians. `slow_power` then measures
    the external acceleration that the window misses: a sustained one changes little within it.
    """

    __slots__ = ("window_s", "m", "v", "qi", "age", "lowpass_s", "lowpass_window_s", "lp", "lp_mean", "lp_v",
                 "lowpass_body", "lowpass_density", "lp_norm", "lag")

    def __init__(self, window_s: float, lowpass_s: float = 0.0, lowpass_window_s: float = 3.0,
                 lag: bool = False) -> None:
        self.window_s = window_s
        self.lowpass_s, self.lowpass_window_s = lowpass_s, lowpass_window_s
        self.qi = (1.0, 0.0, 0.0, 0.0)
        self.lag = LowpassLag(lowpass_s) if lag and lowpass_s > 0.0 else None
        self.lose_frame()

    def lose_frame(self) -> None:
        """The gyro sample could not be integrated: restart the window."""
        self.m: tuple[float, float, float] | None = None
        self.v = 0.0
        self.age = 0.0
        self.lp: tuple[float, float, float] | None = None  # low-passed a_I
        self.lp_mean = (0.0, 0.0, 0.0)  # its slower mean
        self.lp_v = 0.0  # its running variance about that mean, g^2
        self.lowpass_body: np.ndarray | None = None  # (3,) unit, body frame; None: not yet available
        self.lowpass_density = math.inf  # g^2 s
        self.lp_norm = 0.0  # | |a| - 1 | low-passed, g

    def state(self) -> np.ndarray:
        """(DIST_STATE,) float64, the state as the compiled filters (`_compiled_accel`) carry it,
        laid out by the `DIST_*` offsets (the lag's `LowpassLag.N` row by row, zeros without it);
        `set_state` takes it back."""
        st = np.zeros(DIST_STATE)
        if self.m is not None:
            st[DIST_HAS_MEAN] = 1.0
            st[DIST_MEAN:DIST_MEAN + 3] = self.m
        st[DIST_VAR], st[DIST_FRAME:DIST_FRAME + 4], st[DIST_AGE] = self.v, self.qi, self.age
        if self.lp is not None:
            st[DIST_HAS_LOWPASS] = 1.0
            st[DIST_LOWPASS:DIST_LOWPASS + 3] = self.lp
        st[DIST_LOWPASS_MEAN:DIST_LOWPASS_MEAN + 3], st[DIST_LOWPASS_VAR] = self.lp_mean, self.lp_v
        if self.lowpass_body is not None:
            st[DIST_HAS_BODY] = 1.0
            st[DIST_BODY:DIST_BODY + 3] = self.lowpass_body
        st[DIST_DENSITY] = self.lowpass_density
        if self.lag is not None:
            st[DIST_LAG_B:DIST_STATE] = self.lag.N.ravel()
        st[DIST_LOWPASS_NORM] = self.lp_norm
        return st

    def set_state(self, state: np.ndarray) -> None:
        s = [float(v) for v in state]
        self.m = tuple(s[DIST_MEAN:DIST_MEAN + 3]) if s[DIST_HAS_MEAN] else None
        self.v, self.qi, self.age = s[DIST_VAR], tuple(s[DIST_FRAME:DIST_FRAME + 4]), s[DIST_AGE]
        self.lp = tuple(s[DIST_LOWPASS:DIST_LOWPASS + 3]) if s[DIST_HAS_LOWPASS] else None
        self.lp_mean, self.lp_v = tuple(s[DIST_LOWPASS_MEAN:DIST_LOWPASS_MEAN + 3]), s[DIST_LOWPASS_VAR]
        self.lowpass_body = np.array(s[DIST_BODY:DIST_BODY + 3]) if s[DIST_HAS_BODY] else None
        self.lowpass_density = s[DIST_DENSITY]
        if self.lag is not None:
            self.lag.N[:] = np.reshape(state[DIST_LAG_B:DIST_STATE], (2, 3, 3))
        self.lp_norm = s[DIST_LOWPASS_NORM]

    def turn(self, dq: tuple, dt_s: float = 0.0, u: np.ndarray | None = None, gain: np.ndarray | None = None) -> None:
        """Advance the frame by the rate increment `dq` (4 floats, body) of a step without an
        accelerometer sample (skipped or gated), so that the frame keeps following the gyro;
        dt_s, u, gain: the step and its rate for the lag (see `update`)."""
        fresh = self.lp is None
        self._turn(dq)
        if self.lag is not None:
            self.lag.step(self.qi, u, gain, dt_s, fresh, False)

    def _turn(self, dq: tuple) -> None:
        self.qi = quat.normalize_floats(quat.multiply_floats(self.qi, dq))

    def update(self, dq: tuple, acc_g: np.ndarray, dt_s: float, u: np.ndarray | None = None,
               gain: np.ndarray | None = None) -> float:
        """Advance the frame by the rate increment `dq` (4 floats, body), feed `acc_g` (3,), g; -> d, g^2.

        u (3,): the step's bias-corrected rate (None: the gyro sample was not integrated, which
        restarts the low-pass), gain (3,): `1 + s`; used only with the lag (`LowpassLag.step`).
        """
        ax, ay, az = float(acc_g[0]), float(acc_g[1]), float(acc_g[2])
        fresh = self.lp is None  # the low-pass (re)starts with this sample: no lag yet
        self._turn(dq)
        wx, wy, wz = quat.rotate_floats(self.qi, (ax, ay, az))  # a_I = R(q_I) a (body -> strapdown frame)
        norm_dev = math.sqrt(ax * ax + ay * ay + az * az) - 1.0
        nd2 = norm_dev * norm_dev
        if self.m is None:
            self.m = (wx, wy, wz)
        mx, my, mz = self.m
        ex, ey, ez = wx - mx, wy - my, wz - mz
        inst = ex * ex + ey * ey + ez * ez
        alpha = -math.expm1(-dt_s / self.window_s)
        self.m = (mx + alpha * ex, my + alpha * ey, mz + alpha * ez)
        self.v += alpha * (inst - self.v)
        self.age += dt_s
        # Weight of the samples seen since the (re)start, 1 - exp(-age / window_s): dividing by
        # it makes v the mean over the samples available so far instead of starting at 0.
        seen = -math.expm1(-self.age / self.window_s)
        if self.lowpass_s > 0.0:
            self._lowpass(wx, wy, wz, abs(norm_dev), dt_s)
        if self.lag is not None:
            self.lag.step(self.qi, u, gain, dt_s, fresh, True)
        return max(self.v / seen, inst, nd2)

    def lag_jacobian(self, hx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The low-passed sample's Jacobians `(H_b, H_s)` for the bias and scale errors
        (`LowpassLag.jacobian`), from hx = [h]x (3, 3)."""
        return self.lag.jacobian(hx, self.qi)

    def slow_power(self, hx: np.ndarray, P_cal: np.ndarray, scale_prior_var: float) -> float:
        """The power (g^2) of the external acceleration slower than the variance window and
        faster than the low-pass: the squared deviation `|m - lp|^2` of the window's mean from the
        low-passed signal (both in the frame I), less what the filter's calibration uncertainty
        explains. A sustained acceleration (a slow translation) moves the window's mean away from
        the low-pass while the window's variance `v` stays small; but so does the frame's drift
        with a bias or scale error, which the low-pass trails by its lag (`LowpassLag`): with the
        lag's Jacobians `H_c = [H_b, H_s]` (`lag_jacobian`, from hx = [h]x (3, 3)) and the
        filter's calibration covariance P_cal ((3, 3) bias, or (6, 6) bias and scale), the
        expected squared lag is `trace(H_c P_cal H_c^T) + scale_prior_var |H_s|_F^2`. The second
        term gives every rate a relative error of the scale prior's size (`init_scale_var`; `ekf`
        passes 0 without scale states, where the gyro is declared calibrated) that the posterior
        does not remove: what a gyro's misalignment, cross-axis sensitivity
        and nonlinearity turn into frame drift is outside the calibration model, and it grows
        with the rate, as the drift of a fast-turning body does. What the low-pass still holds
        of gross samples (a saturated stretch, an impact) is explained too, by at least the
        low-passed norm deviation `lp_norm^2` (|a - e_z| >= | |a| - 1 |, sample by sample). Only
        the excess counts; 0 until the low-pass has run for its time constant (it starts at one
        sample, whose disturbance it carries), and without the lag."""
        if self.lag is None or self.lp is None or self.m is None or self.age < self.lowpass_s:
            return 0.0
        (mx, my, mz), (lx, ly, lz) = self.m, self.lp
        dev = (mx - lx) ** 2 + (my - ly) ** 2 + (mz - lz) ** 2
        H_b, H_s = self.lag_jacobian(hx)
        H_c = H_b if P_cal.shape[0] == 3 else np.hstack((H_b, H_s))
        explained = float(np.trace(H_c @ P_cal @ H_c.T)) + scale_prior_var * float(np.sum(H_s * H_s))
        explained += self.lp_norm * self.lp_norm
        return max(0.0, dev - explained)

    def _lowpass(self, wx: float, wy: float, wz: float, norm_dev: float, dt_s: float) -> None:
        """Feed a_I (g) and its norm deviation `| |a| - 1 |` (g) to the low-pass; update
        `lowpass_body`, `lowpass_density` and `lp_norm` (the norm deviation low-passed alike)."""
        if self.lp is None:
            self.lp = self.lp_mean = (wx, wy, wz)
            self.lp_norm = norm_dev
        beta = -math.expm1(-dt_s / self.lowpass_s)
        gamma = -math.expm1(-dt_s / self.lowpass_window_s)
        lx, ly, lz = self.lp
        lx, ly, lz = lx + beta * (wx - lx), ly + beta * (wy - ly), lz + beta * (wz - lz)
        self.lp = (lx, ly, lz)
        self.lp_norm += beta * (norm_dev - self.lp_norm)
        mx, my, mz = self.lp_mean
        ex, ey, ez = lx - mx, ly - my, lz - mz
        self.lp_mean = (mx + gamma * ex, my + gamma * ey, mz + gamma * ez)
        self.lp_v += gamma * (ex * ex + ey * ey + ez * ez - self.lp_v)
        seen = -math.expm1(-self.age / self.lowpass_window_s)
        self.lowpass_density = 2.0 * self.lowpass_s * self.lp_v / seen
        w, x, y, z = self.qi
        bx, by, bz = quat.rotate_floats((w, -x, -y, -z), (lx, ly, lz))  # back into the body frame
        norm = math.sqrt(bx * bx + by * by + bz * bz)
        self.lowpass_body = np.array((bx / norm, by / norm, bz / norm)) if norm > 0.0 else None


class LowpassLag:
    """How the low-passed accelerometer direction of `AccDisturbance` depends on the gyro
    calibration errors: the lag of the low-pass behind gravity's drift in the strapdown frame.

    The frame I turns with the corrected rate `w_c = diag(1 + s) (w_meas - b)`, the body with
    the true one. A bias error db and a scale error ds (error state: true = estimate + error)
    leave the rate error `dw = diag(u) ds - diag(1 + s) db`, u = w_meas - b, and gravity in I
    moves by `g_I x (R_I dw) dt` per step (R_I = R(q_I), body to I). The first-order low-pass
    (gain beta) lags it by the deficit `D = g_I - lp`, `D <- (1 - beta) (D + dg_I)`, so
    `D = g_I x (N_s ds - N_b db)` with

        N <- (1 - beta) (N + R_I J dt),   J = diag(u) for N_s, diag(1 + s) for N_b,

    and without the decay on a step whose sample did not enter the low-pass. Rotated back into
    the body, the low-passed direction is `g_b - [g_b]x R_I^T (N_s ds - N_b db)`: with
    `g_b = h + [h]x e` (`ekf`'s attitude error) it measures the calibration errors through

        H = [[h]x, [h]x R_I^T N_b, -[h]x R_I^T N_s]

    instead of adding their drift to its noise (`lowpass_drift_density`). VQF (Laidig & Seel
    2023, Sec. 3.4) likewise estimates the bias in motion from the low-passed signal. The
    state `N = [N_b, N_s]` (2, 3, 3) lives in the `AccDisturbance` whose frame it follows.
    """

    __slots__ = ("lowpass_s", "N")

    def __init__(self, lowpass_s: float) -> None:
        self.lowpass_s = lowpass_s
        self.N = np.zeros((2, 3, 3))

    def step(self, qi: tuple, u: np.ndarray | None, gain: np.ndarray, dt_s: float, fresh: bool,
             lowpassed: bool) -> None:
        """One step: qi the frame's quaternion after it (4 floats), u (3,) the bias-corrected
        rate, gain (3,) `1 + s`; fresh: the low-pass started at this sample (no lag; a step
        whose gyro sample was not integrated always restarts it, and passes u None);
        lowpassed: the sample entered the low-pass (else no decay)."""
        if fresh:
            self.N[:] = 0.0
            return
        RI = quat.rotation_matrix_floats(*qi)
        self.N[0] += RI * (gain * dt_s)
        self.N[1] += RI * (u * dt_s)
        if lowpassed:
            self.N *= math.exp(-dt_s / self.lowpass_s)

    def jacobian(self, hx: np.ndarray, qi: tuple) -> tuple[np.ndarray, np.ndarray]:
        """The low-passed direction's Jacobians `(H_b, H_s)` (3, 3) for the bias and scale
        errors, from hx = [h]x (3, 3) and the frame's quaternion qi."""
        A = hx @ quat.rotation_matrix_floats(*qi).T
        return A @ self.N[0], -(A @ self.N[1])


def models_lag(p, bias: bool) -> bool:
    """Whether a filter with parameters `p` (`FilterParams`) models the low-pass's lag
    (`LowpassLag`): it has calibration states (`bias`: the bias block, `ErrorLayout.bias`) and uses
    the low-passed sample."""
    return bias and p.disturbance_corr_s > 0.0 and p.acc_lowpass_s > 0.0


def lowpass_drift_density(lowpass_s: float, rate_noise_rad2_s: float) -> float:
    """Density (g^2 s) of the strapdown frame's random drift within the low-pass window.

    The frame `I` of `AccDisturbance` turns with the filter's corrected rates. Over one window
    the rate noise (density q, rad^2/s) turns it away from the world by an angle of variance
    `lowpass_s q`; gravity's low-passed direction turns with it (an angle of e rad moves a 1 g
    vector by e g), and as an error of correlation time `lowpass_s` its low-frequency density
    is twice `lowpass_s` times that variance. The drift that a bias or scale error causes is
    not noise: the filters with those states model it in the measurement (`LowpassLag`).
    """
    return 2.0 * lowpass_s * (lowpass_s * rate_noise_rad2_s)


def lowpass_residual_density(density_g2_s: float, lowpass_s: float, rate_noise_rad2_s: float) -> float:
    """The density (g^2 s) with which a filter should weigh what is left of the external
    acceleration in the low-passed sample, from its Gauss-Markov density `density_g2_s`
    (`AccDisturbance.lowpass_density`, `2 lowpass_s v_lp`).

    The Gauss-Markov model treats the residual as a noise that averages out like a white one
    beyond its correlation time: its mean over a window T has the variance
    `density_g2_s / T`. But the external acceleration of a body whose velocity stays bounded
    is a derivative, and its mean over T is a change of velocity divided by T: for motion no
    slower than the low-pass (residual of variance v_lp, velocity excursions of about
    `lowpass_s sqrt(v_lp)`), the variance of that mean is about `2 v_lp lowpass_s^2 / T^2`,
    smaller by `lowpass_s / T`. A filter with process noise density Q (rad^2/s) averages a
    measurement of density L over about `T = sqrt(L / Q)`: the steady-state Kalman filter of a
    random walk (step variance Q dt) observed in white noise (variance L / dt) has the gain
    sqrt(Q / L) dt per step when that is small. The density whose mean over T has the
    bounded-velocity variance is `L = density_g2_s lowpass_s / T`; with `T = sqrt(L / Q)`,
    `L = (density_g2_s lowpass_s sqrt(Q))^(2/3)`. It applies where T exceeds `lowpass_s`
    (`density_g2_s > lowpass_s^2 Q`, where the two expressions meet); below, and without
    process noise (no finite T), the Gauss-Markov density stands.
    """
    if rate_noise_rad2_s <= 0.0 or not density_g2_s > lowpass_s * lowpass_s * rate_noise_rad2_s:
        return density_g2_s
    return (density_g2_s * lowpass_s * math.sqrt(rate_noise_rad2_s)) ** (2.0 / 3.0)


def acc_measurement(acc_g: np.ndarray, dist: AccDisturbance, density_g2_s: float, corr_s: float, d_g2: float,
                    drift_g2_s: float, rate_noise_rad2_s: float) -> tuple[np.ndarray, float, bool]:
    """The accelerometer measurement of one update and its noise density: `(z (3,) g, density
    g^2 s, lowpassed)`.

    The raw sample `acc_g` has the density `density_g2_s + 2 corr_s d_g2` (white noise plus
    the external acceleration, see `AccDisturbance`); the low-passed one
    `density_g2_s + lowpass_residual_density(dist.lowpass_density, ...) + drift_g2_s` (what is
    left of the external acceleration, as a filter with the rate noise density
    `rate_noise_rad2_s` sees it, plus the frame drift of `lowpass_drift_density`). The one with the smaller
    density is used: the raw sample while the body is quiet or the gyro still uncalibrated
    (it answers at once), the low-passed one through sustained translation, tapping and
    vibration (it averages them out). Either is a measurement of gravity in the body frame
    for the same update equations.
    """
    raw = density_g2_s + 2.0 * corr_s * d_g2
    if dist.lowpass_body is not None:
        residual = lowpass_residual_density(dist.lowpass_density, dist.lowpass_s, rate_noise_rad2_s)
        lowpassed = density_g2_s + residual + drift_g2_s
        if lowpassed < raw:
            return dist.lowpass_body, lowpassed, True
    return acc_g, raw, False


class AccStep(NamedTuple):
    """What one accelerometer update takes of its step (`accelerometer_update_input`; the kernels'
    `_compiled_accel.AccStep` has the same fields in the same order)."""

    dq: tuple  # the step's rate increment exp(theta / 2), 4 floats, body frame
    dt: float  # the step, s
    scale: float  # the gate's factor on the variance (`acc_variance_scale`)
    rate_noise: float  # the filter's rate noise density, rad^2/s: the frame's drift, the residual's weight
    u: Any  # the lag's input (`AccDisturbance.update`): the bias-corrected rate (3,), rad/s, or None
    gain: Any  # ... and the scale gain `1 + s` (3,), or None


class SlowDisturbance(NamedTuple):
    """The slow external acceleration's inputs (`AccDisturbance.slow_power`; the kernels'
    `_compiled_accel.SlowDisturbance` has the same fields in the same order)."""

    corr_s: float  # its correlation time, s (`ekf`'s `slow_disturbance_corr_s`); 0: none
    h: Any  # (3,) gravity's direction in the body frame at the estimate
    P_cal: Any  # the error covariance's calibration block, (3, 3) bias or (6, 6) bias and scale
    scale_prior_var: float  # the scale prior's variance (`init_scale_var`; 0 without scale states)

    @classmethod
    def none(cls) -> "SlowDisturbance":
        return cls(corr_s=0.0, h=None, P_cal=None, scale_prior_var=0.0)


def accelerometer_update_input(dist: AccDisturbance, acc_g: np.ndarray, step: AccStep, slow: SlowDisturbance,
                               p) -> tuple[np.ndarray, float, bool]:
    """What one accelerometer update of `ekf`, `ukf` or `ukf-bias` uses: `(z (3,) g, its variance
    per axis g^2, low-passed)`.

    dist: the filter's disturbance estimator, advanced here by the step's rate increment
    `step.dq` with the sample `acc_g` (3,) g; step.scale: the gate's factor
    (`acc_variance_scale`); step.rate_noise: the filter's rate noise density, for the frame
    drift and the residual's weight; step.u, step.gain: the step's rate for the lag
    (`AccDisturbance.update`). slow.corr_s > 0 (`ekf`'s `slow_disturbance_corr_s`, with the lag):
    the external acceleration has a second, slow component, of power
    `AccDisturbance.slow_power([h]x, P_cal, scale_prior_var)` and correlation time slow.corr_s,
    whose density `2 corr_s d_slow` the raw sample's noise takes where it exceeds the fast one's
    `2 disturbance_corr_s d` (the larger of the two). p: the filter's `FilterParams`. Without the
    disturbance model: the raw sample and R / dt.
    (`_compiled_accel.accelerometer_update_input` is the same in the kernels.)
    """
    if p.disturbance_corr_s <= 0.0:
        return acc_g, p.acc_noise_g2_s / step.dt * step.scale, False
    d = dist.update(step.dq, acc_g, step.dt, step.u, step.gain)
    if slow.corr_s > 0.0:  # as the power of the fast process with the same density
        d = max(d, dist.slow_power(quat.skew(slow.h), slow.P_cal, slow.scale_prior_var)
                * (slow.corr_s / p.disturbance_corr_s))
    drift = lowpass_drift_density(p.acc_lowpass_s, step.rate_noise)
    meas, density, lowpassed = acc_measurement(acc_g, dist, p.acc_noise_g2_s, p.disturbance_corr_s, d, drift,
                                               step.rate_noise)
    return meas, density / step.dt * step.scale, lowpassed
