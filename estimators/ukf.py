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

What FilterPy (2.0.0) provides and what is replaced
----------------------------------------------------
`QuaternionUKF` subclasses `filterpy.kalman.UnscentedKalmanFilter` and keeps its
bookkeeping (`x`, `P`, `R`, `K`, `y`, `S`, `sigmas_f`, `sigmas_h`, `x_prior`/`x_post`...) and
its hooks: `QuaternionSigmaPoints` has FilterPy's sigma-point interface (`n`, `num_sigmas()`,
`sigma_points(x, P)`, `Wm`, `Wc`), `x_mean_fn` is the iterative quaternion mean,
`residual_x` the quaternion log difference, `state_add` composition with the exponential
map, `fx`/`hx` the process and measurement models. Traps worked around:

* `UnscentedKalmanFilter.predict()` re-draws sigma points from the predicted (x, P)
  after the transform, so `update` would not use the propagated points as Kraft does, and
  it adds Q *after* the transform. `QuaternionUKF.predict_kraft` is Kraft's instead (draws from
  P + Q, keeps the propagated points and their error vectors for the update).
* FilterPy's `predict`/`update` stay as FilterPy wrote them (our steps are `predict_kraft`
  and `update_kraft`), so the object is still a working FilterPy filter.
* FilterPy's `unscented_transform` and `cross_variance` size the covariance from the state
  vector (4 or 7 entries) and fail for a 3x3 / 6x6 error covariance:
  `unscented_transform_state` (passed as `UT=`) and an overridden `cross_variance` size it
  from the residuals. FilterPy's own `unscented_transform` is still used for the
  (Euclidean) measurement side.
* `batch_filter` cannot pass the gyro to `fx`: `RecursiveEstimator` loops the steps and
  passes the gyro sample as a keyword argument.
* FilterPy's sigma-point classes check `size(x) == n`; ours take the (n+1)-entry state
  with an n x n covariance.

`ukf-bias` in 9-D (a recording with a magnetometer): after the accelerometer update, the
heading-only magnetometer update of `ekf` (its module docstring: gates, hard-iron fit, H = [v^T,
0, 0]); that measurement is linear in the error state, so it is applied as one Kalman update to
the mean and covariance (Joseph form), the same in every implementation, as the rest update is.
`ukf` stays 6-D.

Three implementations of the same step (`impl` parameter): `"filterpy"` calls the
per-sigma-point hooks and FilterPy's own `update()` (the reference for the unscented
transform); `"numpy"` runs predict and update as a handful of vectorised numpy calls over all
sigma points at once (`tests/test_ukf.py` checks the two agree to 1e-12); `"compiled"` (the
default) makes `estimate` run the whole recording in one numba kernel, `_compiled.ukf_kernel`,
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
the raw sample, as in `ekf` (`_attitude.AccDisturbance`, `_attitude.acc_measurement`). For
that sample `ukf-bias` adds to step 6 the lag of the low-pass behind the frame's drift under
each sigma point's bias and scale, `Z_i += H_b (b_i - b) + H_s (s_i - s)`
(`_attitude.LowpassLag`, the same Jacobians as `ekf`'s), so that it measures the calibration
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
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from filterpy.kalman import UnscentedKalmanFilter

from fusion import quaternion as quat
from fusion.quaternion import exp_floats, left_matrix, multiply_floats, right_matrix, unit_array
from fusion.types import ImuSamples

from ._attitude import (
    HARD_IRON_STATE,
    AccDisturbance,
    HardIron,
    MagReference,
    RestDetector,
    accelerometer_update_input,
    acc_variance_scale,
    bias_rest_update,
    heading_update,
    heading_variance,
    magnetometer_input,
    inv_sym3,
    models_lag,
    repair_covariance,
    stuck_gyro_state,
    sqrt_psd,
)
from .filter_params import BiasFilterParams, FilterParams, check_nonneg
from .kalman_base import KalmanFilter, error_state_covariances, initial_quaternion

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
    """The unscented-transform fields of `ukf` and `ukf-bias` (on top of `FilterParams`).

    sigma: sigma-point scheme, kraft (Kraft 2003) | julier | merwe; kappa, alpha, beta their
        parameters (kappa for julier and merwe, alpha and beta for merwe only; setting one
        for a scheme that ignores it is an error).
    mean_tol_rad (tol), mean_max_iter (iters): stopping rule of the iterative mean (step 5).
    impl: compiled (default: `estimate` runs the whole recording in the numba kernel of
        `_compiled`, the numpy step's arithmetic) | numpy (the vectorised numpy step, the
        reference; "lean", its former name, still works with a warning) | filterpy (per-point
        hooks + FilterPy's update), same numbers. `reset`/`step` (streaming) run the numpy step
        for compiled and numpy.
    """

    sigma: Sigma = "kraft"
    kappa: float = 1.0
    alpha: float = 1.0
    beta: float = 2.0
    mean_tol_rad: float = field(default=1e-9, metadata={"alias": "tol"})
    mean_max_iter: int = field(default=20, metadata={"alias": "iters"})
    impl: Impl = "compiled"

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
        QuaternionSigmaPoints(error_dim(self), self.sigma, self.kappa, self.alpha, self.beta)

    def _only_with(self) -> dict[str, tuple[str, tuple[Any, ...]]]:
        return {**super()._only_with(), "kappa": ("sigma", ("julier", "merwe")),
                "alpha": ("sigma", ("merwe",)), "beta": ("sigma", ("merwe",))}


@dataclass(frozen=True)
class UKFParams(UKFOptions):
    """Parameters of `ukf`, the quaternion UKF after Kraft 2003.

    The fields of `FilterParams` (Q, R, P0, tauc, tauw, acc, gate, gate_g, hf, Qinvalid) and
    `UKFOptions` (sigma, kappa, alpha, beta, tol, iters, impl), with these defaults of its own:
    process_noise_rad2_s (Q) = 1e-3 rad^2/s, disturbance_corr_s (tauc) = 0.5 s, gate_g = 0.1 g,
    heading_free (hf) = False (not in Kraft 2003; see the module docstring), acc_lowpass_s
    (taulp) = 0 (raw accelerometer samples only, as in Kraft 2003: with the low-passed samples
    `ukf` gains inclination but loses more in heading on both the course recordings and
    BROAD: `fusion compare --estimators ukf,ukf:taulp=1` shows by how much); plus
    scale_noise_s (Qs): rate-dependent attitude process noise, s: `Qs w_i^2 dt` is added to
        the step variance of axis i (a stand-in for an unmodelled gyro scale error).

    Defaults: Q = 1e-3 rad^2/s, R = 3e-5 g^2 s (the `FilterParams` density), not tuned on
    the recordings. With the adaptive accelerometer noise the scores hardly depend on Q and
    R (a plateau); the sweep that shows it: `fusion ablate --estimator ukf --param
    Q=1e-4,1e-3,1e-2 --param R=1e-5,3e-5,1e-4,1e-3,1e-2 --dataset all --data-dir
    ../shared/data/ece276a`.
    """

    owner: ClassVar[str] = "ukf"

    process_noise_rad2_s: float = field(default=1e-3, metadata={"alias": "Q"})
    disturbance_corr_s: float = field(default=0.5, metadata={"alias": "tauc"})
    gate_g: float = 0.1
    heading_free: bool = field(default=False, metadata={"alias": "hf"})
    acc_lowpass_s: float = field(default=0.0, metadata={"alias": "taulp"})
    scale_noise_s: float = field(default=2e-2, metadata={"alias": "Qs"})

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
    those of `ekf`; the two filters differ only in how they propagate the covariance (sigma
    points here, Jacobians there). heading_free (hf) is on by default.
    """

    owner: ClassVar[str] = "ukf-bias"


# --------------------------------------------------------------------------- sigma points
class QuaternionSigmaPoints:
    """Sigma points on the n-dimensional error state, with FilterPy's interface.

    n: error dimension (3: attitude; 6: attitude and gyro bias).
    scheme: "kraft" | "julier" | "merwe". Points are `W_0 = 0` and `+-` the columns of
    `sqrt(c P)` (c = n, n + kappa, n + lambda); `Wm`, `Wc` (2n + 1,) weights, centre first.
    `sigma_points(x, P)` maps them onto the state: x (n + 1,) = [q_wxyz, b...], P (n, n).
    """

    def __init__(self, n: int, scheme: str = "kraft", kappa: float = 1.0, alpha: float = 1.0, beta: float = 2.0) -> None:
        if n not in (3, 6, 9):
            raise ValueError(f"sigma points: error dimension must be 3, 6 or 9, got {n}")
        self.n, self.scheme = n, scheme
        self.kappa, self.alpha, self.beta = float(kappa), float(alpha), float(beta)
        m = 2 * n + 1
        if scheme == "kraft":  # step 2: +-sqrt(n P), 2n points, equal weights
            c = float(n)
            wm0 = wc0 = 0.0  # the centre only starts the iterative mean
        elif scheme == "julier":  # Julier & Uhlmann 1997
            c = n + self.kappa
            if not (self.kappa >= 0.0 and math.isfinite(self.kappa)):
                raise ValueError(
                    f"sigma points julier: kappa = {kappa} gives the centre point the negative weight "
                    f"{self.kappa / c if c else float('-inf'):.3g}; the quaternion mean needs kappa >= 0"
                )
            wm0 = wc0 = self.kappa / c
        elif scheme == "merwe":  # van der Merwe 2004, scaled points
            if not (self.alpha > 0.0 and math.isfinite(self.alpha) and math.isfinite(self.kappa) and math.isfinite(self.beta)):
                raise ValueError(f"sigma points merwe: alpha must be > 0 and all parameters finite, got alpha={alpha}, kappa={kappa}, beta={beta}")
            lam = self.alpha**2 * (n + self.kappa) - n
            c = n + lam
            if c <= 0.0 or lam < 0.0:
                raise ValueError(
                    f"sigma points merwe: alpha={alpha}, kappa={kappa} give lambda = {lam:.4g} and a centre "
                    f"mean weight {lam / c if c > 0 else float('-inf'):.4g} < 0; the iterative quaternion mean "
                    f"needs non-negative weights: choose kappa >= n / alpha^2 - n = {n / self.alpha**2 - n:.4g}"
                )
            wm0 = lam / c
            wc0 = wm0 + 1.0 - self.alpha**2 + self.beta
            if wc0 < 0.0:
                raise ValueError(f"sigma points merwe: covariance centre weight {wc0:.4g} < 0 (alpha={alpha}, beta={beta}); choose beta >= alpha^2 - 1 - lambda/(n+lambda)")
        else:
            raise ValueError(f"sigma points: scheme must be kraft, julier or merwe, got {scheme!r}")
        self.c = c
        self.sqrt_c = math.sqrt(c)
        self.Wm = np.full(m, 0.5 / c)
        self.Wc = np.full(m, 0.5 / c)
        self.Wm[0], self.Wc[0] = wm0, wc0
        self.last_sqrt_recovered = False

    def num_sigmas(self) -> int:
        return 2 * self.n + 1

    def offsets(self, P: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(2n + 1, n) error-state offsets: 0, then +- the columns of sqrt(c P) (step 2)."""
        n = self.n
        L, self.last_sqrt_recovered = sqrt_psd(P)
        L = L * self.sqrt_c
        if out is None:
            out = np.zeros((2 * n + 1, n))
        out[1 : n + 1] = L.T
        out[n + 1 :] = -L.T
        return out

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """(2n + 1, n + 1) state sigma points `[q exp(W_i / 2), b + W_i^b]` (steps 2-3)."""
        x = np.asarray(x, dtype=float)
        P = np.asarray(P, dtype=float)
        if x.shape != (self.n + 1,) or P.shape != (self.n, self.n):
            raise ValueError(f"sigma points: expected x ({self.n + 1},) and P ({self.n}, {self.n}), got {x.shape} and {P.shape}")
        off = self.offsets(P)
        out = np.empty((len(off), self.n + 1))
        out[:, :4] = quat.from_rotvec(off[:, :3]) @ left_matrix(*x[:4]).T  # step 3: q * exp(W_i)
        out[:, 4:] = x[4:] + off[:, 3:]
        return out


# --------------------------------------------------------------------------- UT hooks
def quaternion_mean(
    quats: np.ndarray, weights: np.ndarray, start: np.ndarray, tol: float = 1e-9, max_iter: int = 20
) -> tuple[np.ndarray, np.ndarray, int]:
    """Iterative weighted mean of unit quaternions (step 5; Kraft 2003).

    quats: (m, 4) wxyz; weights: (m,) summing to 1, >= 0; start: (4,) first guess.
    Repeats `e_i = log(q_t^-1 q_i)` (wrapped: q_i and -q_i give the same e_i),
    `e = sum w_i e_i`, `q_t <- q_t exp(e / 2)` until `|e| < tol` or `max_iter` passes.
    Returns `(mean (4,), residuals (m, 3) rad about the mean, iterations used)`; when the
    cap is hit the last iterate is returned (the caller counts it).
    """
    qw, qx, qy, qz = start.tolist()
    for it in range(1, max_iter + 1):
        err = quat.to_rotvec(quats @ left_matrix(qw, -qx, -qy, -qz).T)  # q_t^-1 * q_i
        e = weights @ err
        qw, qx, qy, qz = quat.normalize_floats(multiply_floats((qw, qx, qy, qz), exp_floats(e[0], e[1], e[2])))
        if math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]) < tol:
            break
    # Residuals about the final mean, to first order (the last step was below tol).
    return np.array([qw, qx, qy, qz]), err - e, it


def state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """FilterPy `residual_x`: error-state difference a - b, `[log(b_q^-1 a_q), a_b - b_b]`."""
    dq = left_matrix(b[0], -b[1], -b[2], -b[3]) @ a[:4]
    rot = quat.to_rotvec(dq)
    return np.concatenate([rot, a[4:] - b[4:]])


def state_add(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """FilterPy `state_add`: `[q exp(dx_rot / 2), b + dx_b]` (step 9), renormalised."""
    q = left_matrix(*x[:4]) @ np.array(exp_floats(dx[0], dx[1], dx[2]))
    return np.concatenate([q / np.linalg.norm(q), x[4:] + dx[3:]])


def unscented_transform_state(sigmas, Wm, Wc, noise_cov=None, mean_fn=None, residual_fn=None):
    """FilterPy-signature UT for the quaternion state (passed as `UT=`; step 5).

    sigmas: (m, n + 1) state points; the covariance is sized from the residuals (n, n),
    which FilterPy's `unscented_transform` cannot do for a 4-vector with a 3x3 P.
    """
    x = mean_fn(sigmas, Wm) if mean_fn is not None else Wm @ sigmas  # Euclidean (measurement side)
    residual_fn = residual_fn if residual_fn is not None else np.subtract
    res = np.array([residual_fn(s, x) for s in sigmas])
    P = res.T @ (Wc[:, None] * res)
    if noise_cov is not None:
        P = P + noise_cov
    return x, P


# --------------------------------------------------------------------------- the filter
class QuaternionUKF(UnscentedKalmanFilter):
    """FilterPy's `UnscentedKalmanFilter` with a quaternion (+ bias) state.

    x: (4,), (7,) or (10,) `[q_wxyz, b_rad_s, s]`; P: (n, n) error covariance, n = 3, 6 or 9.
    `predict_kraft(dt, gyr_rad_s, Q)` / `update_kraft(z, R)` are Kraft's steps, vectorised;
    `predict_reference` / `update_reference` run the same steps through the per-point hooks
    and FilterPy's own `update`. FilterPy's `predict` and `update` are not overridden: they
    work on this object as FilterPy defines them (pass `UT=unscented_transform_state`, whose
    covariance is sized from the error state, and the gyro as `gyr_rad_s=`). FilterPy's
    `predict` is not Kraft's (it adds Q after the transform and re-draws the sigma points
    before the update), which is why the estimator uses `predict_kraft`. `batch_filter` and
    `rts_smoother` cannot apply to a quaternion state: both size covariances by the state
    vector's length (4 or 7, not the error state's 3 or 6), `batch_filter` cannot pass the gyro
    to `fx`, and `rts_smoother` adds `K (x' - x)` to the state in Euclidean space (`gn` is the
    smoother here).
    """

    def __init__(self, points: QuaternionSigmaPoints, mean_tol_rad: float = 1e-9, mean_max_iter: int = 20) -> None:
        n = points.n
        self.n_err = n
        self.has_bias = n >= 6
        self.has_scale = n == 9
        self.mean_tol, self.mean_max_iter = mean_tol_rad, int(mean_max_iter)
        super().__init__(
            dim_x=n + 1,
            dim_z=3,
            dt=None,
            hx=self.hx_gravity,
            fx=self.fx_rotate,
            points=points,
            x_mean_fn=self.state_mean,
            residual_x=state_residual,
            state_add=state_add,
        )
        # FilterPy sizes P, Q, K from dim_x; the error state is one smaller.
        self.P = np.eye(n)
        self.Q = np.zeros((n, n))
        self.K = np.zeros((n, 3))
        self.x = np.zeros(n + 1)
        self.x[0] = 1.0
        self._offsets = np.zeros((2 * n + 1, n))
        self._residuals = np.zeros((2 * n + 1, n))
        self._Wc_col = self.Wc[:, None].copy()
        self.mean_iterations = 0
        self.sqrt_recovered = False
        self.heading_free = False

    # -- models (per point, used by the reference path) --
    def fx_rotate(self, x: np.ndarray, dt: float, gyr_rad_s: np.ndarray | None = None) -> np.ndarray:
        """Process model for one state point: `q exp(diag(1 + s) (w - b) dt / 2)` (steps 1, 4).

        gyr_rad_s None: an invalid gyro sample, nothing is integrated.
        """
        if gyr_rad_s is None:
            return x.copy()
        w = gyr_rad_s - x[4:7] if self.has_bias else gyr_rad_s
        if self.has_scale:
            w = w * (1.0 + x[7:10])
        q = right_matrix(*exp_floats(*(w * dt))) @ x[:4]
        return np.concatenate([q, x[4:]])

    @staticmethod
    def hx_gravity(x: np.ndarray) -> np.ndarray:
        """Measurement model: gravity in the body frame, g (step 6)."""
        return quat.gravity_in_body(x[:4])

    def state_mean(self, sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
        """FilterPy `x_mean_fn`: iterative quaternion mean, weighted bias mean (step 5)."""
        q, _, self.mean_iterations = quaternion_mean(sigmas[:, :4], Wm, sigmas[0, :4], self.mean_tol, self.mean_max_iter)
        return np.concatenate([q, Wm @ sigmas[:, 4:]])

    def cross_variance(self, x, z, sigmas_f, sigmas_h):
        """P_xz sized (n, dim_z) from the residuals (FilterPy sizes it from x). Step 8."""
        Pxz = np.zeros((self.n_err, sigmas_h.shape[1]))
        for i in range(sigmas_f.shape[0]):
            Pxz += self.Wc[i] * np.outer(self.residual_x(sigmas_f[i], x), self.residual_z(sigmas_h[i], z))
        return Pxz

    # -- numpy path --
    def predict_kraft(self, dt: float, gyr_rad_s: np.ndarray | None, Q: np.ndarray) -> None:
        """Steps 1-5 for all sigma points at once. gyr_rad_s: (3,) rad/s, body, or None
        (invalid sample: nothing integrated); Q: (n, n)."""
        pts: QuaternionSigmaPoints = self.points_fn
        x = self.x
        off = pts.offsets(self.P + Q, self._offsets)  # step 2
        self.sqrt_recovered = pts.last_sqrt_recovered
        X = quat.from_rotvec(off[:, :3]) @ left_matrix(x[0], x[1], x[2], x[3]).T  # step 3
        sig = self.sigmas_f
        if gyr_rad_s is None:
            sig[:, :4] = X
            sig[:, 4:] = x[4:] + off[:, 3:]
        elif self.has_bias:
            b = x[4:7] + off[:, 3:6]
            rv = gyr_rad_s - b
            if self.has_scale:
                s = x[7:10] + off[:, 6:9]
                rv *= 1.0 + s
                sig[:, 7:10] = s
            rv *= dt  # step 1, per point
            d = quat.from_rotvec(rv)
            sig[:, :4] = quat.multiply(X, d)  # step 4: Y_i = X_i * q_delta_i, row-wise
            sig[:, 4:7] = b
        else:
            w = gyr_rad_s * dt
            sig[:, :4] = X @ right_matrix(*exp_floats(w[0], w[1], w[2])).T  # steps 1, 4
        Y = sig[:, :4]
        q, err, self.mean_iterations = quaternion_mean(Y, self.Wm, Y[0], self.mean_tol, self.mean_max_iter)  # step 5
        res = self._residuals
        res[:, :3] = err
        if self.has_bias:
            bm = self.Wm @ sig[:, 4:]
            res[:, 3:] = sig[:, 4:] - bm
            self.x = np.concatenate([q, bm])
        else:
            self.x = q
        self.P = res.T @ (self._Wc_col * res)  # step 5: P_pred (Q entered in step 2)
        self.x_prior = self.x
        self.P_prior = self.P

    def update_kraft(self, z: np.ndarray, R: np.ndarray, lag: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Steps 6-9 with the propagated points. z: (3,) accelerometer, g; R: (3, 3) g^2;
        lag: the low-passed sample's calibration Jacobians `(H_b, H_s)` (`_attitude.LowpassLag`),
        None for the raw sample."""
        Z = quat.gravity_in_body(self.sigmas_f[:, :4])  # step 6
        if lag is not None:  # the low-pass's lag behind the frame drift of each point's calibration
            res = self._residuals
            Z = Z + res[:, 3:6] @ lag[0].T
            if res.shape[1] > 6:
                Z = Z + res[:, 6:9] @ lag[1].T
        zp = self.Wm @ Z  # step 7
        dZ = Z - zp
        WdZ = self._Wc_col * dZ
        S = dZ.T @ WdZ + R  # step 8: P_zz
        Pxz = self._residuals.T @ WdZ  # step 8: P_xz
        K = Pxz @ inv_sym3(S)  # step 9
        if self.heading_free:
            # Not in Kraft 2003: drop the correction about the predicted vertical (see UKFBiasParams).
            h = zp / math.sqrt(zp @ zp)
            K[:3] -= np.outer(h, h @ K[:3])
            if self.has_bias:
                K[3:6] -= np.outer(h, h @ K[3:6])
            # Covariance for a general gain: P - K Pxz^T - Pxz K^T + K S K^T.
            KPxz = K @ Pxz.T
            self.P = self.P - KPxz - KPxz.T + K @ S @ K.T
        else:
            self.P = self.P - Pxz @ K.T  # step 9: P - K P_zz K^T, with K P_zz = P_xz
        y = z - zp
        dx = (K @ y).tolist()
        x = self.x
        q = unit_array(multiply_floats(x[:4].tolist(), exp_floats(dx[0], dx[1], dx[2])))  # step 9: q exp(K y / 2)
        if self.has_bias:
            self.x = np.concatenate([q, x[4:] + dx[3:]])
        else:
            self.x = q
        self.K, self.S, self.y = K, S, y

    # -- reference path: FilterPy hooks, one point at a time --
    def predict_reference(self, dt: float, gyr_rad_s: np.ndarray, Q: np.ndarray) -> None:
        """Steps 1-5 through the hooks: sigma_points(x, P + Q), fx per point, own UT."""
        sigmas = self.points_fn.sigma_points(self.x, self.P + Q)  # steps 2-3 (Q before the UT)
        for i, s in enumerate(sigmas):
            self.sigmas_f[i] = self.fx(s, dt, gyr_rad_s=gyr_rad_s)  # steps 1, 4
        self.x, self.P = unscented_transform_state(self.sigmas_f, self.Wm, self.Wc, None, self.x_mean, self.residual_x)  # step 5
        # No re-draw of sigma points here (FilterPy's predict would): Kraft's update uses Y_i.
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update_reference(self, z: np.ndarray, R: np.ndarray, lag: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Steps 6-9 by FilterPy's own `UnscentedKalmanFilter.update` (Euclidean UT for z);
        lag as in `update_kraft`, added to the measurement model per point."""
        if lag is None:
            UnscentedKalmanFilter.update(self, z, R=R)
            return
        mean = self.x.copy()

        def hx_lagged(x: np.ndarray) -> np.ndarray:
            z_x = quat.gravity_in_body(x[:4]) + lag[0] @ (x[4:7] - mean[4:7])
            return z_x + lag[1] @ (x[7:10] - mean[7:10]) if len(x) > 7 else z_x

        UnscentedKalmanFilter.update(self, z, R=R, hx=hx_lagged)


# --------------------------------------------------------------------------- estimators
class UKF(KalmanFilter):
    """`ukf`: the quaternion UKF after Kraft 2003 (see the module docstring for the steps)."""

    Params = UKFParams
    with_bias = False

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        p = self.params
        n = error_dim(p)
        points = QuaternionSigmaPoints(n, p.sigma, p.kappa, p.alpha, p.beta)
        kf = QuaternionUKF(points, p.mean_tol_rad, p.mean_max_iter)
        kf.heading_free = p.heading_free
        kf.x = np.concatenate([initial_quaternion(type(self).__name__, init_quat_wxyz), np.zeros(n - 3)])
        kf.P, self._Qrate, self._Qbad = error_state_covariances(p, n)
        self.kf = kf
        self.n = n
        self._scale_noise = 0.0 if n > 3 else p.scale_noise_s
        self._eye3 = np.eye(3)
        # ukf-bias: the low-passed sample's lag in the measurement model, as in `ekf`
        self._with_lag = models_lag(p, n)
        self._dist = AccDisturbance(p.disturbance_window_s, p.acc_lowpass_s, p.acc_lowpass_window_s, self._with_lag)
        self._rest = RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s) if self.with_bias else None
        self._stuck = stuck_gyro_state()
        if self.with_bias:  # ukf-bias in 9-D: the magnetometer's gates and hard-iron fit, as in `ekf`
            self._mag = MagReference(p.mag_norm_gate_frac, p.mag_dip_gate_rad, p.mag_min_undisturbed_s, p.mag_ref_s)
            self._hard_iron = HardIron(p.mag_hard_iron_window_s, p.mag_hard_iron_residual_ut, p.mag_hard_iron_coverage)
        self.mag_used = False  # whether the last step made the magnetometer's heading update (ukf-bias)
        self.hard_iron_used = False  # ... with the sphere fit's offset removed
        self.acc_var = math.nan  # accelerometer variance of the last update, g^2 (nan: none)
        self.at_rest = False  # whether the last step made the rest bias update
        self.nis = math.nan  # normalised innovation squared of the last update (nan: none)
        self.lowpassed = False  # whether the last update used the low-passed accelerometer
        self._predict = kf.predict_reference if p.impl == "filterpy" else kf.predict_kraft
        self._update = kf.update_reference if p.impl == "filterpy" else kf.update_kraft
        self.n_skipped = self.n_sqrt_recovered = self.n_cov_repaired = self.n_mean_capped = 0

    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool,
             mag_ut: np.ndarray | None = None) -> np.ndarray:
        """`RecursiveEstimator.step`, plus mag_ut: (3,) the magnetometer sample at the step's end,
        uT, body frame, or None: the heading update of `ukf-bias` in 9-D (`ukf` ignores it)."""
        p, kf, n = self.params, self.kf, self.n
        gyr_valid = self._usable(gyr_rad_s, dt_s, acc_g, gyr_valid)
        self.acc_var, self.at_rest, self.nis, self.lowpassed = math.nan, False, math.nan, False
        self.mag_used = self.hard_iron_used = False
        Q = self._Qrate * dt_s
        x = kf.x
        w = np.zeros(3)  # the step's corrected rate (rad/s; zero when not integrated)
        if not gyr_valid or not (math.isfinite(gyr_rad_s[0]) and math.isfinite(gyr_rad_s[1]) and math.isfinite(gyr_rad_s[2])):
            gyr = None  # no rate integration; inflate the attitude noise instead
            Q = Q + self._Qbad * (dt_s * dt_s)
            gyr_valid = False
            dq = (1.0, 0.0, 0.0, 0.0)
            self._dist.lose_frame()
        else:
            gyr = gyr_rad_s
            # The mean rate increment, for the disturbance estimator's strapdown frame.
            w = gyr_rad_s - x[4:7] if n > 3 else gyr_rad_s
            if n > 6:
                w = w * (1.0 + x[7:10])
            dq = exp_floats(w[0] * dt_s, w[1] * dt_s, w[2] * dt_s)
            if self._scale_noise > 0.0:
                # ukf only: gyro scale-factor uncertainty as rate noise density Qs w_i^2 per axis.
                Q = Q.copy()
                Q[0, 0] += self._scale_noise * gyr_rad_s[0] * gyr_rad_s[0] * dt_s
                Q[1, 1] += self._scale_noise * gyr_rad_s[1] * gyr_rad_s[1] * dt_s
                Q[2, 2] += self._scale_noise * gyr_rad_s[2] * gyr_rad_s[2] * dt_s
        self._predict(dt_s, gyr, Q)
        self.n_sqrt_recovered += kf.sqrt_recovered
        self.n_mean_capped += kf.mean_iterations >= p.mean_max_iter
        if self._rest is not None and gyr_valid and self._rest.update(gyr_rad_s, acc_g, dt_s):
            # Zero-rate update at rest (VQF, Sec. 3.4): the gyro reads the bias; H = [0, I, 0] is
            # linear, so this is the exact Kalman update, the same for both implementations.
            x = kf.x
            dx, kf.P = bias_rest_update(x[4:7], kf.P, gyr_rad_s, p.rest_noise_rad2_s / dt_s)
            qn = unit_array(multiply_floats(x[:4].tolist(), exp_floats(dx[0], dx[1], dx[2])))
            kf.x = np.concatenate([qn, x[4:] + dx[3:]])
            self.at_rest = True
        scale = acc_variance_scale(acc_g, p.gate, p.gate_g) if p.use_acc else math.inf
        rate, gain = self._lag_rate(gyr_rad_s if gyr_valid else None)
        if scale < math.inf:
            q_rate = p.process_noise_rad2_s  # ukf: plus the scale noise Qs w_i^2, a rate noise density too
            if gyr_valid and self._scale_noise > 0.0:
                q_rate += self._scale_noise * float(np.max(gyr_rad_s * gyr_rad_s))
            meas, r, self.lowpassed = accelerometer_update_input(p, self._dist, acc_g, dq, dt_s, scale, q_rate, rate,
                                                                 gain)
            self.acc_var = r
            lag = None
            if self._with_lag and self.lowpassed:
                lag = self._dist.lag_jacobian(quat.skew(quat.gravity_in_body(kf.x[:4])))
            self._update(meas, self._eye3 * r, lag)
            y = kf.y
            self.nis = float(y @ inv_sym3(kf.S) @ y)  # normalised innovation squared, chi-square(3) if consistent
        else:
            self.n_skipped += 1
            if p.disturbance_corr_s > 0.0:  # the strapdown frame follows the gyro through skipped updates
                self._dist.turn(dq, dt_s, rate, gain)
        if (self.with_bias and mag_ut is not None and math.isfinite(mag_ut[0]) and math.isfinite(mag_ut[1])
                and math.isfinite(mag_ut[2])):
            # 9-D: the heading-only magnetometer update of `ekf` (`_attitude.heading_update`); H is
            # linear in the error state, so it is the same Kalman update for every implementation
            x = kf.x
            q = tuple(x[:4].tolist())
            usable, east, north, self.hard_iron_used = magnetometer_input(p, self._mag, self._hard_iron, q, mag_ut,
                                                                          dt_s)
            if usable:
                r = heading_variance(p, q, w[0] * dt_s, w[1] * dt_s, w[2] * dt_s, dt_s)
                dx, kf.P = heading_update(q, kf.P, n, east, north, r)
                qn = unit_array(multiply_floats(x[:4].tolist(), exp_floats(dx[0], dx[1], dx[2])))
                kf.x = np.concatenate([qn, x[4:] + dx[3:]])
                self.mag_used = True
        x = kf.x
        if n > 3:
            np.clip(x[4:7], -p.bias_max_rad_s, p.bias_max_rad_s, out=x[4:7])
        if n > 6:
            np.clip(x[7:10], -p.scale_max, p.scale_max, out=x[7:10])
        kf.P, repaired = repair_covariance(kf.P)
        self.n_cov_repaired += repaired
        return x[:4]

    def _lag_rate(self, gyr_rad_s: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The lag's inputs (`AccDisturbance.update`) from the current mean's calibration: the
        bias-corrected rate (None: not integrated) and `1 + s`; (None, None) without the lag."""
        if not self._with_lag:
            return None, None
        x = self.kf.x
        gain = 1.0 + x[7:10] if self.n > 6 else np.ones(3)
        return (None if gyr_rad_s is None else gyr_rad_s - x[4:7]), gain

    def current(self) -> dict[str, Any]:
        kf = self.kf
        out = {"cov": kf.P, "mean_iterations": kf.mean_iterations, "acc_var_g2": self.acc_var, "nis": self.nis,
               "acc_lowpassed": self.lowpassed}
        if self.with_bias:
            out["gyr_bias_rad_s"] = kf.x[4:7]
            out["at_rest"] = self.at_rest
            out["mag_used"] = self.mag_used
            out["mag_hard_iron"] = self.hard_iron_used
            if self.n > 6:
                out["gyr_scale"] = kf.x[7:10]
        return out

    def diagnostics(self) -> dict[str, Any]:
        return {
            "updates_skipped": self.n_skipped,
            "sqrt_recoveries": self.n_sqrt_recovered,
            "cov_repairs": self.n_cov_repaired,
            "mean_iteration_cap_hits": self.n_mean_capped,
        }

    def _run_kernel(self, kernels: Any, imu: ImuSamples, out: dict[str, np.ndarray], dist: np.ndarray,
                    rest: np.ndarray) -> None:
        p, kf = self.params, self.kf
        x, P = kf.x.copy(), kf.P.copy()
        o = kernels.settings(p, self.n, self._rest, scale_noise=self._scale_noise, sqrt_c=kf.points_fn.sqrt_c,
                             mean_tol=p.mean_tol_rad, mean_max_iter=p.mean_max_iter)
        mag_state = self._mag.state() if self.with_bias else np.zeros(5)
        hard_iron = self._hard_iron.state() if self.with_bias else np.zeros(HARD_IRON_STATE)
        (self.n_skipped, self.n_sqrt_recovered, self.n_cov_repaired, self.n_mean_capped) = kernels.ukf_kernel(
            *kernels.inputs(imu), *kernels.mag_inputs(imu, self.magnetometer), x, P, self._Qrate, self._Qbad, kf.Wm,
            kf.Wc, dist, rest, mag_state, hard_iron, o,
            out["quat"], out["cov"], out["gyr_bias_rad_s"], out["gyr_scale"], out["mean_iterations"],
            out["acc_var_g2"], out["at_rest"], out["nis"], out["acc_lowpassed"], out["mag_used"], out["mag_hard_iron"])
        kf.x, kf.P, kf.mean_iterations = x, P, int(out["mean_iterations"][-1])
        if self.with_bias:
            self._mag.set_state(mag_state)
            self._hard_iron.set_state(hard_iron)


class UKFBias(UKF):
    """`ukf-bias`: the UKF with the gyro bias (and scale factors) in the state, 6 or 9-dof error."""

    Params = UKFBiasParams
    with_bias = True
    magnetometer = True  # 9-D where the recording has a magnetometer (the heading-only update of `ekf`)
    LAST_ROW = {**KalmanFilter.LAST_ROW, "mag_used": "mag_used", "mag_hard_iron": "hard_iron_used"}
