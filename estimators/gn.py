"""`gn`: the batch smoother solved on the manifold by Gauss-Newton / Levenberg-Marquardt.

Minimises the cost of `fusion.estimators.smoother_cost`, with the weighting and defaults of
`fusion.estimators.smoother.SmootherParams` (motion + robust accelerometer terms
weighted by the sensor noise) over all orientations at once. Updates are on the manifold,
`q_t <- q_t * exp([0, delta_t / 2])`; each motion residual touches two neighbours, so the
normal equations are block-tridiagonal (3x3 blocks), stored in LAPACK band form and solved
by `scipy.linalg.solveh_banded` in O(T) time and memory. Optional calibration variables
(a constant gyro bias per axis, per-axis scale errors) add a dense border
to the matrix, eliminated by a Schur complement (the banded solve takes P + 1 right-hand sides).

Levenberg-Marquardt (Marquardt 1963): solve (H + lambda diag(H)) delta = -g, accept the
step if the cost decreases (lambda /= 10), otherwise reject it (lambda *= 10). Stops when
the relative cost decrease of an accepted step is below `tol` or after `max_iter` iterations.

Per-sample variables are the rotation increment and, with the velocity model, the two
horizontal velocities (5x5 blocks). Scale-error variables are released only after the rest
has converged with them at zero, and only those the recording determines (`released_scales`);
they are kept only if they lower the cost significantly (`BatchSmoother.significant_scales`).

Observability of the calibration (diagnostics "theta_std"): the posterior std of each
calibration variable, from the inverse of its Schur complement at the solution, next to
its prior std. A variable the data cannot see keeps a posterior std near the prior's.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg import solveh_banded

from fusion.quaternion import retract

from .smoother import BatchSmoother, SolverLog, progress_bar, solution_diagnostics
from .smoother_cost import SmootherProblem, banded_lower


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


def released_scales(posterior_std: np.ndarray, prior_std: np.ndarray, ratio: float) -> np.ndarray:
    """(S,) which scale errors the recording determines, judged at the stage-1 solution.

    Scale error k_i is released if its posterior std `posterior_std` (S,) (data and prior, every
    other variable marginalised: `theta_posterior_std`) is below `ratio` times its prior std `prior_std`
    (S,), i.e. if the recording carries at least 1 / ratio^2 - 1 times the prior's information
    about it (3 times for ratio 0.5). That information comes from rotation about axis i that
    the accelerometer can check (a scale error on a vertical axis only changes the heading,
    which nothing observes); a recording with little of it keeps k_i = 0 rather than fit
    unmodelled linear acceleration with a scale error.
    """
    return posterior_std < ratio * prior_std


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
        log = SolverLog(lin.cost, q)
        damping = 1e-6
        converged = False
        iterations = 0
        # Two stages. Stage 1 solves with the scale errors held at zero (from a drifting start,
        # dead reckoning, their first steps would otherwise absorb the drift). Stage 2 releases a
        # scale error only if the recording determines it (`released_scales`); the others stay 0.
        nb = len(problem.bias_idx)
        free = np.arange(problem.n_theta) < nb if problem.n_theta > nb else None
        staged = free is not None  # in stage 1
        stage1_iter = max(1, p.max_iter // 2)
        released = np.zeros(problem.n_theta - nb, bool)
        stage1 = None  # (q, theta, v, cost, theta_std) where stage 1 ended, for `significant_scales`
        # Stage 1 takes at most half of max_iter, stage 2 at least max_iter.
        limit = p.max_iter + (stage1_iter if staged else 0)
        bar = progress_bar(p.progress, limit, self.name)
        try:
            for iterations in range(1, limit + 1):
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
                    log.record(lin.cost, q)
                    damping = max(damping / 10.0, 1e-12)
                    bar.update(1)
                    bar.set_postfix(cost=f"{lin.cost:.6g}")
                    stage_done = decrease < p.tol or (staged and iterations >= stage1_iter)
                if stage_done:
                    if staged:
                        staged = False
                        std = theta_posterior_std(lin)
                        stage1 = (q, theta, v, lin.cost, std)
                        released = released_scales(std[nb:], 1.0 / np.sqrt(problem.w_theta[nb:]), p.scale_release_ratio)
                        free = np.concatenate([np.ones(nb, bool), released])
                        damping = 1e-6
                        if released.any():
                            continue
                    converged = True
                    break
        finally:
            bar.close()
        diagnostics = {
            **log.diagnostics(iterations, converged),
            **solution_diagnostics(problem, theta, theta_posterior_std(lin), released, v),
            "stage1": stage1,
        }
        return q, diagnostics
