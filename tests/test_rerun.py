"""`fusion compare --rerun FILE.rrd` (`fusion.evaluation.report.rerun_log`): the file is read back with
Rerun's own reader (`rerun.chunk.RrdReader`) and holds every entity with the samples it should,
the truth's quaternions (reordered to Rerun's x y z w) to 1e-6, the estimates on the IMU's stamps,
the events and every estimator's flags as steps (read back per sample: the estimator's own); without the `viz` extra, `--rerun` says what to install."""
from __future__ import annotations

import importlib.util
from collections import defaultdict

import numpy as np
import pytest

from fusion import datasets
from fusion.cli import main
from fusion.evaluation import runs
from optional_helpers import require_module
from report_fixtures import recording, sim_with_events, toy, write_csv_dataset  # noqa: F401 (toy is a fixture)

N = 300  # samples of each toy recording (3 s at 100 Hz); truth gap over samples 200-230


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_csv_dataset(tmp_path_factory.mktemp("data"), count=2, n=N)


def read_back(path) -> dict[str, dict]:
    """Entity path -> {"time": (K,) int64 ns, component name -> list of rows} over the file's
    temporal chunks (rows of several chunks of one entity concatenated in time order); static
    components under "static"."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    out: dict[str, dict] = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        entity = out[chunk.entity_path]
        for name in batch.schema.names:
            if name.startswith("rerun.controls"):
                continue
            column = batch.column(name)
            if name in ("time", "iteration"):
                entity[name].extend(column.cast(pa.int64()).to_pylist())
            else:
                entity["static" if chunk.is_static else "temporal"].append(name)
                entity[name].extend(column.to_pylist())
    for entity in out.values():  # chunks may come in any order: sort each entity's rows by time
        if entity.get("time"):
            order = np.argsort(entity["time"], kind="stable")
            for name, rows in entity.items():
                if name not in ("static", "temporal") and len(rows) == len(order):
                    entity[name] = [rows[i] for i in order]
    return {name: dict(entity) for name, entity in out.items()}


def quats(entity: dict) -> np.ndarray:
    """(K, 4) quat_wxyz of a Transform3D entity (Rerun stores x y z w)."""
    xyzw = np.array([row[0] for row in entity["Transform3D:quaternion"]], float)
    return xyzw[:, [3, 0, 1, 2]]


def scalars(entity: dict) -> np.ndarray:
    """(K,) or (K, C) values of a Scalars entity."""
    values = np.array(entity["Scalars:scalars"], float)
    return values[:, 0] if values.ndim == 2 and values.shape[1] == 1 else values


def seconds(entity: dict) -> np.ndarray:
    return np.asarray(entity["time"], np.int64) / 1e9


@pytest.fixture(scope="module")
def written(toy, data, tmp_path_factory):
    """One compare run (ekf: beliefs; toysmooth: a cost per iteration) written with --rerun, with
    an output folder (the journal's parts) and without (parts in memory)."""
    require_module("rerun")
    tmp = tmp_path_factory.mktemp("rrd")
    out = {}
    for name, options in (("memory", {}), ("folder", {"out": tmp / "run"})):
        run = runs.run_compare("ekf,toysmooth", "all", data, jobs=1, rerun=tmp / f"{name}.rrd", **options)
        out[name] = (run, read_back(tmp / f"{name}.rrd"))
    return out


@pytest.mark.parametrize("kind", ["memory", "folder"])
def test_every_entity_holds_its_samples_and_the_truth_to_1e_6(written, data, kind):
    run, rrd = written[kind]
    for rec in (datasets.load(f"lab/rec{k}", data) for k in (1, 2)):
        root = "/" + rec.id
        t0 = rec.imu.t[0]
        valid = rec.truth.valid
        truth = rrd[f"{root}/world/truth/body"]
        assert len(truth["time"]) == valid.sum() == N - 30
        np.testing.assert_allclose(quats(truth), rec.truth.quat_wxyz[valid], rtol=0, atol=1e-6)
        np.testing.assert_allclose(seconds(truth), rec.truth.t[valid] - t0, rtol=0, atol=1e-9)
        for label in ("ekf", "toysmooth"):
            body = rrd[f"{root}/world/{label}/body"]
            assert len(body["time"]) == N
            np.testing.assert_allclose(seconds(body), rec.imu.t - t0, rtol=0, atol=1e-9)
            row = next(r for r in run.results if r.dataset == rec.id and r.estimator == label)
            for kind_name in ("total", "inclination", "heading"):
                err = rrd[f"{root}/error/{kind_name}/{label}"]
                assert len(err["time"]) == row.scored_samples  # the scored samples, no others
            # its RMSE, recomputed from the series in the file (float32 there), is the table's
            total = scalars(rrd[f"{root}/error/total/{label}"])
            assert np.sqrt(np.mean(total ** 2)) == pytest.approx(row.rmse_deg["total"], rel=1e-4)
            # the slot beside the truth: the body's frame is moved, not rotated
            assert "Transform3D:translation" in rrd[f"{root}/world/{label}"]["static"]
        for axis_entity, values in (("imu/gyro_deg_s", np.degrees(rec.imu.gyr_rad_s)), ("imu/acc_g", rec.imu.acc_g)):
            np.testing.assert_allclose(scalars(rrd[f"{root}/{axis_entity}"]), values, rtol=1e-6, atol=1e-6)
        assert f"{root}/imu/mag_ut" not in rrd  # no magnetometer in these recordings
        assert len(rrd[f"{root}/beliefs/ekf/sigma_deg"]["time"]) == N
        assert np.all(scalars(rrd[f"{root}/beliefs/ekf/sigma_deg"]) > 0)
        assert f"{root}/beliefs/toysmooth/sigma_deg" not in rrd  # no covariance: no beliefs
        assert scalars(rrd[f"{root}/cost/toysmooth"]) == pytest.approx(100.0 * 0.5 ** np.arange(12), rel=1e-12)
        # the truth's gap (samples 200-229 NaN) is an event: 1 from its start to its end, 0 elsewhere
        gap = rrd[f"{root}/events/no_truth"]
        np.testing.assert_allclose(seconds(gap), [0.0, rec.truth.t[200] - t0, rec.truth.t[229] - t0,
                                                  rec.imu.t[-1] - t0], atol=1e-9)
        assert scalars(gap).tolist() == [0.0, 1.0, 0.0, 0.0]
        assert any("no truth" in text[0] for text in rrd[f"{root}/events/log"]["TextLog:text"])
        # camera frames rendered with the truth every 0.5 s over its span, none inside its gap
        grid = rec.truth.t[0] - t0 + 0.5 * np.arange(10)
        grid = grid[(grid <= rec.truth.t[-1] - t0) & ~((grid > rec.truth.t[199] - t0) & (grid < rec.truth.t[230] - t0))]
        np.testing.assert_allclose(seconds(rrd[f"{root}/world/truth/body/camera"]), grid, atol=1e-6)
        assert len(grid) == 5
        assert rrd[f"{root}/world/truth/body/camera"]["EncodedImage:media_type"][0] == ["image/jpeg"]


def test_with_and_without_an_output_folder_the_files_agree(written):
    (_, memory), (_, folder) = written["memory"], written["folder"]
    temporal = sorted(k for k, v in memory.items() if v.get("time"))
    assert temporal == sorted(k for k, v in folder.items() if v.get("time"))
    for entity in temporal:
        assert memory[entity]["time"] == folder[entity]["time"], entity


def test_flags_switches_are_steps():
    from fusion.evaluation.report.rerun_log import event_steps, flag_steps

    x = np.arange(8) * 0.1
    t, v = flag_steps(x, np.array([0, 0, 1, 1, 1, 0, 1, 1], bool))
    assert t.tolist() == pytest.approx([0.0, 0.2, 0.5, 0.6, 0.7]) and v.tolist() == [0.0, 1.0, 0.0, 1.0, 1.0]
    t, v = flag_steps(x, np.ones(8, bool))
    assert t.tolist() == pytest.approx([0.0, 0.7]) and v.tolist() == [1.0, 1.0]
    t, v = flag_steps(x, np.array([0, 0, 0, 0, 0, 0, 0, 1], bool))  # switched on at the last sample
    assert t.tolist() == pytest.approx([0.0, 0.7]) and v.tolist() == [0.0, 1.0]
    t, v = event_steps([(0.0, 0.3), (0.5, 0.7)], end=0.7)  # on from the start; off at the end
    assert t.tolist() == pytest.approx([0.0, 0.0, 0.3, 0.5, 0.7]) and v.tolist() == [0.0, 1.0, 0.0, 1.0, 0.0]


def test_the_python_api_writes_whole_results_and_marks_the_invalid_gyro(toy, tmp_path):
    """`write_results` from `compare`'s whole results; the samples marked invalid for the
    estimators are the event `gyro_invalid`; a label with parameters is one entity (escaped)."""
    rr = require_module("rerun")
    from fusion.evaluation.compare import compare
    from fusion.evaluation.report.rerun_log import write_results

    rec = recording(N, bad_gyro=(100, 140), rid="toy/1")
    results = compare("dr,toy:g=1.05", [rec])
    path = write_results(tmp_path / "api.rrd", [rec], results, camera_hz=0)
    rrd = read_back(path)
    t = rec.imu.t - rec.imu.t[0]
    event = rrd["/toy/1/events/gyro_invalid"]
    np.testing.assert_allclose(seconds(event), [0.0, t[100], t[140], t[-1]], atol=1e-9)
    assert scalars(event).tolist() == [0.0, 1.0, 0.0, 0.0]
    np.testing.assert_allclose(quats(rrd["/toy/1/world/dr/body"]), results[0].trajectory.quat_wxyz, atol=1e-6)
    toy_entity = f"/toy/1/world/{rr.escape_entity_path_part('toy:g=1.05')}/body"
    np.testing.assert_allclose(quats(rrd[toy_entity]), results[1].trajectory.quat_wxyz, atol=1e-6)
    assert rrd[f"/toy/1/world/{rr.escape_entity_path_part('toy:g=1.05')}/body"]["Boxes3D:labels"] == [["toy:g=1.05"]]
    assert "/toy/1/world/truth/body/camera" not in rrd  # camera_hz=0: no frames


def test_without_the_extra_rerun_says_what_to_install_before_any_work(toy, data, tmp_path, monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rerun" else real(name, *a))
    ran = []
    monkeypatch.setattr(runs, "run", lambda *a, **k: ran.append(1))
    code = main(["compare", "--estimators", "toy", "--dataset", "all", "--data-dir", str(data), "--no-progress",
                 "--rerun", str(tmp_path / "x.rrd")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "pip install 'fusion[viz]'" in err[0]
    assert not ran and not (tmp_path / "x.rrd").exists()


@pytest.mark.parametrize("name, problem", [("x.json", "must end in .rrd"), ("missing/x.rrd", "does not exist")])
def test_a_bad_file_name_is_one_line_before_any_work(toy, data, tmp_path, monkeypatch, capsys, name, problem):
    require_module("rerun")
    ran = []
    monkeypatch.setattr(runs, "run", lambda *a, **k: ran.append(1))
    code = main(["compare", "--estimators", "toy", "--dataset", "all", "--data-dir", str(data), "--no-progress",
                 "--rerun", str(tmp_path / name)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and problem in err[0] and not ran


@pytest.fixture(scope="module")
def sim_run():
    """ekf and VQF on a short simulated recording with rests and a gyro freeze (`sim_with_events`)."""
    require_module("vqf")
    from fusion.evaluation.compare import compare

    rec = sim_with_events()
    return rec, compare("ekf,vqf", [rec])


def test_every_flag_is_written_and_reads_back_sample_for_sample(sim_run, tmp_path):
    """Each estimator's per-sample flags (`series.flags_of`: VQF's rest detection, the ekf's use of
    the low-passed accelerometer) are steps under beliefs/<estimator>/flags/<name>: one row at the
    first sample, one per switch and one at the last; the step value at every IMU stamp is the flag."""
    require_module("rerun")
    from fusion.evaluation.run import series
    from fusion.evaluation.report.rerun_log import write_results

    rec, results = sim_run
    rrd = read_back(write_results(tmp_path / "flags.rrd", [rec], results, camera_hz=0))
    x = rec.imu.t - rec.imu.t[0]
    written = set()
    for r in results:
        for name, flag in series.flags_of(r.trajectory).items():
            entity = rrd[f"/sim/events/beliefs/{r.estimator}/flags/{name}"]
            t, v = seconds(entity), scalars(entity)
            switches = np.flatnonzero(flag[1:] != flag[:-1]) + 1
            assert len(t) == len(switches) + 2 - (switches[-1] == len(flag) - 1 if len(switches) else 0)
            per_sample = v[np.searchsorted(t, x + 1e-7, side="right") - 1].astype(bool)  # +1e-7 s: ns rounding
            assert len(per_sample) == len(rec.imu) == len(flag)
            np.testing.assert_array_equal(per_sample, flag)
            written.add((r.estimator, name))
    assert {("vqf", "rest_detected"), ("ekf", "acc_lowpassed")} <= written
    # the ekf's scale test: its ln L at every sample where it runs (float32 in the series)
    llr = np.asarray(results[0].trajectory.diagnostics["scale_llr"], float)
    entity = rrd["/sim/events/beliefs/ekf/scale_llr"]
    assert np.isfinite(llr).sum() == len(entity["time"]) > 0.9 * len(rec.imu)
    np.testing.assert_allclose(scalars(entity), llr[np.isfinite(llr)], rtol=1e-6, atol=1e-7)
    # the recording's events, kept in the series, are the file's
    rest = rrd["/sim/events/events/rest"]
    (first, last) = series.events_of(rec)["rest"]
    np.testing.assert_allclose(seconds(rest), [0.0, 0.0, first[1], last[0], last[1]], atol=1e-6)
    assert scalars(rest).tolist() == [0.0, 1.0, 0.0, 1.0, 0.0]
    assert len(rrd["/sim/events/events/gyro_freeze"]["time"]) == 4
