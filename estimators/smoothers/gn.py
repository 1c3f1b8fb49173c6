"""`gn`: the batch smoother solved on the manifold by Gauss-Newton / Levenberg-Marquardt.

Minimises the cost of `fusion.estimators.smoothers.cost`, with the weighting and defaults of
`fusion.estimators.smoothers.smoother.SmootherParams` (motion + robust accelerometer terms
weighted by the sensor noise) over all orientations at once. Updates are on the manifold,
`q_t <- q_t * exp([0, delta_t / 2])`; each motion residual touches two neighbours, so the
normal equations are block-tridiagonal (3x3 blocks) and solved in O(T) time and memory.
Optional calibration variables (a constant gyro bias per axis, per-axis scale errors) add a
dense border to the matrix, eliminated by a Schur complement. By default the compiled kernels
(`fusion.estimators.smoothers._compiled`) linearise and eliminate block by block in one pass;
with impl="numpy" the reference stores the matrix in LAPACK band form and solves it with
`scipy.linalg.solveh_banded` (the border's P columns as further right-hand sides).

Levenberg-Marquardt (Marquardt 1963): solve (H + lambda diag(H)) delta = -g, accept the
step if the cost decreases (lambda /= 10, down to 1e-12), otherwise reject it (lambda *= 10).
Stops when the relative cost decrease of an accepted step is below `tol` or after `max_iter`
iterations. lambda starts at 1e-9 (`INITIAL_DAMPING`), not at the customary 1e-3 to 1e-6:
Marquardt's scaling by diag(H) is set by the stiffest term, the motion term's 1 / (Q dt) per
sample (10^6 at 100 Hz), while a smooth heading correction spread over the recording, which
the magnetometer term asks for, has a curvature many decades below it (for a profile over N
samples about diag(H) (pi / N)^2, 10^-9 of it for 52,000 samples). A lambda of 1e-6 damps that
correction into a crawl: on BROAD trial 15 (9-D) the solve took 26 iterations with it and 13
with 1e-9, to a lower cost (docs/results.md, "The smoothers' iterations, measured").

Per-sample variables are the rotation increment and, with the velocity model, the two
horizontal velocities (5x5 blocks). Scale-error variables are released only after a first
stage with them at zero (to `tol`, or cut at half of `max_iter`), and only those the recording
determines (`released_scales`); they are kept only if they lower the cost significantly
(`BatchSmoother.significant_scales`). The second stage has at least `max_iter` iterations; if
it releases nothing after a first stage that was cut, it goes on with the same variables.
`converged` says that the cost stopped decreasing (by `tol`), not that a budget ran out.

On a recording with a magnetometer (9-D) the magnetometer then corrects the heading, and only
the heading: by default its heading residual joins the cost (`smoothers.cost`, the magnetometer
term, measured and gated at the 6-D solution by `fusion.estimators.smoothers.mag`) and the cost
is solved again from there (that 6-D solve only until the inclination has settled:
`presolve_tol_rad`); mag_term=stage corrects the 6-D solution afterwards instead.

Observability of the calibration (diagnostics "theta_std"): the posterior std of each
calibration variable, from the inverse of its Schur complement at the solution, next to
its prior std. A variable the data cannot see keeps a posterior std near the prior's.
"""
from __future__ import annotations

import numpy as np

from .cost import SmootherProblem
from .smoother import BatchSmoother, SolverLog, inclination_step, progress_bar, solution_diagnostics
from .solve import solve_normal_equations, theta_posterior_std  # noqa: F401 (their home until now)


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


INITIAL_DAMPING = 1e-9  # lambda at the start of each stage (module docstring); 1e-12 its floor


class GaussNewtonSmoother(BatchSmoother):
    """Whole-trajectory smoother: manifold Levenberg-Marquardt on block-tridiagonal normal equations."""

    name = "gn"

    def solve(self, problem: SmootherProblem, q: np.ndarray, presolve: bool = False) -> tuple[np.ndarray, dict]:
        """Levenberg-Marquardt from q (T, 4) unit quaternions (calibration variables from zero).

        Returns the optimised (T, 4) quaternions and the diagnostics. presolve: a stage also ends
        when an accepted step, taken with at most the initial damping, changes no sample's
        inclination by more than `presolve_tol_rad` (`BatchSmoother.solve`).
        """
        p = self.params
        theta = np.zeros(problem.n_theta)
        v = problem.zero_velocity()
        ops = self.operations(problem)
        damping = INITIAL_DAMPING
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
        lin = ops.linearize(q, theta, v, shift=damping, free=free, gradient=False)  # always at the current point
        log = SolverLog(lin.cost, q, ops.norm_error)
        bar = progress_bar(p.progress, limit, self.name)
        try:
            for iterations in range(1, limit + 1):
                while True:
                    delta, dtheta = ops.solve(lin, damping, free)
                    q_new, v_new, theta_new, cost_new = ops.trial(q, v, theta, delta, dtheta, 1.0)
                    if cost_new <= lin.cost or damping > 1e12:
                        break
                    damping *= 10.0
                at_minimum = cost_new > lin.cost  # no descent even with heavy damping
                stage_done = at_minimum
                if not at_minimum:
                    decrease = (lin.cost - cost_new) / max(lin.cost, 1e-300)
                    at_minimum = decrease < p.tol or (presolve and damping <= INITIAL_DAMPING
                                                      and inclination_step(q, delta[:, :3]) < p.presolve_tol_rad)
                    stage_done = at_minimum or (staged and iterations >= stage1_iter)
                    q, theta, v = q_new, theta_new, v_new
                    damping = max(damping / 10.0, 1e-12)
                    # At a stage's end the linearisation serves the posterior std (undamped, every variable).
                    lin = ops.linearize(q, theta, v, shift=0.0 if stage_done else damping, free=None if stage_done else free,
                                        gradient=False)
                    log.record(lin.cost, q)
                    bar.update(1)
                    bar.set_postfix(cost=f"{lin.cost:.6g}")
                if stage_done:
                    if staged and not presolve:
                        staged = False
                        std = ops.theta_std(q, theta, v, lin)
                        stage1 = (q, theta, v, lin.cost, std)
                        released = released_scales(std[nb:], 1.0 / np.sqrt(problem.w_theta[nb:]), p.scale_release_ratio)
                        free = np.concatenate([np.ones(nb, bool), released])
                        if released.any():
                            damping = INITIAL_DAMPING
                            continue
                        if not at_minimum:  # stage 1 was cut at its cap: stage 2 goes on with the same variables
                            continue
                    converged = True
                    break
        finally:
            bar.close()
        diagnostics = {
            **log.diagnostics(iterations, converged),
            **solution_diagnostics(problem, theta, ops.theta_std(q, theta, v, lin), released, v),
            "stage1": stage1,
        }
        return q, diagnostics
