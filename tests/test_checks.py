"""Sensor checks (`fusion inspect`), gyro calibration against VICON (`fusion calibrate`) and
its leave-one-out protocol."""
import json

import numpy as np
import pytest

from fusion import datasets, gyro_fit
from fusion.calibration import calibrate
from fusion.checks import check_recording
from fusion.cli import main
from fusion.sim import SimSettings, simulate
from fusion.types import Recording

# From ../shared/data/README.md: gyro freezes, seconds after the first sample.
FREEZES_S = {1: (8.6, 9.8), 2: (8.6, 10.1), 4: (6.3, 9.1), 5: (5.1, 6.8), 8: (29.5, 32.4), 9: (7.1, 9.9)}
SCALE_RATIO = (1.09, 1.04, 0.96)


def sim_recording(rid="simx", **changes):
    settings = SimSettings(**{"duration_s": 60.0, **changes})
    raw, truth = simulate(settings)
    calib = calibrate(raw)
    return Recording(rid, datasets.calibrated_samples(raw, calib, True), truth, raw, calib)


def test_injected_faults_are_reported_with_times_and_sizes():
    rec = sim_recording(freezes_s=((20.0, 21.5),), truth_clock_offset_s=0.015)
    check = check_recording(rec)
    (freeze,) = check.freezes
    assert freeze.interval.start_s == pytest.approx(20.0, abs=0.1)
    assert freeze.interval.stop_s == pytest.approx(21.5, abs=0.1)
    np.testing.assert_allclose(freeze.level_counts, SimSettings().freeze_counts, atol=1.0)
    assert check.vicon.clock.offset_s == pytest.approx(0.015, abs=0.002)
    # the freeze is what the estimators are told to skip
    t = rec.imu.t - rec.imu.t[0]
    inside = (t > 20.1) & (t < 21.4)
    assert not rec.imu.gyr_valid[inside].any() and rec.imu.gyr_valid[t < 19].all()


def test_saturation_is_reported():
    check = check_recording(sim_recording(motion_scale=2.5))
    assert sum(check.range.beyond_nominal_samples) > 0
    assert check.range.saturated_samples > 0
    assert max(check.range.max_abs_deg_s) > 300


def test_calibrate_recovers_injected_scales():
    fit = gyro_fit.fit_recordings([sim_recording()])
    np.testing.assert_allclose(fit.sensitivity_ratio, SCALE_RATIO, rtol=0.005)


def test_leave_one_out_never_fits_on_the_scored_recording():
    """Three recordings share the board's scales; one has a wildly different gyro. Its own fold
    must not see it, and every other fold must be pulled by it."""
    odd = sim_recording("odd", gyro_sensitivity_ratio=(1.3, 1.3, 1.3), seed=3)
    recs = [sim_recording(f"r{i}", seed=i) for i in range(2)] + [odd]
    folds = dict(gyro_fit.leave_one_out(recs))
    np.testing.assert_allclose(folds["odd"].sensitivity_ratio, SCALE_RATIO, rtol=0.005)
    assert folds["odd"].fitted_on == ["r0", "r1"]
    for rid in ("r0", "r1"):
        assert "odd" in folds[rid].fitted_on and rid not in folds[rid].fitted_on
        assert folds[rid].sensitivity_ratio[0] > 1.12  # the odd one moved the fit


@pytest.mark.parametrize("n", range(1, 10))
def test_real_recordings_freezes_and_gaps(data_dir, n):
    check = check_recording(datasets.load(f"ece276a/{n}", data_dir))
    found = [(f.interval.start_s, f.interval.stop_s) for f in check.freezes]
    if n in FREEZES_S:
        assert len(found) == 1
        np.testing.assert_allclose(found[0], FREEZES_S[n], atol=0.1)
    else:
        assert found == []
    if n in (6, 7):
        assert 100 < check.vicon.missing_samples < 200 and check.vicon.gaps
    else:
        assert check.vicon.missing_samples == 0
    # VICON lags the IMU by -5 to +21 ms with each gyro reading stamped at its interval's midpoint
    # (recording 8 -4.8 ms, recording 1 +20.8 ms; 5 ms more, the README's 3-24 ms, stamped at t[k])
    assert -0.008 < check.vicon.clock.offset_s < 0.025


def test_inspect_and_calibrate_cli(data_dir, tmp_path, capsys):
    code = main(["inspect", "--dataset", "ece276a/4", "--data-dir", str(data_dir), "--no-progress",
                 "--json", str(tmp_path / "i.json")])
    out = capsys.readouterr().out
    assert code == 0 and "gyro freezes (s)       6.3" in out
    doc = json.loads((tmp_path / "i.json").read_text())
    assert doc["recordings"][0]["id"] == "ece276a/4"
    calib = tmp_path / "calib.json"
    code = main(["calibrate", "--dataset", "ece276a/[1-3]", "--data-dir", str(data_dir), "--no-progress", "--out", str(calib)])
    assert code == 0
    ratio = 1 / np.array(gyro_fit.read(calib).gyro_scale_factor)
    np.testing.assert_allclose(ratio, SCALE_RATIO, atol=0.03)  # the README's +9 %, +4 %, -4 %
    # applying the file changes the numbers of every command
    main(["compare", "--estimators", "dr", "--dataset", "ece276a/3", "--data-dir", str(data_dir), "--no-progress",
          "--json", str(tmp_path / "a.json")])
    main(["compare", "--estimators", "dr", "--dataset", "ece276a/3", "--data-dir", str(data_dir), "--no-progress",
          "--json", str(tmp_path / "b.json"), "--calibration", str(calib)])
    a, b = (json.loads((tmp_path / f).read_text())["results"][0]["rmse_deg"]["total"] for f in ("a.json", "b.json"))
    assert b < a


def test_inspect_prints_the_gyro_bias_after_calibration_and_the_zero_rate_level_apart(data_dir):
    """The bias the estimators see, in deg/s after calibration (a few deg/s at most; the course's
    calibration removes the first rest's level, so about 0 there), and apart from it, labelled, the
    zero-rate level in counts that the calibration removed; BROAD, in physical units, gets its rests
    and its bias too (about 0.2 deg/s, the data README's figure)."""
    from fusion.checks import format_check

    check = check_recording(datasets.load("ece276a/1", data_dir))
    first = check.rests[0]
    text = format_check(check)
    (line,) = [l for l in text.splitlines() if l.strip().startswith("gyro bias ") and "drift" not in l]
    bias = np.array([float(v) for v in line.split("[", 1)[1].split("]", 1)[0].split(",")])
    assert np.all(np.abs(bias) < 3.0) and line.rstrip().endswith("after calibration)")
    np.testing.assert_allclose(bias, first.gyro_bias_deg_s, atol=0.006)
    (level,) = [l for l in text.splitlines() if l.strip().startswith("zero-rate level")]
    assert "[" + ", ".join(f"{v:.1f}" for v in first.gyro_mean_counts) + "] counts at the first rest" in level
    assert 300 < min(first.gyro_mean_counts) and max(first.gyro_mean_counts) < 420  # about 382 counts
    assert text.index("gyro bias ") < text.index("gyro bias drift")
    broad = check_recording(datasets.load("broad/01_undisturbed_slow_rotation_A", data_dir))
    assert broad.rests and broad.range is not None and broad.range.method == "flat tops"
    assert np.all(np.abs(broad.rests[0].gyro_bias_deg_s) < 1.0)
    assert "zero-rate level" not in format_check(broad) and "rests (s)" in format_check(broad)
