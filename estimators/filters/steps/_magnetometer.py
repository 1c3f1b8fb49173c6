"""The magnetometer's heading update (`ekf`, `ukf-bias`, 9-D): the reference field and its
disturbance gates, the hard-iron sphere fit, and the heading-only Kalman update.

Contract: `magnetometer_input` takes one finite sample (3,) uT, body frame, and the estimate
`R_world_body` (ENU world, z up, magnetic north along +y) and says whether it may correct the
heading, with its horizontal field (east, north) at the estimate; `heading_update` is then the
Kalman update of the heading only, with `heading_variance` as its variance.

Papers: Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation with bias estimation
and magnetic disturbance rejection", Information Fusion 91, Sec. 3.3 (heading-only correction;
disturbance rejection by the field's norm and dip); Vasconcelos et al. 2011, "Geometric approach
to strapdown magnetometer calibration in sensor frame", IEEE TAES 47(2), eqs. 4-6 (the sphere fit,
hard iron only); Sola 2017, "Quaternion kinematics for the error-state Kalman filter", Sec.
6.1-6.3 (the Joseph form).

`MagReference.state()` and `HardIron.state()` pack their states into `MAG_STATE` and
`HARD_IRON_STATE` float64 numbers (the `MAG_*` and `HARD_IRON_*` offsets below), the states the
compiled filters carry (`_compiled_magnetometer`).
"""
from __future__ import annotations

import math

import numpy as np

from fusion import quaternion as quat

from ._error_state import ATTITUDE, BIAS, ErrorLayout

# The layout of `MagReference.state()`: offsets into the (MAG_STATE,) float64 array.
MAG_HAS_REF = 0  # flag: the reference has been started
MAG_NORM = 1  # the reference norm, uT
MAG_DIP = 2  # the reference dip, rad
MAG_LEARNED = 3  # time spent learning it, s
MAG_TIME_OK = 4  # time in the gates without interruption, s
MAG_PSI = 5  # the heading gate's low-passed innovation, rad
MAG_REJECTED = 6  # time the heading gate has rejected without interruption, s
MAG_STATE = 7
# The heading gate's bound on the normalised innovation squared: the chi-square distribution's
# 99.9 % quantile with one degree of freedom (scipy.stats.chi2.ppf(0.999, 1)).
HEADING_GATE_CHI2 = 10.827566170662733
# The layout of `HardIron.state()`, the sphere fit's running sums: A (4 x 4, row by row), b (4),
# sum of y^2, sum of weights.
HARD_IRON_A = 0
HARD_IRON_B = 16
HARD_IRON_YY = 20
HARD_IRON_W = 21
HARD_IRON_STATE = 22


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

    A field whose direction bends while its norm and dip do not (a magnet or steel in the room, off
    the sensor's path of turns) passes both gates; the *heading gate* (`heading_gate`) catches it
    by its innovation, the classical innovation gate of a Kalman filter (Bar-Shalom, Li &
    Kirubarajan 2001, "Estimation with Applications to Tracking and Navigation", Sec. 5.4.2, the
    normalised innovation squared against a chi-square bound). The heading innovation psi of each
    sample that passed the gates is low-passed (time constant `heading_gate_s`, which averages the
    sensor's white noise away); the sample may correct the heading while
    `psi_lp^2 < HEADING_GATE_CHI2 (H P H^T + sigma^2)`, with H P H^T the filter's own heading
    variance and sigma (`heading_gate_rad`) the field direction's tolerated slow deviation (the
    heading measurement's variance Rm / dt models a white error, which a bent field is not).
    Recovery: after `heading_gate_max_s` of rejection without interruption the field is believed
    again (the heading, not the field, may be what is wrong: a gyro bias turns it in that time),
    and the samples correct the heading until the innovation is back inside the bound.
    `heading_gate_rad = inf` turns the heading gate off.
    """

    __slots__ = ("norm_gate", "dip_gate", "min_time", "ref_s", "heading_gate", "heading_gate_s", "heading_gate_max_s",
                 "has_ref", "norm", "dip", "learn_time", "time_ok", "psi", "rejected")

    def __init__(self, norm_gate_frac: float, dip_gate_rad: float, min_undisturbed_s: float, ref_s: float,
                 heading_gate_rad: float = math.inf, heading_gate_s: float = 1.0,
                 heading_gate_max_s: float = math.inf) -> None:
        self.norm_gate, self.dip_gate, self.min_time, self.ref_s = norm_gate_frac, dip_gate_rad, min_undisturbed_s, ref_s
        self.heading_gate, self.heading_gate_s, self.heading_gate_max_s = (heading_gate_rad, heading_gate_s,
                                                                           heading_gate_max_s)
        self.has_ref = False
        self.norm = self.dip = self.learn_time = self.time_ok = self.psi = self.rejected = 0.0

    @classmethod
    def of(cls, p) -> "MagReference":
        """The reference and gates of a filter's parameters (`BiasFilterParams`, the mag_* fields)."""
        return cls(p.mag_norm_gate_frac, p.mag_dip_gate_rad, p.mag_min_undisturbed_s, p.mag_ref_s,
                   p.mag_heading_gate_rad, p.mag_heading_gate_s, p.mag_heading_gate_max_s)

    def state(self) -> np.ndarray:
        """(MAG_STATE,) float64, laid out by the `MAG_*` offsets: the state as the compiled filters
        carry it (`_compiled_magnetometer`); `set_state` takes it back."""
        st = np.zeros(MAG_STATE)
        st[MAG_HAS_REF], st[MAG_NORM], st[MAG_DIP] = float(self.has_ref), self.norm, self.dip
        st[MAG_LEARNED], st[MAG_TIME_OK] = self.learn_time, self.time_ok
        st[MAG_PSI], st[MAG_REJECTED] = self.psi, self.rejected
        return st

    def set_state(self, state: np.ndarray) -> None:
        self.has_ref = bool(state[MAG_HAS_REF])
        self.norm, self.dip = float(state[MAG_NORM]), float(state[MAG_DIP])
        self.learn_time, self.time_ok = float(state[MAG_LEARNED]), float(state[MAG_TIME_OK])
        self.psi, self.rejected = float(state[MAG_PSI]), float(state[MAG_REJECTED])

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

    def heading_gate_update(self, psi_rad: float, heading_var_rad2: float, dt_s: float) -> bool:
        """Feed the heading innovation psi_rad (rad, `heading_innovation`) of a sample that passed
        the gates, with the filter's heading variance H P H^T (rad^2), over the step dt_s (s);
        -> the sample may correct the heading (see the class docstring)."""
        self.psi += min(dt_s / self.heading_gate_s, 1.0) * (psi_rad - self.psi)
        if self.psi * self.psi < HEADING_GATE_CHI2 * (heading_var_rad2 + self.heading_gate * self.heading_gate):
            self.rejected = 0.0
            return True
        self.rejected += dt_s
        return self.rejected > self.heading_gate_max_s


def field_norm_dip(q: tuple, mag_ut: np.ndarray) -> tuple[float, float, float, float]:
    """The magnetometer sample `mag_ut` (3,) (uT, body) in the world of the estimate q (4 floats,
    `R_world_body`, ENU, z up): `(norm (uT), dip (rad, positive down), east, north)` with
    east, north (uT) its horizontal components."""
    e, n, u = quat.rotate_floats(q, (float(mag_ut[0]), float(mag_ut[1]), float(mag_ut[2])))
    horizontal = math.hypot(e, n)
    return math.sqrt(e * e + n * n + u * u), math.atan2(-u, horizontal), e, n


def heading_innovation(q: tuple, P: np.ndarray, east_ut: float, north_ut: float) -> tuple[float, float]:
    """`(psi, H P H^T)`: the heading innovation's negative, the angle of the horizontal field from
    north (rad; `heading_update`), and the filter's heading variance (rad^2), for the heading gate
    (`MagReference.heading_gate_update`)."""
    v = quat.gravity_in_body_floats(*q)
    return math.atan2(-east_ut, north_ut), float(v @ P[ATTITUDE, ATTITUDE] @ v)


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
    layout = ErrorLayout.of(n, N - n)
    v = quat.gravity_in_body_floats(*q)
    psi = math.atan2(-east_ut, north_ut)
    H = np.zeros(N)
    H[ATTITUDE] = v
    PHt = P @ H
    S = float(H @ PHt) + r_rad2
    K = PHt / S
    K[ATTITUDE] = v * float(v @ K[ATTITUDE])
    if layout.bias:
        K[BIAS] = v * float(v @ K[BIAS])
    K[layout.velocity] = 0.0
    IKH = np.eye(N) - np.outer(K, H)
    P = IKH @ P @ IKH.T + r_rad2 * np.outer(K, K)
    return K * -psi, P


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
        """(HARD_IRON_STATE,) float64: the running sums (the `HARD_IRON_*` offsets); `set_state`
        takes them back."""
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
    """`HardIron.update` on the sums s (HARD_IRON_STATE,) in place: s <- (1 - alpha) s + alpha (sample's terms)."""
    x = (mx, my, mz, 1.0)
    y = mx * mx + my * my + mz * mz
    keep = 1.0 - alpha
    for i in range(4):
        for j in range(4):
            s[HARD_IRON_A + 4 * i + j] = keep * s[HARD_IRON_A + 4 * i + j] + alpha * x[i] * x[j]
        s[HARD_IRON_B + i] = keep * s[HARD_IRON_B + i] + alpha * x[i] * y
    s[HARD_IRON_YY] = keep * s[HARD_IRON_YY] + alpha * y * y
    s[HARD_IRON_W] = keep * s[HARD_IRON_W] + alpha


def solve4(s: np.ndarray) -> tuple[float, float, float, float] | None:
    """x with A x = b from the sums s (`HardIron`), Gaussian elimination with partial pivoting;
    None when a pivot vanishes."""
    a = [[s[HARD_IRON_A + 4 * i + j] for j in range(4)] + [s[HARD_IRON_B + i]] for i in range(4)]
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
    w = s[HARD_IRON_W]
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
        xb += x[i] * s[HARD_IRON_B + i]
        for j in range(4):
            xAx += x[i] * s[HARD_IRON_A + 4 * i + j] * x[j]
    res = (s[HARD_IRON_YY] - 2.0 * xb + xAx) / w
    # |m|^2 - [m, 1] x = |m - o|^2 - r^2 ~ 2 r (|m - o| - r)
    if not res < (2.0 * r * residual_ut) ** 2:
        return None
    # covariance of the samples: the coverage of the sphere
    mx, my, mz = s[HARD_IRON_A + 3] / w, s[HARD_IRON_A + 7] / w, s[HARD_IRON_A + 11] / w
    cxx, cxy, cxz = s[HARD_IRON_A + 0] / w - mx * mx, s[HARD_IRON_A + 1] / w - mx * my, s[HARD_IRON_A + 2] / w - mx * mz
    cyy, cyz, czz = s[HARD_IRON_A + 5] / w - my * my, s[HARD_IRON_A + 6] / w - my * mz, s[HARD_IRON_A + 10] / w - mz * mz
    det = cxx * (cyy * czz - cyz * cyz) - cxy * (cxy * czz - cyz * cxz) + cxz * (cxy * cyz - cyy * cxz)
    if not det > (coverage * r) ** 6:
        return None
    if not ox * ox + oy * oy + oz * oz > residual_ut * residual_ut:
        return None  # an offset within the fit's residual is not one (soft iron, noise)
    return ox, oy, oz, r


def magnetometer_input(p, mag: MagReference, hard_iron: HardIron, q: tuple, P: np.ndarray, mag_ut, dt_s: float
                       ) -> tuple[bool, float, float, bool]:
    """One magnetometer sample through the gates (`ekf`, `ukf-bias`): `(usable, east, north,
    hard_iron_used)`.

    p: the filter's parameters (`BiasFilterParams`, the mag_* fields); mag, hard_iron: its
    `MagReference` and `HardIron`, advanced here; q: the estimate (4 floats); P: its error
    covariance (the attitude block first); mag_ut: (3,) the finite sample, uT, body; dt_s: the
    step, s. The sample goes into the sphere fit; while the fit is trusted and its radius is the
    reference norm, the sample without the fitted offset replaces it if that is in the gates. A
    sample that passed the norm and dip gates then meets the heading gate
    (`MagReference.heading_gate_update`). `east, north` (uT): its horizontal field at q, for
    `heading_update`.
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
    if usable:
        usable = mag.heading_gate_update(*heading_innovation(q, P, east, north), dt_s)
    return usable, east, north, hard_iron_used


def heading_variance(p, q: tuple, tx: float, ty: float, tz: float, dt_s: float) -> float:
    """The heading measurement's variance for one step, rad^2: `Rm / dt (1 + (w / mrate)^2)`, w
    the rate about the vertical (the step's rotation (tx, ty, tz), rad, body, over dt_s, on
    `R(q)^T e_z`): a magnetometer that lags the gyro errs by the angle turned over its lag."""
    vx, vy, vz = quat.gravity_in_body_floats(*q)
    w_up = (tx * vx + ty * vy + tz * vz) / dt_s
    return p.mag_heading_noise_rad2_s / dt_s * (1.0 + (w_up / p.mag_rate_rad_s) ** 2)
