"""Scoring: known error splits, q/-q invariance, gaps skipped."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.evaluation.scoring.metrics import error_angles, score
from fusion.types import Trajectory

RNG = np.random.default_rng(3)
TRUTH = Rotation.from_rotvec(RNG.normal(size=(500, 3)))


def test_pure_heading_error():
    """A world-frame yaw error of 10 deg: total 10, heading 10, inclination 0."""
    est = Rotation.from_euler("z", 10, degrees=True) * TRUTH
    err = {k: np.degrees(v) for k, v in error_angles(TRUTH, est).items()}
    np.testing.assert_allclose(err["total"], 10, atol=1e-9)
    np.testing.assert_allclose(err["heading"], 10, atol=1e-9)
    np.testing.assert_allclose(err["inclination"], 0, atol=1e-6)


def test_pure_tilt_error():
    """A world-frame error of 7 deg about a horizontal axis: inclination 7, heading 0."""
    axis = np.array([np.cos(0.4), np.sin(0.4), 0.0])
    est = Rotation.from_rotvec(np.radians(7) * axis) * TRUTH
    err = {k: np.degrees(v) for k, v in error_angles(TRUTH, est).items()}
    np.testing.assert_allclose(err["total"], 7, atol=1e-9)
    np.testing.assert_allclose(err["inclination"], 7, atol=1e-9)
    np.testing.assert_allclose(err["heading"], 0, atol=1e-9)


def test_swing_twist_split_of_a_combined_error():
    """Error = Rz(30) * Rx(20) in the world: inclination 20, heading 30 (the twist of the split)."""
    est = Rotation.from_euler("z", 30, degrees=True) * Rotation.from_euler("x", 20, degrees=True) * TRUTH
    err = {k: np.degrees(v) for k, v in error_angles(TRUTH, est).items()}
    np.testing.assert_allclose(err["inclination"], 20, atol=1e-9)
    np.testing.assert_allclose(err["heading"], 30, atol=1e-9)
    total = np.degrees((Rotation.from_euler("z", 30, degrees=True) * Rotation.from_euler("x", 20, degrees=True)).magnitude())
    np.testing.assert_allclose(err["total"], total, atol=1e-9)


def test_q_and_minus_q_score_the_same():
    t = np.arange(500) * 0.01
    truth = Trajectory(t, TRUTH.as_quat(scalar_first=True))
    est_q = (Rotation.from_rotvec([0.1, 0.2, 0.3]) * TRUTH).as_quat(scalar_first=True)
    a = score(truth, Trajectory(t, est_q))
    b = score(truth, Trajectory(t, -est_q))
    c = score(Trajectory(t, -truth.quat_wxyz), Trajectory(t, est_q))
    for kind in a.rmse_deg:
        assert a.rmse_deg[kind] == pytest.approx(b.rmse_deg[kind], abs=1e-9)
        assert a.rmse_deg[kind] == pytest.approx(c.rmse_deg[kind], abs=1e-9)


def test_error_angles_equal_scipys_rotation_algebra():
    """The quaternion algebra of the scoring against the same definitions written with SciPy's
    `Rotation` (geodesic angle, gravity directions, twist of the world-frame error), on random
    orientations, arrays and `Rotation` stacks alike, unnormalised inputs included."""
    r_true, r_est = Rotation.random(2000, random_state=3), Rotation.random(2000, random_state=4)
    up = np.array([0.0, 0.0, 1.0])
    g_true, g_est = r_true.inv().apply(up), r_est.inv().apply(up)
    world = (r_est * r_true.inv()).as_quat(scalar_first=True)
    expected = {"total": (r_true.inv() * r_est).magnitude(),
                "inclination": np.arccos(np.clip(np.sum(g_true * g_est, axis=1), -1, 1)),
                "heading": 2 * np.arctan2(np.abs(world[:, 3]), np.abs(world[:, 0]))}
    scaled = 3.0 * r_est.as_quat(scalar_first=True)  # a quaternion of norm 3 is the same rotation
    for got in (error_angles(r_true, r_est), error_angles(r_true.as_quat(scalar_first=True), scaled)):
        for kind, value in expected.items():
            np.testing.assert_allclose(got[kind], value, rtol=0, atol=1e-7 if kind == "inclination" else 1e-12)


def test_truth_gaps_are_skipped_not_interpolated():
    t = np.arange(100) * 0.01
    q = np.tile([1.0, 0, 0, 0], (100, 1))
    q[40:50] = np.nan
    truth = Trajectory(t, q)
    est_t = np.arange(200) * 0.005 + 0.0025  # two estimates per truth interval
    est = Trajectory(est_t[est_t < 0.99], np.tile([1.0, 0, 0, 0], ((est_t < 0.99).sum(), 1)))
    s = score(truth, est)
    in_gap = (est.t > 0.39) & (est.t < 0.50)
    assert not np.any(s.mask & in_gap)
    assert s.mask[~in_gap].all()
    assert s.rmse_deg["total"] == 0.0


def test_scores_only_the_overlap():
    truth = Trajectory(np.arange(100) * 0.01 + 0.5, np.tile([1.0, 0, 0, 0], (100, 1)))
    est = Trajectory(np.arange(100) * 0.01, np.tile([1.0, 0, 0, 0], (100, 1)))
    assert score(truth, est).samples == 50
    with pytest.raises(ValueError, match="share no valid time"):
        score(Trajectory(np.arange(10) + 100.0, np.tile([1.0, 0, 0, 0], (10, 1))), est)
