"""Tests of the quaternion UKF (`ukf`) and `ukf-bias`."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.estimators import ESTIMATORS, build
from fusion.estimators.kernels._linalg import sqrt_psd
from fusion.estimators.dr import DeadReckoning
from fusion.estimators.filters.quaternion_ukf import QuaternionSigmaPoints, quaternion_mean
from fusion.estimators.filters.ukf import UKF, UKFBias, UKFBiasParams, UKFParams
from fusion import quaternion as quat
from fusion.types import ImuSamples

from motion_helpers import turning_body


def synthetic(n: int = 600, seed: int = 0, noise: float = 0.0, bias=(0.0, 0.0, 0.0)):
    """A smooth rotation with exact accelerometer: (ImuSamples, true (n, 4) quaternions).

    Jittered time steps (about 100 Hz); the gyro reads the true rate (+ bias + noise), the
    accelerometer gravity in the body frame (+ noise) (`motion_helpers.turning_body`).
    """
    dt = 0.01 + np.random.default_rng(seed).uniform(-1e-3, 1e-3, n - 1)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    w = np.stack([1.5 * np.sin(1.3 * t), 1.0 * np.cos(0.7 * t + 0.3), 0.8 * np.sin(0.9 * t + 1.0)], axis=1)
    q0 = quat.normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    return turning_body(t, w, q0, gyr_std=noise, acc_std=noise, bias=bias, seed=seed + 1, source="synthetic")


def inclination_deg(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    a, b = quat.gravity_in_body(q_true), quat.gravity_in_body(q_est)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


# ---------------------------------------------------------------- helpers
def test_sqrt_psd_recovers_singular_matrix():
    a = np.diag([1e-3, 0.0, 2e-3])
    L, recovered = sqrt_psd(a)
    assert recovered
    assert np.allclose(L @ L.T, a, atol=1e-15)


# ---------------------------------------------------------------- iterative mean (step 5)
@pytest.mark.parametrize("spread", [1e-3, 0.3, 1.2])
def test_mean_of_symmetric_points_is_the_centre(spread):
    rng = np.random.default_rng(2)
    q = quat.normalize(rng.normal(size=4))
    offsets = rng.normal(size=(4, 3)) * spread
    pts = quat.multiply(q, quat.from_rotvec(np.concatenate([offsets, -offsets])))
    w = np.full(8, 1 / 8)
    start = quat.multiply(q, quat.from_rotvec(np.array([0.2, -0.1, 0.05])))  # a poor first guess
    mean, res, iters = quaternion_mean(pts, w, start, tol=1e-12, max_iter=50)
    assert np.allclose(quat.canonical(mean), quat.canonical(q), atol=1e-10)
    assert iters < 50
    assert np.allclose(w @ res, 0.0, atol=1e-10)
    assert np.allclose(res, np.concatenate([offsets, -offsets]), atol=1e-9)


def test_mean_handles_q_and_minus_q_in_the_same_set():
    rng = np.random.default_rng(3)
    q = quat.normalize(rng.normal(size=4))
    offsets = rng.normal(size=(3, 3)) * 0.1
    pts = quat.multiply(q, quat.from_rotvec(np.concatenate([offsets, -offsets])))
    pts[::2] *= -1.0  # flip the sign of half the points: the same rotations
    mean, _, _ = quaternion_mean(pts, np.full(6, 1 / 6), pts[1], tol=1e-12, max_iter=50)
    assert np.allclose(quat.canonical(mean), quat.canonical(q), atol=1e-10)


def test_mean_stops_at_its_cap_and_converges_fast_for_filter_spreads():
    rng = np.random.default_rng(4)
    q = quat.normalize(rng.normal(size=4))
    pts = quat.multiply(q, quat.from_rotvec(rng.normal(size=(6, 3)) * 0.05))
    w = np.full(6, 1 / 6)
    _, _, iters = quaternion_mean(pts, w, q, tol=1e-9, max_iter=20)
    assert iters <= 4
    _, _, capped = quaternion_mean(pts, w, q, tol=0.0 + 1e-300, max_iter=3)
    assert capped == 3


# ---------------------------------------------------------------- sigma-point schemes
@pytest.mark.parametrize("scheme,kw", [("kraft", {}), ("julier", {"kappa": 2.0}), ("merwe", {"alpha": 1.0, "kappa": 1.0})])
def test_sigma_points_reproduce_mean_and_covariance(scheme, kw):
    pts = QuaternionSigmaPoints(3, scheme, **kw)
    assert np.isclose(pts.Wm.sum(), 1.0)
    P = np.array([[2e-3, 1e-4, 0.0], [1e-4, 1e-3, -2e-4], [0.0, -2e-4, 3e-3]])
    off = pts.offsets(P)
    assert np.allclose(pts.Wm @ off, 0.0, atol=1e-15)
    cov = off.T @ (pts.Wc[:, None] * off)
    extra = pts.Wc.sum() - 1.0  # Merwe's beta term sits on the (zero) centre offset
    assert np.allclose(cov, P, atol=1e-15), extra
    x = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    sig = pts.sigma_points(x, P)
    assert sig.shape == (7, 4)
    assert np.allclose(quat.relative_rotvec(x, sig), off, atol=1e-12)


@pytest.mark.parametrize(
    "scheme,kw,match",
    [
        ("merwe", {"alpha": 1e-3, "kappa": 0.0}, "negative|< 0"),
        ("merwe", {"alpha": 0.5, "kappa": 0.0}, "kappa >="),
        ("julier", {"kappa": -1.0}, "kappa >= 0"),
        ("unscented", {}, "kraft, julier or merwe"),
    ],
)
def test_impossible_sigma_settings_raise(scheme, kw, match):
    with pytest.raises(ValueError, match=match):
        QuaternionSigmaPoints(3, scheme, **kw)
    with pytest.raises(ValueError):
        UKFParams(sigma=scheme, **kw)


def test_sigma_points_reject_wrong_shapes():
    pts = QuaternionSigmaPoints(3)
    with pytest.raises(ValueError, match="expected x"):
        pts.sigma_points(np.array([1.0, 0, 0, 0, 0]), np.eye(3))
    with pytest.raises(ValueError, match="expected x"):
        pts.sigma_points(np.array([1.0, 0, 0, 0]), np.eye(4))


# ---------------------------------------------------------------- parameters
@pytest.mark.parametrize(
    "spec",
    ["ukf:Q=-1", "ukf:R=-1e-3", "ukf:R=0", "ukf:P0=nan", "ukf:tol=0", "ukf:iters=0", "ukf-bias:Qb=-1",
     "ukf:sigma=merwe,alpha=0.01", "ukf:bogus=1", "ukf:gate_g=0"],
)
def test_bad_parameters_raise(spec):
    with pytest.raises(ValueError):
        build(spec)


@pytest.mark.parametrize(
    "spec,match",
    [("ukf:alpha=0.1", "ukf: alpha applies only with sigma=merwe; it is ignored with sigma=kraft"),
     ("ukf:beta=0", "ukf: beta applies only with sigma=merwe; it is ignored with sigma=kraft"),
     ("ukf:sigma=julier,alpha=0.5", "alpha applies only with sigma=merwe; it is ignored with sigma=julier"),
     ("ukf:kappa=2", "ukf: kappa applies only with sigma=julier or merwe; it is ignored with sigma=kraft"),
     ("ukf-bias:gate_g=0.3", "ukf-bias: gate_g applies only with gate=skip or inflate; it is ignored with gate=off"),
     ("ukf-bias:scale=false,Qsw=1e-6", "scale_walk_1_s applies only with estimate_scale=true"),
     ("ukf-bias:scale=false,saxes=xyz", "scale_axes applies only with estimate_scale=true")],
)
def test_parameter_ignored_by_the_chosen_option_raises(spec, match):
    with pytest.raises(ValueError, match=match):
        build(spec)


@pytest.mark.parametrize("spec,expected", [
    ("ukf:sigma=merwe,alpha=0.9,beta=2,kappa=2", UKFParams(sigma="merwe", alpha=0.9, beta=2.0, kappa=2.0)),
    ("ukf:sigma=julier,kappa=2", UKFParams(sigma="julier", kappa=2.0)),
    ("ukf:kappa=1", UKFParams()),  # kraft's value, the default: accepted, and nothing changes
    ("ukf-bias:gate=inflate,gate_g=0.3", UKFBiasParams(gate="inflate", gate_g=0.3)),
    ("ukf-bias:scale=false", UKFBiasParams(estimate_scale=False)),
])
def test_parameters_of_the_chosen_option_are_accepted(spec, expected):
    assert build(spec).params == expected


def test_registry_and_aliases():
    assert ESTIMATORS["ukf"] is UKF and ESTIMATORS["ukf-bias"] is UKFBias
    est = build("ukf:R=1e-3,Q=1e-2,sigma=julier,kappa=2")
    assert est.params == UKFParams(acc_noise_g2_s=1e-3, process_noise_rad2_s=1e-2, sigma="julier", kappa=2.0)
    assert UKFParams.equal_variances().acc_noise_g2_s == 1e-6  # 1e-4 g^2 per 100 Hz sample


def test_filterpy_impl_refuses_heading_free():
    with pytest.raises(ValueError, match="heading_free"):
        UKFBiasParams(impl="filterpy")


@pytest.mark.parametrize("spec", ["ukf:hf=true", "ukf-bias", "ekf"])
def test_heading_free_update_does_not_turn_about_the_vertical(spec):
    # One step with zero rate and a tilted accelerometer reading: the correction must be a
    # rotation about a horizontal (world) axis, i.e. leave the heading unchanged.
    t = np.array([0.0, 0.01])
    q0 = quat.normalize(np.array([0.9, 0.2, -0.3, 0.25]))
    g = quat.gravity_in_body(q0)
    acc = np.stack([g, quat.normalize(g + np.array([0.05, -0.08, 0.02]))])
    imu = ImuSamples(t, np.zeros((2, 3)), acc)
    est = build(spec + ("," if ":" in spec else ":") + "P0=1e-2").estimate(imu, q0)
    world_step = quat.to_rotvec(quat.multiply(est.quat_wxyz[1], quat.conjugate(q0)))
    assert np.linalg.norm(world_step) > 1e-3  # the update did something
    assert abs(world_step[2]) < 1e-6 * np.linalg.norm(world_step) + 1e-12


def test_bad_initial_quaternion_raises():
    imu, truth = synthetic(20)
    with pytest.raises(ValueError, match="init_quat_wxyz"):
        UKF().estimate(imu, np.array([np.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="init_quat_wxyz"):
        UKF().estimate(imu, np.zeros(4))


# ---------------------------------------------------------------- exact cases
@pytest.mark.parametrize("cls,kw", [
    (UKF, {}), (UKF, {"sigma": "julier"}), (UKF, {"sigma": "merwe", "kappa": 1.0}), (UKF, {"impl": "filterpy"}),
    (UKF, {"impl": "numpy"}),
    (UKFBias, {"bias_walk_rad2_s3": 0.0, "init_bias_var_rad2_s2": 0.0, "init_scale_var": 0.0,
               "scale_walk_1_s": 0.0}),
    (UKFBias, {"bias_walk_rad2_s3": 0.0, "init_bias_var_rad2_s2": 0.0, "init_scale_var": 0.0,
               "scale_walk_1_s": 0.0, "impl": "numpy"}),
])
def test_without_accelerometer_and_noise_equals_dead_reckoning(cls, kw):
    imu, _ = synthetic(400)
    valid = np.ones(len(imu), bool)
    valid[100:130] = False  # invalid gyro samples are not integrated, as in dr
    imu = imu.replace(gyr_valid=valid)
    q0 = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    params = cls.Params(use_acc=False, process_noise_rad2_s=0.0, init_var_rad2=0.0, invalid_gyr_var_rad2_s2=0.0, **kw)
    est = cls(params).estimate(imu, q0)
    ref = DeadReckoning().estimate(imu, q0)
    assert np.max(np.abs(quat.canonical(est.quat_wxyz) - quat.canonical(ref.quat_wxyz))) < 1e-9


@pytest.mark.parametrize("cls", [UKF, UKFBias])
@pytest.mark.parametrize("n,noise,cov_atol", [(300, 0.02, 1e-14), (1500, 0.05, 1e-13)])
def test_numpy_step_equals_filterpy_reference(cls, n, noise, cov_atol):
    imu, truth = synthetic(n, noise=noise, bias=(0.02, -0.01, 0.03))
    # The numpy step takes the residuals about the final mean to first order in the last
    # mean update (< mean_tol_rad); with a tight tolerance both paths agree to rounding
    # (accumulated over the longer run: 1e-14 of covariances up to 1e-2).
    # FilterPy's update has no gain projection, so heading_free is off for both. The scale test
    # is the same code in both (after the update) and is left out, so that the noisier run keeps
    # the scale uncertainty in the low-pass's lag model, which it exercises.
    kw = {"scale_test_error": 0.0} if cls is UKFBias else {}
    a = cls(cls.Params(impl="numpy", mean_tol_rad=1e-14, heading_free=False, **kw)).estimate(imu, truth[0])
    b = cls(cls.Params(impl="filterpy", mean_tol_rad=1e-14, heading_free=False, **kw)).estimate(imu, truth[0])
    assert np.allclose(a.quat_wxyz, b.quat_wxyz, rtol=0, atol=1e-12)
    assert np.allclose(a.diagnostics["cov"], b.diagnostics["cov"], rtol=0, atol=cov_atol)
    if cls is UKFBias and noise > 0.02:  # the noisier run takes the low-passed sample with its lag model
        assert a.diagnostics["acc_lowpassed"].sum() > n // 4


# Inclination RMSE bounds: measured 0.526 deg (ukf, any sigma points), 1.03 (ukf-bias), 0.395
# (ukf:Q=1e-2,R=1e-4), + 15 % (was 1.5 for all).
@pytest.mark.parametrize("spec,bound", [("ukf", 0.61), ("ukf:sigma=julier", 0.61), ("ukf:sigma=merwe,kappa=1", 0.61),
                                        ("ukf-bias", 1.19), ("ukf:Q=1e-2,R=1e-4", 0.46)])
def test_tracks_synthetic_motion(spec, bound):
    imu, truth = synthetic(1500, noise=0.01, bias=(0.02, -0.01, 0.03), seed=5)
    est = build(spec).estimate(imu, truth[0])
    assert np.sqrt(np.mean(inclination_deg(truth, est.quat_wxyz) ** 2)) < bound
    assert np.all(np.isfinite(est.quat_wxyz))
    assert np.allclose(np.linalg.norm(est.quat_wxyz, axis=1), 1.0, atol=1e-12)


def test_ukf_bias_learns_a_gyro_bias():
    bias = np.array([0.03, -0.02, 0.01])
    imu, truth = synthetic(3000, noise=0.005, bias=bias, seed=6)
    est = UKFBias(UKFBiasParams(bias_walk_rad2_s3=1e-5)).estimate(imu, truth[0])
    b = est.diagnostics["gyr_bias_rad_s"][-500:].mean(axis=0)
    # Gravity makes the two horizontal-in-world components observable, and the turning body shows
    # each body axis horizontal in turn: the bias error is 6.0 % of the bias (measured), + 15 %
    # (was 50 %).
    assert np.linalg.norm(b - bias) < 0.07 * np.linalg.norm(bias)


# Inclination RMSE over the last 300 samples: measured 0.074 (ukf) and 0.605 deg (ukf-bias), + 15 %
# (was 2.0 for both).
@pytest.mark.parametrize("spec,bound", [("ukf", 0.085), ("ukf-bias", 0.70)])
def test_recovers_after_nan_and_saturated_stretch(spec, bound):
    imu, truth = synthetic(1500, noise=0.005, seed=7)
    gyr, acc = imu.gyr_rad_s.copy(), imu.acc_g.copy()
    gyr[500:600] = np.nan
    acc[520:560] = np.nan
    acc[560:600] = 8.0  # saturated accelerometer
    est = build(spec).estimate(imu.replace(gyr_rad_s=gyr, acc_g=acc), truth[0])
    assert np.all(np.isfinite(est.quat_wxyz))
    assert np.all(np.isfinite(est.diagnostics["cov"][1:]))
    assert np.sqrt(np.mean(inclination_deg(truth[1200:], est.quat_wxyz[1200:]) ** 2)) < bound


# ---------------------------------------------------------------- real and simulated recordings
FILTERS = ("ukf", "ukf-bias", "ekf")


@pytest.fixture(scope="module")
def real_runs(data_dir):
    """Every filter (defaults) and dr on ece276a 1-9 from the truth: {(spec, n): (Trajectory, Score)}."""
    from fusion.evaluation.scoring.metrics import score
    from fusion import datasets

    out = {}
    for n in range(1, 10):
        # the targets are stated without dropout handling (the gyro freezes integrated)
        rec = datasets.load(f"ece276a/{n}", data_dir, dropouts=False)
        q0 = datasets.initial_orientation(rec, "truth")
        for spec in ("dr",) + FILTERS:
            est = build(spec).estimate(rec.imu, q0)
            out[spec, n] = (est, score(rec.truth, est))
    return out


@pytest.mark.parametrize("spec", FILTERS)
def test_covariance_stays_spd_on_every_real_recording(real_runs, spec):
    for n in range(1, 10):
        est, _ = real_runs[spec, n]
        cov = est.diagnostics["cov"]
        assert np.all(np.isfinite(cov)), n
        assert np.array_equal(cov, np.swapaxes(cov, 1, 2)), n  # exactly symmetric
        assert np.linalg.eigvalsh(cov).min() > 0.0, n
        assert est.diagnostics["cov_repairs"] == 0, n  # SPD without the recovery
        assert est.diagnostics.get("sqrt_recoveries", 0) == 0, n


# The real recordings with the gyro freezes left in (dropout detection off): the bounds are the
# filters' first defaults here (2.11 / 17.4 for ukf, 2.10 / 17.2 for ukf-bias and ekf) with a
# margin, not a measurement. Without the online stuck-gyro check (`stuck=false`) the filters
# measure 4.20 / 3.95 / 3.63 deg inclination (ukf / ukf-bias / ekf): an unflagged freeze looks to
# them like a long linear acceleration. With it: 1.93 / 1.62 / 1.59 (total 6.53 / 5.50 / 5.46).
@pytest.mark.parametrize("spec,inclination,total", [("ukf", 3.0, 18.0), ("ukf-bias", 2.2, 18.0), ("ekf", 2.2, 18.0)])
def test_mean_rmse_on_real_recordings(real_runs, spec, inclination, total):
    inc = [real_runs[spec, n][1].rmse_deg["inclination"] for n in range(1, 10)]
    tot = [real_runs[spec, n][1].rmse_deg["total"] for n in range(1, 10)]
    assert np.mean(inc) <= inclination
    assert np.mean(tot) <= total


@pytest.fixture(scope="module")
def default_runs(data_dir):
    """Every filter with its defaults on ece276a 1-9, loaded as `fusion compare` does (gyro
    freezes detected and masked): {(spec, n): Score}."""
    from fusion.evaluation.scoring.metrics import score
    from fusion import datasets

    out = {}
    for n in range(1, 10):
        rec = datasets.load(f"ece276a/{n}", data_dir)
        q0 = datasets.initial_orientation(rec, "truth")
        for spec in FILTERS:
            out[spec, n] = score(rec.truth, build(spec).estimate(rec.imu, q0))
    return out


# The course targets for filters whose defaults must also hold on BROAD: no worse than the
# course-tuned filters were (ekf 1.95 / 6.86): the bounds are that target, not a margin on a
# measurement. Measured: ekf 1.55 / 5.34, ukf-bias 1.59 / 5.38, ukf 1.92 / 6.78 (inclination /
# total, deg).
@pytest.mark.parametrize("spec,inclination,total", [("ukf", 2.0, 7.0), ("ukf-bias", 1.95, 6.86), ("ekf", 1.95, 6.86)])
def test_mean_rmse_on_real_recordings_with_default_loading(default_runs, spec, inclination, total):
    assert np.mean([default_runs[spec, n].rmse_deg["inclination"] for n in range(1, 10)]) <= inclination
    assert np.mean([default_runs[spec, n].rmse_deg["total"] for n in range(1, 10)]) <= total


def test_ukf_beats_dead_reckoning_inclination_on_every_recording(real_runs):
    for n in range(1, 10):
        assert real_runs["ukf", n][1].rmse_deg["inclination"] < real_runs["dr", n][1].rmse_deg["inclination"], n


# Bounds on the built-in simulated recording (exact truth, 180 s, sustained ~0.07 g hand
# accelerations). Measured: dr 14.2 / 19.7, ukf 1.48 / 17.2 (heading random walk under linear
# acceleration), ukf:hf=true 2.22 / 13.4, ukf-bias 0.95 / 6.49, ekf 1.03 / 6.88 deg (inclination /
# total RMSE; with the 1 s low-pass it had before its cross-validated 2 s: 0.88 / 6.18); the bounds
# add about 15 % (ekf's were ukf-bias's, 1.1 / 7.5).
@pytest.mark.parametrize(
    "spec,inclination,total",
    [("ukf", 1.7, 19.5), ("ukf:hf=true", 2.55, 15.5), ("ukf-bias", 1.1, 7.5), ("ekf", 1.19, 7.91)],
)
def test_bounds_on_the_simulated_recording(spec, inclination, total):
    from fusion.evaluation.scoring.metrics import score
    from fusion import datasets

    rec = datasets.load("sim")
    est = build(spec).estimate(rec.imu, datasets.initial_orientation(rec, "truth"))
    s = score(rec.truth, est)
    assert s.rmse_deg["inclination"] <= inclination
    assert s.rmse_deg["total"] <= total
    cov = est.diagnostics["cov"]
    assert np.linalg.eigvalsh(cov[1:]).min() > 0.0


@pytest.mark.parametrize("spec,reference", [("ukf", "impl=numpy"), ("ukf-bias", "impl=numpy"), ("ekf", "impl=numpy")])
def test_streaming_reset_and_step_equal_estimate(spec, reference):
    """A streaming user resets from the initial orientation alone and steps; the same numbers as
    `estimate` with the numpy step (bit for bit) and as the compiled default (to 1e-10)."""
    imu, truth = synthetic(300, noise=0.01, seed=3)
    batch = build(f"{spec}:{reference}").estimate(imu, truth[0])
    compiled = build(spec).estimate(imu, truth[0])
    est = build(spec)
    est.reset(truth[0])
    (gyr, valid), dt = imu.interval_rates(), imu.dt
    out = [est.step(gyr[k], dt[k], imu.acc_g[k + 1], valid[k]).copy() for k in range(len(imu) - 1)]
    np.testing.assert_array_equal(np.array(out), batch.quat_wxyz[1:])
    np.testing.assert_allclose(np.array(out), compiled.quat_wxyz[1:], rtol=0, atol=1e-10)
    cov = batch.diagnostics["cov"]
    assert cov.shape == compiled.diagnostics["cov"].shape == (len(imu),) + est.current()["cov"].shape
    np.testing.assert_array_equal(cov[-1], est.current()["cov"])
    np.testing.assert_allclose(compiled.diagnostics["cov"][-1], est.current()["cov"], rtol=0, atol=1e-10)


def test_filterpy_api_works_on_the_quaternion_ukf():
    """FilterPy's own `predict`/`update` run on `QuaternionUKF` (they are not overridden): a
    board held still with a 20-deg tilt is found from the accelerometer."""
    from fusion.estimators.filters.quaternion_ukf import QuaternionUKF, unscented_transform_state

    tilt = Rotation.from_euler("x", 20, degrees=True)
    z = tilt.inv().apply([0.0, 0.0, 1.0])  # what the accelerometer reads, g
    kf = QuaternionUKF(QuaternionSigmaPoints(3))
    kf.P, kf.Q, kf.R = np.eye(3) * 0.5, np.eye(3) * 1e-6, np.eye(3) * 1e-3
    for _ in range(200):
        kf.predict(0.01, UT=unscented_transform_state, gyr_rad_s=np.zeros(3))  # FilterPy's predict
        kf.update(z)  # FilterPy's update
    assert np.isclose(np.linalg.norm(kf.x), 1.0) and kf.P.shape == (3, 3)
    est = Rotation.from_quat(kf.x, scalar_first=True)
    inclination = np.degrees(np.arccos(np.clip(est.inv().apply([0, 0, 1]) @ z, -1, 1)))
    assert inclination < 0.5
