"""`gd`: projected gradient descent on the batch smoother's cost.

The cost family of `gn` (`fusion.estimators.smoother_cost`) but not, by default, the same
weighting: `gd` defaults to weighting="scalar" (motion weight `wm` = 10, accelerometer 1, no
robust loss) without calibration variables or velocity model, because the noise model's
weights make the problem too ill-conditioned for gradient descent; `gd:weighting=noise` and
`gn:weighting=scalar` put the two solvers on one cost (`tests/test_smoother.py` compares them).
Each iteration moves every quaternion along its normalised tangent-space gradient,

    q_t' = cos(alpha_t) q_t + sin(alpha_t) p_t,   p_t = -G_t / ||G_t||

with G_t the Riemannian gradient in R^4 (the Euclidean gradient projected onto the
tangent space of the unit sphere at q_t; for right perturbations delta_t it is
`q_t * [0, 2 dc/ddelta_t]`). q_t' stays on the sphere exactly since q_t is orthogonal to p_t.
Step sizes: one alpha per quaternion, found by a halving schedule: start from
twice the previous accepted alpha (capped at `step_rad`), halve every alpha whose quaternion's
local cost (the terms touching it, neighbours held) does not decrease, up to `halvings`
times; quaternions without a decreasing step stay put. If the joint update raises the total
cost (neighbours moved together), all alphas are halved until it does not.

`update="normalise"` is the common alternative: step along the *Euclidean* gradient
(which has a radial part from the accelerometer term) and renormalise,
q_t' = normalize(q_t - alpha_t G_euc,t / ||G_euc,t||).

`weighting="scalar"` (a cost option shared with `gn`; "seed" is its deprecated alias) replaces
the noise model by scalar weights (motion `wm`, default 10, accelerometer 1, no robust loss):
the "weight of the motion term" ablation.

Analytic gradients only (no autodiff). Cost per iteration -> diagnostics["loss"].
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import time

import numpy as np

from fusion import quaternion as quat

from .smoother import BatchSmoother, SmootherParams, progress_bar
from .smoother_cost import SmootherProblem

ARMIJO = 0.5


@dataclass(frozen=True)
class GDParams(SmootherParams):
    """`SmootherParams` (the cost) plus the descent's own settings.

    Defaults differ from `gn`: the scalar weighting (motion 10, accelerometer 1;
    with the noise model's weights the problem is too ill-conditioned for gradient descent:
    see benchmarks/bench_smoother.py), no calibration variables or velocity model, and a longer
    run (500 iterations, tol 1e-6: a gradient step gains less than a Gauss-Newton step).

    update: "geodesic" (cos/sin step on the sphere) or "normalise" (step, then normalise).
    step_rad (alpha): largest per-quaternion step, rad of quaternion arc (rotation 2 alpha).
    halvings: halvings of the step-size search per iteration.
    """

    max_iter: int = field(default=500, metadata={"alias": "iters"})
    tol: float = 1e-6
    # gd minimises the plain cost: no calibration variables, no velocity model (gn's defaults).
    bias_axes: str = field(default="", metadata={"alias": "bias"})
    scale_axes: str = field(default="", metadata={"alias": "scale"})
    velocity_acc_noise_g_sqrt_s: float = field(default=np.inf, metadata={"alias": "sv"})
    velocity_bound_m_sqrt_s: float = field(default=np.inf, metadata={"alias": "vb"})
    weighting: Literal["noise", "scalar", "seed"] = "scalar"
    update: Literal["geodesic", "normalise"] = "geodesic"
    step_rad: float = field(default=0.05, metadata={"alias": "alpha"})
    halvings: int = 12

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.bias_axes or self.scale_axes:
            raise ValueError("gd does not estimate gyro bias or scale (bias_axes/scale_axes); use gn")
        if np.isfinite(self.velocity_acc_noise_g_sqrt_s) or np.isfinite(self.velocity_bound_m_sqrt_s):
            raise ValueError("gd does not estimate velocity (velocity_acc_noise_g_sqrt_s/velocity_bound_m_sqrt_s); use gn")
        if not 0 < self.step_rad <= np.pi / 2:
            raise ValueError(f"step_rad={self.step_rad!r}: must be in (0, pi/2]")
        if self.halvings < 1:
            raise ValueError(f"halvings={self.halvings}: must be at least 1")


class GradientDescentSmoother(BatchSmoother):
    """Whole-trajectory smoother by projected gradient descent (analytic gradients)."""

    Params = GDParams
    name = "gd"

    def _candidate(self, q: np.ndarray, direction: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        a = alpha[:, None]
        if self.params.update == "geodesic":
            out = np.cos(a) * q + np.sin(a) * direction  # stays on the sphere
        else:
            out = q + a * direction
        return quat.normalize(out)  # exact no-op up to rounding for "geodesic"

    def solve(self, problem: SmootherProblem, q: np.ndarray) -> tuple[np.ndarray, dict]:
        """Projected gradient descent from q (T, 4) unit quaternions; returns (q, diagnostics)."""
        p = self.params
        theta = np.zeros(0)
        T = len(q)
        alpha = np.full(T, p.step_rad)
        cost = problem.cost(q, theta)
        losses = [cost]
        norm_error = [float(np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)))]
        converged = False
        iterations = 0
        bar = progress_bar(p.progress, p.max_iter, self.name)
        start = time.perf_counter()
        elapsed = [0.0]
        try:
            for iterations in range(1, p.max_iter + 1):
                lin = problem.linearize(q, theta, hessian=False)
                # Riemannian gradient in R^4: q * [0, 2 dc/ddelta] (tangent to the sphere at q).
                G = quat.multiply(q, np.concatenate([np.zeros((T, 1)), 2.0 * lin.grad_q], axis=1))
                if p.update == "normalise":
                    # Euclidean gradient = tangent part + radial part (q . grad_euc) q; only the
                    # accelerometer term is not scale-invariant: d/ds c(s q) at s = 1 = -2 rho' w r_a . h.
                    h = quat.gravity_in_body(q)
                    r_a = problem.acc - h
                    _, wa = problem.acc_terms(r_a)
                    G = G + (-2.0 * wa * np.sum(r_a * h, axis=1))[:, None] * q
                norm = np.linalg.norm(G, axis=1, keepdims=True)
                direction = -G / np.where(norm > 0, norm, 1.0)
                # Per-quaternion step search with a halving schedule.
                alpha = np.minimum(2.0 * alpha, p.step_rad)
                alpha[norm[:, 0] == 0] = 0.0
                local_old = problem.local_costs(q, q, theta)
                slope = norm[:, 0]  # -d(local cost)/d(alpha) at alpha = 0
                accepted = alpha == 0
                for _ in range(p.halvings):
                    local_new = problem.local_costs(self._candidate(q, direction, alpha), q, theta)
                    # Armijo sufficient decrease with c = 1/2 (Nocedal & Wright eq. 3.4): on a
                    # quadratic it accepts at most the exact minimiser along p_t, so no overshoot.
                    accepted |= local_new <= local_old - ARMIJO * alpha * slope
                    if accepted.all():
                        break
                    alpha = np.where(accepted, alpha, 0.5 * alpha)
                alpha[~accepted] = 0.0
                for _ in range(60):  # neighbours moved together: back off until the total decreases
                    q_new = self._candidate(q, direction, alpha)
                    cost_new = problem.cost(q_new, theta)
                    if cost_new <= cost:
                        break
                    alpha *= 0.5
                else:
                    converged = True
                    break
                decrease = (cost - cost_new) / max(cost, 1e-300)
                q, cost = q_new, cost_new
                losses.append(cost)
                norm_error.append(float(np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0))))
                elapsed.append(time.perf_counter() - start)
                bar.update(1)
                if iterations % 50 == 0:
                    bar.set_postfix(cost=f"{cost:.6g}")
                if decrease < p.tol:
                    converged = True
                    break
        finally:
            bar.close()
        diagnostics = {
            "loss": np.array(losses), "elapsed_s": np.array(elapsed), "norm_error": np.array(norm_error),
            "iterations": iterations, "converged": converged,
        }
        return q, diagnostics
