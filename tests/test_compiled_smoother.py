"""The compiled smoothers (`impl=compiled`, numba) against their numpy reference (`impl=numpy`).

Kernel by kernel: the cost, the gradient and the Gauss-Newton blocks against
`SmootherProblem.cost` / `linearize`, the elimination's solves against
`solve_normal_equations` and `gd.Preconditioner`, the posterior std against
`theta_posterior_std`, dead reckoning and the re-levelling against `DeadReckoning` and
`levelled`, for every option of the cost. Then whole solves: the same iterations, the same
`converged`, the cost at every iteration equal to 1e-9 (relative), on the simulated
recording, ece276a/1 and a BROAD trial. The two paths differ in rounding only (the
summation order of the cost, the elimination order of the solve).
"""
from __future__ import annotations

import dataclasses
import inspect
import tracemalloc

import numpy as np
import pytest

from fusion import datasets
from fusion import quaternion as quat
from fusion.estimators import build
from fusion.estimators.smoothers import _compiled as cs
from fusion.estimators.smoothers import _compiled_cost as kernel_cost
from fusion.estimators.smoothers import _compiled_layout as layout
from fusion.estimators.smoothers import _compiled_linearize as kernel_linearize
from fusion.estimators.smoothers import _compiled_ranges as ranges
from fusion.estimators.smoothers import _compiled_start as start
from fusion.estimators.smoothers.gd import RIDGE, Preconditioner
from fusion.estimators.smoothers.smoother import initial_trajectory, levelled
from fusion.estimators.smoothers.cost import SmootherProblem, Weights
from fusion.estimators.smoothers.solve import solve_normal_equations, theta_posterior_std
from fusion.types import ImuSamples

COST_RTOL = 1e-9  # the target: final costs equal to the reference within 1e-9


# ----------------------------------------------------------------------------- kernels
CONFIGS = {
    "default": dict(loss="huber", bias_axes="xy", scale_axes="xy", velocity=True, rest=True),
    "no velocity": dict(loss="huber", bias_axes="xy", scale_axes="xy", velocity=False, rest=True),
    "cauchy, bias xyz, scale z": dict(loss="cauchy", bias_axes="xyz", scale_axes="z", velocity=True, rest=True),
    "geman-mcclure, scale only": dict(loss="geman-mcclure", bias_axes="", scale_axes="xyz", velocity=True, rest=False),
    "plain least squares, no calibration": dict(loss="none", bias_axes="", scale_axes="", velocity=False, rest=False),
    # 9-D: the magnetometer's heading term (`SmootherProblem.with_magnetometer`)
    "default, magnetometer": dict(loss="huber", bias_axes="xy", scale_axes="xy", velocity=True, rest=True, mag="huber"),
    "no calibration, magnetometer without loss": dict(loss="none", bias_axes="", scale_axes="", velocity=False, rest=False,
                                                      mag="none"),
}


def _problem(config: dict, T: int = 60, seed: int = 0):
    """A random problem with invalid gyro steps, two missing accelerometer samples,
    accelerometer residuals on both sides of the robust loss's scale, and rest steps; a random
    point (q (T, 4), theta (P,), v (T, V))."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(0.005 + 0.01 * rng.random(T))
    valid = np.ones(T, bool)
    valid[20:24] = False
    q0 = quat.normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    steps = quat.from_rotvec(rng.normal(size=(T - 1, 3)) * 0.1)
    q = quat.cumulative_product(np.concatenate([quat.normalize(q0 + 0.05)[None], steps]))
    acc = quat.gravity_in_body(q) + rng.normal(size=(T, 3)) * np.where(np.arange(T) % 3 == 0, 0.5, 0.05)[:, None]
    acc[[7, 31]] = np.nan
    imu = ImuSamples(t, rng.normal(size=(T, 3)), acc, valid)
    velocity = dict(velocity_acc_noise_g2_s=1e-4, velocity_bound_m2_s=0.25) if config["velocity"] else {}
    weights = Weights(process_noise_rad2_s=4e-4, acc_noise_g2_s=2.5e-3, loss=config["loss"], loss_scale_g=0.3,
                      bias_axes=config["bias_axes"], scale_axes=config["scale_axes"], **velocity)
    rest = (np.arange(T - 1) % 6 == 2) if config["rest"] else None
    problem = SmootherProblem.from_imu(imu, q0, weights, rest=rest)
    if config.get("mag"):
        # heading errors on both sides of the loss's scale (0.1 rad) and past +-pi, some samples gated out
        q_ref = quat.normalize(q + rng.normal(size=(T, 4)) * 0.1)
        w_mag = rng.uniform(10.0, 1000.0, T) * (np.arange(T) % 5 != 1)
        problem = problem.with_magnetometer(w_mag, rng.normal(size=T) * 0.3 + np.where(np.arange(T) % 9 == 0, 3.0, 0.0),
                                            q_ref, config["mag"], 0.1)
    return problem, q, rng.normal(size=problem.n_theta) * 0.02, rng.normal(size=(T, problem.n_vel)) * 0.1


def _close(got, ref, rtol=1e-11):
    """Equal to rtol relative to the largest entry of ref (blocks mix weights of 1e-1 and 1e5)."""
    got, ref = np.asarray(got), np.asarray(ref)
    assert got.shape == ref.shape
    scale = np.max(np.abs(ref), initial=0.0)
    np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * max(scale, 1e-300))


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_cost_gradient_and_blocks_equal_the_reference(config):
    problem, q, theta, v = _problem(config)
    ref = problem.linearize(q, theta, v=v)
    _, wa = problem.acc_terms(problem.residuals(q, theta, v)["acc"])
    if config["loss"] == "huber":  # both branches
        assert 0 < np.sum(wa < problem.w_acc * (1 - 1e-12)) < np.sum(problem.w_acc > 0) - 10
    ops = cs.CompiledOps(problem, blocks=True)
    assert ops.cost(q, theta, v) == pytest.approx(problem.cost(q, theta, v), rel=1e-13)
    lin = ops.linearize(q, theta, v)
    assert lin.cost == pytest.approx(ref.cost, rel=1e-13)
    for key in ("grad_q", "grad_theta", "diag", "off", "cross", "theta_block"):
        _close(getattr(lin, key), getattr(ref, key))
    gradient_only = cs.CompiledOps(problem).linearize(q, theta, v, hessian=False)
    _close(gradient_only.grad_q, ref.grad_q)
    _close(gradient_only.grad_theta, ref.grad_theta)


@pytest.mark.parametrize("update", ["geodesic", "normalise"])
@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_trial_point_and_its_cost_equal_the_reference(config, update):
    from fusion.estimators.smoothers.smoother import ReferenceOps

    problem, q, theta, v = _problem(config)
    rng = np.random.default_rng(5)
    d_q, d_theta = rng.normal(size=(len(q), 3 + problem.n_vel)) * 0.05, rng.normal(size=problem.n_theta) * 0.01
    for alpha in (1.0, 0.25):
        got = cs.CompiledOps(problem).trial(q, v, theta, d_q, d_theta, alpha, update)
        ref = ReferenceOps(problem).trial(q, v, theta, d_q, d_theta, alpha, update)
        for a, b in zip(got[:3], ref[:3]):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)
        assert got[3] == pytest.approx(ref[3], rel=1e-13)


@pytest.mark.parametrize("kind", [0, 1, 2])
@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_the_cost_in_two_ranges_is_the_cost_in_one(config, kind, monkeypatch):
    """A long recording's cost pass runs as two ranges of samples on two threads (`range_cost`):
    the moved point and the kept per-sample terms are those of one pass, bit for bit (each sample
    computes the same numbers; the step across the split reads its next sample without writing
    it), and the cost differs only in the order of the sum."""
    problem, q, theta, v = _problem(config)
    arrays, consts = layout.problem_arrays(problem), layout.constants()
    x = np.random.default_rng(5).normal(size=(len(q), 5)) * 0.05
    out = {}
    for split in (False, True):
        monkeypatch.setattr(ranges, "SPLIT_MIN_SAMPLES", 2 if split else 10**9)
        assert len(ranges.cost_ranges(len(q))) == (3 if split else 2)
        q_out, v_out, keep = np.full_like(q, np.nan), np.full_like(v, np.nan), np.full((len(q), 5, 5), np.nan)
        cost = kernel_cost.range_cost(arrays, consts, q, v, theta, x, 0.5, kind, q_out, v_out, keep)
        out[split] = cost, q_out, v_out, keep
    (one, *written_one), (two, *written_two) = out[False], out[True]
    for a, b in zip(written_one, written_two):
        np.testing.assert_array_equal(a, b)
    if kind:
        assert np.all(np.isfinite(written_two[0])) and np.all(np.isfinite(written_two[1]))
    assert two == pytest.approx(one, rel=1e-14)


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_elimination_solves_the_normal_equations(config):
    """The damped Gauss-Newton step of gn (solve_normal_equations, with held calibration
    variables), gd's chain direction for its own and for another gradient (Preconditioner),
    the posterior std, and gd's slope g.p from the elimination: all equal to the banded LAPACK
    solves (and g.p to the reference gradient times the step)."""
    problem, q, theta, v = _problem(config)
    ref = problem.linearize(q, theta, v=v)
    P = problem.n_theta
    frees = [None] + ([np.arange(P) < P // 2] if P > 1 else [])
    for shift in (1e-6, 0.1):
        for free in frees:
            ops = cs.CompiledOps(problem)
            lin = ops.linearize(q, theta, v, shift=shift, free=free, gradient=False)
            assert len(lin.grad_q) == 0
            d_q, d_theta = ops.solve(lin, shift, free)
            if free is None:
                want_q, want_theta = solve_normal_equations(ref, shift)
            else:
                sub = dataclasses.replace(ref, grad_theta=ref.grad_theta[free], cross=ref.cross[:, :, free],
                                          theta_block=ref.theta_block[np.ix_(free, free)])
                want_q, want_theta_free = solve_normal_equations(sub, shift)
                want_theta = np.zeros(P)
                want_theta[free] = want_theta_free
            _close(d_q, want_q, 1e-8)
            _close(d_theta, want_theta, 1e-8)
            assert np.all(d_theta[~free] == 0.0) if free is not None else True
    free = np.ones(P, bool)
    ops = cs.CompiledOps(problem)
    lin = ops.linearize(q, theta, v, shift=RIDGE, free=free)
    other = (np.random.default_rng(2).normal(size=ref.grad_q.shape), np.random.default_rng(3).normal(size=P))
    for grad in (None, other):
        got = ops.solve(lin, RIDGE, free, grad=grad)
        want = Preconditioner(ref, "chain", free).direction(*(grad or (ref.grad_q, ref.grad_theta)))
        _close(got[0], want[0], 1e-8)
        _close(got[1], want[1], 1e-8)
    if P:
        np.testing.assert_allclose(ops.theta_std(q, theta, v), theta_posterior_std(ref), rtol=1e-10)
    # gd's slope g.p without a kept gradient: -g^T M^-1 g from the elimination
    for free in frees:
        ops = cs.CompiledOps(problem)
        lin = ops.linearize(q, theta, v, shift=RIDGE, free=free, gradient=False)
        d_q, d_theta = ops.solve(lin, RIDGE, free)
        want = float(np.sum(ref.grad_q * d_q) + ref.grad_theta @ d_theta)
        assert want < 0 and ops.slope(lin, d_q, d_theta) == pytest.approx(want, rel=1e-9)
        with pytest.raises(ValueError, match="slope"):
            ops.slope(ops.linearize(q, theta, v, shift=RIDGE, gradient=False), d_q, d_theta)  # not its step


def _factors(ops) -> list:
    """Copies of what an elimination stored: M (its last row is never written), c and N."""
    M, c, N = ops._storage
    return [M[:-1].copy(), c.copy(), N.copy()]


def _eliminations(problem, q, theta, v):
    """Every elimination the solvers make, with what each leaves behind: gn's damped step with all
    and with held calibration variables, at the point and at a trial point (reading the trial's
    kept terms), gd's direction for another right-hand side, the posterior std."""
    P = problem.n_theta
    rng = np.random.default_rng(4)
    out = []
    for shift, free in [(1e-6, None), (0.1, (np.arange(P) < P // 2) if P > 1 else None)]:
        ops = cs.CompiledOps(problem)
        lin = ops.linearize(q, theta, v, shift=shift, free=free, gradient=True)
        out += [lin.cost, lin.grad_q.copy(), lin.grad_theta.copy(), *_factors(ops), *ops._schur]
        d_q, d_theta = ops.solve(lin, shift, free)
        out += [d_q.copy(), d_theta.copy(), ops.slope(lin, d_q, d_theta) if len(lin.grad_q) == 0 else 0.0]
        q2, v2, theta2, cost2 = ops.trial(q, v, theta, d_q * 0.3, d_theta * 0.3, 1.0)
        lin2 = ops.linearize(q2, theta2, v2, shift=shift, free=free, gradient=False)
        out += [lin2.cost, *_factors(ops), *ops._schur]  # (cost2: summed in two ranges, another order)
        other = (rng.normal(size=(len(q), 3 + problem.n_vel)), rng.normal(size=P))
        out += [x.copy() for x in ops.solve(lin2, shift, free, grad=other)]
        out += [ops.theta_std(q2, theta2, v2)]
    return out


@pytest.mark.parametrize("config", CONFIGS.values(), ids=CONFIGS.keys())
def test_the_elimination_in_ranges_is_the_elimination_in_one_pass(config, monkeypatch):
    """A long recording's linearisation runs on two threads: the blocks of a range of samples
    are computed while those of the range before are eliminated (`_eliminate_in_ranges`). Ranges
    of 7 samples (the last one shorter) give the cost, the gradient, the stored factors, the
    Schur complement, the steps and the posterior std of one pass, bit for bit."""
    problem, q, theta, v = _problem(config)
    one = _eliminations(problem, q, theta, v)
    monkeypatch.setattr(ranges, "SPLIT_MIN_SAMPLES", 2)
    monkeypatch.setattr(ranges, "RANGE_SAMPLES", (7, 7))
    in_ranges = _eliminations(problem, q, theta, v)
    assert len(one) == len(in_ranges)
    for a, b in zip(one, in_ranges):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(np.linalg.LinAlgError):
        cs.CompiledOps(problem).linearize(q, theta, v, shift=-2.0)  # not positive definite, found in a range


def test_a_matrix_that_is_not_positive_definite_is_an_error():
    problem, q, theta, v = _problem(CONFIGS["default"])
    ops = cs.CompiledOps(problem)
    with pytest.raises(np.linalg.LinAlgError):
        ops.linearize(q, theta, v, shift=-2.0)  # H - 2 diag(H) has negative diagonal entries
    with pytest.raises(np.linalg.LinAlgError):
        solve_normal_equations(problem.linearize(q, theta, v=v), -2.0)  # as the reference


def test_start_kernels_equal_dead_reckoning_and_levelled():
    """Dead reckoning as a sequential product (the reference's parallel scan multiplies in
    another order) and the re-levelling, with missing accelerometer samples and invalid steps."""
    imu, _, q0 = _sim(120.0)
    acc = imu.acc_g.copy()
    acc[500:520] = np.nan
    imu = imu.replace(acc_g=acc)
    dr = initial_trajectory("dr", "gn", imu, q0)
    np.testing.assert_allclose(start.dead_reckoned(imu, q0), dr, rtol=0, atol=1e-13)
    out = start.levelled_trajectory(imu, dr, 10.0)
    np.testing.assert_allclose(out, levelled(imu, dr, 10.0), rtol=0, atol=1e-15)
    assert start.norm_error(out) == pytest.approx(np.max(np.abs(np.linalg.norm(out, axis=1) - 1.0)), abs=1e-18)


# ----------------------------------------------------------------------------- names
# Every kernel's declared reference (`kernels._numba.mirrors`): `tests/test_compiled.py`,
# `test_every_kernel_carries_the_name_of_the_reference_it_declares`, for the filters, the smoothers
# and the peers' twins alike.


def test_the_packed_layouts_do_not_overlap():
    """What a trial keeps of a sample fits in M's row without overlap (`KEEP_*`), the cost's sums
    are numbered 0 .. N_SUMS - 1, and a carry holds its parts one after another, with room for
    `eliminate_blocks`'s block (`carry_offsets`)."""
    keep = [(layout.KEEP_STEP, 4), (layout.KEEP_MOTION, 3), (layout.KEEP_ACC, 2), (layout.KEEP_MAG, 6)]
    slots = [i for at, n in keep for i in range(at, at + n)]
    assert len(set(slots)) == len(slots) and max(slots) < layout.B_MAX**2
    sums = [layout.SUM_ACC, layout.SUM_MOTION, layout.SUM_VEL, layout.SUM_VZERO, layout.SUM_REST, layout.SUM_MAG,
            layout.SUM_PRIOR]
    assert sorted(sums) == list(range(layout.N_SUMS))
    for P in (0, 1, 4):
        offsets = layout.carry_offsets(P)
        sizes = [b - a for a, b in zip(offsets, offsets[1:])]
        assert offsets[0] == 0 and sizes == [layout.B_MAX**2, layout.B_MAX, layout.B_MAX * P, layout.N_SUMS, P, P * P]
        assert layout.carry_size(P) == offsets[-1] >= layout.CARRY_OFF_BLOCK + layout.B_MAX**2
        assert kernel_linearize.carry_offsets(P) == offsets  # the compiled definition is the same one


def test_compiled_ops_have_the_reference_ops_interface():
    """`CompiledOps` has every public method of `ReferenceOps`, with its parameters first."""
    from fusion.estimators.smoothers.smoother import ReferenceOps

    methods = [name for name, f in vars(ReferenceOps).items() if callable(f) and not name.startswith("_")]
    assert set(methods) == {"cost", "trial", "slope", "linearize", "solve", "theta_std"}
    for name in methods:
        ref = list(inspect.signature(getattr(ReferenceOps, name)).parameters)
        got = list(inspect.signature(getattr(cs.CompiledOps, name)).parameters)
        assert got[:len(ref)] == ref, (name, ref, got)


# ----------------------------------------------------------------------------- whole solves
def _sim(duration_s: float):
    from fusion.calibration import calibrate
    from fusion.sim import SimSettings, simulate

    raw, truth = simulate(SimSettings(duration_s=duration_s))
    imu = calibrate(raw).apply(raw)
    q0, _ = truth.interpolate(imu.t[:1])
    return imu, truth, q0.as_quat(scalar_first=True)[0]


def assert_same_solve(spec: str, imu, q0) -> tuple[dict, dict]:
    """spec with impl=compiled and impl=numpy: the same iterations and outcome, the cost at
    every iteration within COST_RTOL, the same calibration and orientations (to 1e-6 rad)."""
    sep = "," if ":" in spec else ":"
    got = build(f"{spec}{sep}progress=false").estimate(imu, q0)
    ref = build(f"{spec}{sep}progress=false,impl=numpy").estimate(imu, q0)
    a, b = got.diagnostics, ref.diagnostics
    assert a["iterations"] == b["iterations"] and a["converged"] == b["converged"], spec
    assert len(a["loss"]) == len(b["loss"]), spec
    np.testing.assert_allclose(a["loss"], b["loss"], rtol=COST_RTOL, err_msg=spec)
    np.testing.assert_array_equal(a["scale_released"], b["scale_released"])
    assert a.get("scale_rejected") == b.get("scale_rejected")
    np.testing.assert_allclose(a["theta"], b["theta"], rtol=0, atol=1e-7, err_msg=spec)
    angle = np.linalg.norm(quat.relative_rotvec(ref.quat_wxyz, got.quat_wxyz), axis=1)
    assert np.max(angle) < 1e-6, spec
    return a, b


@pytest.mark.parametrize("spec", ["gn", "gd", "gn:weighting=scalar", "gd:update=normalise,every=3", "gd:precond=block,iters=20",
                                  "gd:precond=none,iters=10", "gn:loss=cauchy,baxes=xyz,saxes=z", "gn:Rv=inf,level=0",
                                  "gn:release=0.01,iters=4"])
def test_compiled_solves_equal_the_reference_on_the_simulator(spec):
    imu, _, q0 = _sim(60.0)
    assert_same_solve(spec, imu, q0)


@pytest.mark.parametrize("spec", ["gn", "gd", "gn:mhi=false,mloss=cauchy", "gn:mterm=stage", "gd:mterm=stage"])
def test_compiled_solves_equal_the_reference_in_9d(spec):
    """With a magnetometer (a field read along the simulator's truth, a carried magnet over a
    third of it): the 6-D solve as above, then the heading term in the cost solved again from
    there (the default), or the heading stage (`smoothers.mag`, mag_term=stage): the same samples
    used and the same orientations."""
    imu, truth, q0 = _sim(60.0)
    rot, _ = truth.interpolate(imu.t)
    mag = rot.inv().apply([0.0, 16.0, -41.0]) + np.random.default_rng(2).normal(0.0, 1.0, (len(imu), 3))
    mag[2000:4000] += [30.0, -25.0, 12.0]
    a, b = assert_same_solve(spec, imu.replace(mag_ut=mag), q0)
    np.testing.assert_array_equal(a["mag_used"], b["mag_used"])
    assert a["mag_used"].mean() > 0.5
    if "mterm=stage" in spec:
        np.testing.assert_allclose(a["mag_heading_correction_rad"], b["mag_heading_correction_rad"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("spec", ["gn", "gd"])
def test_compiled_solves_equal_the_reference_on_a_course_recording(data_dir, spec):
    """ece276a/1 (5,645 samples, a gyro freeze), the default cost: stage 1, release of the
    scale errors and their significance test."""
    rec = datasets.load("ece276a/1", data_dir / "ece276a")
    a, _ = assert_same_solve(spec, rec.imu, datasets.initial_orientation(rec, "truth"))
    assert a["scale_released"].any()


@pytest.mark.parametrize("spec", ["gn", "gd"])
def test_compiled_solves_equal_the_reference_on_a_broad_trial(data_dir, spec):
    """BROAD trial 15 (fast translation, 285.7 Hz), its first minute (17,000 samples)."""
    pytest.importorskip("h5py")
    rec = datasets.load("broad/15_undisturbed_fast_translation_A", data_dir)
    imu = rec.imu
    n = 17000
    part = imu.window(0, n)
    assert_same_solve(spec, part, datasets.initial_orientation(rec, "truth"))


# ----------------------------------------------------------------------------- memory
@pytest.mark.parametrize("name", ["gn", "gd"])
def test_memory_is_linear_with_a_small_constant(name):
    """Peak of the numpy allocations (tracemalloc) during a compiled solve of 20 minutes of the
    simulator (120,000 samples), per sample: the elimination keeps 5 (6 + F) floats per
    sample, the solvers a handful of (T, 4) and (T, 5) arrays. The numpy reference needs
    several kilobytes per sample (its (T, 5, 5) temporaries and band matrices)."""
    imu, _, q0 = _sim(1200.0)
    est = build(f"{name}:progress=false")
    problem = est.problem(imu, q0)
    q = est.start(imu, q0)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        est.solve(problem, q)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak / len(imu) < 900, peak / len(imu)


# ----------------------------------------------------------------------------- the disk cache
# The modules whose kernels `CompiledOps` runs (`smoothers._compiled`'s docstring).
KERNEL_MODULES = ("smoothers._compiled_terms", "smoothers._compiled_cost", "smoothers._compiled_linearize",
                  "smoothers._compiled_start")  # below fusion.estimators
# The kernels `load` runs from Python; the others run inside them.
LOADED_KERNELS = ("cost", "linearize", "linearize_eliminate", "eliminate_blocks", "back_substitute", "dead_reckoning",
                  "levelled", "norm_error", "dot")

_CACHE_STATS = r"""
import importlib, json
from numba.core.registry import CPUDispatcher
from fusion.estimators.smoothers import _compiled as cs
cs.load()
stats = {}
for module in %r:
    for name, kernel in vars(importlib.import_module("fusion.estimators." + module)).items():
        if isinstance(kernel, CPUDispatcher):
            stats[name] = [sum(kernel.stats.cache_hits.values()), sum(kernel.stats.cache_misses.values())]
print(json.dumps(stats))
""" % (KERNEL_MODULES,)


def test_a_new_process_loads_the_kernels_from_the_disk_cache():
    """This process has compiled the kernels or loaded them from the cache (`load`); a new
    process must find every one `load` runs there, and compile none of the kernels of any module
    (numba's hit and miss counts). A kernel whose signature the cache cannot match again (e.g. a
    type numba cannot look up by name) is compiled anew in every process, seconds each time."""
    import json
    import subprocess
    import sys

    cs.load()
    if kernel_linearize.linearize.stats.cache_path is None:
        pytest.skip("no writable numba cache folder here: the kernels are compiled in every process by design")
    out = subprocess.run([sys.executable, "-c", _CACHE_STATS], capture_output=True, text=True, check=True).stdout
    stats = json.loads(out.strip().splitlines()[-1])
    assert all(stats[name][0] >= 1 for name in LOADED_KERNELS), stats
    assert all(miss == 0 for _, miss in stats.values()), stats
