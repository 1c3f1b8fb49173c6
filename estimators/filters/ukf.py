"""`ukf`: a quaternion UKF after Kraft 2003, and `ukf-bias`, the same with gyro bias and scale.

Kraft 2003: E. Kraft, "A quaternion-based unscented Kalman filter for orientation tracking",
Proc. 6th Int. Conf. Information Fusion, pp. 47-54. The numbered steps below are this
module's and the code refers to them. They are written in our notation, without the paper's
equation numbers, which could not be checked against a copy of it; the one place cited is
the iterative mean, its Sec. 3.4, as two independent implementations (sfwa/ukf, Google's
Cartographer) cite it. "As in Kraft's filter" marks what the public implementations of the
paper consulted all do alike; where this module departs from them it says so. The notebook
`docs/tutorial/03_quaternion_ukf.py` runs every step on a real sample and lists the sources.

One departure throughout: Kraft's state also holds the angular velocity, which the gyro
measures; here, as in the reduced variant course implementations use, the gyro is the
control input of the process model and the state is the quaternion (and, for `ukf-bias`,
the gyro bias).

State: the orientation quaternion `q = R_world_body` (plus the gyro bias `b`, rad/s, for
`ukf-bias`); covariance `P` on the body-frame rotation-vector error `e`, `q_true = q exp(e/2)`
(3x3, or 6x6 with the bias error). Per IMU sample:

1. control input: the gyro, `q_delta = exp(w dt / 2)` (with `w - b_i` per sigma point for
   `ukf-bias`);
2. sigma points: the columns of `+-sqrt(c (P + Q))`, process noise entering *before* the
   transform as in Kraft's filter (scheme `kraft`: 2n points, equal weights 1/(2n) and
   c = n, the one factor with which the points reproduce P + Q exactly; implementations
   that follow the paper differ here, some scale by 2n, and the paper's own factor was not
   checked);
3. each turned into a quaternion by the exponential map, `X_i = q exp(W_i / 2)`;
4. propagated, `Y_i = X_i q_delta`;
5. the iterative quaternion mean: error rotation vectors `e_i = log(q_t^-1 Y_i)`, wrapped
   to the shortest rotation (angle in [0, pi], so q and -q agree), averaged with the mean
   weights and re-applied, `q_t <- q_t exp(e/2)`, until `|e| < mean_tol_rad` or
   `mean_max_iter` iterations (Kraft's gradient-descent mean, Sec. 3.4);
   `P_pred = sum Wc e_i e_i^T`, the errors taken about the mean in the body frame;
6. predicted measurement per sigma point: gravity in the body frame `Z_i = R(Y_i)^T e_z`
   (the accelerometer part of Kraft's measurement model), from the propagated points `Y_i`
   (not re-drawn from `P_pred`, as in Kraft's filter);
7. its mean `z = sum Wm Z_i`;
8. the innovation covariance `P_zz = sum Wc (Z_i - z)(Z_i - z)^T + R` and the cross
   covariance `P_xz = sum Wc e_i (Z_i - z)^T`;
9. gain `K = P_xz P_zz^-1`, update through the exponential map on the right (body frame),
   `q <- q exp(K (a - z) / 2)`, and `P <- P_pred - K P_zz K^T`.

The steps are written in `fusion.estimators.filters.quaternion_ukf`: `QuaternionSigmaPoints`, the
iterative mean `quaternion_mean` and `QuaternionUKF`, a FilterPy `UnscentedKalmanFilter` (what
FilterPy provides and what is replaced is said there). This module holds the estimators and
their parameters.

`ukf-bias` in 9-D (a recording with a magnetometer): after the accelerometer update, the
heading-only magnetometer update of `ekf` (its module docstring: gates, hard-iron fit, H = [v^T,
0, 0]); that measurement is linear in the error state, so it is applied as one Kalman update to
the mean and covariance (Joseph form), the same in every implementation, as the rest update is.
`ukf` stays 6-D.

Three implementations of the same step (`impl` parameter): `"filterpy"` calls the
per-sigma-point hooks and FilterPy's own `update()` (the reference for the unscented
transform); `"numpy"` runs predict and update as a handful of vectorised numpy calls over all
sigma points at once (`tests/test_ukf.py` checks the two agree to 1e-12); `"compiled"` (the
default) makes `estimate` run the whole recording in one numba kernel, `_compiled_ukf.estimate`,
which does the numpy step's arithmetic in explicit loops and records the same diagnostics
(`tests/test_compiled.py` checks it against numpy to 1e-10). The numpy step stays the
readable reference and is what `reset`/`step` (the streaming interface) run for compiled and
numpy alike. Why numba: see `_compiled`. Timings of the three:
`python benchmarks/bench_filters.py`; the time per sample of every estimator is in
`docs/results.md`.

Sigma-point schemes (`sigma`): `"kraft"` (2n points at +-sqrt(n (P+Q)), weights 1/(2n); a
zero-weight centre point is carried along only to start the iterative mean, which changes
no result), `"julier"` (centre point, kappa), `"merwe"` (scaled, alpha/beta/kappa). Schemes
whose centre weight would be negative are refused with a ValueError: a negative weight
makes the quaternion mean an extrapolation that the iterative mean cannot guarantee.

Robustness (all filters): gyro samples with `gyr_valid` False or non-finite values are
not integrated (zero rate) and add `invalid_gyr_var_rad2_s2` dt^2 to the attitude process
noise; non-finite accelerometer samples skip the update; the matrix square root falls back
from Cholesky to a clipped eigen-decomposition and the covariance is symmetrised (and
eigenvalue-clipped if needed) after every update; counts of these recoveries are in the
trajectory diagnostics. Quaternions are renormalised every step. The accelerometer noise
adapts to the measured external acceleration, and through sustained translation, tapping
or vibration the update uses the accelerometer low-passed in a gyro-only frame instead of
the raw sample, as in `ekf` (`_accel.AccDisturbance`, `_accel.acc_measurement`). For
that sample `ukf-bias` adds to step 6 the lag of the low-pass behind the frame's drift under
each sigma point's bias and scale, `Z_i += H_b (b_i - b) + H_s (s_i - s)`
(`_accel.LowpassLag`, the same Jacobians as `ekf`'s), so that it measures the calibration
in motion.

Defaults. Equal variances P0 = Q = R = 1e-4 I per 100 Hz sample (`UKFParams.equal_variances()`:
Q = 1e-2 rad^2/s, R = 1e-6 g^2 s, no disturbance model or scale noise) are a common start.
They apply nearly the whole accelerometer innovation every sample, so hand-motion
accelerations become attitude noise and, through the correlations of the unobservable
heading with the tilt, a heading random walk. Kraft's filter with the package's densities is
`ukf:tauc=0,Qs=0` (Q = 1e-3 rad^2/s, R = 3e-5 g^2 s); the default `ukf` adds the adaptive
accelerometer noise (`tauc`) and the rate-dependent process noise (`Qs`). What each of them
changes, measured on the course recordings: `docs/results.md`, "What the default `ukf` adds
to Kraft's filter"; the defaults' scores: the README's Results.

Beyond Kraft 2003 (`ukf-bias`, option `heading_free` for `ukf`): the accelerometer sees only
the tilt, yet the optimal gain also turns the estimate about the vertical through the
tilt-heading correlations of P; with unmodelled hand accelerations that is what drives the
heading random walk. `heading_free` removes the gain's component about the predicted
vertical (attitude and bias rows) and updates P with the general-gain formula
`P - K Pxz^T - Pxz K^T + K Pzz K^T`, so the covariance stays consistent with the gain used.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from fusion import quaternion as quat
from fusion.quaternion import exp_floats, multiply_floats, unit_array
from fusion.types import ImuSamples

from ..kernels._linalg import inv_sym3, repair_covariance
from ..params import param, param_as
from ..search import Tunable
from .steps._error_state import X_BIAS, X_CALIBRATION, X_QUAT, X_SCALE, ErrorLayout, axes_mask
from .filter_params import BiasFilterParams, FilterParams, check_nonneg
from .kalman_base import KalmanFilter, Motion, error_state_covariances, initial_quaternion
from .steps._accel import AccDisturbance, models_lag
from .steps._magnetometer import HARD_IRON_STATE, MAG_STATE, HardIron, MagReference
from .steps._rest import RestDetector
from .steps._scale_test import ScaleTest
from .steps._stuck import stuck_gyro_state

Sigma = Literal["kraft", "julier", "merwe"]
Impl = Literal["compiled", "numpy", "filterpy", "lean"]  # "lean": the former name of "numpy", with a warning


# --------------------------------------------------------------------------- parameters
def error_dim(p: Any) -> int:
    """Error-state dimension of a UKF parameter set: 3 (ukf), 6 or 9 (ukf-bias, with scale)."""
    if not isinstance(p, BiasFilterParams):
        return 3
    return 9 if p.estimate_scale else 6


@dataclass(frozen=True)
class UKFOptions(FilterParams):
    """The unscented-transform fields of `ukf` and `ukf-bias` (on top of `FilterParams`); each
    field's unit, meaning, reference and valid range are at the field (`fusion list ukf`)."""

    sigma: Sigma = param(
        "kraft", unit="", valid="kraft | julier | merwe",
        reference="Kraft 2003 (kraft); Julier & Uhlmann 1997 (julier); van der Merwe 2004 (merwe, scaled points)",
        meaning="The sigma-point scheme: kraft (+-sqrt(n P), equal weights, the centre only starting the iterative "
                "mean), julier (+-sqrt((n + kappa) P), centre weight kappa / (n + kappa)) or merwe (scaled points, "
                "lambda = alpha^2 (n + kappa) - n).")
    kappa: float = param(1.0, unit="1", valid="finite; >= 0 for julier; applies only with sigma=julier or merwe",
                         reference="Julier & Uhlmann 1997; van der Merwe 2004",
                         meaning="The sigma points' spread parameter kappa of the julier and merwe schemes.")
    alpha: float = param(1.0, unit="1", valid="> 0, finite; applies only with sigma=merwe",
                         reference="van der Merwe 2004",
                         meaning="The merwe scheme's scaling alpha of the sigma points about the mean.")
    beta: float = param(2.0, unit="1", valid="finite, with a non-negative centre weight; applies only with sigma=merwe",
                        reference="van der Merwe 2004",
                        meaning="The merwe scheme's beta, added to the centre point's covariance weight (2 is "
                                "optimal for a Gaussian).")
    mean_tol_rad: float = param(
        1e-9, alias="tol", unit="rad", valid="> 0, finite", reference="Kraft 2003 (step 5, the iterative mean)",
        meaning="The iterative quaternion mean stops once its correction is smaller than this.")
    mean_max_iter: int = param(
        20, alias="iters", unit="", valid="a whole number >= 1", reference="Kraft 2003 (step 5, the iterative mean)",
        meaning="The iterative quaternion mean stops after this many iterations at most.")
    impl: Impl = param(
        "compiled", unit="", valid="compiled | numpy | filterpy (lean: the former name of numpy, with a warning)",
        meaning="Which code runs `estimate`: compiled (the whole recording in the numba kernel of `_compiled_ukf`, "
                "the numpy step's arithmetic), numpy (the vectorised numpy step, the reference) or filterpy "
                "(per-point hooks and FilterPy's update), the same numbers; `reset` and `step` run the numpy step "
                "for compiled and numpy.")

    def _check(self) -> None:
        super()._check()
        owner = self.owner
        if not (math.isfinite(self.mean_tol_rad) and self.mean_tol_rad > 0.0):
            raise ValueError(f"{owner}: mean_tol_rad must be > 0, got {self.mean_tol_rad!r}")
        if int(self.mean_max_iter) != self.mean_max_iter or self.mean_max_iter < 1:
            raise ValueError(f"{owner}: mean_max_iter must be a whole number >= 1, got {self.mean_max_iter!r}")
        if self.impl == "lean":  # the former name of the numpy reference, as `ekf` calls it
            warnings.warn(f"{owner}: impl=lean is now called impl=numpy (as for ekf and the smoothers); "
                          "'lean' will be removed in the next release", FutureWarning, stacklevel=4)
            object.__setattr__(self, "impl", "numpy")
        if self.impl not in ("compiled", "numpy", "filterpy"):
            raise ValueError(f"{owner}: impl must be compiled, numpy or filterpy, got {self.impl!r}")
        if self.impl == "filterpy" and self.heading_free:
            raise ValueError(
                f"{owner}: impl=filterpy runs FilterPy's own update, which cannot project the gain; "
                "use heading_free=false (hf=false) with it"
            )
        # Builds the sigma-point weights once, so an impossible scheme fails here, not mid-run.
        from .quaternion_ukf import QuaternionSigmaPoints  # FilterPy, when a UKF is asked for

        QuaternionSigmaPoints(error_dim(self), self.sigma, self.kappa, self.alpha, self.beta)

    def _only_with(self) -> dict[str, tuple[str, tuple[Any, ...]]]:
        return {**super()._only_with(), "kappa": ("sigma", ("julier", "merwe")),
                "alpha": ("sigma", ("merwe",)), "beta": ("sigma", ("merwe",))}


@dataclass(frozen=True)
class UKFParams(UKFOptions):
    """Parameters of `ukf`, the quaternion UKF after Kraft 2003: the fields of `FilterParams` and
    `UKFOptions`, some with defaults of their own (Q = 1e-3 rad^2/s, tauc = 0.5 s, gate_g = 0.1 g,
    hf = false, taulp = 0: raw accelerometer samples only, as in Kraft 2003, since with the
    low-passed samples `ukf` gains inclination but loses more in heading on both the course
    recordings and BROAD: `fusion compare --estimators ukf,ukf:taulp=1` shows by how much), plus
    scale_noise_s (Qs). Each field's unit, meaning, reference and valid range are at the field
    (`fusion list ukf`).

    Defaults: Q = 1e-3 rad^2/s, R = 3e-5 g^2 s (the `FilterParams` density), not tuned on
    the recordings. With the adaptive accelerometer noise the scores hardly depend on Q and
    R (a plateau); the sweep that shows it: `fusion ablate --estimator ukf --param
    Q=1e-4,1e-3,1e-2 --param R=1e-5,3e-5,1e-4,1e-3,1e-2 --dataset all --data-dir
    ../shared/data/ece276a`.
    """

    owner: ClassVar[str] = "ukf"

    # Search ranges (`fusion.estimators.search`; R's is `FilterParams`'): Q two decades either side,
    # its grid the sweep above (Q=1e-4,1e-3,1e-2); tauc a decade either side, its grid a factor of 3.
    process_noise_rad2_s: float = param_as(FilterParams, "process_noise_rad2_s", 1e-3,
                                           search=Tunable(1e-5, 1e-1, grid=(1e-4, 1e-3, 1e-2)))
    disturbance_corr_s: float = param_as(FilterParams, "disturbance_corr_s", 0.5,
                                         search=Tunable(0.05, 5.0, grid=(0.15, 0.5, 1.5)))
    gate_g: float = param_as(FilterParams, "gate_g", 0.1)
    # not in Kraft 2003; see the module docstring
    heading_free: bool = param_as(FilterParams, "heading_free", False)
    # 0: Kraft's filter, raw samples only (no search range: 0 is outside a log range)
    acc_lowpass_s: float = param_as(FilterParams, "acc_lowpass_s", 0.0, search=None)
    # two decades either side (0, Kraft's filter, is outside a log range)
    scale_noise_s: float = param(
        2e-2, alias="Qs", unit="s", valid=">= 0, finite; 0: Kraft's process noise",
        meaning="Rate-dependent attitude process noise: Qs w_i^2 dt is added to the step variance of axis i, a "
                "stand-in for an unmodelled gyro scale error.",
        search=Tunable(2e-4, 2.0))

    def _check(self) -> None:
        check_nonneg(self.owner, scale_noise_s=self.scale_noise_s)
        super()._check()

    @classmethod
    def equal_variances(cls, **changes: Any) -> "UKFParams":
        """P0 = Q = R = 1e-4 (Q and R per 100 Hz sample), no disturbance model or scale noise."""
        values = dict(process_noise_rad2_s=1e-2, acc_noise_g2_s=1e-6, init_var_rad2=1e-4, scale_noise_s=0.0,
                      disturbance_corr_s=0.0)
        values.update(changes)
        return cls(**values)


@dataclass(frozen=True)
class UKFBiasParams(UKFOptions, BiasFilterParams):
    """Parameters of `ukf-bias`: the UKF with the gyro bias (and scale factors) in the state.

    The fields of `BiasFilterParams` (those of `FilterParams` plus bias, scale and rest
    detection) and of `UKFOptions`, with their defaults: the state model, the noise
    densities, the adaptive accelerometer noise, the rest bias update and the defaults are
    those of `ekf` without its velocity states (`ekf:Rv=inf`, whose low-pass is 2 s to this
    filter's 1 s), with the same scale test in 6-D ("Scale test" in `fusion.estimators.filters.ekf`);
    the two filters then differ only in how they propagate the covariance (sigma points here,
    Jacobians there). heading_free (hf) is on by default.
    """

    owner: ClassVar[str] = "ukf-bias"



# --------------------------------------------------------------------------- estimators
class UKF(KalmanFilter):
    """`ukf`: the quaternion UKF after Kraft 2003 (see the module docstring for the steps)."""

    Params = UKFParams
    with_bias = False

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        from .quaternion_ukf import QuaternionSigmaPoints, QuaternionUKF  # FilterPy, when a UKF is built

        p = self.params
        n = error_dim(p)
        self.layout = L = ErrorLayout.of(n)
        points = QuaternionSigmaPoints(n, p.sigma, p.kappa, p.alpha, p.beta)
        kf = QuaternionUKF(points, p.mean_tol_rad, p.mean_max_iter)
        kf.heading_free = p.heading_free
        kf.x = np.concatenate([initial_quaternion(type(self).__name__, init_quat_wxyz), np.zeros(n - 3)])
        kf.P, self._Qrate, self._Qbad = error_state_covariances(p, n)
        self.kf = kf
        self.n = n
        self._scale_noise = 0.0 if L.bias else p.scale_noise_s
        self._eye3 = np.eye(3)
        # ukf-bias: the low-passed sample's lag in the measurement model, as in `ekf`
        self._with_lag = models_lag(p, L.bias)
        self._dist = AccDisturbance(p.disturbance_window_s, p.acc_lowpass_s, p.acc_lowpass_window_s, self._with_lag)
        self._rest = RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s, tilt_rad=p.rest_tilt_rad) if self.with_bias else None
        self._stuck = stuck_gyro_state()
        # ukf-bias with scale states: the scale test of `ekf` (6-D)
        self._scale_test = (ScaleTest(p.init_scale_var, p.calibrated_scale_var, p.scale_test_error,
                                       axes_mask(p.scale_axes))
                            if L.scale and self.with_bias else ScaleTest.off())
        if self.with_bias:  # ukf-bias in 9-D: the magnetometer's gates and hard-iron fit, as in `ekf`
            self._mag = MagReference.of(p)
            self._hard_iron = HardIron(p.mag_hard_iron_window_s, p.mag_hard_iron_residual_ut, p.mag_hard_iron_coverage)
        self.mag_used = False  # whether the last step made the magnetometer's heading update (ukf-bias)
        self.hard_iron_used = False  # ... with the sphere fit's offset removed
        self.acc_var = math.nan  # accelerometer variance of the last update, g^2 (nan: none)
        self.at_rest = False  # whether the last step made the rest bias update
        self.nis = math.nan  # normalised innovation squared of the last update (nan: none)
        self.lowpassed = False  # whether the last update used the low-passed accelerometer
        self._kf_predict = kf.predict_reference if p.impl == "filterpy" else kf.predict_kraft
        self._kf_update = kf.update_reference if p.impl == "filterpy" else kf.update_kraft
        self.n_skipped = self.n_sqrt_recovered = self.n_cov_repaired = self.n_mean_capped = 0

    # ------------------------------------------------------------------ the parts of `KalmanFilter.step`
    def _predict(self, gyr_rad_s: np.ndarray, dt_s: float, gyr_valid: bool) -> Motion:
        """Steps 1-5 (`QuaternionUKF.predict_kraft`, or `predict_reference` with impl=filterpy)."""
        p, kf, L = self.params, self.kf, self.layout
        Q = self._Qrate * dt_s
        x = kf.x
        w = np.zeros(3)  # the step's corrected rate (rad/s; zero when not integrated)
        valid = gyr_valid and math.isfinite(gyr_rad_s[0]) and math.isfinite(gyr_rad_s[1]) and math.isfinite(gyr_rad_s[2])
        if not valid:
            gyr = None  # no rate integration; inflate the attitude noise instead
            Q = Q + self._Qbad * (dt_s * dt_s)
            dq = (1.0, 0.0, 0.0, 0.0)
            self._dist.lose_frame()
        else:
            gyr = gyr_rad_s
            # The mean rate increment, for the disturbance estimator's strapdown frame.
            w = gyr_rad_s - x[X_BIAS] if L.bias else gyr_rad_s
            if L.scale:
                w = w * (1.0 + x[X_SCALE])
            dq = exp_floats(w[0] * dt_s, w[1] * dt_s, w[2] * dt_s)
            if self._scale_noise > 0.0:
                # ukf only: gyro scale-factor uncertainty as rate noise density Qs w_i^2 per axis.
                Q = Q.copy()
                Q[0, 0] += self._scale_noise * gyr_rad_s[0] * gyr_rad_s[0] * dt_s
                Q[1, 1] += self._scale_noise * gyr_rad_s[1] * gyr_rad_s[1] * dt_s
                Q[2, 2] += self._scale_noise * gyr_rad_s[2] * gyr_rad_s[2] * dt_s
        self._kf_predict(dt_s, gyr, Q)
        self.n_sqrt_recovered += kf.sqrt_recovered
        self.n_mean_capped += kf.mean_iterations >= p.mean_max_iter
        return Motion(valid=valid, dq=dq, theta=(w[0] * dt_s, w[1] * dt_s, w[2] * dt_s), u=None)

    def _acc_correct(self, meas: np.ndarray, r: float, h: np.ndarray) -> None:
        """Steps 6-9 (`QuaternionUKF.update_kraft`, or `update_reference`), with the low-passed
        sample's lag in the measurement model where it is modelled (`_accel.LowpassLag`)."""
        kf = self.kf
        lag = None
        if self._with_lag and self.lowpassed:
            lag = self._dist.lag_jacobian(quat.skew(h))
        self._kf_update(meas, self._eye3 * r, lag)
        y = kf.y
        self.nis = float(y @ inv_sym3(kf.S) @ y)  # normalised innovation squared, chi-square(3) if consistent

    def _finish(self) -> np.ndarray:
        p, kf, L = self.params, self.kf, self.layout
        x = kf.x
        if L.bias:
            np.clip(x[X_BIAS], -p.bias_max_rad_s, p.bias_max_rad_s, out=x[X_BIAS])
        if L.scale:
            np.clip(x[X_SCALE], -p.scale_max, p.scale_max, out=x[X_SCALE])
        kf.P, repaired = repair_covariance(kf.P)
        self.n_cov_repaired += repaired
        return x[X_QUAT]

    @property
    def _cov(self) -> np.ndarray:
        return self.kf.P

    @_cov.setter
    def _cov(self, P: np.ndarray) -> None:
        self.kf.P = P

    def _attitude(self) -> tuple:
        return tuple(self.kf.x[X_QUAT].tolist())

    def _bias(self) -> np.ndarray:
        return self.kf.x[X_BIAS]

    def _scale(self) -> np.ndarray:
        return self.kf.x[X_SCALE]

    def _vertical(self) -> np.ndarray:
        return quat.gravity_in_body(self.kf.x[X_QUAT])

    def _inject(self, dx: np.ndarray) -> None:
        """The correction through the exponential map on the right, renormalised (step 9)."""
        x = self.kf.x
        qn = unit_array(multiply_floats(x[X_QUAT].tolist(), exp_floats(dx[0], dx[1], dx[2])))
        self.kf.x = np.concatenate([qn, x[X_CALIBRATION] + dx[self.layout.calibration]])

    def _lag_rate(self, gyr_rad_s: np.ndarray, motion: Motion) -> tuple[Any, Any]:
        """The lag's inputs (`AccDisturbance.update`) from the current mean's calibration: the
        bias-corrected rate (None: not integrated) and `1 + s`; (None, None) without the lag."""
        if not self._with_lag:
            return None, None
        x = self.kf.x
        gain = 1.0 + x[X_SCALE] if self.layout.scale else np.ones(3)
        return (gyr_rad_s - x[X_BIAS] if motion.valid else None), gain

    def _rate_noise(self, gyr_rad_s: np.ndarray, motion: Motion) -> float:
        q_rate = self.params.process_noise_rad2_s  # ukf: plus the scale noise Qs w_i^2, a rate noise density too
        if motion.valid and self._scale_noise > 0.0:
            q_rate += self._scale_noise * float(np.max(gyr_rad_s * gyr_rad_s))
        return q_rate

    def current(self) -> dict[str, Any]:
        kf = self.kf
        out = {"cov": kf.P, "mean_iterations": kf.mean_iterations, "acc_var_g2": self.acc_var, "nis": self.nis,
               "acc_lowpassed": self.lowpassed}
        if self.with_bias:
            out["gyr_bias_rad_s"] = kf.x[X_BIAS]
            out["at_rest"] = self.at_rest
            out["mag_used"] = self.mag_used
            out["mag_hard_iron"] = self.hard_iron_used
            if self.layout.scale:
                out["gyr_scale"] = kf.x[X_SCALE]
            out["scale_llr"] = self._scale_test.llr
        return out

    def diagnostics(self) -> dict[str, Any]:
        return {
            "updates_skipped": self.n_skipped,
            "sqrt_recoveries": self.n_sqrt_recovered,
            "cov_repairs": self.n_cov_repaired,
            "mean_iteration_cap_hits": self.n_mean_capped,
            **({"scale_decision": self._scale_test.decision} if self.with_bias else {}),
        }

    def _run_kernel(self, kernels: Any, imu: ImuSamples, out: Any, dist: np.ndarray, rest: np.ndarray) -> None:
        from . import _compiled_ukf

        p, kf = self.params, self.kf
        x, P = kf.x.copy(), kf.P.copy()
        unscented = kernels.UnscentedSettings(scale_noise=self._scale_noise, sqrt_c=kf.points_fn.sqrt_c,
                                              mean_tol=p.mean_tol_rad, mean_max_iter=p.mean_max_iter)
        o = kernels.settings(p, self.layout, self._rest, self._scale_test, unscented=unscented)
        st = kernels.SensorStates(dist=dist, rest=rest,
                                  mag=self._mag.state() if self.with_bias else np.zeros(MAG_STATE),
                                  hard_iron=self._hard_iron.state() if self.with_bias else np.zeros(HARD_IRON_STATE),
                                  test=self._scale_test.state())
        (self.n_skipped, self.n_sqrt_recovered, self.n_cov_repaired, self.n_mean_capped) = _compiled_ukf.estimate(
            kernels.inputs(imu, self.magnetometer), x, P, self._Qrate, self._Qbad, kf.Wm, kf.Wc, st, o, out)
        kf.x, kf.P, kf.mean_iterations = x, P, int(out.mean_iterations[-1])
        self._scale_test.set_state(st.test)
        if self.with_bias:
            self._mag.set_state(st.mag)
            self._hard_iron.set_state(st.hard_iron)


class UKFBias(UKF):
    """`ukf-bias`: the UKF with the gyro bias (and scale factors) in the state, 6 or 9-dof error."""

    Params = UKFBiasParams
    with_bias = True
    magnetometer = True  # 9-D where the recording has a magnetometer (the heading-only update of `ekf`)
    LAST_ROW = {**KalmanFilter.LAST_ROW, "mag_used": "mag_used", "mag_hard_iron": "hard_iron_used"}
