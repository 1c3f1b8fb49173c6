"""Filter-specific helpers shared by the recursive attitude filters (`ukf`, `ukf-bias`, `ekf`):
covariance square root and repair, a 3x3 inverse, accelerometer gating and disturbance
measure, rest detection and the rest bias update.

Everything here works on one filter step's tiny arrays, so it is written for low per-call
overhead. Quaternion and SO(3) algebra lives in `fusion.quaternion` (its scalar path).

Conventions: quaternions scalar-first `[w, x, y, z]`, `R_world_body`; error rotation vectors
are body-frame (right) perturbations, `q_true = q * exp(e / 2)`, as in
`fusion.quaternion.relative_rotvec`.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf

from fusion import quaternion as quat
from fusion.checks import FreezeDetector

SQRT_FLOOR = 0.0  # eigenvalues of a failed square root are clipped to this (sqrt_psd)
COV_FLOOR = 1e-15  # eigenvalues of a repaired covariance are clipped to this (repair_covariance)
COV_RESET_VAR = 1e-2  # a non-finite covariance is replaced by this times I (repair_covariance)
REST_WINDOW_S = 0.5  # time constant of the rest detector's accelerometer low-pass, s
# Default rest detection (`RestDetector`) of the filters and the smoothers: gyro norm, rad/s;
# accelerometer deviation, g; minimum duration, s.
REST_GYR_RAD_S, REST_ACC_G, REST_TIME_S = 0.035, 0.05, 1.5


def inv_sym3(s: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric 3x3 matrix by its adjugate (numpy.linalg.inv costs more here).

    The caller guarantees positive definiteness (a covariance plus R > 0).
    """
    (a, b, c), (_, d, e), (_, _, f) = s.tolist()
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    return np.array(((A, B, C), (B, D, E), (C, E, F))) / det


def sqrt_psd(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """A square root `L` with `L @ L.T = a` for a symmetric positive semi-definite matrix.

    Cholesky first (fast). If it fails (a singular matrix, e.g. P = Q = 0 in the
    dead-reckoning test, or round-off pushed an eigenvalue below zero), the documented
    recovery: symmetrise, clip negative eigenvalues to zero and return `V sqrt(lambda)`,
    a square root of the nearest PSD matrix. Returns `(L, recovered)`.
    """
    c, info = dpotrf(a, lower=1, clean=1)  # LAPACK Cholesky, without numpy.linalg's overhead
    if info == 0:
        return c, False
    lam, vec = np.linalg.eigh(0.5 * (a + a.T))
    return vec * np.sqrt(np.maximum(lam, SQRT_FLOOR)), True


def repair_covariance(p: np.ndarray, floor: float = COV_FLOOR) -> tuple[np.ndarray, bool]:
    """Symmetrise `p`; if an eigenvalue is below `floor` (or not finite), clip it there.

    Returns `(p, repaired)`. Called after every update so that the covariance handed to
    the next step is symmetric positive definite (the SPD test checks it).
    """
    p = 0.5 * (p + p.T)
    if not math.isfinite(p.sum()):  # one reduction instead of an elementwise test
        return np.eye(len(p)) * COV_RESET_VAR, True
    # Cheap test first: a Cholesky succeeds exactly for SPD matrices.
    if dpotrf(p, lower=1)[1] == 0:
        return p, False
    lam, vec = np.linalg.eigh(p)
    return (vec * np.maximum(lam, floor)) @ vec.T, True


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
    `lag_jacobian` gives the low-passed sample's calibration Jacobians.
    """

    __slots__ = ("window_s", "m", "v", "qi", "age", "lowpass_s", "lowpass_window_s", "lp", "lp_mean", "lp_v",
                 "lowpass_body", "lowpass_density", "lag")

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

    def state(self) -> np.ndarray:
        """(41,) float64, the state as the compiled filters (`_compiled`) carry it: `[has_mean,
        m (3), v, q_I (4, wxyz), age, has_lowpass, lp (3), lp_mean (3), lp_v, has_body,
        lowpass_body (3), lowpass_density, N_b (9), N_s (9)]` (the lag's `LowpassLag.N`, row by
        row; zeros without it); `set_state` takes it back."""
        none3 = (0.0, 0.0, 0.0)
        lag = np.zeros(18) if self.lag is None else self.lag.N.ravel()
        return np.array([float(self.m is not None), *(self.m or none3), self.v, *self.qi, self.age,
                         float(self.lp is not None), *(self.lp or none3), *self.lp_mean, self.lp_v,
                         float(self.lowpass_body is not None),
                         *(none3 if self.lowpass_body is None else self.lowpass_body), self.lowpass_density, *lag])

    def set_state(self, state: np.ndarray) -> None:
        s = [float(v) for v in state]
        self.m = tuple(s[1:4]) if s[0] else None
        self.v, self.qi, self.age = s[4], tuple(s[5:9]), s[9]
        self.lp = tuple(s[11:14]) if s[10] else None
        self.lp_mean, self.lp_v = tuple(s[14:17]), s[17]
        self.lowpass_body = np.array(s[19:22]) if s[18] else None
        self.lowpass_density = s[22]
        if self.lag is not None:
            self.lag.N[:] = np.reshape(state[23:41], (2, 3, 3))

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
            self._lowpass(wx, wy, wz, dt_s)
        if self.lag is not None:
            self.lag.step(self.qi, u, gain, dt_s, fresh, True)
        return max(self.v / seen, inst, nd2)

    def lag_jacobian(self, hx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The low-passed sample's Jacobians `(H_b, H_s)` for the bias and scale errors
        (`LowpassLag.jacobian`), from hx = [h]x (3, 3)."""
        return self.lag.jacobian(hx, self.qi)

    def _lowpass(self, wx: float, wy: float, wz: float, dt_s: float) -> None:
        """Feed a_I (g) to the low-pass; update `lowpass_body` and `lowpass_density`."""
        if self.lp is None:
            self.lp = self.lp_mean = (wx, wy, wz)
        beta = -math.expm1(-dt_s / self.lowpass_s)
        gamma = -math.expm1(-dt_s / self.lowpass_window_s)
        lx, ly, lz = self.lp
        lx, ly, lz = lx + beta * (wx - lx), ly + beta * (wy - ly), lz + beta * (wz - lz)
        self.lp = (lx, ly, lz)
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


def models_lag(p, n: int) -> bool:
    """Whether a filter with parameters `p` (`FilterParams`) and error dimension n models the
    low-pass's lag (`LowpassLag`): it has calibration states and uses the low-passed sample."""
    return n > 3 and p.disturbance_corr_s > 0.0 and p.acc_lowpass_s > 0.0


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


class RestDetector:
    """Rest detection for gyro-bias estimation (after Laidig & Seel 2023, VQF, Sec. 3.4).

    At rest the gyro reads its bias. A sample counts as still when the gyro reading is below
    `gyr_th_rad_s` in norm and the accelerometer is within `acc_th_g` of its low-pass value
    (time constant `window_s`) and within `acc_th_g` of 1 g; the recording is at rest once
    that has held for `min_time_s` without interruption.
    """

    __slots__ = ("gyr_th", "acc_th", "min_time", "window_s", "lp", "time_still")

    def __init__(self, gyr_th_rad_s: float, acc_th_g: float, min_time_s: float, window_s: float = REST_WINDOW_S) -> None:
        self.gyr_th, self.acc_th, self.min_time, self.window_s = gyr_th_rad_s, acc_th_g, min_time_s, window_s
        self.lp: np.ndarray | None = None
        self.time_still = 0.0

    def state(self) -> np.ndarray:
        """(5,) float64 `[has_lowpass, lp (3), time_still]`: the state as the compiled filters
        (`_compiled`) carry it; `set_state` takes it back."""
        lp = np.zeros(3) if self.lp is None else self.lp
        return np.array([float(self.lp is not None), *lp, self.time_still])

    def set_state(self, state: np.ndarray) -> None:
        self.lp = np.array(state[1:4], dtype=float) if state[0] else None
        self.time_still = float(state[4])

    def update(self, gyr_rad_s: np.ndarray, acc_g: np.ndarray, dt_s: float) -> bool:
        """Feed one step (gyro (3,) rad/s, accelerometer (3,) g, body); -> at rest now."""
        if not (math.isfinite(float(acc_g.sum())) and math.isfinite(float(gyr_rad_s.sum()))):
            self.time_still = 0.0
            return False
        if self.lp is None:
            self.lp = np.array(acc_g, dtype=float)
        alpha = -math.expm1(-dt_s / self.window_s)
        dev = acc_g - self.lp
        self.lp = self.lp + alpha * dev
        g = float(gyr_rad_s @ gyr_rad_s)
        a = float(acc_g @ acc_g)
        still = (
            g < self.gyr_th * self.gyr_th
            and float(dev @ dev) < self.acc_th * self.acc_th
            and abs(math.sqrt(a) - 1.0) < self.acc_th
        )
        self.time_still = self.time_still + dt_s if still else 0.0
        return self.time_still >= self.min_time


# ------------------------------------------------------------------ stuck gyro (online)
STUCK_STATE = 21  # `stuck_gyro_update`'s state: see `stuck_gyro_state`
# Its thresholds (window_s, steps, acc_p2p_g): the offline detector's (`FreezeDetector`).
STUCK_THRESHOLDS = (FreezeDetector.window_s, FreezeDetector.gyro_p2p_steps, FreezeDetector.acc_p2p_g)


def stuck_gyro_state() -> np.ndarray:
    """(21,) float64, a fresh state of `stuck_gyro_update`: `[resolution (3), previous reading (3),
    has previous, run's gyro low (3) and high (3), its accelerometer low (3) and high (3),
    run duration s, has run]`; the resolution starts unknown (inf)."""
    state = np.zeros(STUCK_STATE)
    state[:3] = np.inf
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
        s[20] = 0.0
        return False
    if s[6] > 0.0:
        for c in range(3):
            d = abs(gyr[c] - s[3 + c])
            if 0.0 < d < s[c]:
                s[c] = d
    for c in range(3):
        s[3 + c] = gyr[c]
    s[6] = 1.0
    extends = s[20] > 0.0
    for c in range(3):
        if not extends:
            break
        band = max(s[10 + c], gyr[c]) - min(s[7 + c], gyr[c])
        extends = math.isfinite(s[c]) and band <= steps * s[c] * (1.0 + 1e-9)
    if extends:
        for c in range(3):
            s[7 + c] = min(s[7 + c], gyr[c])
            s[10 + c] = max(s[10 + c], gyr[c])
            s[13 + c] = min(s[13 + c], acc[c])
            s[16 + c] = max(s[16 + c], acc[c])
        s[19] += dt_s
    else:
        for c in range(3):
            s[7 + c] = s[10 + c] = gyr[c]
            s[13 + c] = s[16 + c] = acc[c]
        s[19] = 0.0
        s[20] = 1.0
    moved = max(s[16] - s[13], s[17] - s[14], s[18] - s[15])
    return s[19] >= window_s and moved > acc_p2p_g


def bias_rest_update(x_bias: np.ndarray, P: np.ndarray, gyr_rad_s: np.ndarray, r_rad2_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the rest pseudo-measurement `gyr = b + noise` (true rate zero).

    x_bias: (3,) bias estimate, rad/s; P: (n, n) error covariance `[attitude, bias, ...]`
    (the bias in rows 3-5); gyr_rad_s: (3,) the reading at rest; r_rad2_s2: its variance per
    axis, (rad/s)^2. At zero rate the scale factor does not enter the model, so
    H = [0, I, 0] is linear and the standard update is exact for the EKF and the UKF alike
    (the attitude and scale rows move through the cross-covariances). Returns
    `(dx (n,), P)`, with P in Joseph form.
    """
    n = len(P)
    S = P[3:6, 3:6] + np.eye(3) * r_rad2_s2
    K = P[:, 3:6] @ inv_sym3(S)
    dx = K @ (gyr_rad_s - x_bias)
    IKH = np.eye(n)
    IKH[:, 3:6] -= K
    return dx, IKH @ P @ IKH.T + (K * r_rad2_s2) @ K.T


class ScaleTest:
    """Wald's sequential probability ratio test ("Sequential tests of statistical hypotheses",
    Ann. Math. Stat. 16(2), 1945, Sec. 3, with its approximate boundaries (1 - beta) / alpha and
    beta / (1 - alpha) for the likelihood ratio) on the gyro's scale factors: is the scale error
    the size a gyro read with its datasheet sensitivity may have, or is the gyro calibrated?

    H1: the scale corrections s of the estimated axes have the prior N(0, P1 I) the filter starts
    from (`init_scale_var`, 10 %). H0: they have N(0, P0 I), P0 < P1 (`calibrated_scale_var`,
    1 %). The filter runs under H1, and its posterior (s, C) of the estimated axes (k of them)
    summarises what the data say. Changing the prior from P1 to P0 adds the information
    1/P0 - 1/P1: it is the pseudo-measurement `s = 0` with the variance r I, 1/r = 1/P0 - 1/P1
    (exact for the linear Gaussian model), so the likelihood ratio of the data under the two
    priors is that pseudo-measurement's innovation likelihood, up to constants:

        ln L = ln p(data | H1) - ln p(data | H0)
             = 1/2 s^T S^-1 s + 1/2 ln det S + k/2 ln((1 - P0 / P1) / P1),   S = C + r I

    (0 at the start, where C = P1 I and s = 0; it grows when the data show a scale error the
    calibrated prior does not allow, and falls as they pin s near zero). With the error
    probabilities alpha = beta = e, Wald's boundaries are +-ln((1 - e) / e): above the upper one
    the test accepts H1 and stops, the scale states going on as they are; below the lower one it
    accepts H0 and conditions the filter on it, making that pseudo-measurement update once
    (`update`): the scale posterior is then the one the prior P0 would have given. The
    smoothers answer the same question with a likelihood-ratio test of their cost
    (`fusion.estimators.smoother`); this is its sequential form, for a causal filter.
    (`_compiled.scale_test` is the same in the kernel.)
    """

    def __init__(self, prior_var: float, calibrated_var: float, error: float, axes: np.ndarray, first: int = 6):
        self.axes = np.flatnonzero(axes)
        self.rows = first + self.axes  # the scale states' rows in the error state
        self.on = bool(error > 0.0 and len(self.axes) and calibrated_var < prior_var)  # else nothing to test
        self.r = 1.0 / (1.0 / calibrated_var - 1.0 / prior_var) if self.on else math.inf
        self.const = 0.5 * len(self.axes) * math.log((1.0 - calibrated_var / prior_var) / prior_var) if self.on else 0.0
        self.bound = math.log((1.0 - error) / error) if self.on else math.inf
        self.decision = 0  # 0 undecided, 1 a scale error (H1), -1 calibrated (H0)
        self.llr = 0.0 if self.on else math.nan  # ln L of the last step (frozen once decided)

    @classmethod
    def off(cls) -> "ScaleTest":
        """A test that never runs (a filter without scale states)."""
        return cls(1.0, 1.0, 0.0, np.zeros(3, dtype=bool))

    def stop(self) -> None:
        """End the test undecided (a filter given a magnetometer sample; "Scale test" in `ekf`)."""
        if self.decision == 0:
            self.on, self.llr = False, math.nan

    def state(self) -> np.ndarray:
        """(3,) `[on, decision, ln L]`: the state the kernels read and write (`_compiled.scale_test`)."""
        return np.array([float(self.on), float(self.decision), self.llr])

    def set_state(self, state: np.ndarray) -> None:
        self.on, self.decision, self.llr = bool(state[0]), int(state[1]), float(state[2])

    def log_likelihood_ratio(self, s: np.ndarray, P: np.ndarray) -> float:
        """ln L (class docstring) for the scale estimate s (3,) and the error covariance P."""
        y = s[self.axes]
        S = P[np.ix_(self.rows, self.rows)] + self.r * np.eye(len(y))
        return 0.5 * float(y @ np.linalg.solve(S, y) + np.linalg.slogdet(S)[1]) + self.const

    def step(self, s: np.ndarray, P: np.ndarray, vertical: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        """One step of the test while undecided: `(dx, P)`, dx the correction of the error state
        when the test accepts H0 now (the pseudo-measurement update, P in Joseph form), else
        `(None, P)` unchanged. vertical: the body-frame vertical h (3,) of a heading-free filter,
        whose gain then makes no turn about h on the attitude and bias rows (as its
        accelerometer update), or None."""
        if not self.on or self.decision != 0:
            return None, P
        self.llr = self.log_likelihood_ratio(s, P)
        if self.llr >= self.bound:
            self.decision = 1
        elif self.llr <= -self.bound:
            self.decision = -1
            return self.update(s, P, vertical)
        return None, P

    def update(self, s: np.ndarray, P: np.ndarray, vertical: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The pseudo-measurement `s = 0` of variance r I on the tested axes, which turns the
        prior P1 into P0: `(dx, P)` (Joseph form; `vertical` as in `step`)."""
        rows = self.rows
        S = P[np.ix_(rows, rows)] + self.r * np.eye(len(rows))
        K = np.linalg.solve(S, P[rows]).T  # P H^T S^-1, H selecting the rows
        if vertical is not None:
            K[:3] -= np.outer(vertical, vertical @ K[:3])
            K[3:6] -= np.outer(vertical, vertical @ K[3:6])
        dx = K @ -s[self.axes]
        IKH = np.eye(len(P))
        IKH[:, rows] -= K
        return dx, IKH @ P @ IKH.T + self.r * (K @ K.T)


def accelerometer_update_input(p, dist: AccDisturbance, acc_g: np.ndarray, dq: tuple, dt_s: float, scale: float,
                               rate_noise_rad2_s: float, u: np.ndarray | None = None,
                               gain: np.ndarray | None = None) -> tuple[np.ndarray, float, bool]:
    """What one accelerometer update of `ekf`, `ukf` or `ukf-bias` uses: `(z (3,) g, its variance
    per axis g^2, low-passed)`.

    p: the filter's `FilterParams`; dist: its disturbance estimator, advanced here by the step's
    rate increment `dq` with the sample `acc_g` (3,) g; scale: the gate's factor
    (`acc_variance_scale`); rate_noise_rad2_s: the filter's rate noise density, for the frame
    drift and the residual's weight; u, gain: the step's rate for the lag (`AccDisturbance.update`).
    Without the disturbance model: the raw sample and R / dt.
    (`_compiled.measurement` is the same in the kernels.)
    """
    if p.disturbance_corr_s <= 0.0:
        return acc_g, p.acc_noise_g2_s / dt_s * scale, False
    d = dist.update(dq, acc_g, dt_s, u, gain)
    drift = lowpass_drift_density(p.acc_lowpass_s, rate_noise_rad2_s)
    meas, density, lowpassed = acc_measurement(acc_g, dist, p.acc_noise_g2_s, p.disturbance_corr_s, d, drift,
                                               rate_noise_rad2_s)
    return meas, density / dt_s * scale, lowpassed


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


class MagReference:
    """The reference magnetic field (norm and dip), learned from the data while undisturbed, and
    the disturbance gate of the magnetometer's heading update (after the magnetic disturbance
    rejection of Laidig & Seel 2023, VQF, Information Fusion 91, Sec. 3.3: a sample counts only
    while its norm and dip agree with a reference learned from undisturbed samples, and only
    after they have agreed for a minimum time).

    Per magnetometer sample, with m_w = R(q) m the field in the (ENU, z up) world at the current
    estimate: norm `|m|` (uT) and dip `atan2(-m_w,z, |m_w,xy|)` (rad, positive downwards; the
    dip needs the inclination only, which the accelerometer owns). The sample is *in the gates*
    when `| |m| - norm_ref | < norm_gate_frac norm_ref` and `|dip - dip_ref| < dip_gate_rad`.
    In the gates, the references follow the sample: `ref <- ref + (dt / min(T, ref_s)) (x - ref)`
    with T the time spent in the gates so far (a running mean over the first `ref_s` seconds, a
    first-order low-pass of time constant `ref_s` after that); the first sample starts them.
    Out of the gates they stay where they are. The sample may correct the heading once the gates
    have held for `min_undisturbed_s` without interruption (`update` returns True).

    A magnet carried with the sensor adds a constant body-frame offset, whose world-frame norm and
    dip change as the sensor turns: its samples leave the gates and the filter runs on the gyro
    (6-D) until the field is back; a magnet fixed in the room is rejected where its field moves
    the norm or the dip out of the gates.
    """

    __slots__ = ("norm_gate", "dip_gate", "min_time", "ref_s", "has_ref", "norm", "dip", "learn_time", "time_ok")

    def __init__(self, norm_gate_frac: float, dip_gate_rad: float, min_undisturbed_s: float, ref_s: float) -> None:
        self.norm_gate, self.dip_gate, self.min_time, self.ref_s = norm_gate_frac, dip_gate_rad, min_undisturbed_s, ref_s
        self.has_ref = False
        self.norm = self.dip = self.learn_time = self.time_ok = 0.0

    def state(self) -> np.ndarray:
        """(5,) float64 `[has_ref, norm_ref (uT), dip_ref (rad), time learned (s), time in the
        gates (s)]`: the state as the compiled filter carries it; `set_state` takes it back."""
        return np.array([float(self.has_ref), self.norm, self.dip, self.learn_time, self.time_ok])

    def set_state(self, state: np.ndarray) -> None:
        self.has_ref = bool(state[0])
        self.norm, self.dip, self.learn_time, self.time_ok = (float(x) for x in state[1:5])

    def in_gates(self, norm_ut: float, dip_rad: float) -> bool:
        """Whether a sample's norm (uT) and dip (rad) are in the gates of the learned reference
        (False before the first sample)."""
        return self.has_ref and abs(norm_ut - self.norm) < self.norm_gate * self.norm and abs(dip_rad - self.dip) < self.dip_gate

    def update(self, norm_ut: float, dip_rad: float, dt_s: float) -> bool:
        """Feed one sample's norm (uT) and dip (rad) over the step dt_s (s); -> usable now."""
        if not self.has_ref:
            self.has_ref = True
            self.norm, self.dip, self.learn_time, self.time_ok = norm_ut, dip_rad, dt_s, 0.0
            return False
        if self.in_gates(norm_ut, dip_rad):
            self.learn_time += dt_s
            alpha = dt_s / min(self.learn_time, self.ref_s)
            self.norm += alpha * (norm_ut - self.norm)
            self.dip += alpha * (dip_rad - self.dip)
            self.time_ok += dt_s
        else:
            self.time_ok = 0.0
        return self.time_ok >= self.min_time


def field_norm_dip(q: tuple, mag_ut: np.ndarray) -> tuple[float, float, float, float]:
    """The magnetometer sample `mag_ut` (3,) (uT, body) in the world of the estimate q (4 floats,
    `R_world_body`, ENU, z up): `(norm (uT), dip (rad, positive down), east, north)` with
    east, north (uT) its horizontal components."""
    e, n, u = quat.rotate_floats(q, (float(mag_ut[0]), float(mag_ut[1]), float(mag_ut[2])))
    horizontal = math.hypot(e, n)
    return math.sqrt(e * e + n * n + u * u), math.atan2(-u, horizontal), e, n


def heading_update(q: tuple, P: np.ndarray, n: int, east_ut: float, north_ut: float,
                   r_rad2: float) -> tuple[np.ndarray, np.ndarray]:
    """The magnetometer's heading-only Kalman update (`ekf` module docstring, 9-D).

    q: the estimate (4 floats, `R_world_body`, ENU); P: (N, N) error covariance `[attitude (3),
    bias (3), scale (3), velocity (2)]` (the blocks that exist; n = 3, 6 or 9 without the
    velocity); east_ut, north_ut: the horizontal field at the estimate (`field_norm_dip`);
    r_rad2: the heading measurement's variance, rad^2. The measured heading error is the
    angle of the horizontal field from north (magnetic north is the world's +y),
    `psi = atan2(-east, north)`, which is 0 at the true attitude; a turn of the estimate by phi
    about the world vertical turns the field, and psi, by phi, and in the body-frame error state
    that turn is `e = v phi` with `v = R(q)^T e_z`, so `H = [v^T, 0, ...]` (scalar) and the
    innovation is `0 - psi`. The gain is
    restricted to heading (Laidig & Seel 2023, Sec. 3.3: the magnetometer corrects the heading
    only, the accelerometer owns the inclination): `K <- v v^T K` on the attitude and bias
    rows, 0 on the velocity rows; the scale rows keep their gain (a scale error turns the
    heading as the board turns, and the heading innovation measures it through the attitude-
    scale covariance); with that gain the Joseph form
    `P <- (I - K H) P (I - K H)^T + r K K^T` stays exact (Sola 2017, Sec. 6.1-6.3).
    Returns `(dx (N,), P)`.
    """
    N = len(P)
    v = quat.gravity_in_body_floats(*q)
    psi = math.atan2(-east_ut, north_ut)
    H = np.zeros(N)
    H[:3] = v
    PHt = P @ H
    S = float(H @ PHt) + r_rad2
    K = PHt / S
    K[:3] = v * float(v @ K[:3])
    if n > 3:
        K[3:6] = v * float(v @ K[3:6])
    K[n:] = 0.0
    IKH = np.eye(N) - np.outer(K, H)
    P = IKH @ P @ IKH.T + r_rad2 * np.outer(K, K)
    return K * -psi, P


# The hard-iron sphere fit's running sums (`HardIron.state`): A (4 x 4, row by row), b (4),
# sum of y^2, sum of weights.
HARD_IRON_STATE = 22


class HardIron:
    """A magnet carried with the sensor: a constant body-frame offset o (hard iron), estimated
    without the attitude by fitting a sphere to the recent samples (the standard hard-iron
    calibration, e.g. Vasconcelos et al. 2011, "Geometric approach to strapdown magnetometer
    calibration in sensor frame", IEEE TAES 47(2), eqs. 4-6 with the soft iron left out): the
    readings m of a field of constant norm r turned in every direction lie on
    `|m - o|^2 = r^2`, linear in `x = [2 o, r^2 - |o|^2]`: `[m^T, 1] x = |m|^2`.

    Least squares over an exponential window of time constant `window_s` (running sums of the
    normal equations, weight `dt / window_s` per sample, the older ones decaying by
    `1 - dt / window_s`): `A x = b`, `A = sum w [m, 1][m, 1]^T`, `b = sum w [m, 1] |m|^2`. The fit
    is trusted (`fit` returns it) only when the samples cover the sphere (the geometric mean of
    the eigenvalues of their covariance, `det^(1/3)`, at least `(coverage r)^2`), fit it (RMS
    residual `|m - o| - r` under `residual_ut`), its offset exceeds that residual (a smaller one,
    from soft iron or noise, is not told apart) and its radius is that of the reference field
    (checked by the caller). An offset that changes within the window (the magnet comes or goes)
    or a field that is not a sphere (a magnet in the room, passed by) leaves a large residual.
    The 4 x 4 system is solved by Gaussian elimination with partial pivoting written out
    (`solve4`), the same operations as the compiled filter's.
    """

    __slots__ = ("window_s", "residual_ut", "coverage", "s")

    def __init__(self, window_s: float, residual_ut: float, coverage: float) -> None:
        self.window_s, self.residual_ut, self.coverage = window_s, residual_ut, coverage
        self.s = np.zeros(HARD_IRON_STATE)

    def state(self) -> np.ndarray:
        """(22,) float64: the running sums (`HARD_IRON_STATE`); `set_state` takes them back."""
        return self.s.copy()

    def set_state(self, state: np.ndarray) -> None:
        self.s = np.array(state, dtype=float)

    def update(self, mx: float, my: float, mz: float, dt_s: float) -> None:
        """Add one sample (uT, body) over the step dt_s (s)."""
        hard_iron_add(self.s, mx, my, mz, min(dt_s / self.window_s, 1.0))

    def fit(self) -> tuple[float, float, float, float] | None:
        """`(ox, oy, oz, r)` (uT) when the fit is trusted, else None."""
        return hard_iron_fit(self.s, self.residual_ut, self.coverage)


def hard_iron_add(s: np.ndarray, mx: float, my: float, mz: float, alpha: float) -> None:
    """`HardIron.update` on the sums s (22,) in place: s <- (1 - alpha) s + alpha (sample's terms)."""
    x = (mx, my, mz, 1.0)
    y = mx * mx + my * my + mz * mz
    keep = 1.0 - alpha
    for i in range(4):
        for j in range(4):
            s[4 * i + j] = keep * s[4 * i + j] + alpha * x[i] * x[j]
        s[16 + i] = keep * s[16 + i] + alpha * x[i] * y
    s[20] = keep * s[20] + alpha * y * y
    s[21] = keep * s[21] + alpha


def solve4(s: np.ndarray) -> tuple[float, float, float, float] | None:
    """x with A x = b from the sums s (`HardIron`), Gaussian elimination with partial pivoting;
    None when a pivot vanishes."""
    a = [[s[4 * i + j] for j in range(4)] + [s[16 + i]] for i in range(4)]
    for c in range(4):
        p = c
        for r in range(c + 1, 4):
            if abs(a[r][c]) > abs(a[p][c]):
                p = r
        if not abs(a[p][c]) > 0.0:
            return None
        a[c], a[p] = a[p], a[c]
        for r in range(c + 1, 4):
            f = a[r][c] / a[c][c]
            for j in range(c, 5):
                a[r][j] -= f * a[c][j]
    x = [0.0, 0.0, 0.0, 0.0]
    for r in range(3, -1, -1):
        v = a[r][4]
        for j in range(r + 1, 4):
            v -= a[r][j] * x[j]
        x[r] = v / a[r][r]
    return x[0], x[1], x[2], x[3]


def hard_iron_fit(s: np.ndarray, residual_ut: float, coverage: float) -> tuple[float, float, float, float] | None:
    """`HardIron.fit` from the sums s: `(ox, oy, oz, r)` (uT) or None (see `HardIron`)."""
    w = s[21]
    if not w > 0.0:
        return None
    x = solve4(s)
    if x is None:
        return None
    ox, oy, oz = 0.5 * x[0], 0.5 * x[1], 0.5 * x[2]
    r2 = x[3] + ox * ox + oy * oy + oz * oz
    if not r2 > 0.0:
        return None
    r = math.sqrt(r2)
    # weighted mean squared residual of [m, 1] x = |m|^2: (sum y^2 - 2 x.b + x^T A x) / w
    xAx = 0.0
    xb = 0.0
    for i in range(4):
        xb += x[i] * s[16 + i]
        for j in range(4):
            xAx += x[i] * s[4 * i + j] * x[j]
    res = (s[20] - 2.0 * xb + xAx) / w
    # |m|^2 - [m, 1] x = |m - o|^2 - r^2 ~ 2 r (|m - o| - r)
    if not res < (2.0 * r * residual_ut) ** 2:
        return None
    # covariance of the samples: the coverage of the sphere
    mx, my, mz = s[3] / w, s[7] / w, s[11] / w
    cxx, cxy, cxz = s[0] / w - mx * mx, s[1] / w - mx * my, s[2] / w - mx * mz
    cyy, cyz, czz = s[5] / w - my * my, s[6] / w - my * mz, s[10] / w - mz * mz
    det = cxx * (cyy * czz - cyz * cyz) - cxy * (cxy * czz - cyz * cxz) + cxz * (cxy * cyz - cyy * cxz)
    if not det > (coverage * r) ** 6:
        return None
    if not ox * ox + oy * oy + oz * oz > residual_ut * residual_ut:
        return None  # an offset within the fit's residual is not one (soft iron, noise)
    return ox, oy, oz, r


def magnetometer_input(p, mag: MagReference, hard_iron: HardIron, q: tuple, mag_ut, dt_s: float
                       ) -> tuple[bool, float, float, bool]:
    """One magnetometer sample through the gates (`ekf`, `ukf-bias`): `(usable, east, north,
    hard_iron_used)`.

    p: the filter's parameters (`BiasFilterParams`, the mag_* fields); mag, hard_iron: its
    `MagReference` and `HardIron`, advanced here; q: the estimate (4 floats); mag_ut: (3,)
    the finite sample, uT, body; dt_s: the step, s. The sample goes into the sphere fit; while
    the fit is trusted and its radius is the reference norm, the sample without the fitted
    offset replaces it if that is in the gates. `east, north` (uT): its horizontal field at q,
    for `heading_update`.
    """
    norm, dip, east, north = field_norm_dip(q, mag_ut)
    hard_iron_used = False
    if p.mag_hard_iron:
        hard_iron.update(mag_ut[0], mag_ut[1], mag_ut[2], dt_s)
        if mag.has_ref:
            fit = hard_iron.fit()
            if fit is not None and abs(fit[3] - mag.norm) < mag.norm_gate * mag.norm:
                # a carried magnet: the sample without the fitted offset, if that is in the gates
                corrected = field_norm_dip(q, (mag_ut[0] - fit[0], mag_ut[1] - fit[1], mag_ut[2] - fit[2]))
                if mag.in_gates(corrected[0], corrected[1]):
                    norm, dip, east, north = corrected
                    hard_iron_used = True
    usable = mag.update(norm, dip, dt_s) and east * east + north * north > 0.0
    return usable, east, north, hard_iron_used


def heading_variance(p, q: tuple, tx: float, ty: float, tz: float, dt_s: float) -> float:
    """The heading measurement's variance for one step, rad^2: `Rm / dt (1 + (w / mrate)^2)`, w
    the rate about the vertical (the step's rotation (tx, ty, tz), rad, body, over dt_s, on
    `R(q)^T e_z`): a magnetometer that lags the gyro errs by the angle turned over its lag."""
    vx, vy, vz = quat.gravity_in_body_floats(*q)
    w_up = (tx * vx + ty * vy + tz * vz) / dt_s
    return p.mag_heading_noise_rad2_s / dt_s * (1.0 + (w_up / p.mag_rate_rad_s) ** 2)
