"""Scoring coverage, calibration files, numerical failures of estimators and panorama bounds:
each bad input is one line naming the file or argument, never a traceback or a silent answer."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.evaluation.scoring.metrics import MIN_COVERAGE, score
from fusion.cli import main
from fusion.types import Trajectory


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def write_csv(path: Path, n: int = 6000, truth_rows: int | None = None) -> Path:
    """A 100 Hz CSV turning slowly about z, truth on its first `truth_rows` rows (all by default)."""
    t = np.arange(n) * 0.01
    rot = Rotation.from_rotvec(np.outer(0.2 * t, [0, 0, 1]))
    gyr = np.tile([0.0, 0.0, 0.2], (n, 1))
    acc = rot.inv().apply([0, 0, 9.80665])
    quat = rot.as_quat(scalar_first=True)
    if truth_rows is not None:
        quat[truth_rows:] = np.nan
    rows = np.column_stack([t, gyr, acc, quat])
    path.write_text("t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz\n" + "\n".join(",".join(f"{x:.9g}" for x in r) for r in rows) + "\n")
    return path


# --- coverage ------------------------------------------------------------------------------

def test_score_reports_scored_samples_and_coverage():
    t = np.arange(6000) * 0.01
    est = Trajectory(t, np.tile([1.0, 0, 0, 0], (6000, 1)))
    truth = Trajectory(np.array([0.0, 0.015]), np.tile([1.0, 0, 0, 0], (2, 1)))  # overlaps by 15 ms
    s = score(truth, est)
    assert s.samples == 2 and s.eligible == 6000 and s.coverage == pytest.approx(2 / 6000)
    movement = t > 30.0  # "broad": coverage of the movement samples
    full = score(Trajectory(t, est.quat_wxyz), est, "broad", movement)
    assert full.samples == int(movement.sum()) and full.coverage == 1.0


def test_low_coverage_row_is_flagged_warned_and_left_out_of_the_means(tmp_path, capsys):
    lab = tmp_path / "lab"
    lab.mkdir()
    write_csv(lab / "a.csv")
    write_csv(lab / "b.csv", truth_rows=3)  # truth covers 20 ms of 60 s: 2 of 6000 samples
    out = tmp_path / "run"
    code, text, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "all", "--data-dir", str(lab),
                          "--no-progress", "--jobs", "1", "--json", str(tmp_path / "r.json"), "--out", str(out))
    assert code == 0, err
    rows = {line.split()[0]: line for line in text.splitlines() if line.startswith(("lab/", "a", "b", "mean"))}
    low = [line for line in text.splitlines() if " LOW" in line and "dr" in line]
    assert len(low) == 1 and "0.0% LOW" in low[0] and low[0].split()[0].endswith("b")
    assert [line for line in text.splitlines() if line.startswith("a ")][0].split()[2:5] == ["0.00"] * 3
    mean = [line for line in text.splitlines() if line.startswith("mean")]
    assert mean and mean[0].startswith("mean (1)"), rows
    assert "LOW: scored on less than 50%" in text
    warning = [line for line in err.splitlines() if "fusion: warning:" in line and "scored on 2 of" in line]
    assert len(warning) == 1 and "flagged and left out of the means" in warning[0]
    doc = json.loads((tmp_path / "r.json").read_text())
    by_id = {Path(r["dataset"]).name: r for r in doc["results"]}
    assert by_id["b"]["scored_samples"] == 2 and by_id["b"]["coverage"] == pytest.approx(2 / 6000)
    assert by_id["a"]["scored_samples"] == 6000 and by_id["a"]["coverage"] == 1.0
    html = (out / "report.html").read_text()
    assert "0.0% LOW" in html and "left out of the means" in html
    assert "<td>dr</td><td class=\"num\">1</td>" in html  # means table: 1 recording scored
    assert MIN_COVERAGE == 0.5


# --- calibration files -----------------------------------------------------------------------

def calib_doc(**overrides) -> dict:
    doc = {"format": "fusion-gyro-calibration", "version": 1, "gyro_scale_factor": [1.0, 1.0, 1.0],
           "clock_offset_s": {}, "info": {}}
    doc.update(overrides)
    return doc


@pytest.mark.parametrize("content, message", [
    (json.dumps(calib_doc(gyro_scale_factor=[True, 1.0, 1.0])), "'gyro_scale_factor' must be a list of 3 numbers (not booleans)"),
    (json.dumps(calib_doc(gyro_scale_factor=["1", 1.0, 1.0])), "'gyro_scale_factor' must be a list of 3 numbers"),
    (json.dumps(calib_doc(clock_offset_s={"sim": True})), "'clock_offset_s' must map"),
    (json.dumps(calib_doc(version=True)), "calibration file version True"),
    ("[" * 100_000 + "]" * 100_000, "JSON nested too deeply"),
    (b"\xff\xfe\x00{", "not UTF-8"),
])
def test_bad_calibration_file_is_one_line_naming_it(tmp_path, capsys, content, message):
    path = tmp_path / "calib.json"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    code, _, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "sim", "--no-progress", "--jobs", "1",
                       "--calibration", str(path))
    assert code == 1
    (line,) = err.strip().splitlines()
    assert line.startswith(f"fusion: error: {path}: ") and message in line


def test_calibration_not_applied_to_csv_is_said(tmp_path, capsys):
    csv = write_csv(tmp_path / "walk.csv", n=500)
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(calib_doc(gyro_scale_factor=[1.1, 1.0, 0.9])))
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", str(csv), "--no-progress", "--jobs", "1",
                         "--calibration", str(calib))
    assert code == 0, err
    warning = [line for line in err.splitlines() if "gyro scale factors not applied" in line]
    assert len(warning) == 1 and str(tmp_path / "walk") in warning[0] and str(calib) in warning[0]
    # and indeed not applied: the same numbers as without the file
    code, out2, _ = run(capsys, "compare", "--estimators", "dr", "--dataset", str(csv), "--no-progress", "--jobs", "1")
    assert [ln for ln in out.splitlines() if "walk" in ln][0].split()[2:5] == \
        [ln for ln in out2.splitlines() if "walk" in ln][0].split()[2:5]


# --- numerical failures inside an estimator ------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("spec", ["ekf:Q=1e308", "gn:R=1e-300", "ukf:R=1e308"])
def test_overflowing_parameters_are_one_line_naming_spec_and_recording(capsys, spec):
    code, _, err = run(capsys, "compare", "--estimators", spec, "--dataset", "sim", "--no-progress", "--jobs", "1")
    assert code == 1
    (line,) = err.strip().splitlines()
    assert line.startswith(f"fusion: error: sim: estimator {spec!r} ") and "check its parameter values" in line


# --- panorama bounds ---------------------------------------------------------------------------

@pytest.mark.parametrize("args, message", [
    (["--size", "100000x100000"], "exceeds 8192 x 4096"),
    (["--rate", "1e6"], "--rate 1000000.0 Hz: must be a frame rate in (0, 60] Hz"),
    (["--rate", "nan"], "--rate nan Hz"),
    (["--out", "p.txt"], "unsupported image extension '.txt'"),
])
def test_panorama_bounds(tmp_path, capsys, args, message):
    argv = ["panorama", "--dataset", "sim", "--estimator", "dr", "--no-progress", "--out", str(tmp_path / "p.png"), *args]
    code, _, err = run(capsys, *argv)
    assert code == 1
    (line,) = err.strip().splitlines()
    assert message in line
    assert not list(tmp_path.iterdir())


def test_rendered_frame_count_is_bounded():
    from fusion.evaluation.panorama import camsim

    truth = Trajectory(np.array([0.0, 3600.0]), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(ValueError, match="hour: 180000 frames at 50 Hz over 3600 s, more than 20000"):
        camsim.simulate_camera(truth, camsim.procedural_scene(64, 32), rate_hz=50, source="hour")
