"""`ekf`: a multiplicative (error-state) EKF with the UKF's process and measurement models.

Nominal state `q = R_world_body` (wxyz) and gyro bias `b` (rad/s, body); error state
`dx = [e, db]` with the body-frame rotation error `q_true = q exp(e / 2)` (the same
convention as `ukf`), covariance P (6x6; 3x3 with `estimate_bias=False`).

Predict (gyro as control input, as in `ukf` step 1):
    theta = (w - b) dt,  q <- q exp(theta / 2)           (Sola 2017, eq. 260a-b)
    F = [[R(theta)^T, -J_r(theta) dt], [0, I]]          (Sola 2017, eq. 270, with J_r for the exact step)
    P <- F P F^T + diag((Q + Qs w_i^2) dt, Qb dt)       (Sola 2017, eq. 269; densities, Sec. 5.4.3)
Rest (bias rows only): after `rest_time_s` still, the zero-rate pseudo-measurement
    gyr = b + n, H = [0, I] (Laidig & Seel 2023, VQF, Sec. 3.4: bias estimation at rest);
    the bias estimate is clipped to `bias_max_rad_s`.
Update (accelerometer = gravity in the body frame, as in `ukf` steps 6-7):
    h(q) = R(q)^T e_z,  H = [[h]x, 0]                    (exp(e)^T h ~ h + h x e)
    R_k = (R + 2 tauc d_k) / dt I   adaptive: d_k the external-acceleration power of
                  `_attitude.AccDisturbance` (Suh 2010, IEEE TIM 59(12), adapts R to the
                  external acceleration; here from attitude-free statistics)
    S = H P H^T + R_k,  K = P H^T S^-1,  dx = K (a - h)  (Sola 2017, eq. 274-276)
    heading_free: K <- (I - h h^T) K on the attitude and bias rows (no turn about the
                  predicted vertical; the Joseph form below is exact for any gain)
    q <- q exp(dx_e / 2),  b <- b + dx_b                 (error injection, reset not modelled)
    P <- (I - K H) P (I - K H)^T + K R K^T               (Joseph form)

FilterPy: this filter sits *beside* `filterpy.kalman.ExtendedKalmanFilter`, not on it.
FilterPy's EKF sizes x and P together (dim_x), adds the correction (`x + K y`) and
predicts with a linear `F x`; for an error-state filter with a quaternion nominal state
every one of those lines would be overridden and only attribute names would remain, at
FilterPy's per-call cost (column-vector bookkeeping, `deepcopy(z)`). The update uses the same
Joseph form as FilterPy's `ExtendedKalmanFilter.update`.

Robustness as in `ukf`: invalid or non-finite gyro samples are not integrated (zero rate,
attitude noise inflated by `invalid_gyr_std_rad_s^2 dt^2`), non-finite accelerometer samples
skip the update, the optional fixed gating (`gate`, `gate_g`; off by default) inflates R or
skips the update when `| |a| - 1 g |` is large, and the covariance is symmetrised (eigenvalues clipped if needed) every step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fusion.types import ImuSamples

from ._attitude import (
    AccDisturbance,
    RestDetector,
    acc_step_variance,
    acc_variance_scale,
    bias_rest_update,
    exp_quat,
    inv_sym3,
    mul_floats,
    repair_covariance,
    unit_array,
)
from .base import RecursiveEstimator
from .ukf import Gate, _check_nonneg, check_bias_params, check_filter_params


@dataclass(frozen=True)
class EKFParams:
    """Parameters of `ekf` (units in the names; aliases in brackets).

    Noise is given as continuous-time densities, so one set means the same at 100 Hz and at
    286 Hz (Sola 2017, Sec. 5.4.3 / 6.3, random impulses: a density sigma^2 over a step dt
    gives the variance sigma^2 dt for a rate noise integrated into an angle, and sigma^2 / dt
    for a white measurement noise sampled once per step):

    process_noise_rad2_s (Q): gyro (attitude process) noise density, rad^2/s; step
        variance `Q dt` per axis.
    acc_noise_g2_s (R): accelerometer noise density, g^2 s; step variance `R / dt` per axis
        (a per-sample variance R_k at rate f is the density R_k / f: 3e-3 g^2 at 100 Hz is
        3e-5 g^2 s). With no disturbance the attitude correction has the time constant
        `sqrt(R / Q)` (0.17 s with the defaults), independent of the rate.
    init_var_rad2 (P0): initial attitude variance per axis, rad^2.
    bias_walk_rad2_s3 (Qb): gyro-bias random-walk density, rad^2/s^3 (step variance Qb dt).
    init_bias_var_rad2_s2 (Pb0): initial bias variance per axis, (rad/s)^2.
    estimate_bias (bias): False drops the bias from the state.
    bias_max_rad_s (bmax): the bias estimate is clipped to this per axis, rad/s (the
        calibration removed the rest bias; a larger one means a wrong update).
    disturbance_corr_s (tauc): correlation time of the external acceleration, s (adaptive R,
        see `_attitude.AccDisturbance`); 0 turns the adaptation off.
    disturbance_window_s (tauw): time constant of its running variance, s.
    rest_gyr_rad_s, rest_acc_g, rest_time_s: rest detection (gyro norm, accelerometer
        deviation, minimum duration) for the zero-rate bias update; rest_time_s = inf
        turns it off.
    rest_noise_rad2_s (Rrest): density of the gyro reading at rest, rad^2/s (step variance
        Rrest / dt).
    use_acc (acc), gate, gate_g, invalid_gyr_std_rad_s (Qbad): as for `ukf` (the fixed
        gate is off by default: the adaptive R replaces it).
    heading_free (hf): see the module docstring and `ukf`.
    scale_noise_s (Qs): gyro scale-factor uncertainty, s: adds the rate-noise density
        `Qs w_i^2` (rad^2/s) on body axis i, i.e. a scale error of standard deviation
        sigma_s with correlation time tau_s gives Qs = 2 tau_s sigma_s^2 (2e-2 s: about 10 %
        over 1 s). Fast rotations then lower the gyro's weight, so a mis-scaled gyro (the
        course board: +9 % x) is corrected within a fraction of a second.

    Defaults (one set for every recording and rate): Q = 1e-3 rad^2/s, R = 3e-5 g^2 s,
    Qs = 2e-2 s, tauc = tauw = 0.5 s. Mean inclination RMSE: ece276a 1-9 1.90 deg
    (total 6.89); BROAD nine trials 1.79 deg, below gyro integration on every trial.
    """

    process_noise_rad2_s: float = field(default=1e-3, metadata={"alias": "Q"})
    acc_noise_g2_s: float = field(default=3e-5, metadata={"alias": "R"})
    scale_noise_s: float = field(default=2e-2, metadata={"alias": "Qs"})
    init_var_rad2: float = field(default=1e-4, metadata={"alias": "P0"})
    bias_walk_rad2_s3: float = field(default=1e-8, metadata={"alias": "Qb"})
    init_bias_var_rad2_s2: float = field(default=1e-5, metadata={"alias": "Pb0"})
    estimate_bias: bool = field(default=True, metadata={"alias": "bias"})
    bias_max_rad_s: float = field(default=0.035, metadata={"alias": "bmax"})
    heading_free: bool = field(default=True, metadata={"alias": "hf"})
    use_acc: bool = field(default=True, metadata={"alias": "acc"})
    disturbance_corr_s: float = field(default=0.5, metadata={"alias": "tauc"})
    disturbance_window_s: float = field(default=0.5, metadata={"alias": "tauw"})
    rest_gyr_rad_s: float = 0.035
    rest_acc_g: float = 0.05
    rest_time_s: float = 1.5
    rest_noise_rad2_s: float = field(default=1e-6, metadata={"alias": "Rrest"})
    gate: Gate = "off"
    gate_g: float = 0.2
    invalid_gyr_std_rad_s: float = field(default=2.0, metadata={"alias": "Qbad"})

    def __post_init__(self) -> None:
        _check_nonneg("ekf", bias_walk_rad2_s3=self.bias_walk_rad2_s3, init_bias_var_rad2_s2=self.init_bias_var_rad2_s2)
        check_filter_params(self, "ekf")
        check_bias_params(self, "ekf")


def _rotation_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """R(q) for a unit quaternion (body -> world)."""
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _right_jacobian(tx: float, ty: float, tz: float) -> np.ndarray:
    """SO(3) right Jacobian J_r(theta) (Sola 2017, the SO(3) right Jacobian); I - [theta]x / 2 near 0."""
    a2 = tx * tx + ty * ty + tz * tz
    S = np.array([[0.0, -tz, ty], [tz, 0.0, -tx], [-ty, tx, 0.0]])
    if a2 < 1e-12:
        return np.eye(3) - 0.5 * S
    a = math.sqrt(a2)
    return np.eye(3) - (1.0 - math.cos(a)) / a2 * S + (a - math.sin(a)) / (a2 * a) * (S @ S)


class EKF(RecursiveEstimator):
    """`ekf`: multiplicative error-state EKF with analytic Jacobians (see module docstring)."""

    Params = EKFParams

    def reset(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> None:
        p = self.params
        q0 = np.asarray(init_quat_wxyz, dtype=float)
        if q0.shape != (4,) or not np.all(np.isfinite(q0)) or np.linalg.norm(q0) == 0.0:
            raise ValueError(f"ekf: init_quat_wxyz must be a finite non-zero (4,) quaternion, got {q0!r}")
        n = 6 if p.estimate_bias else 3
        self.n = n
        self.q = q0 / np.linalg.norm(q0)
        self.b = np.zeros(3)
        self.P = np.zeros((n, n))
        self.P[:3, :3] = np.eye(3) * p.init_var_rad2
        self._Qrate = np.zeros((n, n))
        self._Qrate[:3, :3] = np.eye(3) * p.process_noise_rad2_s
        if p.estimate_bias:
            self.P[3:, 3:] = np.eye(3) * p.init_bias_var_rad2_s2
            self._Qrate[3:, 3:] = np.eye(3) * p.bias_walk_rad2_s3
        self._Qbad = np.zeros((n, n))
        self._Qbad[:3, :3] = np.eye(3) * p.invalid_gyr_std_rad_s**2
        self._eye3 = np.eye(3)
        self._dist = AccDisturbance(p.disturbance_window_s)
        self._rest = RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s)
        self._F = np.eye(n)
        self._H = np.zeros((3, n))
        self._I = np.eye(n)
        N = len(imu)
        self._cov = np.full((N, n, n), np.nan)
        self._cov[0] = self.P
        self._bias = np.zeros((N, 3))
        self._acc_var = np.full(N, np.nan)
        self._at_rest = np.zeros(N, bool)
        self.n_skipped = self.n_cov_repaired = 0

    def step(self, k: int, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        p = self.params
        Q = self._Qrate * dt_s
        F = self._F
        q, b = self.q.tolist(), self.b
        if gyr_valid and math.isfinite(gyr_rad_s[0]) and math.isfinite(gyr_rad_s[1]) and math.isfinite(gyr_rad_s[2]):
            tx, ty, tz = (gyr_rad_s - b) * dt_s if p.estimate_bias else gyr_rad_s * dt_s
            if p.scale_noise_s > 0.0:
                c = p.scale_noise_s / dt_s
                Q = Q.copy()
                Q[0, 0] += c * tx * tx
                Q[1, 1] += c * ty * ty
                Q[2, 2] += c * tz * tz
        else:  # no rate integration; inflate the attitude noise instead
            tx = ty = tz = 0.0
            Q = Q + self._Qbad * (dt_s * dt_s)
        d = exp_quat(tx, ty, tz)
        q = mul_floats(q, d)  # q exp(theta / 2), as 4 floats
        F[:3, :3] = _rotation_matrix(*d).T  # Sola 2017: error transition R(theta)^T
        if self.n == 6:
            F[:3, 3:] = -dt_s * _right_jacobian(tx, ty, tz)
        P = F @ self.P @ F.T + Q
        if self.n == 6 and gyr_valid and self._rest.update(gyr_rad_s, acc_g, dt_s):
            # Zero-rate update at rest (VQF, Sec. 3.4): the gyro reads the bias.
            dx, P = bias_rest_update(self.b, P, gyr_rad_s, p.rest_noise_rad2_s / dt_s)
            q = mul_floats(q, exp_quat(dx[0], dx[1], dx[2]))
            self.b = self.b + dx[3:]
            self._at_rest[k + 1] = True
        scale = acc_variance_scale(acc_g, p.gate, p.gate_g) if p.use_acc else math.inf
        if scale < math.inf:
            d = self._dist.update(q, acc_g, dt_s) if p.disturbance_corr_s > 0.0 else 0.0
            r = acc_step_variance(p.acc_noise_g2_s, p.disturbance_corr_s, d, dt_s) * scale
            self._acc_var[k + 1] = r
            w, x, y, z = q
            h = np.array([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z])
            H = self._H
            H[0, 1], H[0, 2] = -h[2], h[1]  # [h]x
            H[1, 0], H[1, 2] = h[2], -h[0]
            H[2, 0], H[2, 1] = -h[1], h[0]
            PHt = P @ H.T
            S = H @ PHt
            S[0, 0] += r
            S[1, 1] += r
            S[2, 2] += r
            K = PHt @ inv_sym3(S)
            if p.heading_free:
                # Remove the attitude correction about the predicted vertical h (|h| = 1):
                # K <- (I - h h^T) K on the attitude rows; the Joseph form stays exact.
                K[:3] -= np.outer(h, h @ K[:3])
                if self.n == 6:
                    K[3:] -= np.outer(h, h @ K[3:])
            dx = K @ (acc_g - h)
            q = mul_floats(q, exp_quat(dx[0], dx[1], dx[2]))
            if self.n == 6:
                self.b = self.b + dx[3:]
            IKH = self._I - K @ H
            P = IKH @ P @ IKH.T + r * (K @ K.T)  # Joseph form
        else:
            self.n_skipped += 1
        if self.n == 6:
            self.b = np.clip(self.b, -p.bias_max_rad_s, p.bias_max_rad_s)
        self.q = unit_array(q)
        self.P, repaired = repair_covariance(P)
        self.n_cov_repaired += repaired
        self._cov[k + 1] = self.P
        self._bias[k + 1] = self.b
        return self.q

    def diagnostics(self) -> dict[str, Any]:
        return {
            "cov": self._cov,
            "gyr_bias_rad_s": self._bias,
            "acc_var_g2": self._acc_var,
            "at_rest": self._at_rest,
            "updates_skipped": self.n_skipped,
            "cov_repairs": self.n_cov_repaired,
        }
