"""Several datasets in one run: each dataset's means apart and the "all datasets" line together
(`fusion.evaluation.compare.across_datasets`), in the printed table, results.json, the report and
an ablation's sweep; the stratified interval of a mean of means (`stats.mean_of_means_interval`)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.stats

from fusion.evaluation import ablate
from fusion.evaluation.compare import ACROSS, across_datasets, format_table, results_json
from fusion.evaluation.job import Result
from fusion.evaluation.stats import CI_METHOD, N_RESAMPLES, SEED, mean_of_means_interval, paired_statistics


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
    from fusion.evaluation.report import write_run

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
