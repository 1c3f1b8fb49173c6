"""`ekf`: a multiplicative (error-state) EKF with gyro bias and scale factors in the state.

Contract: `EKF.step` (the reference, numpy) takes one gyro interval (rate (3,) rad/s, body; dt s;
its validity), the accelerometer sample at its end ((3,) g, body) and optionally the magnetometer
sample ((3,) uT, body), and returns `R_world_body` (wxyz) after it; `estimate` runs the same loop
over a recording, compiled by default (`_compiled_ekf.estimate`, the same numbers to 1e-10:
`tests/test_compiled.py`). How well each choice below does on the recordings, with the commands
that measure it: `docs/results.md`, "`ekf`'s choices, measured".

State. Nominal: `q = R_world_body` (wxyz), gyro bias `b` (rad/s, body), gyro scale-factor
corrections `s` (per body axis) and the horizontal velocity `v` (m/s, world, ENU). Error state
`dx = [e, db, ds, dv]` (11) with the body-frame rotation error `q_true = q exp(e / 2)` (the
convention of `ukf`), covariance P (11 x 11; without the scale, the bias or the velocity model,
the blocks that remain, in this order).

Gyro model (Titterton & Weston, "Strapdown Inertial Navigation Technology", 2nd ed. 2004, Ch. 4;
Farrell, "Aided Navigation", 2008): `w_true = diag(1 + s) (w_meas - b - n)`, n white with density
Q. `s` is the *correction*: a gyro that reads 9 % high has s = 1/1.09 - 1 = -0.083.

Predict (gyro as control input; Sola 2017, "Quaternion kinematics for the error-state Kalman
filter", Secs. 5.3-5.4, in discrete time, with the exact rotation of the step instead of its
first-order approximation):
    u = w_meas - b,  theta = diag(1 + s) u dt,  q <- q exp(theta / 2)
    F = [[R(theta)^T, -J_r(theta) diag(1 + s) dt, J_r(theta) diag(u) dt],
         [0,          I,                            0                   ],
         [0,          0,                            I                   ]]
        (J_r the SO(3) right Jacobian: a rate error dw over the step moves the end attitude by
        J_r(theta) dw dt in the body frame)
    P <- F P F^T + diag(Q dt, Qb dt, Qsw dt)   (random impulses whose variance grows with dt,
        Sola 2017, Sec. 5.4)
Rest (bias rows; `_rest`): after `rest_time_s` still, the zero-rate pseudo-measurement
    gyr = b + n, H = [0, I, 0] (Laidig & Seel 2023, "VQF", Information Fusion 91, Sec. 3.4);
    the bias estimate is clipped to `bias_max_rad_s`, the scale to `scale_max`.
Update (accelerometer = gravity in the body frame; Sola 2017, Secs. 6.1-6.3: correction,
injection, reset with the reset Jacobian taken as I; `_accel`):
    h(q) = R(q)^T e_z (g),  H = [[h]x, 0, 0]          (exp(e)^T h ~ h + h x e)
    R_k = (R + max(2 tauc d_k, 2 tauslow d_slow)) / dt I   adaptive: d_k the external-acceleration
                  power of `_accel.AccDisturbance`, measured without the filter's attitude (Suh 2010,
                  IEEE TIM 59(12), adapts R to the external acceleration); d_slow its slow part, which
                  the 0.5 s window misses (a sustained acceleration, as of a slow translation, changes
                  little within it): the squared deviation of the window's mean from the low-pass in
                  the strapdown frame, less what the calibration explains, trace(H_c P_c H_c^T) with
                  the lag's Jacobians H_c = [H_b, H_s] below and, with scale states, the scale prior
                  added to P_ss (the rate errors the model lacks), and less the low-passed norm deviation squared (what
                  the low-pass holds of gross samples) (`_accel.AccDisturbance.slow_power`); a
                  Gauss-Markov process of correlation time tauslow (2 s), after the external-
                  acceleration state of Lee, Park & Robinovitch 2012, IEEE TIM 61(8), but as noise
    a <- the accelerometer low-passed in the gyro-only strapdown frame (VQF, Sec. 3.2, eq. 7),
                  rotated back into the body, with R_k = (R + S_lp + S_drift) / dt, whenever
                  that density is the smaller (`_accel.acc_measurement`). S_lp is the residual
                  external acceleration (`_accel.lowpass_residual_density`), S_drift the rate
                  noise's drift of the frame; the lag by which the low-pass trails gravity when
                  the frame drifts with a bias or scale error is modelled, not added as noise:
                  H = [[h]x, H_b, H_s] (`_accel.LowpassLag`)
    S = H P H^T + R_k,  K = P H^T S^-1,  dx = K (a - h)
    heading_free: K <- (I - h h^T) K on the attitude and bias rows (no turn about the
                  predicted vertical; the Joseph form below is exact for any gain)
    guard: with NIS = y^T S^-1 y above the 99.9 % point of chi-square(3) (Bar-Shalom, Li &
                  Kirubarajan 2001, Sec. 5.4), the bias and scale rows of K are zero
    q <- q exp(dx_e / 2),  b <- b + dx_b,  s <- s + dx_s
    P <- (I - K H) P (I - K H)^T + K R_k K^T             (Joseph form)
The scale factors become observable through the accelerometer whenever the board turns about a
body axis that is not vertical (the z scale needs the z axis tilted while turning).

Velocity (after the prediction, before the rest and accelerometer updates; off with
`velocity_bound_m2_s` = inf or `use_acc` = False): a hand-held, worn or carried IMU moves with a
bounded velocity, so the horizontal specific force, integrated, must stay bounded too: the
smoothers' velocity model (`fusion.estimators.smoothers.cost`), after what VQF exploits with its
low-pass in an almost inertial frame (Sec. 3.2), as states of the filter (strapdown velocity
integration, Titterton & Weston 2004, Ch. 3; Sola 2017, Sec. 5.3.3 for its error-state Jacobian):
    v <- v + (R(q) a)_xy g dt,   P <- V P V^T,  V = I but dv/de = -(R(q) [a]x)_xy g dt
        (white acceleration noise of variance density Qv g^2 in Q: Qv g^2 dt on v)
    pseudo-measurement v = 0 with the variance Rv / dt (density Rv), H = [0, 0, 0, I],
        heading-free gain and Joseph form as for the accelerometer
A tilt error e turns 1 g into the horizontal acceleration g e, which a bounded velocity cannot
absorb for long, while a linear acceleration that averages out over seconds can: the velocity
states follow the translation (`tests/test_ekf.py`) instead of the attitude taking it for gravity.
With them, the low-passed sample corrects the attitude and the velocity, not the gyro bias and
scale (`lowpass_calibration`, `lpcal`, False; their gain rows are zero, which the Joseph form keeps
exact): the velocity integrates the same samples that the low-pass averages, and taken as two
independent measurements of the calibration they would count that information twice. Without the
velocity states the low-passed sample is the only correction of the calibration in motion and
keeps it.

Scale test (6-D; after the updates of each step, until it decides; `scale_test_error` (sprt) = 0
turns it off; `_scale_test.ScaleTest`): Wald's sequential probability ratio test (Wald 1945,
"Sequential tests of statistical hypotheses", Ann. Math. Stat. 16(2), Sec. 3) between H1:
s ~ N(0, Ps0 I), the prior of a gyro read with its datasheet sensitivity, and H0: s ~ N(0, Psc I),
Psc = 1e-4 (1 %), a calibrated gyro. Exchanging the prior is a pseudo-measurement `s = 0` of
variance r I, 1/r = 1/Psc - 1/Ps0, so the log-likelihood ratio is, up to constants,
    ln L = 1/2 s^T S^-1 s + 1/2 ln det S + k/2 ln((1 - Psc/Ps0) / Ps0),  S = P_ss + r I
(k the number of scale axes, P_ss their covariance). With alpha = beta = sprt (0.1), above
ln((1 - alpha) / alpha) = 2.2 the test accepts the scale error and stops; below -2.2 it accepts the
calibrated gyro and makes the pseudo-measurement update once (heading-free gain and Joseph form as
above). Until it decides, the filter is the one without the test (`tests/test_ekf.py` checks the
expression against the two priors' evidence computed directly). At the first magnetometer sample
the test ends undecided: the 9-D filter keeps the 10 % prior, whose scale rows the heading update
corrects.

Magnetometer (9-D, where the recording has one: `ImuSamples.mag_ut`; after the accelerometer
update, with the sample at the step's end; `_magnetometer`). The world is ENU (x east, y north,
z up). The accelerometer owns the inclination; the magnetometer corrects the heading only (VQF,
Sec. 3.3):
    m_w = R(q) m = (east, north, up),  psi = atan2(-east, north)      (0 at the true heading)
    v = R(q)^T e_z (the vertical in the body frame): a turn by phi about the world vertical is
        the error e = v phi and turns psi by phi, so H = [v^T, 0, 0, 0] (scalar)
    r_k = Rm / dt (1 + (w_up / mrate)^2),  w_up = (theta . v) / dt the rate about the vertical
        (a magnetometer sampled late or low-passed errs by the angle turned over its lag)
    S = H P H^T + r_k,  K = P H^T / S,  then K <- v v^T K on the attitude and bias rows (heading
        only) and 0 on the velocity rows; the scale rows keep theirs,  dx = K (0 - psi)
    q <- q exp(dx_e / 2), b <- b + dx_b, s <- s + dx_s;  P <- (I - K H) P (I - K H)^T + r_k K K^T
        (Joseph form, exact for the restricted gain; Sola 2017, Secs. 6.1-6.3)
Disturbances (`_magnetometer.MagReference`, VQF Sec. 3.3): the reference norm |m| and dip
atan2(-up, |(east, north)|) are learned while the samples agree with them; a sample counts while
|norm - ref| < mnorm ref and |dip - ref| < mdip, and only after that has held for `mtime` s. A
magnet carried with the sensor adds a constant body-frame offset o (hard iron), fitted without
the attitude (`_magnetometer.HardIron`: the sphere |m - o| = r, linear least squares in
[2 o, r^2 - |o|^2] over an exponential window; Vasconcelos et al. 2011, IEEE TAES 47(2), eqs. 4-6,
the hard-iron part); while the fit is trusted, samples are used with o removed. A field bent in
direction only passes those gates; the heading gate holds it off: the innovation psi, low-passed
over `mhgs` s, must satisfy psi^2 < chi2_1(0.999) (H P H^T + mhg^2) (the normalised innovation
squared against its chi-square bound; Bar-Shalom et al. 2001, Sec. 5.4.2), with a recovery rule
after `mhgmax` s of rejection (`_magnetometer.MagReference.heading_gate_update`). `--mag off`, or a
recording without a magnetometer, runs the 6-D filter, bit for bit (`tests/test_mag_filters.py`).

Known limitation (shared by `ukf-bias`): a scale error shows as an attitude error proportional to
the angle turned. When the board only rocks (bounded angles, under 1 rad/s) while it is moved back
and forth, the linear acceleration has power at the rocking frequencies, and the filter, which
models it as noise that is white at the scale of `disturbance_corr_s` (or, for the low-passed
sample, as the derivative of a bounded velocity), takes part of it for a scale error; with the
10 % prior (`init_scale_var`) it fits a scale error to an exactly calibrated gyro and loses
inclination (`tests/test_ekf.py`, a strict xfail). The scale test does not remove it: while the
translation is taken for a scale error, the data do not favour the calibrated prior. `scale=false`
or a narrower prior avoids it where the gyro is known to be calibrated.

FilterPy: this filter sits *beside* `filterpy.kalman.ExtendedKalmanFilter`, not on it: FilterPy's
EKF sizes x and P together, adds the correction (`x + K y`) and predicts with a linear `F x`; for
an error-state filter with a quaternion nominal state every one of those lines would be
overridden. The update uses the same Joseph form as FilterPy's `ExtendedKalmanFilter.update`.

Robustness as in `ukf`: invalid or non-finite gyro samples are not integrated (zero rate, no bias
or scale coupling, attitude noise inflated by `invalid_gyr_var_rad2_s2 dt^2`), non-finite
accelerometer samples skip the update, the optional fixed gating (`gate`, `gate_g`; off by
default) inflates R or skips the update when `| |a| - 1 g |` is large, and the covariance is
symmetrised (eigenvalues clipped if needed) every step (`_linalg.repair_covariance`).

Two implementations (`impl`): `EKF.step` below, in numpy, is the reference and what `reset`/`step`
(the streaming interface) always run; `"compiled"` (the default) makes `estimate` run the whole
recording in `_compiled_ekf.estimate` (the loop of `KalmanFilter.step` with `EKF`'s parts, its
sections the sequence's), whose helpers carry the names of the methods they mirror
(`_compiled_ekf._correct`, `_compiled_ekf._velocity_step`); `"numpy"` makes `estimate` loop `step`. Where a newcomer changing
the filter looks: the step's sequence in `kalman_base.KalmanFilter.step` (shared with the UKFs),
`EKF`'s parts below, the sensor concerns in `steps/`, and each one's `_compiled_*` twin.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from fusion.quaternion import (exp_floats, gravity_in_body_floats, multiply_floats, right_jacobian_floats, rotation_matrix_floats,
                               skew_floats, unit_array)
from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples

from ..kernels._linalg import inv_sym3, repair_covariance
from ..params import param, param_as
from ..search import Tunable
from .steps._error_state import ATTITUDE, BIAS, BIAS_AT, SCALE, ErrorLayout, axes_mask
from .filter_params import SOLA_NOISE, VQF, BiasFilterParams
from .kalman_base import KalmanFilter, Motion, error_state_covariances, initial_quaternion
from .steps._accel import AccDisturbance, SlowDisturbance, models_lag
from .steps._magnetometer import HardIron, MagReference
from .steps._rest import RestDetector
from .steps._scale_test import ScaleTest
from .steps._stuck import stuck_gyro_state


@dataclass(frozen=True)
class EKFParams(BiasFilterParams):
    """Parameters of `ekf`: the fields of `BiasFilterParams` (and through it `FilterParams`) with
    their defaults, plus the velocity states, the slow disturbance and the implementation; each
    field's unit, meaning, reference and valid range are at the field (`fusion list ekf`).

    The defaults are one set for every recording and rate. `acc_lowpass_s` (taulp) is 2 s here
    (1 s in `BiasFilterParams`): chosen by leave-one-recording-out over the nine course
    recordings and BROAD's fourteen trials together, where every fold picks it
    (`benchmarks/cross_validate.py`; for `ukf-bias`, which has no velocity states, the same
    procedure does not pick 2 s).
    """

    owner: ClassVar[str] = "ekf"
    former_std: ClassVar[tuple[str, ...]] = BiasFilterParams.former_std + (
        "velocity_acc_noise_g_sqrt_s", "sv", "velocity_bound_m_sqrt_s", "vb")

    # Search ranges (`fusion.estimators.search`): taulp as in `FilterParams` (0.3-10 s, around the
    # leave-one-out choice); Qv and Rv two decades either side (cross_validate.py tries 9e-6-9e-4 and
    # 0.25-4; BROAD's fast trials move at about 1 m/s).
    acc_lowpass_s: float = param_as(BiasFilterParams, "acc_lowpass_s", 2.0)

    estimate_bias: bool = param(
        True, alias="bias", unit="", valid="true | false (false needs estimate_scale=false)",
        meaning="Keep the gyro bias in the state; false drops it (and needs scale=false), and the bias and "
                "rest-detection fields apply only with it.")
    velocity_acc_noise_g2_s: float = param(
        1e-4, alias="Qv", unit="g^2 s", valid="> 0, finite", reference=SOLA_NOISE,
        meaning="Density of the white acceleration noise in the velocity states' integration (the smoothers' "
                "default).",
        search=Tunable(1e-6, 1e-2))
    velocity_bound_m2_s: float = param(
        1.0, alias="Rv", unit="m^2/s", valid="> 0; inf: no velocity states",
        reference="Titterton & Weston 2004, Ch. 3 (strapdown velocity integration); " + VQF + ", Sec. 3.2",
        meaning='Density of the pseudo-measurement v = 0 that bounds the horizontal velocity states: per second, '
                'one observation "v = 0" of variance Rv (m/s)^2 ("Velocity" in the module docstring).',
        search=Tunable(1e-2, 1e2))
    lowpass_calibration: bool = param(
        False, alias="lpcal", unit="", valid="true | false",
        meaning="With the velocity states, let the low-passed accelerometer sample also correct the gyro bias and "
                "scale (false, the default, corrects the attitude and velocity only); without the velocity states "
                "it always does.")
    # 1-5 s change little (docs/results.md, "Slow translation, simulated")
    slow_disturbance_corr_s: float = param(
        2.0, alias="tauslow", unit="s", valid=">= 0, finite; 0: no slow component",
        reference="Lee, Park & Robinovitch 2012, IEEE TIM 61(8) (a Gauss-Markov external acceleration)",
        meaning="Correlation time of the slow external acceleration (a sustained linear acceleration, as of a slow "
                "translation), whose power the raw sample's noise takes from the deviation of the disturbance "
                "window's mean from the low-pass, less what the calibration's uncertainty and gross samples "
                "explain (`_accel.AccDisturbance.slow_power`); 0 turns it off, and it needs the bias states, "
                "tauc > 0 and taulp > 0.")
    impl: Literal["compiled", "numpy"] = param(
        "compiled", unit="", valid="compiled | numpy",
        meaning="Which code runs `estimate`: compiled (the whole recording in the numba kernel of `_compiled_ekf`) "
                "or numpy (a loop of the numpy `step`, the reference), the same numbers either way to rounding; "
                "`reset` and `step` are the numpy code in both.")

    def _check(self) -> None:
        super()._check()
        if not (self.velocity_acc_noise_g2_s > 0.0 and math.isfinite(self.velocity_acc_noise_g2_s)):
            raise ValueError(f"ekf: velocity_acc_noise_g2_s must be a finite number > 0, "
                             f"got {self.velocity_acc_noise_g2_s!r}")
        if not self.velocity_bound_m2_s > 0.0:
            raise ValueError(f"ekf: velocity_bound_m2_s must be > 0 (inf: no velocity model), "
                             f"got {self.velocity_bound_m2_s!r}")
        if self.impl not in ("compiled", "numpy"):
            raise ValueError(f"ekf: impl must be compiled or numpy, got {self.impl!r}")
        if not (self.slow_disturbance_corr_s >= 0.0 and math.isfinite(self.slow_disturbance_corr_s)):
            raise ValueError(f"ekf: slow_disturbance_corr_s must be a finite number >= 0 (0: off), "
                             f"got {self.slow_disturbance_corr_s!r}")
        if self.estimate_scale and not self.estimate_bias:
            raise ValueError("ekf: estimate_scale needs estimate_bias (the error state is [attitude, bias, scale])")

    def _only_with(self) -> dict[str, tuple[str, tuple[Any, ...]]]:
        bias = ("estimate_bias", (True,))
        names = ("bias_walk_rad2_s3", "init_bias_var_rad2_s2", "bias_max_rad_s", "rest_gyr_rad_s", "rest_acc_g",
                 "rest_time_s", "rest_tilt_rad", "rest_noise_rad2_s", "slow_disturbance_corr_s")
        return {**super()._only_with(), **{name: bias for name in names}}

    @property
    def velocity_states(self) -> int:
        """2 with the velocity model (a finite `velocity_bound_m2_s` and the accelerometer in
        use), else 0."""
        return 2 if math.isfinite(self.velocity_bound_m2_s) and self.use_acc else 0


# Normalised innovation squared above which the bias and scale are not corrected: the 99.9 %
# point of chi-square with 3 degrees of freedom (the innovation consistency test, Bar-Shalom,
# Li & Kirubarajan 2001, Sec. 5.4).
_CHI2_3DOF = 16.27
# The velocity model starts at rest (the recordings start still, for the calibration), to this std.
VELOCITY_INIT_STD_M_S = 0.1


class EKF(KalmanFilter):
    """`ekf`: multiplicative error-state EKF with analytic Jacobians (see module docstring).

    Its step is `KalmanFilter.step`; this class supplies the prediction, the velocity model, the
    accelerometer correction and the injection."""

    Params = EKFParams
    LAST_ROW = {**KalmanFilter.LAST_ROW, "bias_guarded": "guarded", "mag_used": "mag_used",
                "mag_hard_iron": "hard_iron_used"}
    magnetometer = True  # 9-D where the recording has a magnetometer (the heading-only update)

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        p = self.params
        self.layout = L = ErrorLayout(bias=p.estimate_bias, scale=p.estimate_scale,
                                      velocity_states=p.velocity_states)
        self.n, self.N = n, N = L.n, L.N  # with the horizontal velocity after [attitude, bias, scale]
        self.q = initial_quaternion("ekf", init_quat_wxyz)
        self._q = tuple(self.q.tolist())  # the attitude within a step, 4 floats, normalised at its end
        self.b = np.zeros(3)
        self.s = np.zeros(3)
        P0, Qrate, Qbad = error_state_covariances(p, n)
        self.P, self._Qrate, self._Qbad = np.zeros((N, N)), np.zeros((N, N)), np.zeros((N, N))
        self.P[:n, :n], self._Qrate[:n, :n], self._Qbad[:n, :n] = P0, Qrate, Qbad
        self.v = np.zeros(2)
        if L.velocity_states:  # at rest at the start, to VELOCITY_INIT_STD_M_S; white acceleration of density Qv g^2
            self.P[L.velocity, L.velocity] = np.eye(2) * VELOCITY_INIT_STD_M_S**2
            self._Qrate[L.velocity, L.velocity] = np.eye(2) * STANDARD_GRAVITY_M_S2**2 * p.velocity_acc_noise_g2_s
        # the low-pass's lag is modelled where there are calibration states (`LowpassLag`)
        self._with_lag = models_lag(p, L.bias)
        self._dist = AccDisturbance(p.disturbance_window_s, p.acc_lowpass_s, p.acc_lowpass_window_s, self._with_lag)
        self._rest = RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s, tilt_rad=p.rest_tilt_rad)
        self._stuck = stuck_gyro_state()
        self._scale_test = (ScaleTest(p.init_scale_var, p.calibrated_scale_var, p.scale_test_error,
                                       axes_mask(p.scale_axes))
                            if L.scale else ScaleTest.off())
        self._mag = MagReference.of(p)
        self._hard_iron = HardIron(p.mag_hard_iron_window_s, p.mag_hard_iron_residual_ut, p.mag_hard_iron_coverage)
        self._F = np.eye(N)
        self._H = np.zeros((3, N))
        self._I = np.eye(N)
        self.acc_var = math.nan  # accelerometer variance of the last update, g^2 (nan: none)
        self.at_rest = False  # whether the last step made the rest bias update
        self.nis = math.nan  # normalised innovation squared of the last update (nan: none)
        self.guarded = False  # whether the last update left the bias and scale alone (chi-square guard)
        self.lowpassed = False  # whether the last update used the low-passed accelerometer
        self.mag_used = False  # whether the last step made the magnetometer's heading update
        self.hard_iron_used = False  # ... with the sphere fit's offset removed
        self.n_skipped = self.n_cov_repaired = 0

    # ------------------------------------------------------------------ the parts of `KalmanFilter.step`
    def _predict(self, gyr_rad_s: np.ndarray, dt_s: float, gyr_valid: bool) -> Motion:
        """Predict (module docstring): q <- q exp(theta / 2), P <- F P F^T + Q."""
        L = self.layout
        Q = self._Qrate * dt_s
        F = self._F
        valid = gyr_valid and math.isfinite(gyr_rad_s[0]) and math.isfinite(gyr_rad_s[1]) and math.isfinite(gyr_rad_s[2])
        u = None
        if valid:
            u = gyr_rad_s - self.b if L.bias else gyr_rad_s
            g = 1.0 + self.s if L.scale else None
            tx, ty, tz = (u * g * dt_s) if L.scale else u * dt_s  # w_true = diag(1 + s) (w_meas - b)
        else:  # no rate integration; inflate the attitude noise instead
            tx = ty = tz = 0.0
            Q = Q + self._Qbad * (dt_s * dt_s)
            self._dist.lose_frame()
        d = exp_floats(tx, ty, tz)
        self._q = multiply_floats(self.q.tolist(), d)  # q exp(theta / 2), as 4 floats
        F[ATTITUDE, ATTITUDE] = rotation_matrix_floats(*d).T  # error transition R(theta)^T
        if L.bias:
            Jdt = right_jacobian_floats(tx, ty, tz) * dt_s
            if L.scale:
                if valid:
                    F[ATTITUDE, BIAS] = -Jdt * g  # d theta / d b = -J_r diag(1 + s) dt
                    F[ATTITUDE, SCALE] = Jdt * u  # d theta / d s = J_r diag(w - b) dt
                else:
                    F[ATTITUDE, BIAS] = 0.0  # the rate was not integrated: no bias or scale enters
                    F[ATTITUDE, SCALE] = 0.0
            else:
                F[ATTITUDE, BIAS] = -Jdt if valid else 0.0
        self.P = F @ self.P @ F.T + Q
        return Motion(valid=valid, dq=d, theta=(tx, ty, tz), u=u)

    def _before_updates(self, acc_g: np.ndarray, dt_s: float) -> None:
        if self.layout.velocity_states:
            self._q, self.P = self._velocity_step(self._q, self.P, acc_g, dt_s)

    def _acc_correct(self, meas: np.ndarray, r: float, h: np.ndarray) -> None:
        """The accelerometer update (module docstring): H = [[h]x, H_b, H_s, 0], the heading-free
        gain, the chi-square guard, the Joseph form."""
        p, L, P = self.params, self.layout, self.P
        H = self._H
        H[0, 1], H[0, 2] = -h[2], h[1]  # [h]x
        H[1, 0], H[1, 2] = h[2], -h[0]
        H[2, 0], H[2, 1] = -h[1], h[0]
        H[:, BIAS_AT:] = 0.0
        if self._with_lag and self.lowpassed:  # the low-pass lags by the frame's drift: H = [[h]x, H_b, H_s]
            H_b, H_s = self._dist.lag_jacobian(H[:, ATTITUDE])
            H[:, BIAS] = H_b
            if L.scale:
                H[:, SCALE] = H_s
        PHt = P @ H.T
        S = H @ PHt
        S[0, 0] += r
        S[1, 1] += r
        S[2, 2] += r
        Sinv = inv_sym3(S)
        K = PHt @ Sinv
        if p.heading_free:
            # Remove the correction about the predicted vertical h (|h| = 1) from the
            # attitude and bias rows: K <- (I - h h^T) K; the Joseph form stays exact.
            K[ATTITUDE] -= np.outer(h, h @ K[ATTITUDE])
            if L.bias:
                K[BIAS] -= np.outer(h, h @ K[BIAS])
        y = meas - h
        self.nis = float(y @ Sinv @ y)  # normalised innovation squared, chi-square(3) if consistent
        # The attitude only, not the bias and scale, is corrected when the innovation is
        # inconsistent with the predicted covariance (a gyro freeze or a large error: not
        # through their linearised correlations), and for the low-passed sample when the
        # velocity states, which measure the frame's drift from the same accelerometer
        # samples, correct the calibration (module docstring). Any gain is exact in the Joseph form.
        self.guarded = L.bias and self.nis > _CHI2_3DOF
        if self.guarded or (L.bias and self.lowpassed and L.velocity_states and not p.lowpass_calibration):
            K[L.calibration] = 0.0
        self._q = self._correct(self._q, K @ y)
        IKH = self._I - K @ H
        self.P = IKH @ P @ IKH.T + r * (K @ K.T)  # Joseph form

    def _finish(self) -> np.ndarray:
        p, L = self.params, self.layout
        if L.bias:
            self.b = np.clip(self.b, -p.bias_max_rad_s, p.bias_max_rad_s)
        if L.scale:
            self.s = np.clip(self.s, -p.scale_max, p.scale_max)
        self.q = unit_array(self._q)
        self._q = tuple(self.q.tolist())
        self.P, repaired = repair_covariance(self.P)
        self.n_cov_repaired += repaired
        return self.q

    @property
    def _cov(self) -> np.ndarray:
        return self.P

    @_cov.setter
    def _cov(self, P: np.ndarray) -> None:
        self.P = P

    def _attitude(self) -> tuple:
        return self._q

    def _bias(self) -> np.ndarray:
        return self.b

    def _scale(self) -> np.ndarray:
        return self.s

    def _vertical(self) -> np.ndarray:
        return gravity_in_body_floats(*self._q)

    def _inject(self, dx: np.ndarray) -> None:
        self._q = self._correct(self._q, dx)

    def _lag_rate(self, gyr_rad_s: np.ndarray, motion: Motion) -> tuple[Any, Any]:
        """The rate the prediction integrated (None: not integrated) and `1 + s` now."""
        return motion.u, 1.0 + self.s

    def _slow(self, h: np.ndarray) -> SlowDisturbance:
        """With the lag, the slow external acceleration (`slow_disturbance_corr_s`), whose power the
        calibration's uncertainty explains in part, with the scale prior as the rate error the
        calibration states lack."""
        p, L = self.params, self.layout
        return SlowDisturbance(corr_s=p.slow_disturbance_corr_s if self._with_lag else 0.0, h=h,
                               P_cal=self.P[L.calibration, L.calibration],
                               scale_prior_var=p.init_scale_var if L.scale else 0.0)

    def _correct(self, q: tuple, dx: np.ndarray) -> tuple:
        """Inject an error-state correction dx (N,): `q exp(dx_e / 2)`, `b + dx_b`, `s + dx_s`, `v + dx_v`."""
        L = self.layout
        if L.bias:
            self.b = self.b + dx[BIAS]
        if L.scale:
            self.s = self.s + dx[SCALE]
        if L.velocity_states:
            self.v = self.v + dx[L.velocity]
        return multiply_floats(q, exp_floats(dx[0], dx[1], dx[2]))

    def _velocity_step(self, q: tuple, P: np.ndarray, acc_g: np.ndarray, dt_s: float) -> tuple[tuple, np.ndarray]:
        """The velocity model after the attitude's prediction (see the module docstring): the
        horizontal world velocity integrates the specific force at the step's end attitude,
        then the bounded-velocity pseudo-measurement `v = 0` corrects it (and, through the
        covariance, the attitude, bias and scale). Returns the corrected (q, P)."""
        p, L = self.params, self.layout
        vel = L.velocity
        R = rotation_matrix_floats(*q)
        if math.isfinite(acc_g[0]) and math.isfinite(acc_g[1]) and math.isfinite(acc_g[2]):
            self.v = self.v + (R[:2] @ acc_g) * (STANDARD_GRAVITY_M_S2 * dt_s)
            # dv/de = -(R [a]x)_xy g dt for the body-frame attitude error at the step's end
            V = np.eye(L.N)
            V[vel, ATTITUDE] = -(R[:2] @ skew_floats(acc_g[0], acc_g[1], acc_g[2])) * (STANDARD_GRAVITY_M_S2 * dt_s)
            P = V @ P @ V.T
        r = p.velocity_bound_m2_s / dt_s
        S = P[vel, vel] + r * np.eye(2)
        K = P[:, vel] @ np.linalg.inv(S)
        if p.heading_free:  # as the accelerometer update: no turn about the vertical h
            h = gravity_in_body_floats(*q)
            K[ATTITUDE] -= np.outer(h, h @ K[ATTITUDE])
            if L.bias:
                K[BIAS] -= np.outer(h, h @ K[BIAS])
        q = self._correct(q, K @ -self.v)
        IKH = self._I.copy()
        IKH[:, vel] -= K
        return q, IKH @ P @ IKH.T + r * (K @ K.T)

    def current(self) -> dict[str, Any]:
        return {"cov": self.P, "gyr_bias_rad_s": self.b, "gyr_scale": self.s, "velocity_m_s": self.v, "acc_var_g2": self.acc_var,
                "at_rest": self.at_rest, "nis": self.nis, "bias_guarded": self.guarded, "acc_lowpassed": self.lowpassed,
                "mag_used": self.mag_used, "mag_hard_iron": self.hard_iron_used, "scale_llr": self._scale_test.llr}

    def diagnostics(self) -> dict[str, Any]:
        return {"updates_skipped": self.n_skipped, "cov_repairs": self.n_cov_repaired,
                "scale_decision": self._scale_test.decision}

    def _run_kernel(self, kernels: Any, imu: ImuSamples, out: Any, dist: np.ndarray, rest: np.ndarray) -> None:
        from . import _compiled_ekf

        q, b, s, v, P = self.q.copy(), self.b.copy(), self.s.copy(), self.v.copy(), self.P.copy()
        st = kernels.SensorStates(dist=dist, rest=rest, mag=self._mag.state(), hard_iron=self._hard_iron.state(),
                                  test=self._scale_test.state())
        o = kernels.settings(self.params, self.layout, self._rest, self._scale_test, chi2=_CHI2_3DOF)
        self.n_skipped, self.n_cov_repaired = _compiled_ekf.estimate(
            kernels.inputs(imu, self.magnetometer), q, b, s, v, P, self._Qrate, self._Qbad, st, o, out)
        self.q, self.b, self.s, self.v, self.P = q, b, s, v, P
        self._q = tuple(self.q.tolist())
        self._mag.set_state(st.mag)
        self._hard_iron.set_state(st.hard_iron)
        self._scale_test.set_state(st.test)
