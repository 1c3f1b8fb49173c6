"""What `compare --out` writes and what reads it back: the trajectories (`--trajectory NAME=DIR` takes
the folder as written, and a 9-D estimate is scored as 9-D again) and the per-sample series, both
as compact as the data allow."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.evaluation.report import render as report
from fusion.evaluation.run import series
from fusion.evaluation.run.job import run_one
from fusion.trajectory_files import read_trajectory, time_decimals, tum_metadata, write_tum

BROAD = "broad/10_undisturbed_slow_translation_A"


def rows_of(path: Path) -> dict[str, dict]:
    return {(r["dataset"], r["estimator"]): r for r in json.loads(Path(path).read_text())["results"]}


@pytest.fixture(scope="module")
def broad_run(data_dir, tmp_path_factory):
    """`compare --out --mag on` with ekf (9-D: the trial has a magnetometer) and ukf (6-D) on a BROAD trial and a
    course recording."""
    out = tmp_path_factory.mktemp("export") / "run"
    assert main(["compare", "--estimators", "ekf,ukf", "--mag", "on", "--dataset", f"{BROAD},ece276a/3", "--data-dir",
                 str(data_dir), "--no-progress", "--jobs", "1", "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_a_9d_export_reads_back_as_9d(broad_run, data_dir, tmp_path, capsys):
    """The header of an exported file says what it holds; a row NAME reads NAME.tum in the folder
    compare --out wrote (here a copy of ekf.tum beside the others) and scores as the 9-D row that
    wrote it (same RMSE to 1e-6 deg: no heading offset removed); with several estimates and no
    NAME.tum, the error lists them."""
    written = rows_of(broad_run / "results.json")
    ekf = written[(BROAD, "ekf")]
    assert ekf["magnetometer"] is True and written[(BROAD, "ukf")]["magnetometer"] is False
    assert json.loads((broad_run / "results.json").read_text())["recordings"][0] == {
        "dataset": BROAD, "protocol": "broad", "truth": "optical motion capture (BROAD)"}
    assert tum_metadata(broad_run / "trajectories" / BROAD / "ekf.tum") == {"estimator": "ekf", "recording": BROAD,
                                                                           "imu": "9-D"}
    assert tum_metadata(broad_run / "trajectories" / "ece276a/3" / "ukf.tum")["imu"] == "6-D"
    assert tum_metadata(broad_run / "trajectories" / BROAD / "truth.tum") == {
        "estimator": "truth", "recording": BROAD, "truth": "optical motion capture (BROAD)"}
    capsys.readouterr()
    assert main(["compare", "--estimators", "dr", "--trajectory", f"again={broad_run}", "--dataset", BROAD,
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1"]) == 1
    assert "no again.tum (it holds ekf.tum, ukf.tum); name the row after one of them" in capsys.readouterr().err
    copy = tmp_path / "copy" / "trajectories" / BROAD
    copy.mkdir(parents=True)
    for name in ("ekf.tum", "ukf.tum", "truth.tum"):
        (copy / name).write_bytes((broad_run / "trajectories" / BROAD / name).read_bytes())
    (copy / "before.tum").write_bytes((copy / "ekf.tum").read_bytes())
    assert main(["compare", "--estimators", "dr", "--trajectory", f"before={tmp_path / 'copy'}", "--dataset", BROAD,
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1", "--json", str(tmp_path / "b.json")]) == 0
    before = rows_of(tmp_path / "b.json")[(BROAD, "before")]
    assert before["magnetometer"] is True
    for kind in ("total", "inclination", "heading"):
        assert before["rmse_deg"][kind] == pytest.approx(ekf["rmse_deg"][kind], abs=1e-6)
    assert before["scored_samples"] == ekf["scored_samples"]


@pytest.mark.slow
def test_a_run_folder_of_one_estimator_is_a_trajectory_folder(data_dir, tmp_path, capsys):
    """compare --out with one estimator; --trajectory NAME=DIR reads each recording's one estimate,
    the 9-D BROAD one as 9-D, the course one as 6-D: the same numbers as the rows that wrote them."""
    out = tmp_path / "ekf-run"
    assert main(["compare", "--estimators", "ekf", "--dataset", f"{BROAD},ece276a/3", "--data-dir", str(data_dir),
                 "--no-progress", "--jobs", "1", "--out", str(out)]) == 0
    for folder in (out, out / "trajectories"):
        json_path = tmp_path / "back.json"
        assert main(["compare", "--estimators", "dr", "--trajectory", f"before={folder}", "--dataset",
                     f"{BROAD},ece276a/3", "--data-dir", str(data_dir), "--no-progress", "--jobs", "1", "--json",
                     str(json_path)]) == 0
        written, back = rows_of(out / "results.json"), rows_of(json_path)
        for rid in (BROAD, "ece276a/3"):
            assert back[(rid, "before")]["magnetometer"] == written[(rid, "ekf")]["magnetometer"] == (rid == BROAD)
            assert back[(rid, "before")]["rmse_deg"]["total"] == pytest.approx(written[(rid, "ekf")]["rmse_deg"]["total"],
                                                                               abs=1e-6)
    capsys.readouterr()
    (out / "trajectories" / BROAD / "ekf.tum").unlink()
    assert main(["compare", "--estimators", "dr", "--trajectory", f"before={out}", "--dataset", BROAD,
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1"]) == 1
    assert "no before.tum (it holds no estimate)" in capsys.readouterr().err


@pytest.mark.slow
def test_the_exported_files_carry_the_datas_precision(broad_run, data_dir):
    """BROAD's stamps are 3.5 ms steps from 0: written with 4 decimals, as they are; the course's Unix stamps
    to the microsecond; quaternions to 1e-7; a file a third the size of full precision."""
    from fusion import datasets

    path = broad_run / "trajectories" / BROAD / "ekf.tum"
    lines = path.read_text().splitlines()
    assert lines[0] == f"# fusion: estimator=ekf recording={BROAD} imu=9-D" and lines[1].startswith("# t tx ty tz")
    first = lines[2].split()
    assert len(first[0].split(".")[1]) == 4 and first[1:4] == ["0", "0", "0"]
    assert all(len(v.split(".")[1]) == 7 for v in first[4:])
    rec = datasets.load(BROAD, data_dir)
    back = read_trajectory(path)
    np.testing.assert_allclose(back.t, rec.imu.t, rtol=0, atol=1e-12)  # the stamps, to a double's rounding
    course = (broad_run / "trajectories" / "ece276a/3" / "ekf.tum").read_text().splitlines()[2].split()
    assert len(course[0].split(".")[1]) == 6
    estimate = run_one(rec, "ekf").trajectory.quat_wxyz  # the full-precision estimate the file was written from
    np.testing.assert_allclose(back.quat_wxyz, estimate, rtol=0, atol=1e-7)
    full = path.with_name("full.tum")
    write_tum(full, rec.imu.t, estimate)
    assert os.path.getsize(path) < 0.6 * os.path.getsize(full)


def test_time_decimals_follow_the_stamps():
    assert time_decimals(np.arange(10) * 0.0035) == 4
    assert time_decimals(1.29e9 + np.array([0.123456, 0.133457])) == 6
    assert time_decimals(1.29e9 + np.arange(10) * 0.0101) == 4
    assert time_decimals(np.array([0.1, 1 / 3])) == 6  # no decimal resolution of its own: 1 us
    assert time_decimals(np.array([12.5, 13.0])) == 1
    assert time_decimals(np.empty(0)) == 0


# --- series ---

@pytest.mark.slow
def test_series_are_compact_and_read_back(broad_run, tmp_path):
    """The series keep the times and the filters' beliefs exactly (float32, as before) and the plot
    arrays to float16, in a fraction of the plain arrays' size; a file written before this encoding
    reads as it was; an unknown encoding is one line naming the file."""
    path = broad_run / "series" / "000.npz"
    s = series.load(path)
    assert s.id == BROAD and s.imu_t.dtype == np.float64 and s.quat.dtype == np.float32
    plain = tmp_path / "plain.npz"
    _save_plain(plain, s)  # as the previous version wrote it
    old = series.load(plain)
    np.testing.assert_array_equal(old.imu_t, s.imu_t)
    np.testing.assert_array_equal(old.quat, s.quat)
    np.testing.assert_array_equal(old.beliefs[1].sigma_rad, s.beliefs[1].sigma_rad)
    assert os.path.getsize(path) < 0.5 * os.path.getsize(plain)
    again = tmp_path / "again.npz"
    series.save(again, old)
    back = series.load(again)
    np.testing.assert_array_equal(back.truth_t, s.truth_t)
    for attr in ("err_rad", "sigma_rad", "nees", "nis", "updated", "bias_rad_s"):
        np.testing.assert_array_equal(getattr(back.beliefs[1], attr), getattr(s.beliefs[1], attr))
    with np.load(again) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["encoding"] = np.array("something-newer")
    np.savez(again, **arrays)
    with pytest.raises(ValueError, match=r"again.npz: not a readable series file .*series encoding 'something-newer'"):
        report.check_series(again)


def test_float16_plot_arrays_and_exact_times(tmp_path):
    rng = np.random.default_rng(1)
    n = 500
    t = 1.3e9 + np.cumsum(rng.uniform(0.009, 0.011, n))
    quat = rng.normal(size=(2, n, 4)).astype(np.float32)
    quat /= np.linalg.norm(quat, axis=2, keepdims=True)
    err = np.abs(rng.normal(size=(2, 3, n)) * 5).astype(np.float32)
    err[:, :, :10] = np.nan
    truth = rng.normal(size=(n, 4))
    truth[100:120] = np.nan
    s = series.RecordingSeries("x/1", t, np.ones(n, bool), t + 0.5, truth, ["a", "b"], [True, False], quat, err)
    series.save(tmp_path / "s.npz", s)
    back = series.load(tmp_path / "s.npz")
    np.testing.assert_array_equal(back.imu_t, t)
    np.testing.assert_array_equal(back.truth_t, t + 0.5)
    np.testing.assert_array_equal(back.quat, quat.astype(np.float16).astype(np.float32))
    np.testing.assert_allclose(back.err_deg, err, rtol=1e-3, equal_nan=True)
    np.testing.assert_allclose(back.truth_quat, truth, rtol=1e-3, atol=1e-4, equal_nan=True)
    assert back.labels == ["a", "b"] and back.causal == [True, False]


def test_flags_and_events_are_kept_compactly_and_older_files_read_without_them(tmp_path):
    """Per-sample flags are stored as packed bits (N/8 bytes each) and read back exactly; the
    recording's events as spans; a file written before either was kept reads with none."""
    n = 1001
    t = 1.3e9 + 0.01 * np.arange(n)
    quat = np.tile(np.array([1, 0, 0, 0], np.float32), (2, n, 1))
    err = np.zeros((2, 3, n), np.float32)
    rng = np.random.default_rng(2)
    rest = rng.random(n) < 0.3
    flags = {0: {"rest_detected": rest, "mag_disturbance_detected": ~rest}, 1: {"accelerometer_ignored": rest[::-1].copy()}}
    events = {"rest": [(0.0, 2.5), (8.0, 10.0)], "gyro freeze": [(4.0, 5.5)]}
    s = series.RecordingSeries("x/1", t, np.ones(n, bool), t, quat[0], ["vqf", "fusion-ahrs"], [True, True], quat, err,
                               flags=flags, events=events)
    path = tmp_path / "s.npz"
    series.save(path, s)
    back = series.load(path)
    assert back.events == events
    assert set(back.flags) == {0, 1} and set(back.flags[0]) == {"rest_detected", "mag_disturbance_detected"}
    for e, mine in flags.items():
        for name, flag in mine.items():
            assert back.flags[e][name].dtype == bool
            np.testing.assert_array_equal(back.flags[e][name], flag)
    with np.load(path) as z:
        assert z["flag_0_rest_detected"].shape == ((n + 7) // 8,)
        arrays = {k: z[k] for k in z.files if not k.startswith(("flag_", "event_"))}
    np.savez(tmp_path / "older.npz", **arrays)  # as written before flags and events were kept
    older = series.load(tmp_path / "older.npz")
    assert older.flags == {} and older.events is None
    np.testing.assert_array_equal(older.imu_t, t)


def test_flags_of_an_estimate_its_bool_diagnostics_and_the_scale_tests_decision():
    """`flags_of`: every (N,) bool diagnostic that is on at least once, but those a filter's belief
    holds (rest, guard); the scale test's decision on from the sample where its frozen ln L begins."""
    from fusion.types import Trajectory

    n = 50
    t = np.arange(n) * 0.01
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    used = np.zeros(n, bool)
    used[10:20] = True
    llr = np.r_[np.linspace(0.0, 2.0, 30), np.full(n - 30, 2.5)]  # decided at sample 30: frozen from then on
    d = {"mag_used": used, "mag_hard_iron": np.zeros(n, bool), "at_rest": used, "bias_guarded": used,
         "nis": np.ones(n), "scale_llr": llr, "scale_decision": 1, "scale_released": np.ones(3, bool)}
    flags = series.flags_of(Trajectory(t, quat, diagnostics=d))
    assert sorted(flags) == ["at_rest", "bias_guarded", "mag_used", "scale_error_accepted"]  # no covariance here
    np.testing.assert_array_equal(flags["scale_error_accepted"], np.arange(n) >= 30)
    np.testing.assert_array_equal(flags["mag_used"], used)
    with_cov = {**d, "cov": np.tile(np.eye(3), (n, 1, 1)), "scale_decision": -1}
    flags = series.flags_of(Trajectory(t, quat, diagnostics=with_cov))
    assert sorted(flags) == ["gyro_calibrated_accepted", "mag_used"]  # rest and guard: in its Belief
    undecided = series.flags_of(Trajectory(t, quat, diagnostics={**d, "scale_decision": 0}))
    assert "scale_error_accepted" not in undecided


def _save_plain(path: Path, s: series.RecordingSeries) -> None:
    """A series file as the version before the encoding wrote it: plain arrays, np.savez."""
    arrays = dict(id=np.array(s.id), imu_t=s.imu_t, gyr_valid=s.gyr_valid, truth_t=s.truth_t, truth_quat=s.truth_quat,
                  labels=np.array(s.labels, dtype=str), causal=np.array(s.causal, bool), quat=s.quat, err_deg=s.err_deg)
    arrays.update({f"loss_{e}": v for e, v in s.losses.items()})
    for e, belief in s.beliefs.items():
        for key, attr, dtype in series._BELIEF_ARRAYS:
            value = getattr(belief, attr)
            if value is not None:
                arrays[f"belief_{e}_{key}"] = np.asarray(value, dtype=dtype)
    np.savez(path, **arrays)
