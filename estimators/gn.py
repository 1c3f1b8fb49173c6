"""`gn`: the batch smoother solved on the manifold by Gauss-Newton / Levenberg-Marquardt.

Minimises the cost of `fusion.estimators.smoother_cost` (motion + robust accelerometer terms
weighted by the sensor noise) over all orientations at once. Updates are on the manifold,
`q_t <- q_t * exp([0, delta_t / 2])`; each motion residual touches two neighbours, so the
normal equations are block-tridiagonal (3x3 blocks), stored in LAPACK band form and solved
by `scipy.linalg.solveh_banded` in O(T) time and memory. Optional calibration variables
(a constant gyro bias per axis, per-axis scale errors; issue 7 item 4) add a dense border
to the matrix, eliminated by a Schur complement (the banded solve takes P + 1 right-hand sides).

Levenberg-Marquardt (Marquardt 1963): solve (H + lambda diag(H)) delta = -g, accept the
step if the cost decreases (lambda /= 10), otherwise reject it (lambda *= 10). Stops when
the relative cost decrease of an accepted step is below `tol` or after `max_iter` iterations.

Per-sample variables are the rotation increment and, with the velocity model, the two
horizontal velocities (5x5 blocks). Scale-error variables are released only after the rest
has converged with them at zero, and only those the recording determines (`released_scales`).

Observability of the calibration (diagnostics "theta_std"): the posterior std of each
calibration variable, from the inverse of its Schur complement at the solution, next to
its prior std. A variable the data cannot see keeps a posterior std near the prior's.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.linalg import solveh_banded

from fusion.types import ImuSamples, Trajectory

from .base import Estimator
from .smoother_cost import AXES, SmootherProblem, Weights, banded_lower, retract


def _check_axes(name: str, value: str) -> None:
    if any(a not in AXES for a in value) or len(set(value)) != len(value):
        raise ValueError(f"{name}={value!r}: expected distinct letters from 'xyz' (or 'none')")


@dataclass(frozen=True)
class SmootherParams:
    """Parameters shared by `gn` and `gd` (the cost), plus the initialisation.

    All noise levels are densities of continuous-time white noise, so one value means the
    same at any sampling rate (see `fusion.estimators.smoother_cost.Weights`):
    gyro_noise_rad_sqrt_s (sg): gyro noise density, rad/sqrt(s); a step of dt s has angle
        variance sg^2 dt.
    acc_noise_g_sqrt_s (sa): accelerometer noise density, g sqrt(s); a sample standing for dt s
        has variance sa^2 / dt.
    loss: robust loss on the accelerometer residual: "huber", "cauchy", "geman-mcclure", "none".
    loss_scale_g (huber, the alias it had when the loss was always Huber): the loss's scale on
        the accelerometer residual norm, g (inf: plain least squares).
    prior_std_rad (p0): std of the anchor of the first orientation at the initial one, rad.
    dropout_noise_rad_sqrt_s (sdrop): angle random walk density where `gyr_valid` is False.
    use_gyr_valid (dropout): honour `imu.gyr_valid` (False: integrate every sample).
    bias_axes (bias): gyro bias variables, e.g. "xy" ("" or "none": none). scale_axes (scale):
        scale errors, likewise.
    bias_prior_rad_s, scale_prior: prior std of those variables around zero.
    scale_release_ratio (release): a requested scale error is estimated only if the recording
        determines it: its posterior std at the stage-1 solution (scales held at zero) is
        below this fraction of its prior std (`released_scales`); the others stay zero.
        Stage 1 ends at `tol` or after half of `max_iter`, so stage 2 always gets its turn.
    velocity_acc_noise_g_sqrt_s (sv), velocity_bound_m_sqrt_s (vb): the horizontal velocity
        model (see `fusion.estimators.smoother_cost`); inf switches it off.

    Defaults, one set for every IMU: the accelerometer is trusted as a gravity sensor only on
    average (sa = 0.2 g sqrt(s): a hand-held or body-worn motion's linear accelerations are
    tenths of a g, correlated over fractions of a second), while the velocity model keeps the
    world-frame linear acceleration's integral bounded (the fact VQF's inertial-frame low-pass
    rests on: Laidig & Seel 2023); the x and y gyro biases and scale errors are estimated
    (prior std 0.05 rad/s and 10 %, a consumer MEMS gyro's tolerances); z's are not: with the
    body z axis near vertical they act on heading only, which a gyro and an accelerometer cannot
    observe, and estimating them spoils the heading. Measured with these defaults: course
    recordings 1-9 1.27 deg inclination / 4.58 total; the nine BROAD trials 0.73 mean inclination
    (offlineVQF 0.54; without scale estimation 0.55 on BROAD but 2.1 / 22 on the course).
    weighting: "noise" (information matrices from the noise stds above) or "seed" (the seeds'
        scalar weights: motion `seed_motion_weight`, accelerometer 1, no Huber loss).
    seed_motion_weight (wm): the seeds' motion weight (10 in one report).
    init: estimator whose output starts the optimisation ("dr", "ukf", ...).
    max_iter (iters), tol: stopping rule (relative cost decrease below tol).
    progress: tqdm bar over iterations on stderr (shown only on a terminal).
    """

    gyro_noise_rad_sqrt_s: float = field(default=0.02, metadata={"alias": "sg"})
    acc_noise_g_sqrt_s: float = field(default=0.2, metadata={"alias": "sa"})
    loss: Literal["huber", "cauchy", "geman-mcclure", "none"] = "huber"
    loss_scale_g: float = field(default=0.1, metadata={"alias": "huber"})
    prior_std_rad: float = field(default=0.01, metadata={"alias": "p0"})
    dropout_noise_rad_sqrt_s: float = field(default=0.3, metadata={"alias": "sdrop"})
    use_gyr_valid: bool = field(default=True, metadata={"alias": "dropout"})
    bias_axes: str = field(default="xy", metadata={"alias": "bias"})
    scale_axes: str = field(default="xy", metadata={"alias": "scale"})
    bias_prior_rad_s: float = 0.05
    scale_prior: float = 0.1
    scale_release_ratio: float = field(default=1.0, metadata={"alias": "release"})
    velocity_acc_noise_g_sqrt_s: float = field(default=0.01, metadata={"alias": "sv"})
    velocity_bound_m_sqrt_s: float = field(default=0.5, metadata={"alias": "vb"})
    weighting: Literal["noise", "seed"] = "noise"
    seed_motion_weight: float = field(default=10.0, metadata={"alias": "wm"})
    init: str = "dr"
    max_iter: int = field(default=50, metadata={"alias": "iters"})
    tol: float = 1e-5
    progress: bool = True

    def __post_init__(self) -> None:
        for name in ("gyro_noise_rad_sqrt_s", "acc_noise_g_sqrt_s", "loss_scale_g", "prior_std_rad", "dropout_noise_rad_sqrt_s",
                     "bias_prior_rad_s", "scale_prior", "seed_motion_weight", "velocity_acc_noise_g_sqrt_s",
                     "velocity_bound_m_sqrt_s"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"{name}={value!r}: must be positive")
        for name in ("bias_axes", "scale_axes"):  # "none" (as typed on a command line) is ""
            if getattr(self, name) == "none":
                object.__setattr__(self, name, "")
            _check_axes(name, getattr(self, name))
        if not 0 < self.scale_release_ratio <= 1:
            raise ValueError(f"scale_release_ratio={self.scale_release_ratio!r}: must be in (0, 1]")
        if self.max_iter < 1:
            raise ValueError(f"max_iter={self.max_iter}: must be at least 1")
        if not self.tol >= 0:
            raise ValueError(f"tol={self.tol!r}: must be >= 0")

    def weights(self) -> Weights:
        """The cost's `Weights` (the seeds' scalar weights when weighting="seed")."""
        seed = self.weighting == "seed"
        return Weights(
            gyro_noise_rad_sqrt_s=self.gyro_noise_rad_sqrt_s, acc_noise_g_sqrt_s=self.acc_noise_g_sqrt_s,
            loss="none" if seed else self.loss, loss_scale_g=np.inf if seed else self.loss_scale_g,
            prior_std_rad=self.prior_std_rad, dropout_noise_rad_sqrt_s=self.dropout_noise_rad_sqrt_s,
            motion_weight=self.seed_motion_weight if seed else None, acc_weight=1.0 if seed else None,
            bias_axes=self.bias_axes, scale_axes=self.scale_axes, bias_prior_rad_s=self.bias_prior_rad_s,
            scale_prior=self.scale_prior,
            velocity_acc_noise_g_sqrt_s=np.inf if seed else self.velocity_acc_noise_g_sqrt_s,
            velocity_bound_m_sqrt_s=np.inf if seed else self.velocity_bound_m_sqrt_s,
        )


def initial_trajectory(init: str, owner: str, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> np.ndarray:
    """(T, 4) starting point: the output of the registered estimator `init` (e.g. "dr", "ukf:R=1e-3")."""
    from . import build  # the registry imports this module

    if init.split(":")[0] == owner:
        raise ValueError(f"{owner}: init={init!r} would initialise the smoother with itself")
    est = build(init)
    quat_wxyz = np.array(est.estimate(imu, init_quat_wxyz).quat_wxyz, dtype=float)
    if not np.all(np.isfinite(quat_wxyz)):
        raise ValueError(f"{owner}: initial estimator {init!r} returned non-finite orientations")
    return quat_wxyz / np.linalg.norm(quat_wxyz, axis=1, keepdims=True)


def progress_bar(enabled: bool, total: int, desc: str):
    """A tqdm bar on stderr, shown only on a terminal (disable=None), or a no-op."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, disable=None if enabled else True, leave=False)


def solve_normal_equations(lin, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve (H + damping diag(H)) [delta; dtheta] = -[g_q; g_theta] in O(T).

    H is block-tridiagonal in the per-sample variables (B = 3 rotation + V velocity) with a
    dense border for the P calibration variables; the border is eliminated by a Schur
    complement. Returns ((T, B), (P,)).
    """
    T, B = lin.diag.shape[:2]
    diag = lin.diag.copy()
    idx = np.arange(B)
    diag[:, idx, idx] *= 1.0 + damping
    ab = banded_lower(diag, lin.off)
    P = lin.cross.shape[2]
    rhs = np.concatenate([-lin.grad_q.reshape(-1, 1), lin.cross.reshape(B * T, P)], axis=1)
    sol = solveh_banded(ab, rhs, lower=True, check_finite=False)
    x0, X1 = sol[:, 0], sol[:, 1:]
    if P == 0:
        return x0.reshape(T, B), np.zeros(0)
    G = lin.theta_block.copy()
    G[np.arange(P), np.arange(P)] *= 1.0 + damping
    C = lin.cross.reshape(B * T, P)
    schur = G - C.T @ X1
    dtheta = np.linalg.solve(schur, -lin.grad_theta - C.T @ x0)
    return (x0 - X1 @ dtheta).reshape(T, B), dtheta


def theta_posterior_std(lin) -> np.ndarray:
    """(P,) marginal std of the calibration variables: sqrt(diag((G - C^T A^-1 C)^-1))."""
    P = lin.cross.shape[2]
    if P == 0:
        return np.zeros(0)
    C = lin.cross.reshape(-1, P)
    X1 = solveh_banded(banded_lower(lin.diag, lin.off), C, lower=True, check_finite=False)
    return np.sqrt(np.diag(np.linalg.inv(lin.theta_block - C.T @ X1)))


def released_scales(lin, n_bias: int, prior_std: np.ndarray, ratio: float) -> np.ndarray:
    """(S,) which scale errors the recording determines, judged at the stage-1 solution `lin`.

    Scale error k_i is released if its posterior std (data and prior, every other variable
    marginalised: `theta_posterior_std`) is below `ratio` times its prior std `prior_std`
    (S,), i.e. if the recording carries at least 1 / ratio^2 - 1 times the prior's information
    about it (3 times for ratio 0.5). That information comes from rotation about axis i that
    the accelerometer can check (a scale error on a vertical axis only changes the heading,
    which nothing observes); a recording with little of it keeps k_i = 0 rather than fit
    unmodelled linear acceleration with a scale error.
    """
    std = theta_posterior_std(lin)[n_bias:]
    return std < ratio * prior_std


class BatchSmoother(Estimator):
    """What `gn` and `gd` share: the problem set-up, the start trajectory and `estimate`;
    each supplies `solve(problem, q) -> (q, diagnostics)`."""

    Params = SmootherParams
    causal = False
    name = ""

    def problem(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> SmootherProblem:
        return SmootherProblem.from_imu(imu, init_quat_wxyz, self.params.weights(), use_valid=self.params.use_gyr_valid)

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        if len(imu) < 2:
            raise ValueError(f"{imu.source}: the smoother needs at least 2 samples, got {len(imu)}")
        problem = self.problem(imu, init_quat_wxyz)
        q = initial_trajectory(p.init, self.name, imu.replace(gyr_valid=problem_valid(imu, p)), init_quat_wxyz)
        q, diagnostics = self.solve(problem, q)
        return Trajectory(imu.t, q, diagnostics=diagnostics)

    def solve(self, problem: SmootherProblem, q: np.ndarray) -> tuple[np.ndarray, dict]:
        raise NotImplementedError


class GaussNewtonSmoother(BatchSmoother):
    """Whole-trajectory smoother: manifold Levenberg-Marquardt on block-tridiagonal normal equations."""

    name = "gn"

    def solve(self, problem: SmootherProblem, q: np.ndarray) -> tuple[np.ndarray, dict]:
        """Levenberg-Marquardt from q (T, 4) unit quaternions (calibration variables from zero).

        Returns the optimised (T, 4) quaternions and the diagnostics.
        """
        p = self.params
        theta = np.zeros(problem.n_theta)
        v = problem.zero_velocity()
        lin = problem.linearize(q, theta, v=v)
        losses = [lin.cost]
        norm_error = [float(np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)))]
        damping = 1e-6
        converged = False
        bar = progress_bar(p.progress, p.max_iter, self.name)
        iterations = 0
        start = time.perf_counter()
        elapsed = [0.0]
        # Two stages. Stage 1 solves with the scale errors held at zero (from a drifting start,
        # dead reckoning, their first steps would otherwise absorb the drift). Stage 2 releases a
        # scale error only if the recording determines it (`released_scales`); the others stay 0.
        nb = len(problem.bias_idx)
        free = np.arange(problem.n_theta) < nb if problem.n_theta > nb else None
        stage1_iter = max(1, p.max_iter // 2) if free is not None else p.max_iter
        released = np.zeros(problem.n_theta - nb, bool)
        try:
            for iterations in range(1, p.max_iter + 1):
                while True:
                    if free is None:
                        delta, dtheta = solve_normal_equations(lin, damping)
                    else:
                        delta, dtheta = np.zeros((len(q), lin.diag.shape[1])), np.zeros(problem.n_theta)
                        sub = dataclasses.replace(lin, grad_theta=lin.grad_theta[free], cross=lin.cross[:, :, free],
                                                  theta_block=lin.theta_block[np.ix_(free, free)])
                        delta, dtheta[free] = solve_normal_equations(sub, damping)
                    q_new = retract(q, delta[:, :3])
                    v_new = v + delta[:, 3:]
                    theta_new = theta + dtheta
                    cost_new = problem.cost(q_new, theta_new, v_new)
                    if cost_new <= lin.cost or damping > 1e12:
                        break
                    damping *= 10.0
                stage_done = cost_new > lin.cost  # no descent even with heavy damping: at the minimum
                if not stage_done:
                    decrease = (lin.cost - cost_new) / max(lin.cost, 1e-300)
                    q, theta, v = q_new, theta_new, v_new
                    lin = problem.linearize(q, theta, v=v)
                    losses.append(lin.cost)
                    norm_error.append(float(np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0))))
                    elapsed.append(time.perf_counter() - start)
                    damping = max(damping / 10.0, 1e-12)
                    bar.update(1)
                    bar.set_postfix(cost=f"{lin.cost:.6g}")
                    stage_done = decrease < p.tol or (free is not None and iterations >= stage1_iter)
                if stage_done:
                    if free is not None and not free.all():
                        released = released_scales(lin, nb, 1.0 / np.sqrt(problem.w_theta[nb:]), p.scale_release_ratio)
                        free = np.concatenate([np.ones(nb, bool), released])
                        damping = 1e-6
                        if released.any():
                            continue
                    converged = True
                    break
        finally:
            bar.close()
        bias, scale = problem.split_theta(theta)
        diagnostics = {
            "loss": np.array(losses),
            "elapsed_s": np.array(elapsed),
            "norm_error": np.array(norm_error),
            "iterations": iterations,
            "converged": converged,
            "gyro_bias_rad_s": bias,
            "gyro_scale_error": scale,
            "theta_names": [f"bias_{a}" for a in p.bias_axes] + [f"scale_{a}" for a in p.scale_axes],
            "theta": theta,
            "theta_std": theta_posterior_std(lin),
            "theta_prior_std": 1.0 / np.sqrt(problem.w_theta),
            "scale_released": released,
            "velocity_m_s": v,
        }
        return q, diagnostics


def problem_valid(imu: ImuSamples, p: SmootherParams) -> np.ndarray:
    """The validity mask the initialisation uses (all True when dropouts are switched off)."""
    return imu.gyr_valid if p.use_gyr_valid else np.ones(len(imu), bool)
