"""`gd`: preconditioned projected (Riemannian) gradient descent on the batch smoother's cost.

`gd` minimises the same cost as `gn` (`fusion.estimators.smoothers.cost`, with the same
defaults: noise weighting, robust accelerometer loss, gyro bias and scale variables, velocity
model); the solver is what differs. On a recording with a magnetometer (9-D) both add the
magnetometer's heading-only term to the cost (`smoothers.cost`; its measurements and gates:
`fusion.estimators.smoothers.mag`) and solve again from the 6-D solution (solved until its inclination
has settled: `presolve_tol_rad`). The unknowns are the unit quaternions q_t (one per
sample), the horizontal velocities v_t and the calibration variables theta. A step moves every
quaternion along the unit sphere,

    q_t <- q_t * exp([0, alpha d_t / 2])                                   (update="geodesic")

where d_t in R^3 is a step in the tangent space at q_t, written as a body-frame rotation
vector. In these coordinates the gradient is the Riemannian gradient: the Euclidean gradient
projected onto the sphere's tangent space at q_t.

Why plain gradient descent is slow here. Its rate is set by the condition number of the
Hessian (Nocedal & Wright 2006, "Numerical Optimization", 2nd ed., sec. 3.3). The motion term
ties each quaternion to its neighbours with the weight 1 / (Q dt), 1,000,000 at 100 Hz;
the accelerometer ties it to gravity with dt / R, 0.25: a ratio of 4 10^6. A gradient
step changes a quaternion through its two neighbours only, so a correction travels about one
sample per iteration along the chain, and the number of iterations grows with the recording
(precond="none" below: after 200 iterations on 56 s of data still far above the minimum).

The remedy: a preconditioner M that solves the whole chain. The search direction is
(N&W eq. 3.2)

    p = -M^-1 g,        g = (gradient over all quaternions, velocities and theta),

with M the Gauss-Newton matrix of the cost, J^T W J (N&W sec. 10.3, eq. 10.23). Each motion
residual involves two neighbouring samples only, so M is block-tridiagonal (3 x 3 blocks, 5 x 5
with the velocities) with a dense border for theta; M^-1 g costs O(T) time and memory: a banded
Cholesky factorisation (LAPACK pbtrf, `scipy.linalg.cholesky_banded`: impl="numpy", the
reference) or, by default, the compiled kernels' block elimination of the same matrix
(`fusion.estimators.smoothers._compiled`), with the border eliminated by a Schur complement.
One solve with M carries a correction along the whole chain, so the number of iterations no
longer grows with the length (benchmarks/bench_smoother.py).
This is preconditioning in the sense of N&W sec. 5.1: steepest descent in the variables
M^(1/2) x, whose Hessian is close to the identity. With M rebuilt at every iterate (the
default, precond_every=1) p is the Gauss-Newton direction, and `gd` differs from `gn` in how
it makes the step safe: a line search along p instead of Levenberg-Marquardt damping.
precond_every=k keeps M for k iterations (the chord / Shamanskii idea: Kelley 1995,
"Iterative Methods for Linear and Nonlinear Equations", SIAM, ch. 5): cheaper iterations, but
a stale M slows down the heading of long recordings (one hour at 100 Hz, tol 1e-5: 69
iterations with k = 2 against 39 with k = 1).

Step length: backtracking line search along the whole-trajectory direction p (N&W
Algorithm 3.1). Try alpha = 1, the natural step of a Newton-like direction (N&W sec. 3.5), and
halve it until the Armijo condition f(x + alpha p) <= f(x) + c1 alpha g.p holds (N&W eq. 3.4,
c1 = 1e-4). On the sphere, "x + alpha p" is a retraction (Absil, Mahony & Sepulchre 2008,
"Optimization Algorithms on Matrix Manifolds", sec. 4.1; line searches on manifolds: sec. 4.2):

- update="geodesic": q_t * exp([0, alpha d_t / 2]), the exponential map (a great circle);
- update="normalise": normalise(q_t + alpha q_t * [0, d_t / 2]): step in R^4 along the tangent
  vector, then back onto the sphere (the course reports' "step, then normalise"; Absil et al.,
  sec. 4.1, give it as the sphere's projection retraction). The two agree to first order in
  alpha, so the same line search applies. (The reports stepped along the Euclidean gradient in
  R^4; its extra radial part only changes the length of the step after normalising, and the
  line search chooses that length, so it is left out.)

The start: the init estimator's output (dead reckoning), re-levelled every `init_level_s`
seconds by the accelerometer (`fusion.estimators.smoothers.smoother.levelled`). On a long recording dead
reckoning drifts upside down (an hour of the simulator: 160 deg of tilt), where the
accelerometer's pull, proportional to the sine of the tilt error, vanishes; a local method
started there stays there.

Stopping: when an iteration with a freshly built M lowers the cost by less than the fraction
`tol` (1e-4, as `gn`: what is left then is mostly the heading of long recordings, which a
gyro and an accelerometer barely observe).

Calibration: as in `gn`, the gyro scale errors are held at zero in a first stage (from a
drifting start they would absorb the drift) and then released where the recording determines
them (`gn.released_scales`) and where they lower the cost significantly
(`BatchSmoother.significant_scales`).
The first stage converges to `tol` (or stops after half of `max_iter`): the significance test
compares its cost with the final one.

Ablations: precond="block" keeps only M's diagonal blocks (each sample's own curvature, no
chain: iterations grow with the length again); precond="none" is plain projected gradient
descent (M = I). They show why the chain is needed.

Analytic gradients only (no autodiff). Cost per iteration -> diagnostics["loss"].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from scipy.linalg import cho_factor, cho_solve, cho_solve_banded, cholesky_banded


from ..params import param, param_as
from .cost import Linearization, SmootherProblem
from .gn import released_scales
from .smoother import (BatchSmoother, SmootherParams, SolverLog, inclination_step, progress_bar, retract,
                       solution_diagnostics)
from .solve import banded_lower

ARMIJO_C1 = 1e-4  # N&W eq. 3.4: "c1 is chosen to be quite small, say 1e-4"
MAX_HALVINGS = 50  # 2^-50: no step of that length decreases the cost in double precision
RIDGE = 1e-12  # relative ridge on M's diagonal, for the factorisation's safety; small enough to leave the
# smooth heading corrections alone, whose curvature is ~1e-9 of M's diagonal on long recordings (`gn.INITIAL_DAMPING`)


@dataclass(frozen=True)
class GDParams(SmootherParams):
    """`SmootherParams` (the cost: the same defaults as `gn`) plus the descent's own settings; each
    field's unit, meaning, reference and valid range are at the field (`fusion list gd`)."""

    owner: ClassVar[str] = "gd"

    max_iter: int = param_as(SmootherParams, "max_iter", 100)
    tol: float = param_as(SmootherParams, "tol", 1e-4, meaning=(
        "The descent stops when an iteration with a freshly built preconditioner lowers the cost by less than "
        "this fraction."))
    precond: Literal["chain", "block", "none"] = param(
        "chain", unit="", valid="chain | block | none",
        reference='Nocedal & Wright 2006, "Numerical Optimization", 2nd ed., sec. 10.3, eq. 10.23 (the Gauss-Newton '
                  "matrix)",
        meaning="The preconditioner: chain (the block-tridiagonal Gauss-Newton matrix, solved along the whole "
                "chain), block (its per-sample diagonal blocks only) or none (the plain gradient).")
    precond_every: int = param(
        1, alias="every", unit="", valid="a whole number >= 1",
        reference='Kelley 1995, "Iterative Methods for Linear and Nonlinear Equations", SIAM, ch. 5 (the chord method)',
        meaning="Rebuild the preconditioner every this many iterations (and after a shortened step, before stopping, "
                "and when calibration variables are released).")
    update: Literal["geodesic", "normalise"] = param(
        "geodesic", unit="", valid="geodesic | normalise",
        reference='Absil, Mahony & Sepulchre 2008, "Optimization Algorithms on Matrix Manifolds", sec. 4.1',
        meaning="How a step moves an orientation on the sphere: geodesic (the exponential map) or normalise (a step in "
                "R^4, then normalised, the projection retraction).")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.precond_every < 1:
            raise ValueError(f"precond_every={self.precond_every}: must be at least 1")


class Preconditioner:
    """M^-1 applied to gradients, for one linearisation `lin` (with Hessian blocks).

    kind "chain": M = the Gauss-Newton matrix (block-tridiagonal, dense border for the free
    calibration variables `free` (P,) bool), factorised once, each `direction` in O(T).
    kind "block": the diagonal blocks only (B x B per sample; P x P for theta).
    kind "none": M = I.
    """

    def __init__(self, lin: Linearization, kind: str, free: np.ndarray):
        self.kind = kind
        self.free = free
        T, B = lin.diag.shape[:2] if kind != "none" else lin.grad_q.shape
        self.shape = (T, B)
        if kind == "none":
            return
        diag = lin.diag.copy()
        idx = np.arange(B)
        diag[:, idx, idx] *= 1.0 + RIDGE
        G = lin.theta_block[np.ix_(free, free)].copy()
        G[np.diag_indices_from(G)] *= 1.0 + RIDGE
        if kind == "block":
            self.diag_inv = np.linalg.inv(diag)
            self.G_inv = np.linalg.inv(G)
            return
        # The chain: A = the per-sample part (banded), C = its border with theta, G = theta's block.
        # Schur complement: [A C; C^T G] [x; y] = [a; b]  ->  (G - C^T A^-1 C) y = b - C^T A^-1 a.
        self.factor = cholesky_banded(banded_lower(diag, lin.off), lower=True, check_finite=False)
        self.C = lin.cross[:, :, free].reshape(B * T, -1)
        if self.C.shape[1]:
            self.A_inv_C = cho_solve_banded((self.factor, True), self.C, check_finite=False)
            self.schur = cho_factor(G - self.C.T @ self.A_inv_C)

    def direction(self, grad_q: np.ndarray, grad_theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """p = -M^-1 g: (T, B) per-sample and (P,) calibration parts (zero where theta is held)."""
        T, B = self.shape
        d_theta = np.zeros(len(grad_theta))
        g_theta = grad_theta[self.free]
        if self.kind == "none":
            d_theta[self.free] = -g_theta
            return -grad_q, d_theta
        if self.kind == "block":
            d_theta[self.free] = -self.G_inv @ g_theta
            return -(self.diag_inv @ grad_q[:, :, None])[:, :, 0], d_theta
        x = cho_solve_banded((self.factor, True), -grad_q.reshape(-1), check_finite=False)
        if self.C.shape[1]:
            y = cho_solve(self.schur, -g_theta - self.C.T @ x)
            x = x - self.A_inv_C @ y
            d_theta[self.free] = y
        return x.reshape(T, B), d_theta


class KernelChain:
    """The chain preconditioner by the compiled kernels (`smoothers._compiled.CompiledOps`):
    p = -M^-1 g with M the Gauss-Newton matrix at lin's point, its diagonal times 1 + RIDGE, for
    the free calibration variables (the others get no step), as `Preconditioner` "chain"."""

    def __init__(self, ops, lin: Linearization, free: np.ndarray):
        self.ops, self.lin, self.free = ops, lin, free

    def direction(self, grad_q: np.ndarray, grad_theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        grad = None if grad_q is self.lin.grad_q and grad_theta is self.lin.grad_theta else (grad_q, grad_theta)
        return self.ops.solve(self.lin, RIDGE, self.free, grad=grad)


class GradientDescentSmoother(BatchSmoother):
    """Whole-trajectory smoother by preconditioned projected gradient descent (analytic gradients)."""

    Params = GDParams
    name = "gd"

    def retract(self, q: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """Move q (T, 4) by the tangent steps delta (T, 3) rad, body frame, and stay on the sphere
        (`smoother.retract` with this smoother's `update`)."""
        return retract(q, delta, self.params.update)

    def preconditioner(self, ops, lin: Linearization, free: np.ndarray):
        """M for the linearisation `lin`: `Preconditioner`, or with the compiled kernels and the
        chain, their elimination of the same matrix (`KernelChain`)."""
        if self.params.precond == "chain" and self.params.impl == "compiled":
            return KernelChain(ops, lin, free)
        return Preconditioner(lin, self.params.precond, free)

    def solve(self, problem: SmootherProblem, q: np.ndarray, presolve: bool = False) -> tuple[np.ndarray, dict]:
        """Preconditioned gradient descent from q (T, 4) unit quaternions (velocities and
        calibration variables from zero); returns (q, diagnostics). presolve: a stage also ends
        when a full step (alpha = 1) changes no sample's inclination by more than
        `presolve_tol_rad` (`BatchSmoother.solve`)."""
        p = self.params
        theta = np.zeros(problem.n_theta)
        v = problem.zero_velocity()
        nb = len(problem.bias_idx)
        # Stage 1 holds the scale errors at zero (from a drifting start they would absorb the drift);
        # stage 2 releases those the recording determines (as in gn).
        free = np.arange(problem.n_theta) < nb
        staged = problem.n_theta > nb
        stage1_iter = max(1, p.max_iter // 2)
        released = np.zeros(problem.n_theta - nb, bool)
        stage1 = None  # (q, theta, v, cost, theta_std) where stage 1 ended, for `significant_scales`

        hessian = p.precond != "none"
        ops = self.operations(problem, blocks=p.precond == "block")
        # With the chain rebuilt at every step, p = -M^-1 g always uses the gradient of M's own point,
        # and g.p comes from the elimination (`ops.slope`): the per-sample gradient need not be kept.
        keep = not (p.precond == "chain" and p.precond_every == 1)
        lin = ops.linearize(q, theta, v, hessian=hessian, shift=RIDGE, free=free, gradient=keep)  # always at the current point
        M = self.preconditioner(ops, lin, free)
        age, builds = 0, 1  # age: steps taken since M was built (0: M is from the current point)
        cost = lin.cost
        log, steps = SolverLog(cost, q, ops.norm_error), []
        alpha = 1.0
        converged = False
        iterations = 0
        # Stage 1 takes at most half of max_iter, stage 2 at least max_iter.
        limit = p.max_iter + (stage1_iter if staged else 0)
        bar = progress_bar(p.progress, limit, self.name)
        try:
            while iterations < limit:
                d_q, d_theta = M.direction(lin.grad_q, lin.grad_theta)
                slope = ops.slope(lin, d_q, d_theta)  # g.p < 0
                # Backtracking line search (N&W Algorithm 3.1) from alpha = 1 for the Newton-like
                # chain direction; the other preconditioners' steps have no natural length, so they
                # start from twice the last accepted one.
                alpha = 1.0 if p.precond == "chain" else min(1.0, 2.0 * alpha)
                accepted = False
                for _ in range(MAX_HALVINGS):
                    q_new, v_new, theta_new, cost_new = ops.trial(q, v, theta, d_q, d_theta, alpha, p.update)
                    if cost_new <= cost + ARMIJO_C1 * alpha * slope:  # Armijo, N&W eq. 3.4
                        accepted = True
                        break
                    alpha *= 0.5
                lagged = age > 0 and p.precond != "none"  # this direction came from an older point's M
                decrease = 0.0  # relative; 0 if no step decreased the cost
                settled = False  # presolve: a full step left every sample's inclination in place
                if accepted:
                    iterations += 1
                    decrease = (cost - cost_new) / max(cost, 1e-300)
                    settled = presolve and alpha == 1.0 and inclination_step(q, d_q[:, :3]) < p.presolve_tol_rad
                    q, v, theta, cost = q_new, v_new, theta_new, cost_new
                    age += 1
                    log.record(cost, q)
                    steps.append(alpha)
                    bar.update(1)
                    bar.set_postfix(cost=f"{cost:.6g}", alpha=f"{alpha:.3g}")
                small = decrease < p.tol or settled
                stage_end = staged and not presolve and (decrease < p.tol or iterations >= stage1_iter)
                if (small and not lagged) and not stage_end:
                    converged = True  # a fresh M's step no longer helps: at the minimum (to tol)
                    break
                # Rebuild M at the current point: every `precond_every` steps, after a shortened
                # step (M's model was poor), when a lagged M stalls, and for the stage change.
                if small or stage_end or age >= p.precond_every or (alpha < 1.0 and p.precond == "chain"):
                    # At the stage change the linearisation serves the posterior std first (undamped, every variable).
                    lin = ops.linearize(q, theta, v, hessian=hessian or stage_end, shift=0.0 if stage_end else RIDGE,
                                        free=None if stage_end else free, gradient=keep)
                    age, builds = 0, builds + 1
                    if stage_end:  # release the scale errors the recording determines (as gn)
                        staged = False
                        std = ops.theta_std(q, theta, v, lin)
                        stage1 = (q, theta, v, cost, std)
                        released = released_scales(std[nb:], 1.0 / np.sqrt(problem.w_theta[nb:]), p.scale_release_ratio)
                        free = np.concatenate([np.ones(nb, bool), released])
                    M = self.preconditioner(ops, lin, free)
                else:
                    lin = ops.linearize(q, theta, v, hessian=False)
        finally:
            bar.close()
        theta_std = ops.theta_std(q, theta, v) if problem.n_theta else np.zeros(0)
        diagnostics = {
            **log.diagnostics(iterations, converged),
            "step": np.array(steps),
            "preconditioner_builds": builds,
            **solution_diagnostics(problem, theta, theta_std, released, v),
            "stage1": stage1,
        }
        return q, diagnostics
