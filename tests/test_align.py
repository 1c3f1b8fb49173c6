"""`--align`: constant world and body rotations between the truth's frames and ours.

The simulated recording's truth is re-expressed in rotated frames, truth'(t) = A^-1 R(t) B^-1
with A = R_ourworld_truthworld (world tilted 20 deg about x) and B = R_truthbody_imubody
(30 deg about an oblique axis); `--align` must find A and B and score as in our frames.
"""
import json
from functools import lru_cache

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluation.align import estimate_alignment
from evaluation.compare import Result, format_table, run_one
from evaluation.metrics import score
from estimators.params import EstimatorSpec
from fusion import datasets
from fusion.cli import main
from fusion.types import Recording, Trajectory

A_TRUE = Rotation.from_rotvec([np.radians(20.0), 0.0, 0.0])  # truth world tilted 20 deg about x
B_TRUE = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]))


@lru_cache(maxsize=1)
def sim() -> Recording:
    return datasets.load("sim")


def rotated(truth: Trajectory, a: Rotation = A_TRUE, b: Rotation = B_TRUE) -> Trajectory:
    """The same truth given in other frames: A^-1 R B^-1 (NaN rows stay NaN)."""
    out = np.full_like(truth.quat_wxyz, np.nan)
    ok = truth.valid
    rot = a.inv() * Rotation.from_quat(truth.quat_wxyz[ok], scalar_first=True) * b.inv()
    out[ok] = rot.as_quat(scalar_first=True)
    return Trajectory(truth.t, out)


def angle_deg(r1: Rotation, r2: Rotation) -> float:
    return float(np.degrees((r1 * r2.inv()).magnitude()))


def noisy_truth_estimate(rec: Recording, noise_deg: float = 2.0, seed: int = 0) -> Trajectory:
    """The true orientation on the IMU stamps with white noise (noise_deg rms per axis)."""
    r, mask = rec.truth.interpolate(rec.imu.t)
    assert mask.all()
    noise = Rotation.from_rotvec(np.random.default_rng(seed).normal(scale=np.radians(noise_deg), size=(len(r), 3)))
    return Trajectory.from_rotation(rec.imu.t, r * noise)


def test_exact_estimate_recovers_both_rotations_to_1e_9_deg():
    rec = sim()
    exact = Trajectory.from_rotation(rec.imu.t, rec.truth.interpolate(rec.imu.t)[0])
    s = score(rotated(rec.truth), exact, align=True)
    assert angle_deg(s.alignment.world, A_TRUE) < 1e-9 and angle_deg(s.alignment.body, B_TRUE) < 1e-9
    assert s.alignment.samples == len(rec.imu)
    assert max(s.rmse_deg.values()) < 1e-9


def test_noisy_estimate_recovers_both_rotations_within_0_1_deg():
    rec = sim()
    est = noisy_truth_estimate(rec, noise_deg=2.0)
    aligned = score(rotated(rec.truth), est, align=True)
    assert angle_deg(aligned.alignment.world, A_TRUE) < 0.1
    assert angle_deg(aligned.alignment.body, B_TRUE) < 0.1
    # the aligned score is the score in our own frames, unaligned (the noise is zero-mean)
    plain = score(rec.truth, est)
    for kind in plain.rmse_deg:
        assert aligned.rmse_deg[kind] == pytest.approx(plain.rmse_deg[kind], abs=0.01)
    # and a large mounting rotation (an axis swap) is found too: the start needs no guess
    swap = Rotation.from_euler("ZX", [90.0, 180.0], degrees=True)
    s = score(rotated(rec.truth, A_TRUE, swap), est, align=True)
    assert angle_deg(s.alignment.body, swap) < 0.1


@pytest.mark.parametrize("name", ["dr", "ukf"])
def test_aligned_scores_do_not_depend_on_the_truth_frames(name):
    """With a real estimator (heading drift and all), aligning against rotated truth gives the
    scores of aligning against our own frames, and rotations composed with the true ones."""
    rec = sim()
    spec = EstimatorSpec(name)
    ours = run_one(rec, spec, align=True)
    theirs = run_one(Recording(rec.id, rec.imu, rotated(rec.truth), calibration=rec.calibration), spec, align=True)
    for kind in ours.rmse_deg:
        assert theirs.rmse_deg[kind] == pytest.approx(ours.rmse_deg[kind], abs=1e-6)
        assert theirs.max_deg[kind] == pytest.approx(ours.max_deg[kind], abs=1e-6)
    a0, b0 = ours.score.alignment.world, ours.score.alignment.body
    assert angle_deg(theirs.score.alignment.world, a0 * A_TRUE) < 1e-6
    assert angle_deg(theirs.score.alignment.body, B_TRUE * b0) < 1e-6
    # both runs started from the accelerometer: the truth's frames cannot give the start
    np.testing.assert_array_equal(ours.trajectory.quat_wxyz, theirs.trajectory.quat_wxyz)


def test_constant_heading_offset_goes_into_the_world_rotation():
    rec = sim()
    est = noisy_truth_estimate(rec, noise_deg=0.0)
    turned = Trajectory.from_rotation(est.t, Rotation.from_euler("z", 40.0, degrees=True) * est.rotation())
    s = score(rec.truth, turned, align=True)
    assert np.degrees(s.alignment.world.as_rotvec()) == pytest.approx([0.0, 0.0, 40.0], abs=1e-9)
    assert s.alignment.body.magnitude() < 1e-9
    assert score(rec.truth, turned).rmse_deg["heading"] == pytest.approx(40.0, abs=1e-6)  # what it hides


def test_align_off_leaves_scores_untouched():
    rec = sim()
    est = noisy_truth_estimate(rec)
    default, off = score(rec.truth, est), score(rec.truth, est, align=False)
    assert default.alignment is None and off.alignment is None
    for kind in default.rmse_deg:
        np.testing.assert_array_equal(default.errors_rad[kind], off.errors_rad[kind])
    result = run_one(rec, EstimatorSpec("dr"))
    assert result.alignment is None and result.to_json()["alignment"] is None
    assert result.rmse_deg == score(rec.truth, result.trajectory).rmse_deg
    assert "no alignment" in format_table([result]).splitlines()[0]


def test_q_and_minus_q_align_the_same():
    rec = sim()
    est = noisy_truth_estimate(rec)
    truth = rotated(rec.truth)
    flipped = Trajectory(truth.t, -truth.quat_wxyz)
    s1, s2 = score(truth, est, align=True), score(flipped, est, align=True)
    assert angle_deg(s1.alignment.world, s2.alignment.world) < 1e-9
    assert s1.rmse_deg["total"] == pytest.approx(s2.rmse_deg["total"], abs=1e-9)


def test_too_few_samples_and_single_axis_motion_are_clear_errors():
    rec = sim()
    est = noisy_truth_estimate(rec)
    two = Trajectory(rec.imu.t[100:102], rec.truth.interpolate(rec.imu.t[100:102])[0].as_quat(scalar_first=True))
    with pytest.raises(ValueError, match="at least 3 time stamps with both truth and estimate, got 2"):
        score(two, est, align=True)
    nan_truth = Trajectory(rec.truth.t, np.full_like(rec.truth.quat_wxyz, np.nan))
    with pytest.raises(ValueError, match="share no valid time stamp"):
        score(nan_truth, est, align=True)
    t = np.linspace(0.0, 10.0, 200)
    spin = Rotation.from_rotvec(np.radians(np.linspace(0.0, 300.0, 200))[:, None] * [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="single axis"):
        estimate_alignment(spin, A_TRUE * spin * B_TRUE)
    still = Rotation.from_quat(np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1)))
    with pytest.raises(ValueError, match="single axis"):
        estimate_alignment(still, still)


def write_csv(path, rec: Recording, truth: Trajectory | None, keep=None) -> None:
    """The recording as a generic CSV (m/s^2), truth slerped onto the IMU stamps; `keep`: the
    rows that keep their truth (the others NaN)."""
    cols = [rec.imu.t[:, None], rec.imu.gyr_rad_s, rec.imu.acc_g * 9.80665]
    header = "t,gx,gy,gz,ax,ay,az"
    if truth is not None:
        r, mask = truth.interpolate(rec.imu.t)
        quat = np.full((len(rec.imu.t), 4), np.nan)
        quat[mask] = r.as_quat(scalar_first=True)
        if keep is not None:
            drop = np.ones(len(quat), bool)
            drop[keep] = False
            quat[drop] = np.nan
        cols.append(quat)
        header += ",qw,qx,qy,qz"
    np.savetxt(path, np.hstack(cols), delimiter=",", header=header, comments="", fmt="%.17g")


def cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_align_prints_and_records_the_rotations(tmp_path, capsys):
    rec = sim()
    write_csv(tmp_path / "ours.csv", rec, rec.truth)
    write_csv(tmp_path / "theirs.csv", rec, rotated(rec.truth))
    runs = {}
    for name in ("ours", "theirs"):
        code, out, err = cli(capsys, "compare", "--estimators", "dr,ukf", "--dataset", str(tmp_path / f"{name}.csv"),
                             "--align", "--no-progress", "--jobs", "2", "--json", str(tmp_path / f"{name}.json"))
        assert code == 0, err
        runs[name] = (out, json.loads((tmp_path / f"{name}.json").read_text()))
    out, doc = runs["theirs"]
    assert doc["settings"]["align"] is True and doc["settings"]["init"] == "default with --align: accel"
    assert "after --align" in out.splitlines()[0]
    block = out[out.index("Alignment, deg"):].splitlines()
    for row in doc["results"]:
        al = row["alignment"]
        assert al["samples"] == len(rec.imu) - 1 or al["samples"] == len(rec.imu)
        # the printed rotation vectors are the JSON's
        (line,) = [ln.split() for ln in block if ln.split()[:2] == [row["dataset"], row["estimator"]]]
        assert [float(x) for x in line[2:5]] == pytest.approx(al["world_deg"], abs=0.006)
        assert [float(x) for x in line[6:9]] == pytest.approx(al["body_deg"], abs=0.006)
        assert float(line[5]) == pytest.approx(al["world_angle_deg"], abs=0.006)
        # against the run in our own frames: the same scores, rotations composed with the true ones
        (mine,) = [r for r in runs["ours"][1]["results"] if r["estimator"] == row["estimator"]]
        for kind in row["rmse_deg"]:
            assert row["rmse_deg"][kind] == pytest.approx(mine["rmse_deg"][kind], abs=1e-6)
        a0 = Rotation.from_rotvec(mine["alignment"]["world_deg"], degrees=True)
        b0 = Rotation.from_rotvec(mine["alignment"]["body_deg"], degrees=True)
        assert angle_deg(Rotation.from_rotvec(al["world_deg"], degrees=True), a0 * A_TRUE) < 1e-6
        assert angle_deg(Rotation.from_rotvec(al["body_deg"], degrees=True), B_TRUE * b0) < 1e-6


def test_cli_without_align_says_so_and_records_null(tmp_path, capsys):
    rec = sim()
    write_csv(tmp_path / "r.csv", rec, rec.truth)
    code, out, err = cli(capsys, "compare", "--estimators", "dr", "--dataset", str(tmp_path / "r.csv"), "--no-progress",
                         "--jobs", "1", "--json", str(tmp_path / "r.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["settings"]["align"] is False and doc["results"][0]["alignment"] is None
    assert "no alignment" in out.splitlines()[0] and "Alignment, deg" not in out


def test_cli_degenerate_truth_is_one_line_error_or_a_row_without_scores(tmp_path, capsys):
    rec = sim()
    write_csv(tmp_path / "few.csv", rec, rec.truth, keep=[500, 501])
    code, out, err = cli(capsys, "compare", "--estimators", "dr", "--dataset", str(tmp_path / "few.csv"), "--align",
                         "--no-progress", "--jobs", "1")
    assert code == 1 and out == ""
    (line,) = err.strip().splitlines()
    assert line.startswith("fusion: error: ") and "at least 3 time stamps" in line and "Traceback" not in err
    # all-NaN truth: the loader drops it (a warning), the row has no scores and no alignment
    write_csv(tmp_path / "blank.csv", rec, rec.truth, keep=[])
    code, out, err = cli(capsys, "compare", "--estimators", "dr", "--dataset", str(tmp_path / "blank.csv"), "--align",
                         "--no-progress", "--jobs", "1", "--json", str(tmp_path / "blank.json"))
    assert code == 0, err
    assert "no finite quaternion" in err and "nan" not in out.lower()
    (cells,) = [ln.split() for ln in out.splitlines() if ln.split()[1:2] == ["dr"]]
    assert cells[2:5] == ["-", "-", "-"]
    (row,) = json.loads((tmp_path / "blank.json").read_text())["results"]
    assert row["rmse_deg"] is None and row["alignment"] is None


def test_report_rerender_keeps_the_alignment(tmp_path, capsys):
    from evaluation.report import render

    rec = sim()
    write_csv(tmp_path / "theirs.csv", rec, rotated(rec.truth))
    out_dir = tmp_path / "run"
    code, out, err = cli(capsys, "compare", "--estimators", "dr", "--dataset", str(tmp_path / "theirs.csv"), "--align",
                         "--no-progress", "--jobs", "1", "--out", str(out_dir))
    assert code == 0, err
    first = (out_dir / "table.txt").read_text()
    assert "after --align" in first and "Alignment, deg" in first
    render(out_dir)
    assert (out_dir / "table.txt").read_text() == first
    md = (out_dir / "report.md").read_text()
    assert "Aligned (--align)" in md and "## Alignment (--align)" in md
    assert "Aligned (--align)" in (out_dir / "report.html").read_text()


def test_format_table_from_json_rows_names_the_alignment():
    row = Result("x", "dr", 10, 0.0, {"total": 1.0, "inclination": 0.5, "heading": 0.8},
                 {"total": 2.0, "inclination": 1.0, "heading": 1.5},
                 alignment={"world_deg": [20.0, 0.0, 0.0], "body_deg": [0.0, 0.0, -3.0],
                            "world_angle_deg": 20.0, "body_angle_deg": 3.0, "samples": 10})
    table = format_table([row])
    assert "after --align" in table.splitlines()[0]
    (line,) = [ln.split() for ln in table.splitlines() if ln.startswith("x ") and "+20.00" in ln]
    assert line[2:9] == ["+20.00", "+0.00", "+0.00", "20.00", "+0.00", "+0.00", "-3.00"]


def test_real_recording_frames_already_agree(data_dir):
    """ece276a: VICON's frames are the IMU's up to 0.5-2 deg; --align finds only that, plus the
    estimator's mean heading error as a turn of A about the vertical."""
    rec = datasets.load("ece276a/1", data_dir)
    result = run_one(rec, EstimatorSpec("gn"), align=True)
    world = np.degrees(result.score.alignment.world.as_rotvec())
    assert np.hypot(world[0], world[1]) < 1.0  # the truth's vertical is ours
    assert result.score.alignment.body.magnitude() < np.radians(2.0)
    assert result.rmse_deg["inclination"] < 1.5
