"""`fusion stress`: every estimator under sensor faults on the one runner. End to end on small CSV
recordings (one with a magnetometer): the table, results.json's rows with their `fault`, the
dose-response (`stress`) and `robustness`, the figures, resume, an estimator failing on one cell,
the results independent of --jobs; and the summary against a hand computation."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.estimators.base import Estimator
from fusion.estimators.dr import DeadReckoning
from fusion.evaluation import runs
from fusion.evaluation.run import journal
from fusion.evaluation.sweeps import stress
from fusion.types import ImuSamples, Trajectory

from report_fixtures import recording
from test_journal import _stop_after


def write_dataset(root: Path) -> Path:
    """Two 6 s CSV recordings with truth under `root/lab/`: rec1 with a magnetometer, rec2 without."""
    folder = root / "lab"
    folder.mkdir(parents=True)
    for k in range(2):
        rec = recording(600, seed=k, gap=None)
        columns = [rec.imu.t, rec.imu.gyr_rad_s, rec.imu.acc_g * 9.80665, rec.truth.quat_wxyz]
        header = "t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz"
        if k == 0:
            columns.append(rec.truth.rotation().inv().apply([0.0, 20.0, -40.0]))
            header += ",mx,my,mz"
        lines = [header] + [",".join(f"{v:.12g}" for v in row) for row in np.column_stack(columns)]
        (folder / f"rec{k + 1}.csv").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("stress") / "data")


def _strip(rows, *keys):
    return [{k: v for k, v in r.items() if k not in ("seconds", *keys)} for r in rows]


def test_stress_end_to_end(data, tmp_path, capsys):
    out = tmp_path / "run"
    argv = ["stress", "--estimators", "dr,ekf", "--data-dir", str(data), "--fault", "gyro-bias-step=5,1",
            "--fault", "mag-hard-iron=20", "--fault", "jitter", "--mag", "on", "--jobs", "2", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert table.index("RMSE in degrees") < table.index("Dose-response") < table.index("Robustness")
    assert "gyro-bias-step (deg/s)  clean" in table and "jitter (ms)" in table and "mag-hard-iron (uT)" in table

    doc = json.loads((out / "results.json").read_text())
    rows = doc["results"]
    # rec1 (magnetometer): clean, 2 bias steps, 5 jitters, 1 hard iron; rec2: no hard iron; x 2 estimators
    assert len(rows) == 2 * (1 + 2 + 5 + 1) + 2 * (1 + 2 + 5)
    assert all(set(r["fault"]) == {"kind", "severity", "unit"} for r in rows)
    assert {r["dataset"] for r in rows if r["fault"]["kind"] == "mag-hard-iron"} == {"lab/rec1"}
    assert [(r["fault"]["kind"], r["fault"]["severity"]) for r in rows[:6]] == [
        ("none", 0.0), ("none", 0.0), ("gyro-bias-step", 1.0), ("gyro-bias-step", 1.0), ("gyro-bias-step", 5.0),
        ("gyro-bias-step", 5.0)]  # recording x fault (mildest first) x estimator
    assert doc["settings"]["kind"] == "stress"
    assert doc["settings"]["faults"] == {"gyro-bias-step": [1.0, 5.0], "jitter": [0.5, 1.0, 2.0, 5.0, 10.0],
                                         "mag-hard-iron": [20.0]}

    # the clean rows are compare's
    assert main(["compare", "--estimators", "dr,ekf", "--data-dir", str(data), "--jobs", "1", "--no-progress",
                 "--mag", "on", "--json", str(tmp_path / "c.json")]) == 0
    compare = json.loads((tmp_path / "c.json").read_text())
    assert _strip(stress.clean_rows(rows), "fault") == _strip(compare["results"])

    # the dose-response, by hand: mean over the recordings of each point
    (d,) = doc["stress"]["datasets"]
    assert [f["kind"] for f in d["faults"]] == ["gyro-bias-step", "jitter", "mag-hard-iron"]
    step = d["faults"][0]
    for e in step["estimators"]:
        for p in [e["clean"], *e["points"]]:
            kind = "none" if p is e["clean"] else "gyro-bias-step"
            mine = [r["rmse_deg"]["total"] for r in rows if r["estimator"] == e["estimator"]
                    and r["fault"]["kind"] == kind and r["fault"]["severity"] == p["severity"]]
            assert p["mean_deg"] == pytest.approx(np.mean(mine), rel=1e-12) and p["scored"] == 2
            assert p["ci95_deg"] is None  # two recordings: no interval (five needed)
    hard = d["faults"][2]["estimators"][1]  # ekf, on the one recording with a magnetometer
    assert hard["estimator"] == "ekf" and hard["recordings"] == 1 and hard["points"][0]["scored"] == 1
    # robustness: the mildest severity at which the mean doubles, else beyond the range
    robust = {(x["estimator"], x["fault"]): x for x in doc["robustness"]["entries"]}
    assert len(robust) == 6
    row = re.split(r"\s{2,}", next(line for line in table[table.index("Robustness"):].splitlines()
                                    if line.startswith("gyro-bias-step (deg/s)")).strip())
    for e, cell in zip(step["estimators"], row[1:], strict=True):  # a fault per row, an estimator per column
        x = robust[(e["estimator"], "gyro-bias-step")]
        hit = next((p["severity"] for p in e["points"] if p["mean_deg"] >= 2 * e["clean"]["mean_deg"]), None)
        assert x["breaks_at"] == hit and x["clean_deg"] == e["clean"]["mean_deg"]
        assert cell == (f"> {x['worst']:g}" if hit is None else f"{hit:g}")

    figures = sorted(p.name for p in (out / "figures").glob("stress-*.png"))
    assert figures == ["stress-gyro-bias-step.png", "stress-jitter.png", "stress-mag-hard-iron.png",
                       "stress-robustness.png"]
    page = (out / "report.html").read_text()
    assert "Robustness" in page and "stress-jitter.png" in page and "fusion stress" in page
    assert (out / "table.txt").read_text().strip() == table.strip()
    assert main(["report", str(out), "--no-progress", "--jobs", "1"]) == 0  # re-rendered from results.json alone
    assert (out / "table.txt").read_text().strip() == table.strip()


def test_results_do_not_depend_on_jobs(data):
    one = runs.run_stress("dr", "all", data, faults=["drops=0.2", "vibration=3"], jobs=1)
    two = runs.run_stress("dr", "all", data, faults=["drops=0.2", "vibration=3"], jobs=2)
    assert _strip(r.to_json() for r in one.results) == _strip(r.to_json() for r in two.results)
    assert len(one.results) == 2 * 3


def test_resume_continues_a_stopped_stress_run(data, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    faults = ["gyro-scale=2,20"]
    with monkeypatch.context() as mp:
        _stop_after(mp, 5)
        with pytest.raises(KeyboardInterrupt):
            runs.run_stress("dr,ekf", "all", data, faults=faults, out=out)
    assert len(journal.read(out / journal.RUN_DIR / journal.JOURNAL)[1]) == 5
    capsys.readouterr()
    assert main(["stress", "--resume", str(out), "--no-progress", "--jobs", "1"]) == 0
    captured = capsys.readouterr()
    assert "5 of 12 jobs done, 7 to run" in captured.err and "Robustness" in captured.out
    whole = runs.run_stress("dr,ekf", "all", data, faults=faults)
    doc = json.loads((out / "results.json").read_text())
    assert _strip(doc["results"]) == _strip(r.to_json() for r in whole.results)
    assert doc["robustness"]["entries"] == json.loads(json.dumps(stress.robustness(stress.stress_summary(
        [r.to_json() for r in whole.results]))))["entries"]


class Fragile(Estimator):
    """Dead reckoning that gives up (raises) when a gyro axis reads faster than 9 rad/s (516 deg/s)."""

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        if np.abs(imu.gyr_rad_s).max() > 9.0:
            raise ValueError("the gyro reads faster than this estimator copes with")
        return DeadReckoning().estimate(imu, init_quat_wxyz)


def test_an_estimator_that_fails_costs_its_cell_only(data, tmp_path, monkeypatch, capsys):
    from fusion import estimators

    monkeypatch.setitem(estimators.ESTIMATORS, "fragile", Fragile)
    out = tmp_path / "run"
    code = main(["stress", "--estimators", "fragile,dr", "--data-dir", str(data), "--fault", "gyro-scale=5,40",
                 "--out", str(out), "--jobs", "2", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err  # a failure under a fault is a result, not an error of the run
    doc = json.loads((out / "results.json").read_text())
    failed = [r for r in doc["results"] if r.get("error")]
    # the swings' peak rates per axis (`report_fixtures.motion`: 250 deg at 0.35 and 0.40 Hz about an axis whose
    # largest component is 0.81): 444 and 508 deg/s; x1.4 exceeds 516 deg/s on both, x1.05 only on rec2 (533)
    assert sorted((r["dataset"], r["fault"]["severity"]) for r in failed) == [
        ("lab/rec1", 40.0), ("lab/rec2", 5.0), ("lab/rec2", 40.0)]
    assert all(r["estimator"] == "fragile" and "faster than this estimator copes" in r["error"] for r in failed)
    assert all(r["rmse_deg"] for r in doc["results"] if not r.get("error"))  # every other cell scored
    assert "3 cells failed under a fault" in captured.err
    x = next(x for x in doc["robustness"]["entries"] if x["estimator"] == "fragile")
    assert (x["breaks_at"], x["failed"]) == (5.0, 1) and stress.robust_cell(x, unit=True) == "5 % (fails)"
    assert "x1" in captured.out and "x2" in captured.out


def test_bad_fault_options_are_one_line_errors(data, capsys):
    for words, message in ((["--fault", "gyro-bias=1"], "unknown fault 'gyro-bias'; available: gyro-bias-step"),
                           (["--fault", "drops=abc"], "expected KIND=L1,L2,... with numbers in s"),
                           (["--fault", "drops=20"], "must be below 10 s"),
                           (["--fault", "jitter=1", "--fault", "jitter=2"], "names jitter twice")):
        assert main(["stress", "--estimators", "dr", "--data-dir", str(data), *words, "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert stress.parse_fault("gyro-saturation=250,1000,500") == ("gyro-saturation", (1000.0, 500.0, 250.0))
    assert main(["stress", "--estimators", "dr", "--data-dir", str(data), "--dataset", "lab/rec2",
                 "--fault", "mag-dipole", "--no-progress"]) == 1  # rec2 has no magnetometer
    assert "no selected recording has a magnetometer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["stress", "--help"])
    text = capsys.readouterr().out
    assert "--fault KIND[=LEVELS]" in text and "mag-soft-iron    %              2, 5, 10, 20, 40" in text


def _row(dataset, estimator, kind, severity, total, error=None):
    return {"dataset": dataset, "estimator": estimator, "fault": {"kind": kind, "severity": severity},
            "rmse_deg": None if error else {"total": total, "inclination": total, "heading": total},
            "coverage": None if error else 1.0, **({"error": error} if error else {})}


def test_the_summary_and_robustness_against_a_hand_computation():
    """Two recordings x one estimator; a saturation (smaller is worse): the curve runs from the
    mildest range, breaks where the mean first doubles (not where it later dips), a failed cell is a
    breakdown, and a fault that never doubles is beyond the range."""
    rows = []
    for d, clean in (("x/1", 1.0), ("x/2", 3.0)):  # clean mean 2
        rows.append(_row(d, "e", "none", 0.0, clean))
        for sev, k in ((1000.0, 1.5), (500.0, 2.5), (250.0, 1.0)):  # means 3, 5 (>= 4: breaks), 2
            rows.append(_row(d, "e", "gyro-saturation", sev, clean * k))
        rows.append(_row(d, "e", "jitter", 1.0, clean * 1.2))
        rows.append(_row(d, "e", "drops", 0.1, clean, error="boom" if d == "x/2" else None))
    summary = stress.stress_summary(rows)
    (d,) = summary["datasets"]
    sat = next(f for f in d["faults"] if f["kind"] == "gyro-saturation")
    assert sat["severities"] == [1000.0, 500.0, 250.0] and sat["lower_is_worse"]
    (e,) = sat["estimators"]
    assert e["clean"]["mean_deg"] == 2.0 and [p["mean_deg"] for p in e["points"]] == [3.0, 5.0, 2.0]
    drops = next(f for f in d["faults"] if f["kind"] == "drops")["estimators"][0]["points"][0]
    assert (drops["mean_deg"], drops["scored"], drops["failed"]) == (1.0, 1, 1)
    robust = {x["fault"]: x for x in stress.robustness(summary)["entries"]}
    assert (robust["gyro-saturation"]["breaks_at"], robust["gyro-saturation"]["ratio"]) == (500.0, 2.5)
    assert robust["jitter"]["breaks_at"] is None and stress.robust_cell(robust["jitter"], unit=True) == "> 1 ms"
    assert robust["drops"]["breaks_at"] == 0.1 and robust["drops"]["failed"] == 1
    assert [f["kind"] for f in d["faults"]] == ["gyro-saturation", "drops", "jitter"]  # the registry's order


def test_rerun_holds_the_dose_response_and_the_faulted_sensors(data, tmp_path):
    from optional_helpers import require_module

    require_module("rerun")
    from test_rerun import read_back

    path = tmp_path / "stress.rrd"
    run = runs.run_stress("dr", "all", data, faults=["gyro-bias-step=1,5", "jitter=2"], rerun=path, jobs=1)
    back = read_back(path)
    summary = stress.stress_summary([r.to_json() for r in run.results])
    for f in summary["datasets"][0]["faults"]:
        (e,) = f["estimators"]
        entity = back[f"/stress/lab/{f['kind']}/dr"]
        assert entity["level"] == list(range(1 + len(f["severities"])))
        np.testing.assert_allclose([v[0] for v in entity["Scalars:scalars"]],
                                   [p["mean_deg"] for p in [e["clean"], *e["points"]]], rtol=1e-12)
        assert back[f"/stress/lab/{f['kind']}/levels"]["TextLog:text"][-1] == [
            f"level {len(f['severities'])}: {f['severities'][-1]:g} {f['unit']}"]
    # the first recording's gyro, clean and at the worst severity: the step's 5 deg/s in the second half
    clean = np.array(back["/sensors/gyro-bias-step/gyro_deg_s/clean"]["Scalars:scalars"])
    faulted = np.array(back["/sensors/gyro-bias-step/gyro_deg_s/faulted"]["Scalars:scalars"])
    step = np.linalg.norm(faulted - clean, axis=1)
    np.testing.assert_allclose(step[-100:], 5.0, rtol=1e-5)  # stored as float32
    assert step[:100].max() == 0.0
    assert len(back["/sensors/jitter/stamp_error_ms"]["Scalars:scalars"]) == 600


def test_a_stress_run_on_a_dask_cluster_gives_the_local_rows(data):
    """The faults are applied on the workers (`runner._dask_job`), from each recording loaded once."""
    from optional_helpers import require_module

    distributed = require_module("distributed")
    faults = ["gyro-bias-walk=0.05", "drops=0.3"]
    local = runs.run_stress("dr,ekf", "all", data, faults=faults, jobs=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        remote = runs.run_stress("dr,ekf", "all", data, faults=faults, scheduler=cluster.scheduler_address)
    assert _strip(r.to_json() for r in remote.results) == _strip(r.to_json() for r in local.results)
    assert {r.fault["kind"] for r in remote.results} == {"none", "gyro-bias-walk", "drops"}
