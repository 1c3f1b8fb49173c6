"""Several datasets in one run: each dataset's means apart and the "all datasets" line together
(`fusion.evaluation.compare.across_datasets`), in the printed table, results.json, the report and
an ablation's sweep; the stratified interval of a mean of means (`stats.mean_of_means_interval`);
`fusion tune` choosing on one dataset and scoring on another, aligned where its truth is in
other frames, its test scores per dataset."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
from scipy.spatial.transform import Rotation

from fusion import datasets
from fusion.cli import main
from fusion.evaluation.sweeps import ablate
from fusion.evaluation.compare import ACROSS, across_datasets, format_table, results_json
from fusion.evaluation.run.job import Result
from fusion.evaluation.scoring.stats import CI_METHOD, N_RESAMPLES, SEED, mean_of_means_interval, paired_statistics


def _results(sizes=(("broad", 6), ("ece276a", 5)), labels=("dr", "ekf"), seed: int = 0,
             missing: tuple[str, str] | None = None) -> list[Result]:
    """Rows of two folders; "dr" worse everywhere; the second folder 3 deg harder. `missing`:
    (folder, label) without rows."""
    rng = np.random.default_rng(seed)
    out = []
    for f, (folder, n) in enumerate(sizes):
        for j in range(n):
            for label in labels:
                if missing == (folder, label):
                    continue
                total = float((8.0 if label == "dr" else 2.0) + rng.gamma(2.0, 0.3) + 3.0 * f)
                rmse = {"total": total, "inclination": total / 3, "heading": total / 2}
                out.append(Result(f"{folder}/{j:02d}", label, 1000, 0.01, rmse, dict(rmse), scored_samples=1000,
                                  coverage=1.0, magnetometer=False))
    return out


def _folder_mean(results, folder, label, kind="total"):
    return np.mean([r.rmse_deg[kind] for r in results if r.estimator == label and r.dataset.startswith(folder + "/")])


# --- the interval ---

def test_one_sample_interval_is_the_rows_own():
    values = np.random.default_rng(1).gamma(2.0, 1.0, 9)
    s = paired_statistics({"a": {f"r{j}": v for j, v in enumerate(values)}})
    assert mean_of_means_interval([values]) == (s.rows[0].ci_low, s.rows[0].ci_high)


def test_stratified_interval_is_scipys_and_weighs_each_sample_once():
    rng = np.random.default_rng(2)
    a, b = rng.gamma(2.0, 1.0, 12), rng.gamma(2.0, 1.0, 6) + 5.0
    low, high = mean_of_means_interval([a, b])
    ci = scipy.stats.bootstrap((a, b), lambda x, y, axis=-1: (x.mean(axis=axis) + y.mean(axis=axis)) / 2,
                               vectorized=True, paired=False, n_resamples=N_RESAMPLES, method=CI_METHOD,
                               rng=np.random.default_rng(SEED)).confidence_interval
    assert (low, high) == pytest.approx((ci.low, ci.high), rel=1e-12)
    center = (a.mean() + b.mean()) / 2
    assert low < center < high
    pooled = np.concatenate([a, b]).mean()
    assert not low < pooled < high  # the recording-weighted mean lies outside: each dataset counts once
    assert mean_of_means_interval([np.full(5, 2.0), np.full(7, 4.0)]) == (3.0, 3.0)
    with pytest.raises(ValueError, match="two finite values"):
        mean_of_means_interval([a, [1.0]])


# --- the summary, the table, results.json ---

def test_all_datasets_line_is_the_mean_of_the_dataset_means():
    results = _results()
    summary = across_datasets(results)
    assert summary["datasets"] == ["broad", "ece276a"]
    per = {(e["dataset"], e["estimator"]): e for e in summary["per_dataset"]}
    for folder, n in (("broad", 6), ("ece276a", 5)):
        for label in ("dr", "ekf"):
            e = per[(folder, label)]
            assert e["recordings"] == n and e["imu"] == "6-D"
            assert e["rmse_deg"]["total"] == pytest.approx(_folder_mean(results, folder, label))
            low, high = e["ci95_deg"]["total"]
            assert low < e["rmse_deg"]["total"] < high
    for e in summary["all"]:
        label = e["estimator"]
        expect = (_folder_mean(results, "broad", label) + _folder_mean(results, "ece276a", label)) / 2
        assert e["rmse_deg"]["total"] == pytest.approx(expect) and e["datasets"] == 2 and e["recordings"] == 11
        pooled = np.mean([r.rmse_deg["total"] for r in results if r.estimator == label])
        assert abs(e["rmse_deg"]["total"] - pooled) > 0.05  # 6 + 5 recordings: the pooled mean differs
        low, high = e["ci95_deg"]["total"]
        assert low < expect < high


def test_table_prints_each_dataset_then_all_datasets():
    results = _results()
    lines = format_table(results).splitlines()
    means = [line for line in lines if line.startswith("mean ")]
    assert [line.split()[:3] for line in means] == [
        ["mean", "broad", "(6)"], ["mean", "broad", "(6)"], ["mean", "ece276a", "(5)"], ["mean", "ece276a", "(5)"],
        ["mean", "all", "datasets"], ["mean", "all", "datasets"]]
    summary = across_datasets(results)
    for line, e in zip(means[4:], summary["all"]):
        assert line.startswith(f"mean {ACROSS} (2)") and line.split()[4] == e["estimator"]
        assert float(line.split()[5]) == pytest.approx(e["rmse_deg"]["total"], abs=0.006)
        low, high = e["ci95_deg"]["total"]
        assert f"[{low:.2f}, {high:.2f}]" in line
    assert any(line.startswith("all datasets: each row the mean of the estimator's per-dataset means") and
               "resampling the recordings within each dataset" in line for line in lines)


def test_too_few_recordings_or_a_missing_dataset_say_so():
    few = _results(sizes=(("broad", 6), ("ece276a", 4)))
    summary = across_datasets(few)
    assert all(e["ci95_deg"]["total"] is None for e in summary["all"])  # 4 in one dataset: no interval
    table = format_table(few)
    all_lines = [line for line in table.splitlines() if line.startswith(f"mean {ACROSS}")]
    assert len(all_lines) == 2 and "[" not in "".join(all_lines)
    assert "resampling the recordings" not in table
    missing = _results(missing=("ece276a", "dr"))
    (dr, ekf) = across_datasets(missing)["all"]
    assert dr["rmse_deg"] is None and dr["datasets"] == 1 and ekf["datasets"] == 2
    line = next(line for line in format_table(missing).splitlines() if line.startswith(f"mean {ACROSS}")
                and " dr " in line)
    assert line.split()[5:8] == ["-", "-", "-"]


def test_one_dataset_has_no_all_line():
    results = _results(sizes=(("broad", 6),))
    assert across_datasets(results)["all"] == []
    assert ACROSS not in format_table(results)


def test_results_json_and_report_carry_them(tmp_path):
    from fusion.evaluation.report.render import write_run

    results = _results()
    doc = results_json(results, {"command": "fusion compare (test)"})
    assert json.loads(json.dumps(doc, allow_nan=False))["datasets"] == across_datasets(results)
    write_run(tmp_path / "run", doc)
    md = (tmp_path / "run" / "report.md").read_text()
    html = (tmp_path / "run" / "report.html").read_text()
    for e in doc["datasets"]["all"]:
        cells = f"| {e['estimator']} | 11 (all 2 datasets, each once) | {e['rmse_deg']['total']:.2f} |"
        assert cells in md
        assert f'<td>{e["estimator"]}</td><td class="num">11 (all 2 datasets, each once)</td>' in html
    assert f"mean {ACROSS} (2)" in (tmp_path / "run" / "table.txt").read_text()


# --- an ablation's sweep ---

def _row(dataset, label, total):
    return {"dataset": dataset, "estimator": label, "rmse_deg": {"total": total, "inclination": 0.0, "heading": 0.0},
            "coverage": 1.0}


def test_sweep_gives_each_dataset_its_best_and_the_common_settings_score():
    # over all four recordings b is best (mean 2.5); a is best on dataset x, b on y
    errors = {("x/1", "a"): 1.0, ("x/2", "a"): 1.0, ("y/1", "a"): 6.0, ("y/2", "a"): 6.0,
              ("x/1", "b"): 2.0, ("x/2", "b"): 2.0, ("y/1", "b"): 3.0, ("y/2", "b"): 3.0}
    s = ablate.sweep_summary([_row(d, lab, e) for (d, lab), e in errors.items()])
    assert s["best_common"] == {"estimator": "b", "mean_rmse_deg": 2.5}
    assert s["datasets"] == [
        {"dataset": "x", "recordings": 2, "best_estimator": "a", "mean_rmse_deg": 1.0, "common_rmse_deg": 2.0},
        {"dataset": "y", "recordings": 2, "best_estimator": "b", "mean_rmse_deg": 3.0, "common_rmse_deg": 3.0}]
    text = ablate.format_sweep(s).splitlines()
    assert "x           2      1.00    2.00  a" in text and "y           2      3.00    3.00  b" in text
    one = ablate.sweep_summary([_row(d, lab, e) for (d, lab), e in errors.items() if d.startswith("x/")])
    assert "datasets" not in one


# --- tune: chosen on one dataset, scored on another ---

A_TRUTH = Rotation.from_rotvec([np.radians(20.0), 0.0, 0.0])  # the second dataset's truth world, tilted
B_TRUTH = Rotation.from_rotvec(np.radians(30.0) * np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]))
ONE_PARAMETER = "ekf:R=3e-5,tauc=0.1"  # Q alone tuned: the default and two grid values


def _write_window(folder: Path, name: str, start_s: float, seconds: float, other_frames: bool) -> None:
    """A window of the simulated recording as a CSV recording (t, gyro rad/s, acc m/s^2, truth
    w x y z); with `other_frames` its truth in a tilted world and a rotated body frame, A^-1 R B^-1."""
    rec = datasets.load("sim")
    imu = rec.imu
    start, stop = np.searchsorted(imu.t, imu.t[0] + start_s + np.array([0.0, seconds]))
    window = imu.window(int(start), int(stop))
    truth, _ = rec.truth.interpolate(window.t)
    if other_frames:
        truth = A_TRUTH.inv() * truth * B_TRUTH.inv()
    table = np.column_stack([window.t, window.gyr_rad_s, window.acc_g * 9.80665, truth.as_quat(scalar_first=True)])
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz"] + [",".join(f"{v:.12g}" for v in row) for row in table]
    (folder / name).write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory) -> Path:
    """Two 15-s recordings in `labA/` (truth in our frames) and two in `labB/` (truth in other frames)."""
    root = tmp_path_factory.mktemp("two")
    for k in range(2):
        _write_window(root / "labA", f"rec{k + 1}.csv", 5.0 + 15.0 * k, 15.0, other_frames=False)
        _write_window(root / "labB", f"rec{k + 3}.csv", 35.0 + 15.0 * k, 15.0, other_frames=True)
    return root


def _tune(root: Path, tmp_path: Path, capsys, *extra: str) -> tuple[dict, str]:
    out = tmp_path / f"tune{len(list(tmp_path.iterdir()))}.json"
    capsys.readouterr()
    code = main(["tune", "--estimators", ONE_PARAMETER, "--data-dir", str(root), "--jobs", "1", "--no-progress",
                 "--json", str(out), *extra])
    text = capsys.readouterr()
    assert code == 0, text.err
    return json.loads(out.read_text()), text.out


def test_tune_on_one_dataset_scored_on_another_and_aligned(two_datasets, tmp_path, capsys):
    plain, _ = _tune(two_datasets, tmp_path, capsys, "--train", "labA/*", "--test", "labB/*")
    doc, printed = _tune(two_datasets, tmp_path, capsys, "--train", "labA/*", "--test", "labB/*", "--align")
    (t_plain,), (t,) = plain["tune"]["estimators"], doc["tune"]["estimators"]
    assert plain["tune"]["folds"] == doc["tune"]["folds"] == [
        {"name": "train", "train": ["labA/rec1", "labA/rec2"], "test": ["labB/rec3", "labB/rec4"]}]
    # labB's truth is 20 deg tilted and 30 deg turned: unaligned every setting scores far off, aligned close
    assert t_plain["out_of_sample_deg"] > 15.0 and t["out_of_sample_deg"] < 6.0
    assert doc["settings"]["align"] is True and plain["settings"]["align"] is False
    assert "--align" in printed.splitlines()[0]
    aligned_rows = [r for r in doc["results"] if r["dataset"].startswith("labB/")]
    assert len(aligned_rows) == 4 and all(r["alignment"] for r in aligned_rows)
    assert all(r["alignment"] is None for r in plain["results"])
    # the fitted body rotation is the one the truth was turned by (B = R_truthbody_imubody, 30 deg), to
    # within what the simulated gyro's scale errors (+9, +4, -4 %) move Wahba's solution on 15 s
    body = Rotation.from_rotvec(aligned_rows[0]["alignment"]["body_deg"], degrees=True)
    assert np.degrees((body * B_TRUTH.inv()).magnitude()) < 2.5
    # the test scores per dataset: one, labB, equal to the out-of-sample figure
    assert t["test_datasets"] == [{"dataset": "labB", "recordings": 2, "default_deg": pytest.approx(t["default_deg"]),
                                   "tuned_deg": pytest.approx(t["out_of_sample_deg"])}]
    assert "per dataset" not in printed  # one test dataset: the table's line is its figure


def test_tune_by_dataset_reports_each_test_dataset(two_datasets, tmp_path, capsys):
    doc, printed = _tune(two_datasets, tmp_path, capsys, "--dataset", "labA/*,labB/*", "--by", "group", "--align")
    (t,) = doc["tune"]["estimators"]
    assert [f["name"] for f in doc["tune"]["folds"]] == ["labA", "labB"]
    per = {d["dataset"]: d for d in t["test_datasets"]}
    for folder in ("labA", "labB"):
        ids = [rid for rid in t["scores_tuned_deg"] if rid.startswith(folder + "/")]
        assert per[folder]["recordings"] == 2
        assert per[folder]["tuned_deg"] == pytest.approx(np.mean([t["scores_tuned_deg"][r] for r in ids]))
        assert per[folder]["default_deg"] == pytest.approx(np.mean([t["scores_default_deg"][r] for r in ids]))
    lines = printed.splitlines()
    head = lines.index("per dataset of the test recordings (mean over its recordings):")
    for line, folder in zip(lines[head + 2:head + 4], ("labA", "labB")):
        cells = line.split()
        assert cells[1:3] == [folder, "2"]
        assert float(cells[3]) == pytest.approx(per[folder]["default_deg"], abs=0.006)
        assert float(cells[4]) == pytest.approx(per[folder]["tuned_deg"], abs=0.006)
    # results.json: the default and tuned rows' means per dataset and together (the compare summary)
    together = {e["estimator"]: e for e in doc["datasets"]["all"]}
    assert together[f"{ONE_PARAMETER} tuned"]["rmse_deg"]["total"] == pytest.approx(
        (per["labA"]["tuned_deg"] + per["labB"]["tuned_deg"]) / 2)


def test_overlapping_train_and_test_are_said_to_be_in_sample(two_datasets, tmp_path, capsys):
    _, printed = _tune(two_datasets, tmp_path, capsys, "--train", "labA/*", "--test", "labA/rec1,labB/*", "--align")
    assert "note: 1 test recording was also tuned on (labA/rec1): its tuned scores are in sample" in printed
    assert "per dataset of the test recordings" in printed
