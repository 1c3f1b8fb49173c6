"""The batch smoother's cost, residuals and analytic Jacobians (shared by `gd` and `gn`).

The cost over the whole recording (weighted least squares with a robust accelerometer term):

    c(q, v, theta) = 1/2 sum_t  w_m,t |r_m,t|^2                          (motion, t = 0 .. T-2)
                   + 1/2 sum_t  w_a,t c^2 rho(|r_a,t|^2 / c^2)            (accelerometer, t = 0 .. T-1)
                   + 1/2 w_0 |r_0|^2 + 1/2 theta^T W_theta theta          (anchor of q_0, calibration prior)
                   + 1/2 sum_t  w_v,t |r_v,t|^2 + 1/2 sum_t w_z,t |v_t|^2   (optional velocity model)
                   + 1/2 sum_t  w_r,t |w_t|^2                            (rest: steps detected at rest)
                   + 1/2 sum_t  w_h,t c_h^2 rho(r_h,t^2 / c_h^2)         (magnetometer, 9-D: heading only)

    r_m,t = 2 log(q_{t+1}^-1 * q_t * exp([0, w_t dt_t / 2]))            (motion residual)
    r_a,t = a_t - h(q_t),   h(q) = R(q)^T e_z                           (observation residual, g)
    r_0   = 2 log(q_init^-1 * q_0)
    w_t   = (1 + k) * g_t - b   (element-wise; k scale errors, b bias, both optional, in theta)
    r_v,t = v_{t+1} - v_t - G P (R(q_t) a_t + R(q_{t+1}) a_{t+1}) dt_t / 2   (m/s; P: world x, y)

Weights are those of continuous-time white noise, so one parameter set means the same at
any sampling rate: gyro noise of variance density Q (rad^2/s) integrates to an angle random
walk, w_m,t = 1 / (Q dt_t) (the angle random walk of IEEE Std 952-1997, Annex C; Q is the
square of the standard-deviation density a datasheet gives in rad/s/sqrt(Hz));
accelerometer noise of density R (g^2 s) gives a sample that stands for dt_t seconds the
variance R / dt_t, w_a,t = dt_t / R, so that the information
per second of accelerometer is rate independent. `rho` is a robust loss (`robust_loss`),
used through iteratively reweighted least squares. Where the gyro sample is invalid
(`gyr_valid` False) the step predicts no rotation and its density is the dropout density.

The velocity model uses what VQF exploits by low-pass filtering the accelerometer in an
almost inertial frame (Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation
with bias estimation and magnetic disturbance rejection", Information Fusion 91): linear
acceleration integrates to a bounded velocity. The horizontal world-frame specific force is
integrated (trapezoidal rule) into a velocity v_t (2 variables per sample, m/s), and a
pseudo-measurement v_t = 0 of density Rv (w_z,t = dt_t / Rv) keeps it bounded. A tilt error
delta turns 1 g into a horizontal acceleration g delta, which the velocity cannot absorb
for long; a linear acceleration that averages out over seconds, can. Each increment touches
two neighbours only, so the normal equations stay block-tridiagonal (5x5 blocks).

At rest the true rate is zero, so the gyro reads its bias (the rest part of VQF's bias
estimation, Laidig & Seel 2023, Sec. 3.4): on steps that a rest detector flags
(`_compiled_rest.rest_steps`, the one the filters use), the rate w_t itself is a residual with the
density Rrest of the gyro noise at rest (w_r,t = dt_t / Rrest), on the axes that have a
bias variable. It touches only the calibration variables. An axis without a bias variable
takes the mean rest reading as a fixed bias (`from_imu`): about the vertical, nothing but the
gyro sees a rotation, so the rest is the only place its bias can be read.

The magnetometer term (9-D, optional; `SmootherProblem.with_magnetometer`) corrects the heading
only, as the magnetometer's correction in VQF (Laidig & Seel 2023, Sec. 3.3: a rotation about
the world's vertical; the accelerometer owns the inclination). Its residual on sample t is the
heading error psi_t of a reference trajectory q_ref (the 6-D solution) against magnetic north,
measured by the magnetometer there (`fusion.estimators.smoothers.mag.measurements`, eq. 1, with
its gates and hard-iron fit), plus the turn of q_t from q_ref,t about the world vertical:

    r_h,t = wrap(psi_t + tau(q_t q_ref,t^-1)),   tau(d) = 2 atan2(d_z, d_w)

tau is the twist about world z of the swing-twist decomposition of d (a rotation about a
horizontal axis has none), so r_h depends on q_t's heading only, and at q_t = q_ref,t turning
q_t by phi about the world vertical adds phi. With q_t <- q_t Exp(delta), q_t Exp(delta)
q_ref^-1 = Exp(R(q_t) delta) d, and the first-order change of tau is k^T R(q_t) delta with

    k = [d_w d_y + d_z d_x, d_z d_y - d_w d_x, d_w^2 + d_z^2] / (d_w^2 + d_z^2)

(k = e_z at d = 1: then the Jacobian is R^T e_z, the body-frame vertical). w_h,t is the heading
measurement's information (0 for a gated-out sample) and rho the robust loss of the
accelerometer's term (`robust_loss`) at scale c_h, rad. A unary term: it adds to the diagonal
blocks and the gradient only.

The anchor `r_0` fixes the gauge: the cost is invariant under a rotation of the whole
trajectory about world z, so without it the normal equations are singular in heading.

Perturbations are on the right, `q_t <- q_t * exp([0, delta_t / 2])` (delta_t in R^3, body
frame). The Jacobians below are exact (SO(3) left/right Jacobians of `fusion.quaternion`, Sola
et al. 2018, "A micro Lie theory", eqs. 143-146); `tests/test_smoother.py` and
`tests/test_smoother_robust.py` check them against finite differences. Everything is
vectorised over samples. The normal equations of a `Linearization` are solved in
`fusion.estimators.smoothers.solve`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np


from fusion import quaternion as quat
from fusion.quaternion import right_jacobian, right_jacobian_inv, rotation_matrix
from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples
from ..params import SMOOTHER_FORMER_STD, FormerSpellings

AXES = "xyz"


# ----------------------------------------------------------------------------- the problem
LOSSES = ("none", "huber", "cauchy", "geman-mcclure")


def robust_loss(kind: str, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """rho(s) and rho'(s) of a robust loss on the normalised squared residual s = |r|^2 / c^2.

    The cost term is `c^2 rho(s)` (so all losses equal |r|^2 for |r| << c):
    - "none": rho = s;
    - "huber": rho = s for s <= 1, 2 sqrt(s) - 1 beyond (linear pull; Huber 1964);
    - "cauchy": rho = log(1 + s) (influence falls as 1/|r|);
    - "geman-mcclure": rho = s / (1 + s) (redescending, bounded; Geman & McClure 1987).
    These are M-estimators as tabulated by Zhang 1997 ("Parameter estimation techniques: a
    tutorial with application to conic fitting", Image and Vision Computing 15); rho' is the
    weight of iteratively reweighted least squares.
    """
    if kind == "none":
        return s, np.ones_like(s)
    if kind == "huber":
        root = np.sqrt(s)
        inside = root <= 1.0
        return np.where(inside, s, 2.0 * root - 1.0), np.where(inside, 1.0, 1.0 / np.maximum(root, 1e-300))
    if kind == "cauchy":
        return np.log1p(s), 1.0 / (1.0 + s)
    if kind == "geman-mcclure":
        return s / (1.0 + s), 1.0 / (1.0 + s) ** 2
    raise ValueError(f"robust loss {kind!r}: expected one of {', '.join(LOSSES)}")


def robust_terms(kind: str, c: float, w: np.ndarray, sq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cost terms `1/2 w c^2 rho(sq / c^2)` and IRLS weights `w rho'` (d term / d r = w rho' r) of
    residuals of squared norms sq (T,), information w (T,) and robust loss `kind` of scale c
    (`robust_loss`; "none": 1/2 w sq and w): the accelerometer's and the magnetometer's terms."""
    if kind == "none":
        return 0.5 * w * sq, w
    c2 = c**2
    rho, drho = robust_loss(kind, sq / c2)
    return 0.5 * w * c2 * rho, w * drho


def sample_durations(t: np.ndarray) -> np.ndarray:
    """(T,) the time each sample stands for, s: half of each neighbouring interval
    (the trapezoidal rule's weights), so that sum_t f_t dt_t approximates the integral of f."""
    dt = np.diff(np.asarray(t, float))
    out = np.zeros(len(t))
    out[:-1] += 0.5 * dt
    out[1:] += 0.5 * dt
    return out


@dataclass(frozen=True)
class Weights(FormerSpellings):
    """Noise model and robust loss of the cost, in continuous time.

    Every noise and prior level is a variance (a variance density for continuous-time noise),
    as in `SmootherParams` and the filters:
    process_noise_rad2_s: gyro noise density Q, rad^2/s (= (rad/s)^2/Hz); the motion residual
        of a step of dt seconds has variance Q dt (integrated white rate noise: a random walk
        in angle).
    acc_noise_g2_s: accelerometer noise density R, g^2 s (= g^2/Hz); a sample standing for dt
        seconds has variance R / dt, so the information per second of accelerometer data does
        not depend on the sampling rate.
    loss: robust loss on the accelerometer residual ("none", "huber", "cauchy", "geman-mcclure").
    loss_scale_g: the loss's scale c on the residual norm, g (inf: plain least squares).
    init_var_rad2: variance of the anchor of q_0 at the initial orientation, rad^2.
    dropout_noise_rad2_s: density of the angle random walk where the gyro is invalid, rad^2/s.
    motion_weight / acc_weight: fixed scalar information per term instead of the noise model
        (scalar weighting: motion 10, accelerometer 1); None uses the noise model.
    bias_axes / scale_axes: which gyro biases / scale errors are variables ("", "xy", "xyz").
    init_bias_var_rad2_s2 / init_scale_var: prior variances of those variables around zero.
    velocity_acc_noise_g2_s: density Qv of the accelerometer noise in the horizontal velocity
        increments, g^2 s (inf: no velocity model).
    velocity_bound_m2_s: density Rv of the pseudo-measurement v = 0, m^2/s: per second of
        recording, one observation "v = 0" of variance Rv (m/s)^2 (inf: no velocity model).
    rest_noise_rad2_s: density Rrest of the gyro reading at rest, rad^2/s: a step of dt
        seconds flagged at rest observes "true rate = 0" with variance Rrest / dt.
    """

    former_std: ClassVar[tuple[str, ...]] = SMOOTHER_FORMER_STD  # `AcceptsFormerSpellings`

    process_noise_rad2_s: float = 4e-4
    acc_noise_g2_s: float = 2.5e-5
    loss: str = "huber"
    loss_scale_g: float = 0.1
    init_var_rad2: float = 1e-4
    dropout_noise_rad2_s: float = 0.09
    motion_weight: float | None = None
    acc_weight: float | None = None
    bias_axes: str = ""
    scale_axes: str = ""
    init_bias_var_rad2_s2: float = 2.5e-3
    init_scale_var: float = 0.04
    velocity_acc_noise_g2_s: float = np.inf
    velocity_bound_m2_s: float = np.inf
    rest_noise_rad2_s: float = 1e-4


@dataclass(frozen=True, eq=False)
class Linearization:
    """Cost, gradient and Gauss-Newton normal equations at one point.

    The variables of sample t are x_t = [delta_t (3), v_t (V)] (V = 2 with the velocity model,
    else 0), B = 3 + V of them. grad_q: (T, B) d cost / d x_t. grad_theta: (P,).
    diag: (T, B, B) blocks H[t, t]; off: (T-1, B, B) blocks H[t, t+1];
    cross: (T, B, P) blocks H[t, theta]; theta_block: (P, P).
    """

    cost: float
    grad_q: np.ndarray
    grad_theta: np.ndarray
    diag: np.ndarray
    off: np.ndarray
    cross: np.ndarray
    theta_block: np.ndarray


@dataclass(frozen=True, eq=False)
class Steps:
    """The gyro increments at one theta. phi: (T-1, 3) rotation vectors w_t dt_t, rad;
    u: (T-1, 4) exp([0, phi / 2]); R_u: (T-1, 3, 3) R(u_t); d_phi: (T-1, 3, P) J_r(phi_t) d phi_t / d theta."""

    phi: np.ndarray
    u: np.ndarray
    R_u: np.ndarray
    d_phi: np.ndarray


def up_in_body(q: np.ndarray) -> np.ndarray:
    """(T, 3) h(q) = R(q)^T e_z, the third row of R(q): `quat.gravity_in_body` for unit q
    (the same numbers; from the rotation matrix it is several times faster on long arrays)."""
    return rotation_matrix(q)[:, 2, :]


@dataclass(eq=False)
class SmootherProblem:
    """The cost of one recording. Build with `SmootherProblem.from_imu`."""

    dt: np.ndarray  # (T-1,) s
    gyr: np.ndarray  # (T-1, 3) rad/s, gyro sample t used over step t
    valid: np.ndarray  # (T-1,) bool, gyro usable on step t
    acc: np.ndarray  # (T, 3) g
    w_motion: np.ndarray  # (T-1,) scalar information of each step
    w_acc: np.ndarray  # (T,) accelerometer information per sample, 1/g^2, 0 where the sample is missing (NaN)
    loss: str  # robust loss on the accelerometer residual (`robust_loss`)
    loss_c: float  # its scale on the residual norm, g; inf: plain least squares
    init_quat: np.ndarray  # (4,)
    w_prior: float
    bias_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    scale_idx: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    w_theta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    w_vel: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T-1,) velocity increments, (s/m)^2; empty: no velocity model
    w_vzero: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) zero-velocity pseudo-measurements, (s/m)^2
    w_rest: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T-1,) zero-rate information of steps at rest, (s/rad)^2; empty: none
    w_mag: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) heading information, rad^-2; empty: no magnetometer term
    mag_ref: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (T, 4) q_ref, the trajectory psi was measured at
    mag_psi: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) heading error of q_ref, rad
    mag_loss: str = "none"  # robust loss on the heading residual (`robust_loss`)
    mag_c: float = np.inf  # its scale, rad

    @classmethod
    def from_imu(cls, imu: ImuSamples, init_quat_wxyz: np.ndarray, weights: Weights, use_valid: bool = True,
                 rest: np.ndarray | None = None) -> "SmootherProblem":
        """imu: calibrated samples; init_quat_wxyz: (4,) anchor of q_0; rest: (T-1,) bool, the
        steps at rest (`_compiled_rest.rest_steps`; None: no rest term)."""
        dt = imu.dt
        rate, valid = imu.interval_rates()
        if not use_valid:
            valid = np.ones(len(dt), bool)
        if weights.motion_weight is not None:
            w_motion = np.full(len(dt), float(weights.motion_weight))
            w_motion[~valid] = weights.motion_weight * (weights.process_noise_rad2_s / weights.dropout_noise_rad2_s)
        else:
            # Angle random walk: variance Q dt per step (rad^2).
            density = np.where(valid, weights.process_noise_rad2_s, weights.dropout_noise_rad2_s)
            w_motion = 1.0 / (density * dt)
        if weights.acc_weight is not None:
            w_acc = np.full(len(imu.t), float(weights.acc_weight))
        else:
            # White accelerometer noise of density R: variance R / dt per sample.
            w_acc = sample_durations(imu.t) / weights.acc_noise_g2_s
        if weights.loss not in LOSSES:
            raise ValueError(f"loss={weights.loss!r}: expected one of {', '.join(LOSSES)}")
        # A non-finite accelerometer sample carries no information: weight 0 (its value is zeroed
        # so that 0 * NaN never reaches the cost).
        acc_ok = np.all(np.isfinite(imu.acc_g), axis=1)
        acc = np.where(acc_ok[:, None], imu.acc_g, 0.0)
        bias_idx = np.array([AXES.index(a) for a in weights.bias_axes], int)
        scale_idx = np.array([AXES.index(a) for a in weights.scale_axes], int)
        w_theta = np.concatenate(
            [np.full(len(bias_idx), 1.0 / weights.init_bias_var_rad2_s2), np.full(len(scale_idx), 1.0 / weights.init_scale_var)]
        )
        velocity = np.isfinite(weights.velocity_acc_noise_g2_s) and np.isfinite(weights.velocity_bound_m2_s)
        if velocity:
            # Horizontal velocity increments: white acceleration noise of density G^2 Qv ((m/s^2)^2 s)
            # integrated over dt has variance G^2 Qv dt; a step touching a missing sample has none.
            w_vel = 1.0 / (STANDARD_GRAVITY_M_S2**2 * weights.velocity_acc_noise_g2_s * dt)
            w_vel = np.where(acc_ok[:-1] & acc_ok[1:], w_vel, 0.0)
            # "Velocity stays bounded": v = 0 observed with density Rv (m^2/s), variance Rv / dt.
            w_vzero = sample_durations(imu.t) / weights.velocity_bound_m2_s
        else:
            w_vel, w_vzero = np.zeros(0), np.zeros(0)
        if rest is not None:
            rest = np.asarray(rest, bool)
            if rest.shape != dt.shape:
                raise ValueError(f"{imu.source}: rest mask has shape {rest.shape}, expected {dt.shape}")
            # Zero true rate observed with density Rrest: variance Rrest / dt per step.
            w_rest = np.where(rest & valid, dt / weights.rest_noise_rad2_s, 0.0)
            # An axis without a bias variable takes the bias its rest steps read (their mean rate), fixed.
            if np.any(w_rest):
                fixed = np.setdiff1d(np.arange(3), bias_idx)
                read = np.average(rate[w_rest > 0], axis=0, weights=w_rest[w_rest > 0])
                rate = rate.copy()
                rate[:, fixed] -= read[fixed]
        else:
            w_rest = np.zeros(0)
        return cls(
            dt=dt, gyr=rate, valid=valid, acc=acc, w_vel=w_vel, w_vzero=w_vzero, w_rest=w_rest,
            w_motion=w_motion, w_acc=np.where(acc_ok, w_acc, 0.0),
            loss=weights.loss if np.isfinite(weights.loss_scale_g) else "none", loss_c=float(weights.loss_scale_g),
            init_quat=quat.normalize(np.asarray(init_quat_wxyz, float)),
            w_prior=1.0 / weights.init_var_rad2, bias_idx=bias_idx, scale_idx=scale_idx, w_theta=w_theta,
        )

    def with_magnetometer(self, w_mag: np.ndarray, psi: np.ndarray, q_ref: np.ndarray, loss: str,
                          scale_rad: float) -> "SmootherProblem":
        """This problem with the magnetometer's heading term: w_mag (T,) information of each
        heading measurement, rad^-2 (0: not used); psi (T,) rad, the heading error of q_ref
        (T, 4) measured by the magnetometer; loss, scale_rad: its robust loss and scale, rad."""
        T = len(self.acc)
        w_mag, psi, q_ref = (np.array(a, dtype=float) for a in (w_mag, psi, q_ref))
        if w_mag.shape != (T,) or psi.shape != (T,) or q_ref.shape != (T, 4):
            raise ValueError(f"magnetometer term: expected ({T},), ({T},), ({T}, 4), got {w_mag.shape}, {psi.shape}, "
                             f"{q_ref.shape}")
        if loss not in LOSSES:
            raise ValueError(f"loss={loss!r}: expected one of {', '.join(LOSSES)}")
        return dataclasses.replace(self, w_mag=np.where(np.isfinite(psi), w_mag, 0.0), mag_psi=np.nan_to_num(psi),
                                   mag_ref=quat.normalize(q_ref), mag_loss=loss if np.isfinite(scale_rad) else "none",
                                   mag_c=float(scale_rad))

    def mag_residual(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T,) r_h (rad) and (T, 3) k (module docstring) at q (T, 4)."""
        d = quat.multiply(q, quat.conjugate(self.mag_ref))
        dw, dx, dy, dz = d[:, 0], d[:, 1], d[:, 2], d[:, 3]
        n2 = dw * dw + dz * dz
        x = self.mag_psi + 2.0 * np.arctan2(dz, dw)
        r = x - 2.0 * np.pi * np.floor((x + np.pi) / (2.0 * np.pi))
        safe = np.where(n2 > 0.0, n2, 1.0)
        k = np.stack([(dw * dy + dz * dx) / safe, (dz * dy - dw * dx) / safe, np.ones_like(dw)], axis=1)
        return r, k

    def mag_terms(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T,) heading cost terms `1/2 w c^2 rho(r^2 / c^2)` and (T,) IRLS weights `w rho'`."""
        return robust_terms(self.mag_loss, self.mag_c, self.w_mag, r * r)

    # -------------------------------------------------------------- pieces
    @property
    def n_theta(self) -> int:
        return len(self.bias_idx) + len(self.scale_idx)

    @property
    def n_vel(self) -> int:
        """Velocity variables per sample: 2 (horizontal, world frame, m/s) with the velocity model, else 0."""
        return 2 if len(self.w_vel) else 0

    def zero_velocity(self) -> np.ndarray:
        """(T, V) the velocity variables' starting point."""
        return np.zeros((len(self.acc), self.n_vel))

    def velocity_residual(self, q: np.ndarray, v: np.ndarray, R: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(T-1, 2) r_v,t = v_{t+1} - v_t - G P (R_t a_t + R_{t+1} a_{t+1}) dt_t / 2, m/s, and (T, 3)
        the world-frame accelerometer R_t a_t, g. P keeps world x and y: gravity (world z) drops out,
        and a tilt error delta turns 1 g into a horizontal acceleration g delta.
        R: (T, 3, 3) R(q) if the caller has it."""
        R = rotation_matrix(q) if R is None else R
        f_world = (R @ self.acc[:, :, None])[:, :, 0]
        mean = 0.5 * (f_world[:-1, :2] + f_world[1:, :2])
        return v[1:] - v[:-1] - STANDARD_GRAVITY_M_S2 * mean * self.dt[:, None], f_world

    def theta_names(self) -> list[str]:
        """The calibration variables' names, in theta's order ("bias_x", ..., "scale_y")."""
        return [f"bias_{AXES[i]}" for i in self.bias_idx] + [f"scale_{AXES[i]}" for i in self.scale_idx]

    def split_theta(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """theta -> (bias (3,) rad/s, scale error (3,))."""
        b = np.zeros(3)
        k = np.zeros(3)
        nb = len(self.bias_idx)
        b[self.bias_idx] = theta[:nb]
        k[self.scale_idx] = theta[nb:]
        return b, k

    def rates(self, theta: np.ndarray, rows=slice(None)) -> np.ndarray:
        """(T-1, 3) w_t = (1 + k) g_t - b, rad/s: the calibrated rate of each step (or of the
        steps `rows` selects)."""
        b, k = self.split_theta(theta)
        return (1.0 + k) * self.gyr[rows] - b

    def rate_jacobian(self, rows=slice(None)) -> np.ndarray:
        """(T-1, 3, P) d w_t / d theta (or for the steps `rows` selects): -1 for a bias, g_t,i
        for a scale error (w is linear in theta)."""
        gyr = self.gyr[rows]
        J = np.zeros((len(gyr), 3, self.n_theta))
        nb = len(self.bias_idx)
        for j, ax in enumerate(self.bias_idx):
            J[:, ax, j] = -1.0
        for j, ax in enumerate(self.scale_idx):
            J[:, ax, nb + j] = gyr[:, ax]
        return J

    def rest_residual(self, theta: np.ndarray) -> np.ndarray:
        """(R, B) the rest residuals: the rate of the R steps at rest, on the B bias axes."""
        return self.rates(theta, self.w_rest > 0)[:, self.bias_idx]

    def step_rotvec(self, theta: np.ndarray) -> np.ndarray:
        """(T-1, 3) phi_t = w_t dt_t, zero on invalid steps."""
        phi = self.rates(theta) * self.dt[:, None]
        phi[~self.valid] = 0.0
        return phi

    def rest_terms(self, theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The rest term at theta: its cost, gradient (P,) and Gauss-Newton block (P, P), which is
        exact (the residual w_t is linear in theta). Only the axes with a bias variable enter: on
        the others the term could not change and would only add a constant."""
        P = self.n_theta
        if not np.any(self.w_rest):
            return 0.0, np.zeros(P), np.zeros((P, P))
        at = self.w_rest > 0
        w, r = self.w_rest[at], self.rest_residual(theta)
        J = self.rate_jacobian(at)[:, self.bias_idx]
        return (0.5 * float(np.sum(w * np.sum(r**2, axis=1))), np.einsum("t,tj,tjp->p", w, r, J),
                np.einsum("t,tjp,tjr->pr", w, J, J))

    def steps(self, theta: np.ndarray) -> "Steps":
        """The gyro increments at theta and what the Jacobians need of them; they depend on theta
        only, so they are cached for the last theta (a solver evaluates them many times)."""
        theta = np.asarray(theta, float)
        key = theta.tobytes()
        cached = getattr(self, "_steps", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        phi = self.step_rotvec(theta)
        u = quat.from_rotvec(phi)
        d_phi = np.zeros((len(phi), 3, self.n_theta))
        if self.n_theta:
            # d phi / d theta = dt d w / d theta; Exp(phi + e) ~ Exp(phi) Exp(J_r(phi) e) (eq. 143).
            d_phi = self.rate_jacobian() * self.dt[:, None, None]
            d_phi[~self.valid] = 0.0
            d_phi = right_jacobian(phi) @ d_phi
        steps = Steps(phi=phi, u=u, R_u=rotation_matrix(u), d_phi=d_phi)
        self._steps = (key, steps)
        return steps

    def step_quat(self, theta: np.ndarray) -> np.ndarray:
        """(T-1, 4) exp([0, phi_t / 2]) (cached for the last theta)."""
        return self.steps(theta).u

    def motion_residual(self, q_a: np.ndarray, q_b: np.ndarray, u: np.ndarray) -> np.ndarray:
        """2 log(q_b^-1 q_a u), all (M, 4) -> (M, 3): the motion residual."""
        return quat.to_rotvec(quat.multiply(quat.multiply(quat.conjugate(q_b), q_a), u))

    def residuals(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """All residuals at (q (T, 4), theta (P,), v (T, V) m/s; None: zero)."""
        u = self.step_quat(theta)
        out = {
            "motion": self.motion_residual(q[:-1], q[1:], u),
            "acc": self.acc - up_in_body(q),
            "prior": quat.to_rotvec(quat.multiply(quat.conjugate(self.init_quat), q[0])),
            "theta": np.asarray(theta, float),
        }
        if self.n_vel:
            v = self.zero_velocity() if v is None else v
            out["velocity"], _ = self.velocity_residual(q, v)
            out["vzero"] = v
        if np.any(self.w_rest):
            out["rest"] = self.rest_residual(theta)
        if len(self.w_mag):
            out["mag"], _ = self.mag_residual(q)
        return out

    def acc_terms(self, r_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T,) accelerometer cost terms `1/2 w_t c^2 rho(|r_t|^2 / c^2)` and (T,) IRLS weights
        `w_t rho'` (d term / d r = w_t rho' r) for residuals r_a (T, 3), g."""
        return robust_terms(self.loss, self.loss_c, self.w_acc, np.sum(r_a**2, axis=1))

    def cost(self, q: np.ndarray, theta: np.ndarray | None = None, v: np.ndarray | None = None) -> float:
        """Total cost at q (T, 4), theta (P,), v (T, V) m/s (None: zero)."""
        theta = np.zeros(self.n_theta) if theta is None else theta
        r = self.residuals(q, theta, v)
        acc_cost, _ = self.acc_terms(r["acc"])
        total = float(np.sum(acc_cost)) + 0.5 * float(
            np.sum(self.w_motion * np.sum(r["motion"] ** 2, axis=1))
            + self.w_prior * r["prior"] @ r["prior"]
            + np.sum(self.w_theta * r["theta"] ** 2)
        )
        if self.n_vel:
            total += 0.5 * float(np.sum(self.w_vel * np.sum(r["velocity"] ** 2, axis=1))
                                 + np.sum(self.w_vzero * np.sum(r["vzero"] ** 2, axis=1)))
        if "rest" in r:  # the rest term of `rest_terms`, from the residual computed above
            total += 0.5 * float(np.sum(self.w_rest[self.w_rest > 0] * np.sum(r["rest"] ** 2, axis=1)))
        if "mag" in r:
            total += float(np.sum(self.mag_terms(r["mag"])[0]))
        return total

    # -------------------------------------------------------------- linearisation
    def linearize(self, q: np.ndarray, theta: np.ndarray | None = None, hessian: bool = True,
                  v: np.ndarray | None = None) -> Linearization:
        """Cost, exact gradient and the Gauss-Newton blocks at (q, theta, v).

        The robust accelerometer term uses the IRLS weight w rho' in both gradient (exact) and
        Hessian (Gauss-Newton approximation; the second-order term of the loss is omitted, as in
        Triggs et al. 2000, "Bundle adjustment - a modern synthesis", sec. 3.3).
        """
        theta = np.zeros(self.n_theta) if theta is None else np.asarray(theta, float)
        T, P, V = len(q), self.n_theta, self.n_vel
        B = 3 + V
        steps = self.steps(theta)
        r_m = self.motion_residual(q[:-1], q[1:], steps.u)
        R = rotation_matrix(q)
        h = R[:, 2, :]  # h(q) = R(q)^T e_z
        r_a = self.acc - h
        r_0 = quat.to_rotvec(quat.multiply(quat.conjugate(self.init_quat), q[0]))
        acc_cost, wa = self.acc_terms(r_a)
        cost = float(np.sum(acc_cost)) + 0.5 * float(
            np.sum(self.w_motion * np.sum(r_m**2, axis=1)) + self.w_prior * r_0 @ r_0
            + np.sum(self.w_theta * theta**2)
        )

        # Motion Jacobians (right perturbations), with A_t = J_r^-1(r_m,t):
        #   d r_m,t / d delta_t     = A_t R(u_t)^T   (u^-1 Exp(d) u = Exp(R(u)^T d))
        #   d r_m,t / d delta_{t+1} = -J_l^-1(r_m,t) = -A_t^T
        # (J_l^-1(r) = J_r^-1(-r) = J_r^-1(r)^T: in eq. 144 [r]x is antisymmetric, [r]x^2 symmetric).
        A = right_jacobian_inv(r_m)
        At = np.swapaxes(A, -1, -2)
        Wr = self.w_motion[:, None] * r_m
        AtWr = (At @ Wr[:, :, None])[:, :, 0]
        grad = np.zeros((T, B))
        grad[:-1, :3] += (steps.R_u @ AtWr[:, :, None])[:, :, 0]  # J0^T W r = R(u) A^T W r
        grad[1:, :3] -= (A @ Wr[:, :, None])[:, :, 0]  # J1^T W r = -A W r
        # Accelerometer: h(q Exp(d)) ~ h + [h]x d, so d r_a / d delta = -[h]x and
        # (-[h]x)^T y = [h]x y = h x y.
        grad[:, :3] += np.cross(h, wa[:, None] * r_a)
        # Anchor: d r_0 / d delta_0 = Jr^-1(r_0).
        J_0 = right_jacobian_inv(r_0)
        grad[0, :3] += self.w_prior * J_0.T @ r_0
        Jh = wh = None
        if len(self.w_mag):
            # Magnetometer (heading only): d r_h / d delta = k^T R, i.e. the body-frame row R^T k.
            r_h, k = self.mag_residual(q)
            mag_cost, wh = self.mag_terms(r_h)
            cost += float(np.sum(mag_cost))
            Jh = (np.swapaxes(R, -1, -2) @ k[:, :, None])[:, :, 0]
            grad[:, :3] += (wh * r_h)[:, None] * Jh

        if V:
            # Velocity increments: R(q Exp(d)) a ~ R a - R [a]x d, so
            #   d r_v,t / d delta_t = G dt_t P R_t [a_t]x / 2 (same form for t+1), d r_v,t / d v_t = -I, / d v_{t+1} = I.
            # Row i of R_t [a_t]x is (R_t,i x a_t)^T (r^T [a]x b = r . (a x b) = b . (r x a)).
            v = self.zero_velocity() if v is None else v
            r_v, _ = self.velocity_residual(q, v, R)
            Ra = np.cross(R[:, :2, :], self.acc[:, None, :])  # (T, 2, 3) P R_t [a_t]x
            half = 0.5 * STANDARD_GRAVITY_M_S2 * self.dt[:, None, None]
            X0, X1 = half * Ra[:-1], half * Ra[1:]  # d r_v,t / d delta_t and / d delta_{t+1}, (T-1, 2, 3)
            Wv = self.w_vel[:, None] * r_v
            grad[:-1, :3] += np.sum(X0 * Wv[:, :, None], axis=1)
            grad[1:, :3] += np.sum(X1 * Wv[:, :, None], axis=1)
            grad[:-1, 3:] -= Wv
            grad[1:, 3:] += Wv
            grad[:, 3:] += self.w_vzero[:, None] * v
            cost += 0.5 * float(np.sum(self.w_vel * np.sum(r_v**2, axis=1)) + np.sum(self.w_vzero * np.sum(v**2, axis=1)))

        # Calibration variables: d r_m,t / d theta = A_t J_r(phi_t) d phi_t / d theta (`Steps.d_phi`).
        # The rest term touches theta only (`rest_terms`).
        rest_cost, rest_grad, rest_block = self.rest_terms(theta)
        cost += rest_cost
        grad_theta = self.w_theta * theta + rest_grad
        Jth = None
        if P:
            Jth = A @ steps.d_phi  # (T-1, 3, P)
            grad_theta = grad_theta + np.sum(Jth * Wr[:, :, None], axis=(0, 1))

        if not hessian:
            return Linearization(cost, grad, grad_theta, np.empty((0, B, B)), np.empty((0, B, B)), np.empty((0, B, P)), np.empty((P, P)))

        wm = self.w_motion[:, None, None]
        J0 = A @ np.swapaxes(steps.R_u, -1, -2)  # d r_m,t / d delta_t; d r_m,t / d delta_{t+1} = -A^T
        J0t = np.swapaxes(J0, -1, -2)
        diag = np.zeros((T, B, B))
        diag[:-1, :3, :3] += wm * (J0t @ J0)
        diag[1:, :3, :3] += wm * (A @ At)
        # Accelerometer: [h]x^T [h]x = |h|^2 I - h h^T, |h| = 1.
        diag[:, :3, :3] += wa[:, None, None] * (np.eye(3) - h[:, :, None] * h[:, None, :])
        diag[0, :3, :3] += self.w_prior * J_0.T @ J_0
        if Jh is not None:
            diag[:, :3, :3] += wh[:, None, None] * (Jh[:, :, None] * Jh[:, None, :])
        off = np.zeros((T - 1, B, B))
        off[:, :3, :3] = -wm * (J0t @ At)  # J0^T J1
        if V:
            # Blocks of J_v0 = [X0, -I] and J_v1 = [X1, I] (rotation, velocity columns).
            wv = self.w_vel[:, None, None]
            X0t, X1t = np.swapaxes(X0, -1, -2), np.swapaxes(X1, -1, -2)
            diag[:-1, :3, :3] += wv * (X0t @ X0)
            diag[:-1, :3, 3:] -= wv * X0t
            diag[:-1, 3:, :3] -= wv * X0
            diag[1:, :3, :3] += wv * (X1t @ X1)
            diag[1:, :3, 3:] += wv * X1t
            diag[1:, 3:, :3] += wv * X1
            idx = np.arange(3, B)
            diag[:, idx, idx] += self.w_vzero[:, None]
            diag[:-1, idx, idx] += self.w_vel[:, None]
            diag[1:, idx, idx] += self.w_vel[:, None]
            off[:, :3, :3] += wv * (X0t @ X1)
            off[:, :3, 3:] += wv * X0t
            off[:, 3:, :3] -= wv * X1
            off[:, idx, idx] -= self.w_vel[:, None]
        cross = np.zeros((T, B, P))
        theta_block = np.diag(self.w_theta).astype(float) + rest_block
        if P:
            cross[:-1, :3] += wm * (J0t @ Jth)  # J0^T Jth
            cross[1:, :3] -= wm * (A @ Jth)  # J1^T Jth
            theta_block = theta_block + np.einsum("tjp,tjr->pr", wm * Jth, Jth)
        return Linearization(cost, grad, grad_theta, diag, off, cross, theta_block)
