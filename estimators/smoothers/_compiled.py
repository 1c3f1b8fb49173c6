"""The batch smoothers' operations on their cost by the compiled kernels: `CompiledOps`.

`gn` and `gd` work on the cost of `fusion.estimators.smoothers.cost` through an object with the
interface of `smoother.ReferenceOps` (cost, trial, slope, linearize, solve, theta_std), whose
numpy code is the reference; `CompiledOps` is the same interface by the numba kernels:

- `smoothers._compiled_layout`: the problem's arrays as the kernels take them, the modes;
- `smoothers._compiled_terms`: the cost's terms, one sample at a time;
- `smoothers._compiled_cost`: the cost over a range of samples, at a point or a trial point;
- `smoothers._compiled_linearize`: cost, gradient and Gauss-Newton blocks in one pass, with the
  block-tridiagonal normal equations eliminated in the same pass (its docstring: the equations);
- `smoothers._compiled_ranges`: a long recording split over two threads, the same results;
- `smoothers._compiled_start`: dead reckoning and the re-levelling that start the solvers.

The numpy code is the reference: every kernel line implements a line of `smoothers.cost` (or of
`fusion.quaternion`, `smoother`), each kernel carries the name of the function it mirrors and
declares it (`kernels._numba.mirrors("fusion.estimators.smoothers.cost.SmootherProblem.cost")`,
as the filters' kernels do; each module lists its kernels without a reference of their own in
`HELPERS`, with why), `tests/test_compiled.py` resolves those names, and
`tests/test_compiled_smoother.py` checks the kernels against them
(cost, gradient, blocks, solves) and both solvers' iterations and final costs against their
`impl=numpy` runs on simulated and real recordings. The two paths differ only in rounding: the
summation order of the cost and the elimination order of the solve.

Like the filters', the kernels are cached on disk next to their files (`_numba._jit`), and the
constants that decide the maths (`fusion.quaternion`'s small-angle rules, 1 g) are passed in at
run time (`smoothers._compiled_layout.constants`).
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from fusion import quaternion as quat

from . import _compiled_linearize as kernel
from ._compiled_cost import range_cost
from ._compiled_layout import B_MAX, POINT, RETRACTIONS, carry_size, constants, problem_arrays, range_blocks
from ._compiled_linearize import back_substitute
from ._compiled_ranges import linearize_ranges, run_beside
from ._compiled_start import dead_reckoning, dot, levelled, norm_error
from .cost import Linearization, SmootherProblem

_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache: run each once on a two-sample
    problem (with velocity and calibration variables, the types every problem has). A compiled
    smoother calls this when it is built, so that its `estimate` is timed as the solver alone."""
    global _loaded
    if _loaded:
        return
    from fusion.types import ImuSamples

    from .cost import Weights

    imu = ImuSamples(np.array([0.0, 0.01]), np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)))
    weights = Weights(bias_axes="x", scale_axes="y", velocity_acc_noise_g2_s=1e-4, velocity_bound_m2_s=0.25)
    problem = SmootherProblem.from_imu(imu, quat.IDENTITY, weights, rest=np.ones(1, bool))
    ops = CompiledOps(problem, blocks=True)
    q, theta, v = np.tile(quat.IDENTITY, (2, 1)), np.zeros(2), np.zeros((2, 2))
    ops.linearize(q, theta, v)
    ops.blocks = False
    lin = ops.linearize(q, theta, v, shift=0.0)
    d_q, d_theta = ops.solve(lin, 0.0)
    ops.trial(q, v, theta, d_q, d_theta, 1.0)
    # the elimination from stored blocks, which a long recording's ranges run (`_eliminate_in_ranges`)
    ops._eliminate_in_ranges(q, v, theta, 0.0, np.arange(2, dtype=np.int64), None, np.empty((2, 5)), np.empty(2))
    ops.theta_std(q, theta, v)
    ops.cost(q, theta, v)
    start = np.empty((2, 4))
    dead_reckoning(problem.gyr, problem.valid, problem.dt, quat.IDENTITY, 1e-12, start)
    levelled(imu.t, imu.acc_g, start, 1.0, 1e-12, np.empty((2, 4)))
    norm_error(start)
    padded = np.zeros((2, B_MAX))
    dot(padded, padded)
    dot(padded[:, :3].copy(), padded[:, :3])  # the step without velocities: a view of the (T, B_MAX) storage
    _loaded = True


# ============================================================================ the solvers' operations
@dataclass(frozen=True, eq=False)
class CompiledLinearization(Linearization):
    """A `Linearization` from the kernels: cost and gradient, the blocks only if asked for
    (`CompiledOps(blocks=True)`), and the point it was taken at, to eliminate there again."""

    point: tuple = ()


class CompiledOps:
    """What `gn` and `gd` do with the cost, by the kernels: the interface of
    `smoother.ReferenceOps`, whose numpy code is the reference.

    The elimination's per-sample storage (M, c, N: the kernel `linearize_eliminate`) is allocated once and
    holds one system at a time: `linearize` with a `shift` eliminates the system at its point
    in the same pass (what the next `solve` needs), and `solve` eliminates again if asked for
    another shift, another set of free calibration variables or another right-hand side. The
    step `solve` returns is written over c: it is valid until the next elimination (the solvers
    use it before they linearise again). blocks: linearisations with a Hessian also carry the
    reference's blocks (`Linearization`: for `gd`'s "block" preconditioner).

    Between a `solve` and the next elimination M is not needed: a `trial` writes there each step's
    u_t = exp(phi_t / 2) and motion residual r_m,t, each sample's robust accelerometer term and
    magnetometer residual at the point it tries (their sines, cosines, arctangents and square
    roots are most of a sample's transcendental functions), and the linearisation at that point,
    if the solver accepts it, reads them instead of computing them again: the same numbers, no
    extra memory.
    """

    def __init__(self, problem: SmootherProblem, blocks: bool = False):
        self.problem = problem
        self.arrays = problem_arrays(problem)
        self.consts = constants()
        self.T, self.P = len(problem.acc), problem.n_theta
        self.B = 3 + problem.n_vel
        self.blocks = blocks
        self.norm_error = norm_error
        self._storage = None  # (M, c, N) of the system `_held` (lin, shift, free indices as bytes)
        self._held = None
        self._schur = None
        self._slope = None  # (lin, g.p) of the last solve with lin's own gradient
        self._kept = None  # (weak reference to q, theta) of the trial whose per-sample terms M holds (`trial`)

    # ---------------------------------------------------------------- cost
    def cost(self, q: np.ndarray, theta: np.ndarray, v: np.ndarray) -> float:
        """The cost at (q (T, 4), theta (P,), v (T, V) m/s)."""
        none = np.zeros((0, B_MAX))
        return range_cost(self.arrays, self.consts, q, v, np.asarray(theta, float), none, 0.0, POINT, none, none,
                          _NO_STORAGE[0])

    def trial(self, q, v, theta, d_q, d_theta, alpha: float, update: str = "geodesic"):
        """(q, v, theta) moved by alpha times the step (d_q (T, B), d_theta (P,)), retracted
        on the sphere by `update` ("geodesic" or "normalise"), and its cost:
        (q_new, v_new, theta_new, cost)."""
        q_new, v_new = np.empty_like(q), np.empty_like(v)
        theta_new = theta + alpha * d_theta
        if self._storage is not None and d_q.base is self._storage[1]:
            d_q = self._storage[1]  # the step `solve` returned: its (T, 5) storage, handed over whole
        # With no eliminated system waiting for its `solve`, M is free until the next elimination: the
        # trial keeps its per-sample terms there (the kernel `cost`'s keep), for `linearize` at q_new (if accepted).
        keep = self._storage[0] if self._storage is not None and self._held is None else _NO_STORAGE[0]
        self._kept = None
        cost = range_cost(self.arrays, self.consts, q, v, theta_new, np.ascontiguousarray(d_q), float(alpha),
                          RETRACTIONS[update], q_new, v_new, keep)
        if keep.shape[0]:
            self._kept = (weakref.ref(q_new), theta_new.copy())
        return q_new, v_new, theta_new, cost

    def slope(self, lin: Linearization, d_q, d_theta) -> float:
        """g.p: lin's gradient along the step (d_q (T, B), d_theta (P,)). If lin keeps no
        per-sample gradient, the step must be the last `solve` of lin's own system, p = -H^-1 g,
        and g.p = -g^T H^-1 g comes from its elimination."""
        if len(lin.grad_q):
            return dot(lin.grad_q, d_q) + float(lin.grad_theta @ d_theta)
        if self._slope is None or self._slope[0] is not lin:
            raise ValueError("slope: the step is not the last solve of this linearisation, whose gradient is not kept")
        return self._slope[1]

    # ---------------------------------------------------------------- linearisation and solves
    def linearize(self, q, theta, v, hessian: bool = True, shift: float | None = None, free=None,
                  gradient: bool = True) -> Linearization:
        """Cost and gradient at (q, theta, v) (gradient=False: no per-sample gradient, grad_q
        has no rows). With `hessian`: the blocks if this object keeps them, else, given a
        `shift`, the system (H + shift diag(H)) x = -g for the free calibration variables `free`
        ((P,) bool; None: all) eliminated for `solve`."""
        theta = np.asarray(theta, float)
        T, B, P = self.T, self.B, self.P
        grad_q, grad_theta = np.empty((T if gradient or (hessian and self.blocks) else 0, B)), np.empty(P)
        if hessian and self.blocks:
            blocks = (np.zeros((T, B, B)), np.zeros((max(T - 1, 0), B, B)), np.zeros((T, B, P)), np.zeros((P, P)))
            cost = kernel.linearize(self.arrays, self.consts, kernel.SmootherPoint(q, v, theta),
                                    kernel.SmootherGradient(grad_q, grad_theta), kernel.SmootherBlocks(*blocks),
                                    self._kept_at(q, theta), _WHOLE(self.T))
            return CompiledLinearization(cost, grad_q, grad_theta, *blocks, point=(q, theta, v))
        if hessian and shift is not None:
            index = self._free_index(free)
            cost = self._eliminate(q, v, theta, float(shift), index, None, grad_q, grad_theta)
        else:
            cost = kernel.linearize(self.arrays, self.consts, kernel.SmootherPoint(q, v, theta),
                                    kernel.SmootherGradient(grad_q, grad_theta), _NO_BLOCKS, self._kept_at(q, theta),
                                    _WHOLE(self.T))
        lin = CompiledLinearization(cost, grad_q, grad_theta, *_NO_BLOCKS, point=(q, theta, v))
        if hessian and shift is not None:
            self._held = (lin, float(shift), index.tobytes())
        return lin

    def solve(self, lin: Linearization, shift: float, free=None, grad=None) -> tuple[np.ndarray, np.ndarray]:
        """x = -(H + shift diag(H))^-1 g with H at lin's point, for the free calibration
        variables (`free` (P,) bool, None: all; the others get no step) and g lin's gradient or
        `grad` = (grad_q (T, B), grad_theta (P,)): ((T, B), (P,))."""
        index = self._free_index(free)
        held = self._held
        if grad is not None or held is None or held[0] is not lin or held[1] != shift or held[2] != index.tobytes():
            q, theta, v = lin.point
            self._eliminate(q, v, theta, float(shift), index, grad, np.empty((0, self.B)), np.empty(self.P))
        self._held = None  # the step overwrites c
        schur, schur_rhs, quad = self._schur
        x_theta = np.linalg.solve(schur, schur_rhs) if len(index) else np.zeros(0)
        # g.x = -b^T H^-1 b (b = -g): the sum over the samples from the sweep, then the Schur complement's.
        self._slope = None if grad is not None else (lin, -(float(quad[0]) + float(schur_rhs @ x_theta)))
        M, c, N = self._storage
        back_substitute(M, c, N, x_theta)
        d_theta = np.zeros(self.P)
        d_theta[index] = x_theta
        return c[:, :self.B], d_theta

    def theta_std(self, q, theta, v, lin: Linearization | None = None) -> np.ndarray:
        """(P,) the calibration variables' posterior std at (q, theta, v): sqrt(diag((G - C^T
        A^-1 C)^-1)) (`theta_posterior_std`), from lin's elimination if it was made there with
        no shift and every variable free, else from one of its own."""
        if self.P == 0:
            return np.zeros(0)
        P = self.P
        held = self._held
        if lin is not None and held is not None and held[0] is lin and held[1] == 0.0 \
                and held[2] == self._free_index(None).tobytes():
            return np.sqrt(np.diag(np.linalg.inv(self._schur[0])))
        theta = np.asarray(theta, float)
        elim = kernel.SmootherElimination(np.empty((2, B_MAX, B_MAX)), np.empty((2, B_MAX)), np.empty((2, B_MAX, P)),
                                          np.empty((P, P)), np.empty(P), np.empty(1))  # the running rows only
        cost = kernel.linearize_eliminate(self.arrays, self.consts, kernel.SmootherPoint(q, v, theta),
                                          kernel.SmootherGradient(np.empty((0, self.B)), np.empty(P)),
                                          self._system(0.0, np.arange(P, dtype=np.int64), None), elim,
                                          self._kept_at(q, theta))
        self._check(cost)
        return np.sqrt(np.diag(np.linalg.inv(elim.schur)))

    # ---------------------------------------------------------------- internals
    def _free_index(self, free) -> np.ndarray:
        return np.arange(self.P, dtype=np.int64) if free is None else np.flatnonzero(free).astype(np.int64)

    @staticmethod
    def _system(shift, index, rhs):
        """The `SmootherSystem` (H + shift diag(H)) x = b for the free variables `index`, b = -g or
        -rhs ((T, B), (P,))."""
        return kernel.SmootherSystem(float(shift), index, *(_NO_RHS if rhs is None else rhs))

    def _elimination(self):
        """The `SmootherElimination` of the held storage and Schur complement."""
        return kernel.SmootherElimination(*self._storage, *self._schur)

    def _kept_at(self, q, theta) -> np.ndarray:
        """M, if it holds the per-sample terms of a trial at exactly (q, theta) (`trial`), else no rows."""
        kept = self._kept
        if kept is not None and kept[0]() is q and np.array_equal(kept[1], theta):
            return self._storage[0]
        return _NO_STORAGE[0]

    def _eliminate(self, q, v, theta, shift, index, rhs, grad_q, grad_theta) -> float:
        F = len(index)
        if self._storage is None or self._storage[2].shape[2] != F:  # N has a column per free variable
            M, c = (np.empty((self.T, B_MAX, B_MAX)), np.empty((self.T, B_MAX))) if self._storage is None else self._storage[:2]
            self._storage = None  # the old N goes before the new one comes
            self._storage = M, c, np.empty((self.T, B_MAX, F))
        self._schur = np.empty((F, F)), np.empty(F), np.empty(1)
        if rhs is not None:
            rhs = np.ascontiguousarray(rhs[0], float), np.ascontiguousarray(rhs[1], float)
        if len(linearize_ranges(self.T)) > 2:
            cost = self._eliminate_in_ranges(q, v, theta, shift, index, rhs, grad_q, grad_theta)
        else:
            cost = kernel.linearize_eliminate(self.arrays, self.consts, kernel.SmootherPoint(q, v, theta),
                                              kernel.SmootherGradient(grad_q, grad_theta),
                                              self._system(shift, index, rhs), self._elimination(),
                                              self._kept_at(q, theta))
        self._kept = None  # M now holds the elimination
        self._check(cost)
        return cost

    def _eliminate_in_ranges(self, q, v, theta, shift, index, rhs, grad_q, grad_theta) -> float:
        """`_eliminate` on two threads: the blocks of one range of samples (`linearize_ranges`) are
        computed (`linearize`) while those of the range before are eliminated (`eliminate_blocks`),
        in two buffers taken in turn. The same numbers as one `linearize_eliminate` pass, bit for bit."""
        P = self.P
        bounds = linearize_ranges(self.T)
        buffers = self._range_buffers(max(b - a for a, b in zip(bounds, bounds[1:])))
        kept = self._kept_at(q, theta)  # read by `linearize`'s ranges only, before `eliminate_blocks` writes those rows
        theta_block, carries = np.empty((P, P)), (np.zeros(carry_size(P)), np.zeros(carry_size(P)))

        point, system, elim = kernel.SmootherPoint(q, v, theta), self._system(shift, index, rhs), self._elimination()

        def blocks(k):  # the blocks of range k, into buffer k % 2
            return kernel.linearize(self.arrays, self.consts, point, kernel.SmootherGradient(buffers[k % 2][3], grad_theta),
                                    kernel.SmootherBlocks(*buffers[k % 2][:3], theta_block), kept,
                                    kernel.SmootherSpan(bounds[k], bounds[k + 1], carries[0]))

        cost = blocks(0)
        for k in range(len(bounds) - 1):
            following = run_beside(blocks, k + 1) if k + 2 < len(bounds) else None
            try:
                diag, off, cross, grad = buffers[k % 2]
                done = kernel.eliminate_blocks(self.arrays, self.consts, point, kernel.SmootherGradient(grad, grad_theta),
                                               kernel.SmootherBlocks(diag, off, cross, theta_block), system, elim,
                                               kernel.SmootherSpan(bounds[k], bounds[k + 1], carries[1]))
                if len(grad_q):
                    grad_q[bounds[k]:bounds[k + 1]] = grad[:bounds[k + 1] - bounds[k]]
            finally:
                if following is not None:
                    cost = following()
            if math.isnan(done):
                return done
        return cost

    def _range_buffers(self, R: int) -> tuple:
        """Two sets of the blocks of a range of R samples (`range_blocks`), for `_eliminate_in_ranges`.
        Allocated for each elimination and dropped after it, so that they never add to the trial's
        trajectories (the peak)."""
        return range_blocks(R, self.B, self.P), range_blocks(R, self.B, self.P)

    def _check(self, cost: float) -> None:
        if math.isnan(cost):
            raise np.linalg.LinAlgError("smoother: the Gauss-Newton matrix is not positive definite")


_NO_CARRY = np.zeros(0)
_NO_RHS = (np.zeros((0, B_MAX)), np.zeros(0))
_NO_BLOCKS = kernel.SmootherBlocks(np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0, 0)), np.zeros((0, 0)))
_NO_STORAGE = (np.zeros((0, B_MAX, B_MAX)), np.zeros((0, B_MAX)), np.zeros((0, B_MAX, 0)))


def _WHOLE(T: int):
    """The `SmootherSpan` of a whole pass over T samples."""
    return kernel.SmootherSpan(0, T, _NO_CARRY)
