"""`ekf` and `ukf-bias` in 9-D: the magnetometer's heading-only update, its disturbance gates and
hard-iron fit, and 6-D unchanged.

Simulated cases use the built-in `sim` recording with the body-frame reading of an ENU field
(north along y, dipping down) along its truth, plus noise; real-data cases use the `data_dir`
fixture (skipped without FUSION_DATA, failing when it is set but the files are missing).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion import quaternion as quat
from fusion.estimators import build
from fusion.estimators.filters.ekf import EKF
from fusion.estimators.filters.ukf import UKF, UKFBias
from fusion.evaluation.scoring.metrics import error_angles, score
from fusion.types import Trajectory

from mag_helpers import q0, sim_with_magnetometer, with_field_bent, with_magnet_carried, with_magnet_passed
from optional_helpers import require_module


@pytest.fixture(scope="module")
def sim():
    """The simulated recording (180 s, 100 Hz) with a 0.2 deg/s z gyro bias added after its
    calibration, the true rotation at each sample, and a noisy (1 uT) magnetometer."""
    return sim_with_magnetometer()


def heading_deg(rot: Rotation, trajectory: Trajectory) -> np.ndarray:
    return np.degrees(error_angles(rot, Rotation.from_quat(trajectory.quat_wxyz, scalar_first=True))["heading"])


def inclination_deg(rot: Rotation, trajectory: Trajectory) -> np.ndarray:
    return np.degrees(error_angles(rot, Rotation.from_quat(trajectory.quat_wxyz, scalar_first=True))["inclination"])


# each 9-D filter with its compiled kernel and its reference step
# The behaviour tests run the compiled filters (the defaults) on the whole 180 s: their numpy
# references are held equal to them in 9-D, gates, carried magnet and hard-iron fit included, by
# tests/test_compiled.py (test_compiled_equals_reference_in_9d), on 4,000 samples at 1e-10.
FILTERS = ["ekf", "ukf-bias"]
REFERENCES = ["ekf:impl=numpy", "ukf-bias:impl=numpy"]


def with_params(spec: str, params: str) -> str:
    return spec + ("," if ":" in spec else ":") + params


def test_the_9d_filters():
    assert EKF.magnetometer and UKFBias.magnetometer and not UKF.magnetometer


@pytest.mark.parametrize("spec", FILTERS)
def test_heading_stays_right_where_6d_drifts(sim, spec):
    imu, rot = sim
    six = build(spec).estimate(imu.replace(mag_ut=None), q0(rot))
    nine = build(spec).estimate(imu, q0(rot))
    drift, held = heading_deg(rot, six), heading_deg(rot, nine)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rms(drift) > 20.0, "the test needs a drifting 6-D heading"
    # measured (ekf; ukf-bias alike): 6-D 25.5 deg RMS, 9-D 4.5 (the simulator's 4 % z scale error, not estimated by
    # default, turns its 120 deg yaw swings into heading errors the 30 s magnetometer time
    # constant does not follow)
    assert rms(held) < 6.0, f"9-D heading error {rms(held):.2f} deg RMS"
    assert nine.diagnostics["mag_used"].mean() > 0.9
    # the magnetometer owns the heading only: the inclination is as good as in 6-D
    assert np.sqrt(np.mean(inclination_deg(rot, nine) ** 2)) < np.sqrt(np.mean(inclination_deg(rot, six) ** 2)) + 0.1


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_a_wrong_initial_heading_converges_to_magnetic_north(sim, spec):
    imu, rot = sim
    seed = quat.multiply(quat.from_rotvec(np.radians([0.0, 0.0, 30.0])), q0(rot))  # 30 deg about the world vertical
    heading = heading_deg(rot, build(spec).estimate(imu, seed))
    assert heading[0] == pytest.approx(30.0, abs=1e-6)
    assert np.sqrt(np.mean(heading[-6000:] ** 2)) < 6.0  # the last 60 s, as from the true start (measured 4-5 deg RMS)


# gates so wide that nothing is rejected, no heading gate, no hard-iron fit: what the magnet would do to an
# ungated update (the heading gate alone, mhg on, holds the passing magnet's peak to 19.5 deg of 34)
UNGATED = "mnorm=10,mdip=3.14,mhg=inf,mhi=false"


@pytest.mark.parametrize("spec", FILTERS)
def test_a_magnet_carried_with_the_sensor_does_not_drag_heading(sim, spec):
    imu, rot = sim
    disturbed = with_magnet_carried(imu, 4000, 10000)  # 40-100 s, after the reference was learned
    est = build(spec).estimate(disturbed, q0(rot))
    heading = heading_deg(rot, est)
    ungated = heading_deg(rot, build(with_params(spec, UNGATED)).estimate(disturbed, q0(rot)))
    assert est.diagnostics["mag_used"][4000:10000].mean() < 0.05  # gated out while the magnet is there
    assert est.diagnostics["mag_used"][-3000:].mean() > 0.9  # and back once it is gone
    # Gated out, the heading follows the gyro (6-D) for the 60 s: it drifts with the residual
    # z bias (measured: up to 22 deg), less than the magnet drags the ungated update (30-32 deg).
    assert np.max(heading) < np.max(ungated) - 5.0, f"gated {np.max(heading):.1f}, ungated {np.max(ungated):.1f} deg"
    assert np.max(heading[-1000:]) < 10.0


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_a_magnet_in_the_room_does_not_drag_heading(sim, spec):
    imu, rot = sim
    disturbed = with_magnet_passed(imu, rot, centre=8000, width=500)
    heading = heading_deg(rot, build(spec).estimate(disturbed, q0(rot)))
    ungated = heading_deg(rot, build(with_params(spec, UNGATED)).estimate(disturbed, q0(rot)))
    # measured: gated up to 14 deg (the 6-D drift while gated out, and the magnet's weak
    # edges, which pass the gates), ungated 34 deg
    assert np.max(heading) < 0.6 * np.max(ungated), f"gated {np.max(heading):.1f}, ungated {np.max(ungated):.1f} deg"


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_a_field_bent_in_the_room_is_held_off_by_the_heading_gate(sim, spec):
    """The field turns 40 deg about the vertical for 30 s with its norm and dip unchanged: the
    norm and dip gates pass it, the heading gate does not."""
    imu, rot = sim
    bent, bend = with_field_bent(imu, rot, 40.0, start_s=60.0, stop_s=85.0)
    gated = build(spec).estimate(bent, q0(rot))
    ungated = build(with_params(spec, "mhg=inf")).estimate(bent, q0(rot))
    rms = lambda e: float(np.sqrt(np.mean(e[bend > 0] ** 2)))  # noqa: E731
    # measured (ekf; ukf-bias alike): 6.5 deg RMS while bent with the gate, 13.6 without; 18 % of
    # the bent samples used (the first ones, before the low-passed innovation leaves the bound)
    assert rms(heading_deg(rot, gated)) < 0.6 * rms(heading_deg(rot, ungated))
    assert gated.diagnostics["mag_used"][bend > 0].mean() < 0.5
    assert ungated.diagnostics["mag_used"][bend > 0].mean() > 0.9
    after = imu.t - imu.t[0] > 100.0  # the field back: used again
    assert gated.diagnostics["mag_used"][after].mean() > 0.9


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_a_lasting_bend_is_believed_after_the_longest_rejection(sim, spec):
    """A field that stays bent (the sensor moved to another room): after `mhgmax` seconds of
    rejection the field is believed again and the heading follows it, as without the gate."""
    imu, rot = sim
    bent, bend = with_field_bent(imu, rot, 40.0, start_s=60.0, stop_s=1e9)
    gated = build(spec).estimate(bent, q0(rot))
    ungated = build(with_params(spec, "mhg=inf")).estimate(bent, q0(rot))
    last = imu.t - imu.t[0] > 160.0
    # measured: 44.9 deg mean heading error over the last 20 s with the gate, 46.0 without (the
    # 40 deg turn of north, and the simulator's scale error)
    assert np.mean(heading_deg(rot, gated)[last]) == pytest.approx(np.mean(heading_deg(rot, ungated)[last]), abs=5.0)
    assert np.mean(heading_deg(rot, gated)[last]) > 30.0
    assert gated.diagnostics["mag_used"][imu.t - imu.t[0] > 120.0].mean() > 0.9


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_the_heading_gate_compiled_equals_its_reference(sim, spec):
    """The gate rejecting and recovering, compiled against the numpy step (the first 100 s, the
    bend from 60 s; `mhgmax` short so that the recovery rule runs too)."""
    imu, rot = sim
    bent, _ = with_field_bent(imu, rot, 40.0, start_s=60.0, stop_s=1e9)
    bent, start = bent.window(0, 10000), q0(rot)
    a = build(with_params(spec, "mhgmax=10")).estimate(bent, start)
    b = build(with_params(spec, "impl=numpy,mhgmax=10")).estimate(bent, start)
    assert not a.diagnostics["mag_used"][6000:].all() and a.diagnostics["mag_used"][9000:].any()
    np.testing.assert_array_equal(a.diagnostics["mag_used"], b.diagnostics["mag_used"])
    np.testing.assert_allclose(a.quat_wxyz, b.quat_wxyz, rtol=0, atol=1e-10)


@pytest.mark.parametrize("spec", FILTERS + REFERENCES)
def test_without_a_magnetometer_the_filter_is_6d_bit_for_bit(sim, spec):
    """No `mag_ut` (`--mag off`, the course board) gives exactly the filter that never looks at
    one: a subclass with `magnetometer = False` given the samples with the field. The numpy
    references on the first 40 s (a property of every step, so of any length)."""
    cls = type(build(spec))

    class SixD(cls):
        magnetometer = False

    imu, rot = sim
    if "impl=numpy" in spec:
        imu, rot = imu.window(0, 4000), rot[:4000]
    params = build(spec).params
    plain = cls(params).estimate(imu.replace(mag_ut=None), q0(rot))
    never = SixD(params).estimate(imu, q0(rot))
    np.testing.assert_array_equal(plain.quat_wxyz, never.quat_wxyz)
    np.testing.assert_array_equal(plain.diagnostics["cov"], never.diagnostics["cov"])
    assert not plain.diagnostics["mag_used"].any()


@pytest.mark.parametrize("spec", ["ekf", "ukf-bias"])
def test_invalid_magnetometer_samples_are_skipped(sim, spec):
    imu, rot = sim
    mag = np.array(imu.mag_ut)
    mag[2000:2500] = np.nan
    valid = np.ones(len(imu), bool)
    valid[5000:5400] = False
    est = build(spec).estimate(imu.replace(mag_ut=mag, mag_valid=valid), q0(rot))
    used = est.diagnostics["mag_used"]
    assert not used[2000:2500].any() and not used[5000:5400].any()
    assert used.mean() > 0.9


def test_the_inputs_are_untouched(sim):
    imu, rot = sim
    before = np.array(imu.mag_ut)
    build("ekf").estimate(imu, q0(rot))
    np.testing.assert_array_equal(imu.mag_ut, before)


@pytest.mark.parametrize("name", ["ekf", "ukf-bias"])
@pytest.mark.parametrize("bad", ["Rm=0", "mnorm=-0.1", "mdip=inf", "mtime=-1", "mref=0", "mrate=0", "mhires=nan",
                                 "mhg=0", "mhgs=inf", "mhgmax=-1"])
def test_bad_magnetometer_parameters_raise(name, bad):
    with pytest.raises(ValueError, match=f"{name}: mag_"):
        build(f"{name}:{bad}")


def test_hard_iron_fields_apply_only_with_the_fit():
    with pytest.raises(ValueError, match="mag_hard_iron_window_s applies only with mag_hard_iron=true"):
        build("ekf:mhi=false,mhiw=5")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["ekf", "ukf-bias"])
@pytest.mark.parametrize("trial, bound_deg", [("01_undisturbed_slow_rotation_A.mat", 1.5),
                                               ("28_disturbed_stationary_magnet_A.mat", 3.5)])
def test_broad_9d_total_error(data_dir, trial, bound_deg, name):
    """BROAD's protocol (movement phases, total error, no heading offset removed in 9-D) on an
    undisturbed trial (measured: ekf 0.92 deg, ukf-bias 0.82) and on a trial past a magnet fixed
    in the room (ekf 2.82, ukf-bias 2.53; VQF's 9-D estimate scores 4.04)."""
    path = data_dir / "broad" / trial
    if not path.is_file():
        pytest.fail(f"FUSION_DATA={data_dir} is set but {path} is missing")
    if path.suffix == ".hdf5":
        require_module("h5py")
    rec = datasets.load(str(path))
    est = build(name).estimate(rec.imu, datasets.initial_orientation(rec))
    nine = score(rec.truth, est, "broad", rec.movement, nine_d=True).rmse_deg["total"]
    six = score(rec.truth, build(name).estimate(rec.imu.replace(mag_ut=None), datasets.initial_orientation(rec)),
                "broad", rec.movement, nine_d=True).rmse_deg["total"]
    assert nine < bound_deg, f"{trial}: 9-D total RMSE {nine:.2f} deg"
    assert nine < six, f"{trial}: 9-D {nine:.2f} deg, the 6-D heading (not offset-corrected) {six:.2f}"


@pytest.mark.slow
def test_broad_carried_magnet_is_fitted_as_hard_iron(data_dir):
    """BROAD trial 36: a magnet fixed 5 cm from the sensor for about a minute. The sphere fit
    finds its offset and the heading update continues with it removed (measured total RMSE
    1.26 deg with the fit, 4.16 without; VQF's 9-D estimate: 2.39)."""
    path = data_dir / "broad" / "36_disturbed_attached_magnet_5cm.hdf5"
    if not path.is_file():
        pytest.fail(f"FUSION_DATA={data_dir} is set but {path} is missing")
    require_module("h5py")
    rec = datasets.load(str(path))
    q0_ = datasets.initial_orientation(rec)
    fitted = build("ekf").estimate(rec.imu, q0_)
    t = rec.imu.t - rec.imu.t[0]
    magnet = (t > 50.0) & (t < 95.0)
    assert fitted.diagnostics["mag_hard_iron"][magnet].mean() > 0.5
    assert not fitted.diagnostics["mag_hard_iron"][t < 30.0].any()  # the undisturbed start: raw samples
    total = {name: score(rec.truth, est, "broad", rec.movement, nine_d=True).rmse_deg["total"]
             for name, est in (("fit", fitted), ("no fit", build("ekf:mhi=false").estimate(rec.imu, q0_)))}
    assert total["fit"] < 1.45 and total["fit"] < total["no fit"] / 2.0, total  # measured + 15 %; a third of it
