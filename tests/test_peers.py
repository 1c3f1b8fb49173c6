"""The peer adapters (VQF, ahrs, imufusion): conventions, seeding, invalid gyro samples.

Each peer runs on recordings simulated from a known sequence of body rates (exact
samples, jittered time stamps): the board upside down, a pure yaw, and a sequence of
quarter turns about each axis. A wrong quaternion order, frame (NED/ENU), unit
(deg/s vs rad/s) or rotation direction gives errors of tens of degrees; the adapters
must stay within a degree (the ahrs and Fusion filters integrate to first order, hence
not 1e-6). Skipped per peer when its library is not installed (`pip install -e '.[peers]'`;
a failure under CI, `optional_helpers.require_module`).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import estimators
from fusion.estimators import build
from fusion.estimators.peers.vqf_fusion import PeerUnavailable, align_heading
from fusion.evaluation.scoring.metrics import error_angles
from fusion import quaternion as quat
from fusion.types import ImuSamples, Trajectory

from optional_helpers import require_module

LIBRARY = {
    "vqf": "vqf",
    "vqf-basic": "vqf",
    "vqf-offline": "vqf",
    "madgwick": "ahrs",
    "mahony": "ahrs",
    "ahrs-ekf": "ahrs",
    "fusion-ahrs": "imufusion",
}
PEERS = list(LIBRARY)
D = np.radians


def simulate(segments, init_wxyz, rate_hz=100.0, jitter_s=0.001, seed=0, timing="start"):
    """Exact IMU samples for piecewise-constant body rates.

    segments: [(duration s, body rate rad/s (3,)), ...]; init_wxyz: (4,) R_world_body.
    Returns (ImuSamples, truth Trajectory): the rate over [t_k, t_k+1] is gyro sample k
    (`timing` "start") or k + 1 ("end"), and the samples say so (`gyr_timing`); the
    accelerometer reads R_k^T e_z (g, no linear acceleration).
    """
    rng = np.random.default_rng(seed)
    rates = np.concatenate([np.tile(np.asarray(w, float), (int(round(d * rate_hz)), 1)) for d, w in segments])
    dt = 1.0 / rate_hz + rng.uniform(-jitter_s, jitter_s, len(rates))
    t = 1000.0 + np.concatenate([[0.0], np.cumsum(dt)])
    truth = quat.cumulative_product(np.vstack([init_wxyz, quat.from_rotvec(rates * dt[:, None])]))
    gyr = np.vstack([rates, rates[-1]]) if timing == "start" else np.vstack([rates[0], rates])
    return ImuSamples(t, gyr, quat.gravity_in_body(truth), gyr_timing=timing), Trajectory(t, truth)


def euler(seq, deg):
    return Rotation.from_euler(seq, deg, degrees=True).as_quat(scalar_first=True)


SCENARIOS = {
    # The board upside down (180 deg about x), yawed, then tilting and turning.
    "upside_down": (euler("xz", [180, 30]), [(1.0, [0, 0, 0]), (2.0, D([20, -10, 30])), (1.0, D([0, 0, -90])),
                                             (2.0, D([-45, 0, 0]))]),
    # A pure yaw of 240 deg about the vertical: only the gyro sees it.
    "pure_yaw": (euler("z", 10), [(1.0, [0, 0, 0]), (4.0, D([0, 0, 60]))]),
    # Quarter turns about body x, then y, then z, then a mixed rate.
    "quarter_turns": (euler("z", -20), [(1.0, [0, 0, 0]), (1.0, D([90, 0, 0])), (1.0, D([0, 90, 0])),
                                        (1.0, D([0, 0, 90])), (2.0, D([30, -60, 20]))]),
}


def errors_deg(truth: Trajectory, est: Trajectory) -> dict[str, np.ndarray]:
    return {k: np.degrees(v) for k, v in error_angles(truth.rotation(), est.rotation()).items()}


def need(peer: str) -> None:
    require_module(LIBRARY[peer])


def test_every_peer_is_registered():
    assert set(PEERS) <= set(estimators.ESTIMATORS)


@pytest.mark.parametrize("scenario", list(SCENARIOS))
@pytest.mark.parametrize("peer", PEERS)
def test_known_rotation_sequence(peer, scenario):
    need(peer)
    init, segments = SCENARIOS[scenario]
    imu, truth = simulate(segments, init)
    est = build(peer).estimate(imu, truth.quat_wxyz[0])
    assert est.quat_wxyz.shape == (len(imu), 4)
    np.testing.assert_allclose(np.linalg.norm(est.quat_wxyz, axis=1), 1.0, atol=1e-5)
    err = errors_deg(truth, est)
    assert err["total"].max() < 1.5, f"{peer} on {scenario}: max error {err['total'].max():.2f} deg"
    if estimators.ESTIMATORS[peer].causal:  # starts exactly at the seed
        assert err["total"][0] < 0.01
    if scenario == "pure_yaw":  # the heading follows the gyro, the inclination never moves
        assert err["inclination"].max() < 0.05


@pytest.mark.parametrize("peer", PEERS)
def test_accelerometer_pulls_a_wrong_seed_upright(peer):
    """Seeded 10 deg off in inclination, the board upside down and slowly turning: the
    accelerometer correction must bring the inclination back (a wrong gravity direction
    or frame would push it away, towards 180 deg)."""
    need(peer)
    init = euler("xz", [180, 30])
    imu, truth = simulate([(15.0, D([0, 0, 5]))], init)
    seed = (Rotation.from_euler("y", 10, degrees=True) * truth.rotation()[0]).as_quat(scalar_first=True)
    err = errors_deg(truth, build(peer).estimate(imu, seed))
    assert err["inclination"][-1] < 1.0
    assert err["inclination"].max() < 10.5


@pytest.mark.parametrize("peer", PEERS)
def test_invalid_gyro_samples_are_not_integrated(peer):
    """A burst of garbage rates marked invalid while the board is still changes nothing."""
    need(peer)
    imu, truth = simulate([(3.0, [0, 0, 0]), (1.0, D([0, 0, 45]))], euler("xz", [20, 40]))
    gyr = np.array(imu.gyr_rad_s)
    valid = np.ones(len(imu), bool)
    gyr[100:200] = [3.0, -2.0, 5.0]
    valid[100:200] = False
    bad = imu.replace(gyr_rad_s=gyr, gyr_valid=valid)
    err = errors_deg(truth, build(peer).estimate(bad, truth.quat_wxyz[0]))
    assert err["total"].max() < 1.0


@pytest.mark.parametrize("peer", PEERS)
def test_inputs_are_not_modified(peer):
    need(peer)
    imu, truth = simulate(*SCENARIOS["quarter_turns"][::-1])
    before = (imu.gyr_rad_s.copy(), imu.acc_g.copy())
    init = truth.quat_wxyz[0].copy()
    build(peer).estimate(imu, init)
    np.testing.assert_array_equal(imu.gyr_rad_s, before[0])
    np.testing.assert_array_equal(imu.acc_g, before[1])
    np.testing.assert_array_equal(init, truth.quat_wxyz[0])


@pytest.mark.parametrize("peer", PEERS)
def test_declared_gyro_timing_is_honoured(peer):
    """A recording in the libraries' own convention ("end": gyro k, then accelerometer k) is
    tracked; the same samples declared "start" (a one-sample shift of the gyro, 2-4 deg at
    these rates) are measurably worse. Fast turns, so that one sample is 3.6 deg."""
    need(peer)
    imu, truth = simulate([(1.0, [0, 0, 0]), (1.0, D([0, 0, 360])), (1.0, D([200, 0, 0])), (1.0, [0, 0, 0])],
                          euler("xz", [20, 40]), timing="end")
    moving = slice(100, 300)
    right = errors_deg(truth, build(peer).estimate(imu, truth.quat_wxyz[0]))["total"][moving]
    shifted = errors_deg(truth, build(peer).estimate(imu.replace(gyr_timing="start"), truth.quat_wxyz[0]))["total"][moving]
    assert np.median(shifted) > np.median(right) + 1.0, f"{peer}: {np.median(right):.2f} vs shifted {np.median(shifted):.2f} deg"
    if peer in ("vqf", "vqf-basic"):  # exact integration of exact rates
        assert right.max() < 1e-6


def test_parameters_use_the_library_names_as_aliases():
    for lib in ("vqf", "ahrs", "imufusion"):
        require_module(lib)
    assert build("vqf:tauAcc=1.5").params.tau_acc_s == 1.5
    assert build("vqf-offline:restBiasEstEnabled=false").params.rest_bias_est is False
    assert build("madgwick:beta=0.1").params.gain == 0.1
    assert build("mahony:kp=2,ki=0").params.k_p == 2.0
    assert build("ahrs-ekf:P0=1e-4").params.init_cov == 1e-4
    assert build("fusion-ahrs:gain=0.2,startup=true").params.startup is True
    assert build("vqf:tauMag=5").params.tau_mag_s == 5.0
    assert build("vqf-basic:tauMag=5").params.library_kwargs() == {"tauAcc": 3.0, "tauMag": 5.0}
    assert build("vqf:magDistRejectionEnabled=false").params.library_kwargs()["magDistRejectionEnabled"] is False
    assert build("fusion-ahrs:magnetic_rejection=10").params.magnetic_rejection_deg == 10.0
    assert build("ahrs-ekf:var_mag=0.1").params.mag_var == 0.1
    assert build("madgwick:impl=library").params.impl == "library"
    with pytest.raises(ValueError, match="tau_acc_s must be positive"):
        build("vqf:tauAcc=-1")
    with pytest.raises(ValueError, match="unknown parameter"):
        build("madgwick:gain_imu=0.1")


def test_parameters_reach_the_library():
    """A different gain gives a different estimate (the parameter is not silently dropped)."""
    require_module("ahrs")
    imu, truth = simulate([(5.0, D([10, 0, 5]))], euler("x", 30))
    seed = euler("x", 40)
    a = build("madgwick").estimate(imu, seed)
    b = build("madgwick:beta=0.5").estimate(imu, seed)
    after_1s = slice(100, 101)
    assert errors_deg(truth, b)["inclination"][after_1s] < errors_deg(truth, a)["inclination"][after_1s] - 1.0


def refusing_the_peer_libraries(real_import_module):
    """An `importlib.import_module` that finds none of the peers' libraries and every other module
    (`peers.importlib` is the `importlib` module itself: SciPy, imported while a test runs, calls it
    too)."""
    def refuse(name, *args, **kwargs):
        if name.partition(".")[0] in set(LIBRARY.values()):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return real_import_module(name, *args, **kwargs)

    return refuse


def test_missing_library_says_what_to_install(monkeypatch):
    import fusion.estimators.peers.vqf_fusion as peers

    monkeypatch.setattr(peers.importlib, "import_module", refusing_the_peer_libraries(peers.importlib.import_module))
    for peer in PEERS:
        with pytest.raises(PeerUnavailable, match=r"pip install -e '\.\[peers\]'"):
            build(peer)


def test_align_heading_turns_about_the_vertical_only():
    rng = np.random.default_rng(1)
    q = Rotation.from_rotvec(rng.normal(size=(50, 3))).as_quat(scalar_first=True)
    ref = (Rotation.from_euler("z", 70, degrees=True) * Rotation.from_quat(q[0], scalar_first=True)).as_quat(scalar_first=True)
    out = align_heading(q, ref)
    np.testing.assert_allclose(quat.canonical(out[0]), quat.canonical(ref), atol=1e-12)
    rel = Rotation.from_quat(out, scalar_first=True) * Rotation.from_quat(q, scalar_first=True).inv()
    np.testing.assert_allclose(np.degrees(rel.as_rotvec()), np.tile([0, 0, 70.0], (50, 1)), atol=1e-9)


def test_ahrs_ekf_enu_frame_would_be_upside_down():
    """Why the adapter keeps ahrs's default frame "NED": with "ENU" the EKF expects the
    accelerometer to read -1 g when level, so fed real specific force it turns over."""
    ahrs = require_module("ahrs.filters")
    imu, truth = simulate([(8.0, D([20, -10, 30]))], euler("x", 20))
    q = euler("yx", [5, 20])
    ekf = ahrs.EKF(frame="ENU", magnetic_ref=0.0)
    for k in range(len(imu) - 1):
        q = ekf.update(q, imu.gyr_rad_s[k], imu.acc_g[k + 1] * 9.81, dt=imu.dt[k])
    final = Rotation.from_quat(truth.quat_wxyz[-1], scalar_first=True).inv() * Rotation.from_quat(q, scalar_first=True)
    assert np.degrees(final.magnitude()) > 170.0


# Reference figures measured with the libraries themselves, given to 0.1 deg with a target of 0.3 deg
# (mean over ece276a 1-9, --init truth, defaults, 330 mV/g and the datasheet gyro scale, no dropout
# handling). Measured through the adapters: vqf 6.67, vqf-offline 3.24, madgwick 6.13, mahony 3.25,
# fusion-ahrs 4.53. The tolerance stays at that 0.3 because vqf-offline is 0.26 below its figure (the
# others are within 0.07).
REFERENCE_INCLINATION_RMSE_DEG = {  # mean over ece276a 1-9, --init truth, defaults
    "vqf": 6.7,
    "vqf-offline": 3.5,
    "madgwick": 6.2,
    "mahony": 3.3,
    "fusion-ahrs": 4.6,
}


@pytest.mark.slow
def test_reference_figures_on_the_course_recordings(data_dir):
    """The adapters reproduce the reference figures within 0.3 deg (330 mV/g, datasheet gyro scale)."""
    for lib in ("vqf", "ahrs", "imufusion"):
        require_module(lib)
    from fusion.evaluation.scoring.metrics import score
    from fusion import datasets
    from fusion.calibration import BoardModel

    board = BoardModel(acc_sensitivity_mv_per_g=330.0, gyro_sensitivity_mv_per_deg_s=3.33, gyro_scale_factor=(1.0, 1.0, 1.0))
    rmse: dict[str, list[float]] = {name: [] for name in REFERENCE_INCLINATION_RMSE_DEG}
    for i in range(1, 10):
        rec = datasets.load(f"ece276a/{i}", data_dir / "ece276a", board=board, dropouts=False)  # as the reference was measured
        q0 = datasets.initial_orientation(rec, "truth")
        for name in rmse:
            rmse[name].append(score(rec.truth, build(name).estimate(rec.imu, q0)).rmse_deg["inclination"])
    means = {name: float(np.mean(v)) for name, v in rmse.items()}
    for name, ref in REFERENCE_INCLINATION_RMSE_DEG.items():
        assert abs(means[name] - ref) <= 0.3, f"{name}: {means[name]:.2f} deg vs reference {ref}"


def test_cli_names_the_missing_extra(monkeypatch, capsys):
    import fusion.estimators.peers.vqf_fusion as peers
    from fusion.cli import main

    monkeypatch.setattr(peers.importlib, "import_module", refusing_the_peer_libraries(peers.importlib.import_module))
    assert main(["compare", "--estimators", "fusion-ahrs", "--dataset", "sim", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fusion: error: estimator 'fusion-ahrs' needs the optional package 'imufusion', which is not "
                   "installed: pip install -e '.[peers]' (or pip install imufusion)"]


# --- 9-D: the magnetometer through each library's API ------------------------------------------

FIELD_ENU_UT = np.array([0.0, 19.0, -45.0])  # north along y, dipping down (67 deg, Berlin-like), uT


def with_field(imu: ImuSamples, truth: Trajectory) -> ImuSamples:
    """The samples with the body-frame reading of an ENU field along the truth."""
    return imu.replace(mag_ut=truth.rotation().inv().apply(FIELD_ENU_UT))


@pytest.mark.parametrize("peer", PEERS)
def test_9d_heading_converges_to_magnetic_north_in_enu(peer):
    """Seeded 30 deg off in heading, every 9-D peer turns to the truth's heading: its world is
    ENU (x east, y north), the frame of BROAD's truth (a library in NWU, left unturned, would end
    90 deg off; one ignoring the magnetometer, 30)."""
    need(peer)
    imu, truth = simulate([(2.0, [0, 0, 0]), (8.0, D([10, -5, 20])), (20.0, [0, 0, 0])], euler("xz", [10, 40]))
    # a real gyro is never exactly zero (Madgwick and Mahony skip every correction on a zero rate)
    noise = np.random.default_rng(1).normal(0.0, 1e-4, imu.gyr_rad_s.shape)
    imu = with_field(imu.replace(gyr_rad_s=imu.gyr_rad_s + noise), truth)
    seed = quat.multiply(euler("z", 30), truth.quat_wxyz[0])
    est = build(peer).estimate(imu, seed)
    assert type(build(peer)).magnetometer
    heading = errors_deg(truth, est)["heading"]
    if not peer.startswith("vqf"):  # VQF's three start as published in 9-D (identity): see `_SeededVQF`
        assert heading[0] == pytest.approx(30.0, abs=1e-6)
    assert np.max(heading[-200:]) < 3.0, f"{peer}: ends {np.max(heading[-200:]):.1f} deg from north"


@pytest.mark.parametrize("peer", PEERS)
def test_without_a_magnetometer_the_peers_are_6d_as_before(peer):
    """`--mag off` (no `mag_ut`) gives the 6-D estimate, bit for bit whatever the field would say."""
    need(peer)
    imu, truth = simulate(SCENARIOS["quarter_turns"][1], SCENARIOS["quarter_turns"][0])
    plain = build(peer).estimate(imu, truth.quat_wxyz[0])
    again = build(peer).estimate(with_field(imu, truth).replace(mag_ut=None), truth.quat_wxyz[0])
    np.testing.assert_array_equal(plain.quat_wxyz, again.quat_wxyz)


@pytest.mark.parametrize("impl", ["compiled", "library"])
@pytest.mark.parametrize("peer", ["madgwick", "mahony", "ahrs-ekf"])
def test_9d_missing_magnetometer_samples_integrate_over_the_real_interval(peer, impl):
    """At 200 Hz, 2 s of turning with the magnetometer missing (NaN) are tracked: for such a sample
    the adapters call the library's `updateIMU` with the real dt (its `updateMARG` falls back to
    `updateIMU` without passing dt on, which would integrate over its default 0.01 s: twice the
    rotation here, 60 deg off by the end of the gap)."""
    need(peer)
    imu, truth = simulate([(2.0, [0, 0, 0]), (4.0, D([0, 0, 30])), (2.0, [0, 0, 0])], euler("xz", [10, 40]),
                          rate_hz=200.0, jitter_s=0.0002)
    noise = np.random.default_rng(2).normal(0.0, 1e-4, imu.gyr_rad_s.shape)  # never exactly zero (see above)
    imu = with_field(imu.replace(gyr_rad_s=imu.gyr_rad_s + noise), truth)
    mag = np.array(imu.mag_ut)
    gap = slice(800, 1200)  # 4-6 s: turning
    mag[gap] = np.nan
    imu = imu.replace(mag_ut=mag)
    assert imu.has_mag and not imu.mag_valid[gap].any()
    err = errors_deg(truth, build(f"{peer}:impl={impl}").estimate(imu, truth.quat_wxyz[0]))["total"]
    assert err.max() < 1.5, f"{peer} ({impl}): {err.max():.1f} deg off, worst at sample {err.argmax()}"


# --- search spaces (`fusion.estimators.search`): declared beside each peer's parameters ----------

# BROAD's best common settings over all 39 trials (9-D), from its example code's grid search
# (Laidig et al., "BROAD - A Benchmark for Robust Inertial Orientation Estimation", Data 2021).
BROAD_BEST = {"madgwick": {"gain": 0.12}, "mahony": {"k_p": 0.74, "k_i": 0.0012}}
TUNED = {
    "madgwick": {"gain"}, "mahony": {"k_p", "k_i"},
    "vqf": {"tau_acc_s", "tau_mag_s"}, "vqf-basic": {"tau_acc_s", "tau_mag_s"},
    "vqf-offline": {"tau_acc_s", "tau_mag_s"},
    "fusion-ahrs": {"gain", "acceleration_rejection_deg", "magnetic_rejection_deg", "rejection_timeout"},
    "ahrs-ekf": {"gyr_var_rad2_s2", "acc_var", "mag_var"},
}

MAGNETOMETER_ONLY = {"tau_mag_s", "magnetic_rejection_deg", "mag_var"}  # not tuned in 6-D


@pytest.mark.parametrize("peer", PEERS)
def test_each_peer_declares_its_search_space(peer):
    """The tuned parameters, each with a small grid that holds the library's default (Fusion's
    recovery period aside: it only matters with a threshold on, and its grid's settings with both
    thresholds off are the default's) and BROAD's published best where there is one; at most 25
    settings per estimator, and every grid value is a valid parameter."""
    from dataclasses import replace
    from math import prod

    from fusion.estimators.search import default_of, search_space

    params = estimators.ESTIMATORS[peer].Params
    space = search_space(params)
    assert set(space) == TUNED[peer]
    for name, tunable in space.items():
        if name != "rejection_timeout":
            assert default_of(params, name) in tunable.grid, f"{peer}.{name}: default not in the grid"
        for value in tunable.grid:
            replace(params(), **{name: value})  # each value is accepted (`__post_init__`)
        assert 2 <= len(tunable.grid) <= 7 or name == "rejection_timeout"
    for name, value in BROAD_BEST.get(peer, {}).items():
        assert value in space[name].grid, f"{peer}.{name}: BROAD's {value} not in the grid"
    assert {name for name, t in space.items() if t.magnetometer} == TUNED[peer] & MAGNETOMETER_ONLY
    assert prod(len(t.grid) for t in space.values()) <= 25  # 9-D
    assert prod(len(t.grid) for t in space.values() if not t.magnetometer) <= 25  # 6-D


def test_the_new_parameters_reach_the_libraries():
    """tauMag (VQF, BasicVQF), Fusion's magnetic rejection and the EKF's var_mag change a 9-D
    estimate with a disturbed field; their default values leave it as it was."""
    for lib in ("vqf", "ahrs", "imufusion"):
        require_module(lib)
    imu, truth = simulate([(2.0, [0, 0, 0]), (8.0, D([10, -5, 20])), (10.0, [0, 0, 0])], euler("xz", [10, 40]))
    noise = np.random.default_rng(3).normal(0.0, 1e-4, imu.gyr_rad_s.shape)
    imu = with_field(imu.replace(gyr_rad_s=imu.gyr_rad_s + noise), truth)
    mag = np.array(imu.mag_ut)
    mag[600:900] += [30.0, -20.0, 10.0]  # a magnet nearby for 3 s
    imu = imu.replace(mag_ut=mag)
    seed = truth.quat_wxyz[0]
    fusion = "fusion-ahrs:rejection_timeout=500"
    for base, changed in [("vqf", "vqf:tauMag=2"), ("vqf-basic", "vqf-basic:tauMag=2"),
                          (fusion, fusion + ",magnetic_rejection=10"), ("ahrs-ekf", "ahrs-ekf:var_mag=0.05")]:
        a, b = build(base).estimate(imu, seed).quat_wxyz, build(changed).estimate(imu, seed).quat_wxyz
        assert np.max(np.abs(a - b)) > 1e-3, f"{changed} changes nothing"
    assert build("vqf:tauMag=9,magDistRejectionEnabled=true").params == build("vqf").params
    assert build("fusion-ahrs:magnetic_rejection=0").params == build("fusion-ahrs").params


def test_vqf_flags_are_the_librarys_rest_and_disturbance_detection():
    """VQF's per-sample flags (`VQF_FLAGS`) are its batch outputs, bit for bit in 9-D (started as
    the library starts); in 6-D (seeded) rest is detected in the final rest and never while turning."""
    need("vqf")
    import vqf

    from fusion.estimators.peers.vqf_fusion import _acc_m_s2, _mag_or_zero, _rate_for_constant_ts

    imu, truth = simulate([(3.0, [0, 0, 0]), (5.0, D([30, -10, 40])), (6.0, [0, 0, 0])], euler("xz", [5, 20]))
    noise = np.random.default_rng(3).normal(0.0, 2e-4, imu.gyr_rad_s.shape)
    imu = with_field(imu.replace(gyr_rad_s=imu.gyr_rad_s + noise), truth)
    est = build("vqf").estimate(imu, truth.quat_wxyz[0])
    gyr, ts = _rate_for_constant_ts(imu)
    lib = vqf.VQF(ts).updateBatch(gyr, np.ascontiguousarray(_acc_m_s2(imu.acc_g)), _mag_or_zero(imu))
    for ours, theirs in (("rest_detected", "restDetected"), ("mag_disturbance_detected", "magDistDetected")):
        assert est.diagnostics[ours].dtype == bool and est.diagnostics[ours].shape == (len(imu),)
        np.testing.assert_array_equal(est.diagnostics[ours], lib[theirs])
    six = build("vqf").estimate(imu.replace(mag_ut=None), truth.quat_wxyz[0]).diagnostics
    assert "mag_disturbance_detected" not in six
    rest, t = six["rest_detected"], imu.t - imu.t[0]
    assert not rest[0] and rest[t > 12.0].all() and not rest[(t > 3.5) & (t < 8.0)].any()


@pytest.mark.parametrize("nine_d", [False, True], ids=["6-D", "9-D"])
def test_fusion_flags_are_the_librarys_after_each_update(nine_d):
    """Fusion's flags (`FUSION_FLAGS`) are the library's after each update: the batch loop gives
    the same estimate and flags as the library stepped by hand; a linear acceleration beyond the
    rejection threshold is ignored while it lasts (and not before)."""
    need("fusion-ahrs")
    from fusion.estimators.peers.vqf_fusion import FUSION_FLAGS, _acc_m_s2
    from fusion.types import STANDARD_GRAVITY_M_S2

    imu, truth = simulate([(2.0, [0, 0, 0]), (4.0, D([20, 0, 10])), (2.0, [0, 0, 0])], euler("x", [5]))
    acc = imu.acc_g.copy()
    acc[300:340] += [0.6, 0.0, 0.0]  # a push of 0.6 g: the accelerometer points 30 deg off
    imu = imu.replace(acc_g=acc)
    if nine_d:
        imu = with_field(imu, truth)
    spec = "fusion-ahrs:acceleration_rejection=10,magnetic_rejection=10,rejection_timeout=500"
    est = build(spec).estimate(imu, truth.quat_wxyz[0])
    names = [name for name, magnetic in FUSION_FLAGS.values() if nine_d or not magnetic]
    assert sorted(k for k, v in est.diagnostics.items() if v.dtype == bool) == sorted(names)
    # the library stepped by hand (the adapter's settings, the same inputs)
    ref = build(spec)
    ref.reset_for(imu, truth.quat_wxyz[0], convention="ENU" if nine_d else "NWU")
    ahrs = ref._ahrs
    (rates, valid), dt = imu.interval_rates(), imu.dt
    quats, rows = [], []
    for k in range(len(imu) - 1):
        ahrs.set_sample_period(dt[k])
        a = _acc_m_s2(imu.acc_g[k + 1]) / STANDARD_GRAVITY_M_S2
        if nine_d:
            ahrs.update(np.degrees(rates[k]), a, imu.mag_ut[k + 1])
        else:
            ahrs.update_no_magnetometer(np.degrees(rates[k]), a)
        quats.append(ahrs.get_quaternion())
        f, st = ahrs.get_flags(), ahrs.get_internal_states()
        everything = {**{k2: getattr(f, k2) for k2 in dir(f) if not k2.startswith("_")},
                      **{k2: getattr(st, k2) for k2 in dir(st) if not k2.startswith("_")}}
        rows.append([everything[lib] for lib, (name, magnetic) in FUSION_FLAGS.items() if nine_d or not magnetic])
    np.testing.assert_array_equal(est.quat_wxyz[1:], quats)
    for j, name in enumerate(names):
        flag = est.diagnostics[name]
        assert not flag[0]
        np.testing.assert_array_equal(flag[1:], [row[j] for row in rows], err_msg=name)
    ignored = est.diagnostics["accelerometer_ignored"]
    assert ignored[301:340].all() and not ignored[:300].any()
