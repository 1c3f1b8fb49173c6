"""The smoothers' rest term: the gyro reads its bias where the recording is at rest."""
import dataclasses

import numpy as np
import pytest

from fusion import datasets, estimators
from fusion.calibration import calibrate
from fusion.datasets import calibrated_samples
from fusion.sim import SimSettings, simulate
from fusion import quaternion as quat
from fusion.datasets import initial_orientation
from fusion.estimators.filters.steps._compiled_rest import rest_steps
from fusion.estimators.smoothers.cost import SmootherProblem, Weights
from fusion.evaluation.scoring.metrics import score

from test_smoother import random_imu, random_point


@pytest.fixture(scope="module")
def sim():
    return datasets.load("sim")


def test_rest_steps_are_the_filters_rest_updates(sim):
    """`rest_steps` flags exactly the steps on which `ekf` makes its zero-rate update (with a tilt
    test, and without it, the default: the smoothers' detector). The simulator's rests are short, and
    its quantised accelerometer (0.55 deg a count) ends a 0.3-deg test's stretches there: 1 deg reaches
    a rest."""
    for spec in ("ekf:rtilt=0.0052", "ekf:rtilt=0.0175", "ekf"):
        est = estimators.build(spec)
        p = est.params
        at_rest = est.estimate(sim.imu, initial_orientation(sim, "truth")).diagnostics["at_rest"]
        flags = rest_steps(sim.imu, p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s, tilt_rad=p.rest_tilt_rad)
        assert spec == "ekf:rtilt=0.0052" or (flags.any() and not flags.all())
        np.testing.assert_array_equal(flags, at_rest[1:])
    assert not rest_steps(sim.imu, p.rest_gyr_rad_s, p.rest_acc_g, np.inf).any()


def test_rest_term_derivatives_match_finite_differences():
    """With a rest mask, the cost's gradient in theta and its theta block (exact for this
    linear residual) agree with central differences of the cost."""
    imu = random_imu(T=30, dropout=False)
    weights = Weights(process_noise_rad2_s=4e-4, acc_noise_g2_s=1e-4, loss_scale_g=np.inf, bias_axes="xyz",
                      scale_axes="xy", rest_noise_rad2_s=2.5e-3)
    rest = np.zeros(len(imu) - 1, bool)
    rest[5:17] = True
    problem = SmootherProblem.from_imu(imu, quat.normalize(np.array([0.9, 0.1, -0.2, 0.3])), weights, rest=rest)
    without = SmootherProblem.from_imu(imu, quat.normalize(np.array([0.9, 0.1, -0.2, 0.3])), weights)
    q, theta = random_point(problem)
    lin, lin0 = problem.linearize(q, theta), without.linearize(q, theta)
    assert lin.cost > lin0.cost
    eps = 1e-4
    E = np.eye(problem.n_theta) * eps
    grad = np.array([(problem.cost(q, theta + e) - problem.cost(q, theta - e)) / (2 * eps) for e in E])
    np.testing.assert_allclose(lin.grad_theta, grad, rtol=1e-5)
    # The rest term is quadratic in theta: its block is the difference of the two problems'
    # theta blocks, and equals the finite-difference Hessian of the cost difference.
    def rest_cost(th):
        return problem.cost(q, th) - without.cost(q, th)
    H = np.array([[(rest_cost(theta + a + b) - rest_cost(theta + a - b) - rest_cost(theta - a + b)
                    + rest_cost(theta - a - b)) / (4 * eps**2) for b in E] for a in E])
    np.testing.assert_allclose(lin.theta_block - lin0.theta_block, H, rtol=1e-4, atol=1e-3 * np.abs(H).max())
    # The residual is w_t itself, on the bias axes, only on the flagged steps.
    r = problem.residuals(q, theta)["rest"]
    assert r.shape == (rest.sum(), 3)
    np.testing.assert_allclose(r, problem.rates(theta)[rest])


def test_axis_without_bias_variable_takes_the_rest_reading():
    """A z gyro offset the calibration did not remove: the rest steps read it, so a smoother
    without a z bias variable subtracts it, and the heading no longer drifts with it."""
    raw, truth = simulate(SimSettings(duration_s=120.0, rest_start_s=12.0, rest_end_s=12.0, quantise=False))
    clean = calibrated_samples(raw, calibrate(raw), True)
    offset = 0.006  # rad/s on z
    imu = clean.replace(gyr_rad_s=np.asarray(clean.gyr_rad_s) + [0.0, 0.0, offset])
    q0 = truth.quat_wxyz[0]
    p = estimators.build("gn").params
    rest = rest_steps(imu, p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s)
    assert rest.sum() > 500
    problem = SmootherProblem.from_imu(imu, q0, p.weights(), rest=rest)
    # The fixed z offset is the rest steps' mean reading (each step weighted by its duration).
    raw_rate, _ = imu.interval_rates()
    read = np.average(raw_rate[rest, 2], weights=imu.dt[rest])
    np.testing.assert_allclose(raw_rate[:, 2] - problem.gyr[:, 2], read)
    assert abs(read - offset) < 1e-3
    heading = {}
    for name, rest_time in (("rest", p.rest_time_s), ("no rest", np.inf)):
        est = estimators.build("gn")
        est.params = dataclasses.replace(est.params, progress=False, rest_time_s=rest_time)
        heading[name] = score(truth, est.estimate(imu, q0)).rmse_deg["heading"]
    assert heading["rest"] < 0.25 * heading["no rest"], heading


@pytest.mark.slow
def test_implausible_scale_error_is_held_at_zero(sim):
    """A scale error estimated beyond `scale_max` is rejected and its axis solved again
    without it; a plausible one is kept."""
    q0 = initial_orientation(sim, "truth")
    gyr = np.asarray(sim.imu.gyr_rad_s)
    for true_x, rejected in ((1.05, ""), (1.6, "x")):
        imu = sim.imu.replace(gyr_rad_s=gyr * [true_x, 1.0, 1.0])
        est = estimators.build("gn")
        est.params = dataclasses.replace(est.params, progress=False)
        d = est.estimate(imu, q0).diagnostics
        assert d.get("scale_rejected", "") == rejected
        if rejected:
            assert d["theta_names"] == ["bias_x", "bias_y", "scale_y"]
        else:
            assert d["theta_names"][-2:] == ["scale_x", "scale_y"]


def test_scale_errors_are_kept_only_when_significant(sim):
    """The simulated board's gyro reads 9 and 4 % high on x and y: the released scale errors
    lower the cost far beyond the chi-square threshold and are kept. Asking for an absurd
    significance level rejects them, and the smoother returns its stage-1 solution."""
    from scipy.stats import chi2

    q0 = initial_orientation(sim, "truth")
    out = {}
    for sig in (0.05, 1e-300):
        est = estimators.build("gn")
        est.params = dataclasses.replace(est.params, progress=False, scale_significance=sig)
        traj = est.estimate(sim.imu, q0)
        out[sig] = (traj, traj.diagnostics, score(sim.truth, traj).rmse_deg["inclination"])
    traj, d, incl = out[0.05]
    assert d["scale_released"].all() and d["scale_lr"] > chi2.ppf(0.95, 2)
    assert np.all(d["gyr_scale_error"][:2] < -0.02)
    traj_r, d_r, incl_r = out[1e-300]
    assert d_r["scale_lr"] == d["scale_lr"] and not d_r["scale_released"].any()
    np.testing.assert_array_equal(d_r["gyr_scale_error"], 0.0)
    # The stage-1 solution: a higher cost than the final one, and worse without the scale errors.
    problem = est.problem(sim.imu, q0)
    assert problem.cost(traj_r.quat_wxyz, d_r["theta"], d_r["velocity_m_s"]) > d["loss"][-1]
    assert incl_r > incl
