"""`gn` and `gd` in 9-D: the magnetometer's heading term in the cost (`smoothers.cost`, the
default) and the heading-only stage after the 6-D solve (`fusion.estimators.smoothers.mag`,
mag_term=stage), their gates and hard-iron fit, and 6-D unchanged.

Simulated cases use the built-in `sim` recording with the body-frame reading of an ENU field
(north along y, dipping down) along its truth, plus noise, and a 0.2 deg/s z gyro bias added
after its calibration so that the 6-D heading drifts; the hard-iron fit is checked on a
synthetic tumbling trajectory that covers the sphere; real-data cases use the `data_dir`
fixture (skipped without FUSION_DATA, failing when it is set but the files are missing).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion import quaternion as quat
from fusion.estimators import build
from fusion.estimators.smoothers.gd import GradientDescentSmoother
from fusion.estimators.smoothers.gn import GaussNewtonSmoother
from fusion.estimators.smoothers.mag import heading_correction, heading_smoother
from fusion.evaluation.scoring.metrics import error_angles, score
from fusion.types import ImuSamples

from mag_helpers import FIELD_ENU_UT, q0, sim_with_magnetometer, with_magnet_carried, with_magnet_passed
from optional_helpers import require_module

UNGATED = ",mnorm=10,mdip=3.14,mhi=false,mloss=none"  # nothing gated out, no hard-iron fit, no robust loss
TERMS = ["cost", "stage"]
SMOOTHERS = ["gn", "gd"]


@pytest.fixture(scope="module")
def sim():
    """The simulated recording (180 s, 100 Hz) with a z gyro bias and a noisy (1 uT) magnetometer."""
    return sim_with_magnetometer()


@pytest.fixture(scope="module")
def six_d(sim):
    """The 6-D solutions of gn and gd on the simulated recording (no magnetometer)."""
    imu, rot = sim
    return {name: build(name).estimate(imu.replace(mag_ut=None), q0(rot)) for name in SMOOTHERS}


def angles(rot: Rotation, q: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.degrees(v) for k, v in error_angles(rot, Rotation.from_quat(q, scalar_first=True)).items()}


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


def test_the_smoothers_are_9d_estimators():
    assert GaussNewtonSmoother.magnetometer and GradientDescentSmoother.magnetometer


@pytest.mark.parametrize("name", SMOOTHERS)
def test_the_heading_stage_holds_heading_where_6d_drifts(sim, six_d, name):
    imu, rot = sim
    nine = build(f"{name}:mterm=stage").estimate(imu, q0(rot))
    six = six_d[name]
    drift, held = angles(rot, six.quat_wxyz), angles(rot, nine.quat_wxyz)
    assert rms(drift["heading"]) > 20.0, "the test needs a drifting 6-D heading"
    # measured (gn): 6-D 24.3 deg RMS, 9-D 2.3 (the simulator's 4 % z scale error, not estimated,
    # turns its yaw swings into heading errors faster than the 10 s correction follows)
    assert rms(held["heading"]) < 3.5, f"9-D heading error {rms(held['heading']):.2f} deg RMS"
    assert nine.diagnostics["mag_used"].mean() > 0.9
    # heading only: the inclination is the 6-D solution's (a rotation about the world vertical)
    np.testing.assert_allclose(held["inclination"], drift["inclination"], atol=1e-6)


@pytest.fixture(scope="module")
def clean_heading(sim):
    """gn's 9-D heading error (deg) on the undisturbed simulated recording, per mag_term."""
    imu, rot = sim
    return {term: angles(rot, build(f"gn:mterm={term}").estimate(imu, q0(rot)).quat_wxyz)["heading"] for term in TERMS}


@pytest.mark.parametrize("term", TERMS)
def test_a_magnet_carried_with_the_sensor_does_not_drag_heading(sim, clean_heading, term):
    """The simulator turns mostly about one axis, too little of the sphere for a trusted
    hard-iron fit: the magnet's samples are gated out and the heading bridges them. Measured:
    at most 1.9 (stage) and 1.3 deg (cost) from the heading without the magnet; 70 and 17 deg
    with no gate, no fit and no robust loss."""
    imu, rot = sim
    disturbed = with_magnet_carried(imu, 4000, 10000)  # 40-100 s
    est = build(f"gn:mterm={term}").estimate(disturbed, q0(rot))
    heading = angles(rot, est.quat_wxyz)["heading"]
    ungated = angles(rot, build(f"gn:mterm={term}" + UNGATED).estimate(disturbed, q0(rot)).quat_wxyz)["heading"]
    used = est.diagnostics["mag_used"]
    assert used[4000:10000].mean() < 0.05 and used[:3500].mean() > 0.9 and used[-3000:].mean() > 0.9
    moved, dragged = np.max(np.abs(heading - clean_heading[term])), np.max(np.abs(ungated - clean_heading[term]))
    assert moved < 2.5 and dragged > 4.0 * moved, (moved, dragged)


@pytest.mark.parametrize("term", TERMS)
def test_a_magnet_in_the_room_does_not_drag_heading(sim, clean_heading, term):
    """Measured: at most 1.9 (stage) and 1.0 deg (cost) from the heading without the magnet;
    24 and 10 deg with no gate, no fit and no robust loss."""
    imu, rot = sim
    disturbed = with_magnet_passed(imu, rot, centre=8000, width=500)
    est = build(f"gn:mterm={term}").estimate(disturbed, q0(rot))
    heading = angles(rot, est.quat_wxyz)["heading"]
    ungated = angles(rot, build(f"gn:mterm={term}" + UNGATED).estimate(disturbed, q0(rot)).quat_wxyz)["heading"]
    assert est.diagnostics["mag_used"][7700:8300].mean() < 0.05  # the magnet's peak is gated out
    moved, dragged = np.max(np.abs(heading - clean_heading[term])), np.max(np.abs(ungated - clean_heading[term]))
    assert moved < 2.5 and dragged > 4.0 * moved, (moved, dragged)


def tumbling(seconds: float = 240.0, rate_hz: float = 50.0):
    """A synthetic trajectory turning through every direction (three incommensurate rotations),
    with its exact gyro and accelerometer: (ImuSamples without magnetometer, Rotation)."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    rot = (Rotation.from_rotvec(np.outer(0.31 * t, [0.0, 0.0, 1.0]))
           * Rotation.from_rotvec(np.outer(1.3 * np.sin(0.23 * t), [1.0, 0.0, 0.0]))
           * Rotation.from_rotvec(np.outer(0.47 * t, [0.0, 1.0, 0.0])))
    # the body rate over (t[k-1], t[k]] ("end" timing); the first sample repeats the second
    step = (rot[:-1].inv() * rot[1:]).as_rotvec() * rate_hz
    gyr = np.vstack([step[:1], step])
    acc = rot.inv().apply([0.0, 0.0, 1.0])
    return ImuSamples(t=t, gyr_rad_s=gyr, acc_g=acc, source="tumbling"), rot


def test_a_carried_magnet_is_fitted_as_hard_iron_and_removed():
    """On a trajectory that covers the sphere, the stage's sphere fit finds a carried magnet's
    offset, uses its samples with the offset removed, and takes out a drifting heading error."""
    imu, rot = tumbling()
    rng = np.random.default_rng(3)
    offset = np.array([20.0, -15.0, 8.0])
    mag = rot.inv().apply(FIELD_ENU_UT) + rng.normal(0.0, 0.5, (len(imu), 3))
    magnet = (imu.t > 80.0) & (imu.t < 160.0)
    mag[magnet] += offset
    imu = imu.replace(mag_ut=mag)
    drift = np.radians(0.3) * imu.t  # a 6-D solution whose heading drifts 0.3 deg/s
    six = quat.multiply(quat.from_rotvec(np.outer(drift, [0.0, 0.0, 1.0])), rot.as_quat(scalar_first=True))
    s = build("gn:mterm=stage").params.mag_settings()
    q, diag = heading_correction(imu, six, s)
    assert diag["mag_hard_iron_fits"], "no trusted fit"
    for fit in diag["mag_hard_iron_fits"]:
        np.testing.assert_allclose(fit[2:5], offset, atol=1.0)
    assert diag["mag_hard_iron"][magnet].mean() > 0.8 and not diag["mag_hard_iron"][~magnet].any()
    heading = angles(rot, q)["heading"]
    assert rms(heading) < 1.0, f"{rms(heading):.2f} deg RMS (6-D: {rms(np.degrees(drift)):.1f})"
    # without the fit those samples are gated out
    _, off = heading_correction(imu, six, dataclasses.replace(s, hard_iron=False))
    assert not off["mag_used"][magnet].any()


def test_the_rts_smoother_is_the_least_squares_solution():
    """The RTS recursion gives the minimiser of the quadratic cost of eq. (3) with its
    measurements: checked against the normal equations solved densely."""
    rng = np.random.default_rng(0)
    T = 60
    psi = rng.normal(0.0, 0.3, T)
    info = rng.uniform(0.0, 50.0, T) * (rng.uniform(size=T) > 0.3)
    walk = rng.uniform(1e-4, 1e-2, T - 1)
    init_var = 0.02
    H = np.diag(info.copy())
    H[0, 0] += 1.0 / init_var
    for t in range(T - 1):
        w = 1.0 / walk[t]
        H[t, t] += w
        H[t + 1, t + 1] += w
        H[t, t + 1] -= w
        H[t + 1, t] -= w
    np.testing.assert_allclose(heading_smoother(psi, info, walk, init_var), np.linalg.solve(H, info * psi), atol=1e-10)


@pytest.mark.parametrize("impl", ["compiled", "numpy"])
def test_without_a_magnetometer_the_smoother_is_6d_bit_for_bit(sim, impl):
    """No `mag_ut` (`--mag off`, the course board) gives exactly the smoother that never looks
    at one: a subclass with `magnetometer = False` given the samples with the field."""

    class SixD(GaussNewtonSmoother):
        magnetometer = False

    imu, rot = sim
    params = build(f"gn:impl={impl}").params
    plain = GaussNewtonSmoother(params).estimate(imu.replace(mag_ut=None), q0(rot))
    never = SixD(params).estimate(imu, q0(rot))
    np.testing.assert_array_equal(plain.quat_wxyz, never.quat_wxyz)
    assert "mag_used" not in plain.diagnostics


@pytest.mark.parametrize("term", TERMS)
@pytest.mark.parametrize("name", SMOOTHERS)
def test_compiled_equals_numpy_in_9d(sim, name, term):
    imu, rot = sim
    compiled = build(f"{name}:impl=compiled,mterm={term}").estimate(imu, q0(rot))
    numpy_ = build(f"{name}:impl=numpy,mterm={term}").estimate(imu, q0(rot))
    np.testing.assert_array_equal(compiled.diagnostics["mag_used"], numpy_.diagnostics["mag_used"])
    angle = np.linalg.norm(quat.relative_rotvec(numpy_.quat_wxyz, compiled.quat_wxyz), axis=1)
    assert np.max(angle) < 1e-6, f"largest difference {np.max(angle):.2e} rad"


@pytest.mark.parametrize("term", TERMS)
def test_invalid_magnetometer_samples_are_skipped(sim, term):
    imu, rot = sim
    mag = np.array(imu.mag_ut)
    mag[2000:2500] = np.nan
    valid = np.ones(len(imu), bool)
    valid[5000:5400] = False
    est = build(f"gn:mterm={term}").estimate(imu.replace(mag_ut=mag, mag_valid=valid), q0(rot))
    used = est.diagnostics["mag_used"]
    assert not used[2000:2500].any() and not used[5000:5400].any()
    assert used.mean() > 0.85
    assert np.all(np.isfinite(est.quat_wxyz))


@pytest.mark.parametrize("term", TERMS)
def test_the_inputs_are_untouched(sim, term):
    imu, rot = sim
    before = [np.array(a) for a in (imu.mag_ut, imu.gyr_rad_s, imu.acc_g, imu.t)]
    build(f"gn:mterm={term}").estimate(imu, q0(rot))
    for a, b in zip((imu.mag_ut, imu.gyr_rad_s, imu.acc_g, imu.t), before):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("bad", ["mterm=both", "Rm=0", "Qm=-1", "mnorm=-0.1", "mdip=inf", "mtime=-1", "mrate=0", "mhuber=0",
                                 "mloss=l1"])
def test_bad_magnetometer_parameters_raise(bad):
    with pytest.raises(ValueError, match="mag_|mloss|mterm"):
        build(f"gn:{bad}")


@pytest.mark.slow
@pytest.mark.parametrize("term, trial, bound_deg", [("cost", "28_disturbed_stationary_magnet_A.mat", 1.4),
                                                     ("cost", "36_disturbed_attached_magnet_5cm.hdf5", 1.9),
                                                     ("stage", "28_disturbed_stationary_magnet_A.mat", 2.6),
                                                     ("stage", "36_disturbed_attached_magnet_5cm.hdf5", 2.8)])
def test_broad_9d_total_error(data_dir, term, trial, bound_deg):
    """BROAD's protocol (movement phases, total error, no heading offset removed in 9-D) on a
    trial past a magnet fixed in the room (gn measured 1.06 deg with the term in the cost, 2.09
    with the stage; VQF's 9-D estimate scores 4.04) and on one with a magnet carried 5 cm from
    the sensor, fitted as hard iron (1.46 and 2.14; VQF 2.39). The stage keeps the 6-D
    inclination exactly; with the term in the cost the heading moves the velocity model's and
    the x/y biases' fit, and the inclination with them (measured on trial 36: 0.65 deg, 6-D
    0.55)."""
    path = data_dir / "broad" / trial
    if not path.is_file():
        pytest.fail(f"FUSION_DATA={data_dir} is set but {path} is missing")
    if path.suffix == ".hdf5":
        require_module("h5py")
    rec = datasets.load(str(path))
    start = datasets.initial_orientation(rec)
    est = build(f"gn:mterm={term}").estimate(rec.imu, start)
    six = build("gn").estimate(rec.imu.replace(mag_ut=None), start)
    nine_score = score(rec.truth, est, "broad", rec.movement, nine_d=True).rmse_deg
    six_score = score(rec.truth, six, "broad", rec.movement, nine_d=True).rmse_deg
    assert nine_score["total"] < bound_deg, f"{trial}: 9-D total RMSE {nine_score['total']:.2f} deg"
    assert nine_score["total"] < six_score["total"], (nine_score, six_score)
    assert nine_score["inclination"] == pytest.approx(six_score["inclination"], abs=1e-6 if term == "stage" else 0.15)
    if "attached" in trial:
        assert est.diagnostics["mag_hard_iron"].any() and est.diagnostics["mag_hard_iron_fits"]


# ----------------------------------------------------------------------------- the heading term in the cost
def _mag_problem(loss: str, T: int = 30, seed: int = 0):
    """A small random problem with the magnetometer's heading term: (problem, q, theta, v)."""
    from fusion.estimators.smoothers.cost import SmootherProblem, Weights

    rng = np.random.default_rng(seed)
    t = np.cumsum(0.005 + 0.01 * rng.random(T))
    q = quat.normalize(rng.normal(size=(T, 4)))
    imu = ImuSamples(t, rng.normal(size=(T, 3)), quat.gravity_in_body(q) + rng.normal(size=(T, 3)) * 0.05)
    weights = Weights(bias_axes="xy", scale_axes="x", velocity_acc_noise_g2_s=1e-4, velocity_bound_m2_s=0.25)
    problem = SmootherProblem.from_imu(imu, q[0], weights)
    q_ref = quat.normalize(q + rng.normal(size=(T, 4)) * 0.2)
    w_mag = rng.uniform(1e3, 1e5, T) * (np.arange(T) % 4 != 0)
    psi = rng.normal(size=T) * 0.3
    return (problem.with_magnetometer(w_mag, psi, q_ref, loss, 0.1), q, rng.normal(size=problem.n_theta) * 0.01,
            rng.normal(size=(T, 2)) * 0.1)


@pytest.mark.parametrize("loss", ["huber", "cauchy", "none"])
def test_the_heading_terms_gradient_and_jacobian_are_exact(loss):
    """The magnetometer term's part of the gradient against central differences of its part of
    the cost, and its Gauss-Newton block against the residual's differences (J^T W J)."""
    problem, q, theta, v = _mag_problem(loss)
    without = dataclasses.replace(problem, w_mag=np.zeros(0))
    lin, lin0 = problem.linearize(q, theta, v=v), without.linearize(q, theta, v=v)
    grad = lin.grad_q[:, :3] - lin0.grad_q[:, :3]
    block = lin.diag[:, :3, :3] - lin0.diag[:, :3, :3]
    r, _ = problem.mag_residual(q)
    _, wh = problem.mag_terms(r)
    h = 1e-6
    num = np.zeros((len(q), 3))
    jac = np.zeros((len(q), 3))
    mag_cost = lambda qq: problem.cost(qq, theta, v) - without.cost(qq, theta, v)  # noqa: E731
    for j in range(3):
        d = np.zeros((len(q), 3))
        d[:, j] = h
        plus, minus = quat.retract(q, d), quat.retract(q, -d)
        jac[:, j] = (problem.mag_residual(plus)[0] - problem.mag_residual(minus)[0]) / (2 * h)
        for i in range(len(q)):  # one sample at a time: the cost's part from sample i
            di = np.zeros((len(q), 3))
            di[i, j] = h
            num[i, j] = (mag_cost(quat.retract(q, di)) - mag_cost(quat.retract(q, -di))) / (2 * h)
    np.testing.assert_allclose(grad, num, rtol=0, atol=1e-5 * np.max(np.abs(num)))
    np.testing.assert_allclose(block, wh[:, None, None] * jac[:, :, None] * jac[:, None, :], rtol=0,
                               atol=1e-6 * np.max(np.abs(block)))
    assert np.any(wh > 0) and np.max(np.abs(grad)) > 0


def test_the_heading_term_sees_the_heading_only():
    """Tilting q about a horizontal world axis leaves the residual as it is; turning it by phi
    about the world vertical from q_ref adds phi."""
    problem, q, _, _ = _mag_problem("huber")
    q_ref = problem.mag_ref
    T = len(q_ref)
    tilt = quat.from_rotvec(np.stack([np.full(T, 0.3), np.full(T, -0.2), np.zeros(T)], axis=1))
    r, _ = problem.mag_residual(quat.multiply(tilt, q_ref))
    np.testing.assert_allclose(r, problem.mag_psi, atol=1e-12)
    turn = quat.from_rotvec(np.stack([np.zeros(T), np.zeros(T), np.full(T, 0.25)], axis=1))
    r, _ = problem.mag_residual(quat.multiply(turn, q_ref))
    np.testing.assert_allclose(r, problem.mag_psi + 0.25, atol=1e-12)


@pytest.mark.parametrize("name", SMOOTHERS)
def test_the_heading_term_in_the_cost_holds_heading_where_6d_drifts(sim, six_d, name):
    imu, rot = sim
    nine = build(f"{name}:mterm=cost").estimate(imu, q0(rot))
    drift, held = angles(rot, six_d[name].quat_wxyz), angles(rot, nine.quat_wxyz)
    # measured (gn): 6-D 24.3 deg RMS, 9-D 3.8 (the heading-error walk is the gyro noise's,
    # 0.01 rad/sqrt(s): a 30 s time constant against the simulator's unmodelled z scale error)
    assert rms(held["heading"]) < 5.0, f"9-D heading error {rms(held['heading']):.2f} deg RMS"
    assert nine.diagnostics["mag_used"].mean() > 0.9
    # the term pulls on heading only: the inclination stays within 0.1 deg RMS of the 6-D one
    assert rms(held["inclination"]) < rms(drift["inclination"]) + 0.1


def test_bad_magnetometer_term_inputs_raise():
    problem, q, _, _ = _mag_problem("huber")
    with pytest.raises(ValueError, match="magnetometer term"):
        problem.with_magnetometer(np.ones(3), np.zeros(3), q[:3], "huber", 0.1)
    with pytest.raises(ValueError, match="loss"):
        problem.with_magnetometer(problem.w_mag, problem.mag_psi, problem.mag_ref, "l1", 0.1)


def test_inclination_step_sees_turns_about_horizontal_axes_only():
    """`inclination_step`: a turn about the body's vertical changes the heading only (0); a turn
    about a horizontal axis changes the inclination by its angle; the largest over the samples."""
    from fusion.estimators.smoothers.smoother import inclination_step

    rot = Rotation.from_euler("xyz", [[10, -20, 30], [0, 0, 0], [-40, 5, 170]], degrees=True)
    q = rot.as_quat(scalar_first=True)
    up_body = quat.gravity_in_body(q)  # the vertical in each body frame
    horizontal = np.cross(up_body, [1.0, 0.0, 0.0])
    horizontal /= np.linalg.norm(horizontal, axis=1, keepdims=True)
    assert inclination_step(q, 0.3 * up_body) == pytest.approx(0.0, abs=1e-12)
    steps = 0.3 * up_body + np.array([0.01, 0.02, 0.005])[:, None] * horizontal
    assert inclination_step(q, steps) == pytest.approx(0.02, rel=1e-9)


@pytest.mark.parametrize("name", SMOOTHERS)
def test_the_presolve_stops_at_the_inclination_and_the_9d_solution_stays(sim, name, monkeypatch):
    """In 9-D the 6-D solve the magnetometer is measured at stops once its inclination has settled
    (`presolve_tol_rad`): fewer iterations than solving it to `tol` (ptol=0), and the 9-D solution
    the same inclination (within 0.01 deg RMS; measured at most 0.0007) and nearly the same heading
    (within 0.25 deg RMS; measured 0.17, 4.00 against 3.83 deg: the heading term measures the
    heading against the 6-D solution's (`SmootherProblem.mag_residual`), exactly only for a pure
    turn about the vertical, so the 9-D minimum moves a little with that reference)."""
    imu, rot = sim
    calls = []
    cls = type(build(name))

    def counting(self, problem, q, presolve=False):
        q, diagnostics = solve(self, problem, q, presolve=presolve)
        calls.append((presolve, diagnostics["iterations"]))
        return q, diagnostics

    solve = cls.solve
    monkeypatch.setattr(cls, "solve", counting)
    fast = build(name + ":progress=false").estimate(imu, q0(rot))
    fast_calls, calls[:] = list(calls), []
    full = build(name + ":progress=false,ptol=0").estimate(imu, q0(rot))
    full_calls = list(calls)
    assert [c[0] for c in fast_calls] == [True, False] and [c[0] for c in full_calls] == [False, False]
    assert fast_calls[0][1] < full_calls[0][1]
    a, b = angles(rot, fast.quat_wxyz), angles(rot, full.quat_wxyz)
    assert abs(rms(a["inclination"]) - rms(b["inclination"])) < 0.01
    assert abs(rms(a["heading"]) - rms(b["heading"])) < 0.25
    assert fast.diagnostics["mag_used"].any()
