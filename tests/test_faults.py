"""Sensor faults (`fusion.faults`): each kind against its model on a simulated recording with exact
truth and a magnetometer, the loader's checks after it, the seeding, and what a fault leaves alone."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion import faults
from fusion.faults import Fault, apply
from fusion.format_checks import GAP_S
from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples, Recording, Trajectory

RATE_HZ = 100.0
B_WORLD_UT = np.array([0.0, 20.0, -40.0])  # a field with the Earth's dip, uT, world frame


def recording(n: int = 4000, rid: str = "sim/faults") -> Recording:
    """A swing about a tilted axis with a yaw drift, on an exact 100 Hz grid (so that the grid holds
    the times a fault is defined at: t_0 + 15 s), with exact truth, an accelerometer reading gravity
    and a magnetometer reading `B_WORLD_UT`, both rotated by the truth; movement flagged from 2 s on."""
    t = 1000.0 + np.arange(n) / RATE_HZ
    s = t - t[0]
    axis = np.array([0.5, 0.3, 0.8]) / np.linalg.norm([0.5, 0.3, 0.8])
    theta = np.radians(120.0) * np.sin(2 * np.pi * 0.3 * s)
    rate = np.radians(120.0) * 2 * np.pi * 0.3 * np.cos(2 * np.pi * 0.3 * s)
    rot = Rotation.from_rotvec(theta[:, None] * axis)
    imu = ImuSamples(t, rate[:, None] * axis, rot.inv().apply([0.0, 0.0, 1.0]), source=rid,
                     mag_ut=rot.inv().apply(B_WORLD_UT))
    return Recording(rid, imu, Trajectory(t, rot.as_quat(scalar_first=True)), movement=s >= 2.0)


@pytest.fixture(scope="module")
def rec() -> Recording:
    return recording()


def _unchanged(a: Recording, b: Recording, *except_: str) -> None:
    """Every IMU array but `except_` equal; the truth the same object."""
    assert b.truth is a.truth
    for name in ("t", "gyr_rad_s", "acc_g", "mag_ut"):
        if name not in except_:
            np.testing.assert_array_equal(getattr(b.imu, name), getattr(a.imu, name))


def test_gyro_bias_step_adds_exactly_the_stated_bias_after_the_middle(rec):
    bad = apply(rec, Fault("gyro-bias-step", 2.0))
    diff = bad.imu.gyr_rad_s - rec.imu.gyr_rad_s
    after = rec.imu.t >= rec.imu.t[0] + faults.GYRO_STEP_AT * (rec.imu.t[-1] - rec.imu.t[0])
    assert after.sum() == len(rec.imu) // 2
    np.testing.assert_array_equal(diff[~after], 0.0)
    assert np.ptp(diff[after], axis=0).max() < 1e-15  # one constant vector
    assert np.linalg.norm(diff[after][0]) == pytest.approx(math.radians(2.0), rel=1e-12)
    _unchanged(rec, bad, "gyr_rad_s")


def test_gyro_bias_walk_has_the_increments_of_its_coefficient(rec):
    k = 0.05
    bias = apply(rec, Fault("gyro-bias-walk", k)).imu.gyr_rad_s - rec.imu.gyr_rad_s
    np.testing.assert_array_equal(bias[0], 0.0)  # from 0
    steps = np.diff(bias, axis=0) / np.sqrt(np.diff(rec.imu.t))[:, None]
    n = steps.size
    # sample std of n unit normals: within 5 standard errors (1 / sqrt(2 n)) of 1
    assert abs(steps.std() / math.radians(k) - 1) < 5 / math.sqrt(2 * n)
    assert abs(steps.mean()) / math.radians(k) < 5 / math.sqrt(n)
    # the same draws at every severity (common random numbers): the bias scales with K
    twice = apply(rec, Fault("gyro-bias-walk", 2 * k)).imu.gyr_rad_s - rec.imu.gyr_rad_s
    np.testing.assert_allclose(twice, 2 * bias, rtol=0, atol=1e-15)


def test_gyro_scale_and_saturations_follow_their_models(rec):
    scaled = apply(rec, Fault("gyro-scale", 5.0))
    np.testing.assert_allclose(scaled.imu.gyr_rad_s, 1.05 * rec.imu.gyr_rad_s, rtol=1e-15)
    clipped = apply(rec, Fault("gyro-saturation", 125.0)).imu.gyr_rad_s
    r = math.radians(125.0)
    assert np.abs(rec.imu.gyr_rad_s).max() > r and np.abs(clipped).max() == pytest.approx(r, rel=1e-15)
    inside = np.abs(rec.imu.gyr_rad_s) <= r
    np.testing.assert_array_equal(clipped[inside], rec.imu.gyr_rad_s[inside])
    np.testing.assert_array_equal(np.abs(clipped[~inside]), r)
    acc = apply(rec, Fault("acc-saturation", 0.8)).imu.acc_g
    assert np.abs(acc).max() == 0.8 and np.abs(rec.imu.acc_g).max() > 0.8
    inside = np.abs(rec.imu.acc_g) <= 0.8
    np.testing.assert_array_equal(acc[inside], rec.imu.acc_g[inside])


def test_drops_remove_runs_of_the_stated_length_and_the_loader_marks_long_ones(rec):
    for gap in (0.1, 1.0):
        bad = apply(rec, Fault("drops", gap))
        steps = np.diff(bad.imu.t)
        gaps = np.flatnonzero(steps > 1.5 / RATE_HZ)
        assert len(gaps) == round((rec.imu.t[-1] - rec.imu.t[0]) / faults.DROP_EVERY_S) == 4
        # a gap removes the samples stamped inside it: the step across is the gap and at most one step more
        assert np.all((steps[gaps] >= gap) & (steps[gaps] <= gap + 1 / RATE_HZ + 1e-9))
        assert len(rec.imu) - len(bad.imu) == pytest.approx(4 * gap * RATE_HZ, abs=4)
        kept = np.searchsorted(rec.imu.t, bad.imu.t)
        np.testing.assert_array_equal(rec.imu.t[kept], bad.imu.t)  # the samples left are the clean ones
        for name in ("gyr_rad_s", "acc_g", "mag_ut"):
            np.testing.assert_array_equal(getattr(bad.imu, name), getattr(rec.imu, name)[kept])
        np.testing.assert_array_equal(bad.movement, rec.movement[kept])
        # the loader's gap check: the gyro sample across a gap longer than GAP_S ("end": the one after it)
        marked = np.flatnonzero(~bad.imu.gyr_valid)
        assert list(marked) == ([g + 1 for g in gaps] if gap > GAP_S else [])
        assert bad.truth is rec.truth


def test_jitter_keeps_the_values_and_the_order_and_errs_by_its_sigma(rec):
    small = apply(rec, Fault("jitter", 0.5))  # 0.5 ms against a 10 ms step: nothing reordered
    _unchanged(rec, small, "t")
    err = small.imu.t - rec.imu.t
    n = len(err)
    assert abs(err.std() / 0.5e-3 - 1) < 5 / math.sqrt(2 * n) and abs(err.mean()) < 5 * 0.5e-3 / math.sqrt(n)
    big = apply(rec, Fault("jitter", 20.0))  # twice the step: reordered, then sorted
    assert np.all(np.diff(big.imu.t) > 0)
    np.testing.assert_array_equal(big.imu.gyr_rad_s, rec.imu.gyr_rad_s)
    assert 0 < np.abs(big.imu.t - rec.imu.t).std() < 20e-3  # sorting keeps each stamp nearer its time


def test_vibration_is_a_sinusoid_of_the_stated_rms_and_frequency(rec):
    bad = apply(rec, Fault("vibration", 2.0))
    added = (bad.imu.acc_g - rec.imu.acc_g) * STANDARD_GRAVITY_M_S2
    u = added[np.argmax(np.linalg.norm(added, axis=1))]
    u /= np.linalg.norm(u)
    np.testing.assert_allclose(np.cross(added, u), 0.0, atol=1e-12)  # along one direction
    along = added @ u
    assert np.sqrt(np.mean(along**2)) == pytest.approx(2.0, rel=1e-3)  # 40 s: whole periods but one sample
    spectrum = np.abs(np.fft.rfft(along))
    assert np.fft.rfftfreq(len(along), 1 / RATE_HZ)[np.argmax(spectrum)] == pytest.approx(faults.VIBRATION_HZ)
    _unchanged(rec, bad, "acc_g")


def test_hard_and_soft_iron_follow_their_models(rec):
    hard = apply(rec, Fault("mag-hard-iron", 30.0)).imu.mag_ut - rec.imu.mag_ut
    assert np.ptp(hard, axis=0).max() < 1e-12 and np.linalg.norm(hard[0]) == pytest.approx(30.0, rel=1e-12)
    soft = apply(rec, Fault("mag-soft-iron", 20.0))
    s = faults.soft_iron_matrix(20.0, faults.rng_for(rec.id, "mag-soft-iron"))
    np.testing.assert_allclose(s, s.T, atol=1e-15)
    eig = np.linalg.eigvalsh(s)
    assert np.abs(eig - 1).max() == pytest.approx(0.20, rel=1e-12)
    np.testing.assert_allclose(soft.imu.mag_ut, rec.imu.mag_ut @ s.T, atol=1e-12)
    _unchanged(rec, soft, "mag_ut")


def test_dipole_field_is_the_gradient_of_its_potential():
    """`dipole_field` against an independent route: B = -mu0 grad(psi), psi = m . r / (4 pi |r|^3)."""
    m = np.array([3.0, -1.0, 2.0])
    r = np.array([[0.2, 0.1, -0.15], [-0.05, 0.3, 0.02]])
    h = 1e-7

    def psi(x):
        return faults.MU0_OVER_4PI * (x @ m) / np.linalg.norm(x, axis=-1) ** 3

    grad = np.stack([(psi(r + h * e) - psi(r - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(faults.dipole_field(m, r), -1e6 * grad, rtol=1e-6)


def test_a_passing_dipole_reaches_exactly_the_stated_field_at_closest_approach(rec):
    severity = 50.0
    bad = apply(rec, Fault("mag-dipole", severity))
    added = bad.imu.mag_ut - rec.imu.mag_ut
    (p,) = faults.dipole_passes(rec, faults.rng_for(rec.id, "mag-dipole"))  # 40 s: one pass, at t_0 + 15 s
    assert p.t_s == rec.imu.t[0] + 15.0 and abs(p.path @ p.towards) < 1e-15
    k = int(np.flatnonzero(rec.imu.t == p.t_s)[0])
    assert np.linalg.norm(added[k]) == pytest.approx(severity, rel=1e-12)  # the rotation keeps the norm
    # the field in the world (rotated back by the truth) is the dipole's at every sample
    world = Rotation.from_quat(rec.truth.quat_wxyz, scalar_first=True).apply(added)
    np.testing.assert_allclose(world, faults.dipole_field(p.moment_am2(severity), p.offset_m(rec.imu.t)), atol=1e-9)
    far = np.abs(rec.imu.t - p.t_s) > 5.0  # 2.5 m away: (0.2 / 2.5)^3 of it at most, times 2
    assert np.linalg.norm(added[far], axis=1).max() < 2 * severity * (0.2 / 2.5) ** 3


def test_magnetometer_faults_need_a_magnetometer(rec):
    from dataclasses import replace

    plain = replace(rec, imu=rec.imu.replace(mag_ut=None))
    assert not faults.applies("mag-dipole", plain) and faults.applies("gyro-scale", plain)
    with pytest.raises(ValueError, match="sim/faults: fault mag-soft-iron changes the magnetometer"):
        apply(plain, Fault("mag-soft-iron", 5.0))


def test_severities_are_checked():
    with pytest.raises(ValueError, match="unknown fault 'gyro-bias'; available: gyro-bias-step"):
        Fault("gyro-bias", 1.0)
    for kind, bad in (("gyro-scale", -1.0), ("jitter", 0.0), ("vibration", float("nan")),
                      ("mag-soft-iron", 100.0), ("drops", 10.0)):
        with pytest.raises(ValueError, match=f"fault {kind}: the severity must be"):
            Fault(kind, bad)
    assert faults.CLEAN.clean and faults.CLEAN.label == "clean" and Fault("drops", 0.2).label == "drops 0.2 s"
    assert Fault.from_json(Fault("jitter", 2.0).to_json()) == Fault("jitter", 2.0)
    for kind in faults.KINDS.values():  # five documented severities, mildest first, each valid
        assert len(kind.levels) == 5 and kind.ordered(kind.levels) == list(kind.levels)
        for level in kind.levels:
            Fault(kind.name, level)


def test_a_fault_is_seeded_by_recording_and_kind_and_leaves_its_input_alone(rec):
    before = {name: np.array(getattr(rec.imu, name)) for name in ("t", "gyr_rad_s", "acc_g", "mag_ut", "gyr_valid")}
    for kind in faults.KINDS.values():
        a = apply(rec, Fault(kind.name, kind.levels[2]))
        b = apply(rec, Fault(kind.name, kind.levels[2]))
        for name in ("t", "gyr_rad_s", "acc_g", "mag_ut", "gyr_valid"):
            np.testing.assert_array_equal(getattr(a.imu, name), getattr(b.imu, name))
            assert not getattr(a.imu, name).flags.writeable
        assert a.id == rec.id and a.truth is rec.truth
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(rec.imu, name), value)
    other = apply(recording(rid="sim/other"), Fault("gyro-bias-step", 2.0)).imu.gyr_rad_s[-1]
    assert not np.allclose(other, apply(rec, Fault("gyro-bias-step", 2.0)).imu.gyr_rad_s[-1])
    assert apply(rec, faults.CLEAN) is rec


def test_a_recording_in_raw_counts_loses_its_raw_counts_under_a_fault():
    from fusion import datasets

    sim = datasets.load("sim")
    bad = apply(sim, Fault("gyro-scale", 5.0))
    assert sim.raw is not None and bad.raw is None  # the counts are the clean sensor's
    np.testing.assert_array_equal(bad.imu.gyr_valid, sim.imu.gyr_valid)
