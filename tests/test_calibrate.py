"""Gyro calibration against VICON (`fusion.gyro_fit`, `fusion calibrate`) and its leave-one-out scoring."""
import json

import numpy as np
import pytest

from fusion import datasets, gyro_fit
from fusion.calibration import calibrate
from fusion.cli import main
from fusion.sim import SimSettings, simulate
from fusion.types import Recording


def sim_recording(rid, **kw):
    raw, truth = simulate(SimSettings(duration_s=50.0, **kw))
    calib = calibrate(raw)
    return Recording(rid, datasets.calibrated_samples(raw, calib), truth, raw, calib)


def test_fit_recovers_injected_scales_with_freeze_and_offset():
    ratio = (1.09, 1.04, 0.96)
    rec = sim_recording("a", gyro_sensitivity_ratio=ratio, freezes_s=((20.0, 22.0),), truth_clock_offset_s=0.02, seed=3)
    result = gyro_fit.fit_recordings([rec])
    np.testing.assert_allclose(result.sensitivity_ratio, ratio, rtol=0.005)
    np.testing.assert_allclose(result.gyro_scale_factor, 1 / np.array(ratio), rtol=0.005)
    assert result.clock_offset_s["a"] == pytest.approx(0.02, abs=0.002)
    assert max(abs(m) for m in result.misalignment_deg) < 0.2
    # the freeze is masked: without the mask the fit would see a wrong rate there
    assert result.samples < len(rec.imu) - 150


def test_applying_the_fit_makes_dead_reckoning_better():
    from fusion.estimators.dr import DeadReckoning
    from fusion.evaluation.scoring.metrics import score

    rec = sim_recording("a", gyro_sensitivity_ratio=(1.09, 1.04, 0.96), seed=4)
    fitted = gyro_fit.with_gyro_scale(rec, gyro_fit.fit_recordings([rec]).gyro_scale_factor)
    q0 = datasets.initial_orientation(rec, "truth")
    before = score(rec.truth, DeadReckoning().estimate(rec.imu, q0)).rmse_deg["total"]
    after = score(fitted.truth, DeadReckoning().estimate(fitted.imu, q0)).rmse_deg["total"]
    assert after < 0.2 * before


def test_leave_one_out_never_fits_on_the_scored_recording():
    normal = (1.09, 1.04, 0.96)
    odd = (1.5, 0.7, 1.3)  # wildly different: any leak into its own fold would show
    recs = [sim_recording(f"n{k}", gyro_sensitivity_ratio=normal, seed=10 + k) for k in range(3)]
    recs.append(sim_recording("odd", gyro_sensitivity_ratio=odd, seed=20))
    folds = dict(gyro_fit.leave_one_out(recs))
    assert set(folds) == {"n0", "n1", "n2", "odd"}
    for held, result in folds.items():
        assert held not in result.fitted_on and len(result.fitted_on) == 3
    np.testing.assert_allclose(folds["odd"].sensitivity_ratio, normal, rtol=0.005)
    # the other folds include the odd recording, so they are pulled away from the normal scales
    assert all(np.max(np.abs(np.subtract(folds[f"n{k}"].sensitivity_ratio, normal))) > 0.02 for k in range(3))


def test_calibration_file_round_trip_and_validation(tmp_path):
    rec = sim_recording("a", truth_clock_offset_s=0.01, seed=5)
    result = gyro_fit.fit_recordings([rec])
    path = tmp_path / "calib.json"
    gyro_fit.write(path, result, with_clock_offset=True)
    doc = json.loads(path.read_text())
    assert doc["format"] == gyro_fit.FORMAT and doc["version"] == 1
    loaded = gyro_fit.read(path)
    np.testing.assert_allclose(loaded.gyro_scale_factor, result.gyro_scale_factor)
    assert loaded.offset_for("a") == pytest.approx(0.01, abs=0.002) and loaded.offset_for("other") == 0.0
    doc["gyro_scale_factor"] = [1.0, -1.0, 1.0]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="plausible"):
        gyro_fit.read(path)
    path.write_text(json.dumps({"format": "something"}))
    with pytest.raises(ValueError, match="not a fusion-gyro-calibration"):
        gyro_fit.read(path)


def test_cli_calibrate_then_apply_on_sim(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "--dataset", "sim", "--out", "c.json", "--clock-offset", "--no-progress"]) == 0
    out = capsys.readouterr().out
    factor = json.loads((tmp_path / "c.json").read_text())["gyro_scale_factor"]
    np.testing.assert_allclose(factor, 1 / np.array(SimSettings().gyro_sensitivity_ratio), rtol=0.005)
    assert "(sensitivity vs nominal +9." in out and "clock offset sim: truth lags by" in out
    rows = {}
    for extra in ([], ["--calibration", "c.json"]):
        assert main(["compare", "--estimators", "dr", "--dataset", "sim", "--no-progress", *extra]) == 0
        line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("sim ")][0]
        rows[bool(extra)] = float(line.split()[2])
    assert rows[True] < 0.3 * rows[False]
    assert main(["compare", "--dataset", "sim", "--calibration", "missing.json", "--no-progress"]) == 1


def test_real_leave_one_out_scales(data_dir):
    recs = [datasets.load(f"ece276a/{n}", data_dir / "ece276a") for n in range(1, 10)]
    folds = gyro_fit.leave_one_out(recs)
    for held, result in folds:
        assert held not in result.fitted_on
        # the README: about +9 %, +4 %, -4 % vs nominal; measured +9.1, +5.6, -3.4 %
        np.testing.assert_allclose(result.sensitivity_ratio, (1.09, 1.055, 0.966), atol=0.01)


def test_leave_one_out_holds_out_a_recording_in_all_its_formats(data_dir, capsys):
    # ece276a/N and ese650/N are one session: a fold fitted on ese650/N would score ece276a/N
    # with a calibration fitted on itself; merged, each session is one fold
    assert main(["calibrate", "--leave-one-out", "--estimators", "dr", "--dataset", "ece276a,ese650",
                 "--data-dir", str(data_dir), "--no-progress"]) == 0
    out = capsys.readouterr().out
    held = [line.split()[0] for line in out.splitlines() if line.startswith(("ece276a/", "ese650/")) and "%," in line]
    assert held == [f"ece276a/{n}" for n in range(1, 10)]
    assert "fit on 9 recordings" in out
