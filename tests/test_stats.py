"""Statistics of a comparison (`fusion.evaluation.scoring.stats`): the numbers equal SciPy's, statsmodels'
and scikit-posthocs' own on the same inputs, Holm's adjustment a case worked by hand, and Nemenyi's
critical difference Demsar's table; properties (order does not matter, a row worse everywhere is
significantly worse, identical rows tie); complete cases; too few recordings; the JSON; the table
column and the report's section with its critical-difference diagram."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.stats

from fusion.evaluation.scoring import stats
from fusion.evaluation.compare import format_table, results_json, summary_groups
from fusion.evaluation.run.job import Result
from fusion.evaluation.scoring.stats import (
    MIN_RECORDINGS, N_RESAMPLES, SEED, RunStatistics, Statistics, no_statistics_reason, paired_statistics,
    run_statistics,
)


def _scores(rows: int = 4, recordings: int = 9, seed: int = 3) -> dict[str, dict[str, float]]:
    """Skewed positive scores (like RMSEs), row i about 0.3 i worse; recordings inserted in a
    shuffled order so that sorting them is part of what is tested."""
    rng = np.random.default_rng(seed)
    ids = [f"rec{j:02d}" for j in rng.permutation(recordings)]
    return {f"est{i}": {r: float(rng.gamma(3.0, 1.0) + 0.3 * i) for r in ids} for i in range(rows)}


def _matrix(scores, s: Statistics) -> np.ndarray:
    """(k, n) scores in the statistics' row and (sorted) recording order."""
    return np.array([[scores[r.label][rec] for rec in s.recordings] for r in s.rows])


# --- the numbers are the libraries' own ---

def test_bootstrap_interval_equals_scipy_bootstrap_row_by_row():
    scores = _scores()
    s = paired_statistics(scores, "total")
    assert s.recordings == tuple(sorted(next(iter(scores.values()))))
    x = _matrix(scores, s)
    for row, values in zip(s.rows, x):
        ci = scipy.stats.bootstrap((values,), np.mean, n_resamples=N_RESAMPLES, confidence_level=0.95, method="BCa",
                                   rng=np.random.default_rng(SEED)).confidence_interval
        assert (row.ci_low, row.ci_high) == pytest.approx((ci.low, ci.high), rel=1e-12)
        assert row.mean == pytest.approx(values.mean(), rel=1e-15)
        assert row.ci_low < row.mean < row.ci_high


def test_wilcoxon_p_equals_scipy_against_the_best_row():
    scores = _scores()
    s = paired_statistics(scores, "total")
    x = _matrix(scores, s)
    best = s.labels.index(s.best)
    assert s.best == min(s.labels, key=lambda lab: np.mean(list(scores[lab].values())))
    for i, row in enumerate(s.rows):
        if i == best:
            assert row.p_value is None and row.p_holm is None and row.not_worse
            continue
        assert row.p_value == scipy.stats.wilcoxon(x[i] - x[best]).pvalue
        assert (row.wins, row.ties, row.losses) == (int(np.sum(x[i] < x[best])), 0, int(np.sum(x[i] > x[best])))
    others = [r.p_value for r in s.rows if r.label != s.best]
    from statsmodels.stats.multitest import multipletests
    assert [r.p_holm for r in s.rows if r.label != s.best] == list(multipletests(others, method="holm")[1])


def test_holm_on_a_case_worked_by_hand():
    """Ten recordings. `worse` loses on all ten: exact two-sided Wilcoxon p = 2 / 2^10; `mostly` loses
    on nine and wins on the one with the smallest difference (W- = 1): p = 2 * 2 / 2^10; `same`
    ties everywhere: p = 1. Holm over m = 3 (Holm 1979): sorted p_(1..3) times 3, 2, 1, running
    maximum: 3 * 2/1024, 2 * 4/1024, 1."""
    base = {f"r{j}": 1.0 + j for j in range(10)}
    scores = {"best": base,
              "worse": {r: v + 0.1 + 0.01 * j for j, (r, v) in enumerate(base.items())},
              "mostly": {r: v + (-0.001 if j == 0 else 0.2 + 0.01 * j) for j, (r, v) in enumerate(base.items())},
              "same": dict(base)}
    s = paired_statistics(scores, "total")
    assert s.best == "best"  # "same" has the same mean: the first label in sorted order wins the tie
    assert s.row("worse").p_value == pytest.approx(2 / 1024, rel=1e-12)
    assert s.row("mostly").p_value == pytest.approx(4 / 1024, rel=1e-12)
    assert s.row("same").p_value == 1.0
    assert s.row("worse").p_holm == pytest.approx(3 * 2 / 1024, rel=1e-12)
    assert s.row("mostly").p_holm == pytest.approx(2 * 4 / 1024, rel=1e-12)
    assert s.row("same").p_holm == 1.0
    assert [s.row(x).not_worse for x in ("best", "worse", "mostly", "same")] == [True, False, False, True]
    assert (s.row("mostly").wins, s.row("mostly").ties, s.row("mostly").losses) == (1, 0, 9)


def test_friedman_and_nemenyi_equal_scipy_and_scikit_posthocs():
    import pandas as pd
    import scikit_posthocs

    scores = _scores(rows=5, recordings=12)
    s = paired_statistics(scores, "inclination")
    x = _matrix(scores, s)
    f = scipy.stats.friedmanchisquare(*x)
    assert s.friedman_statistic == pytest.approx(f.statistic, rel=1e-12)
    assert s.friedman_p == pytest.approx(f.pvalue, rel=1e-12)
    labels = list(s.labels)
    nemenyi = scikit_posthocs.posthoc_nemenyi_friedman(pd.DataFrame(x.T, columns=labels))
    np.testing.assert_allclose(np.array(s.nemenyi_p), nemenyi.loc[labels, labels].to_numpy(), rtol=1e-12)
    ranks = scipy.stats.rankdata(x, axis=0).mean(axis=1)
    assert [r.rank for r in s.rows] == pytest.approx(ranks, rel=1e-12)
    assert sum(r.rank for r in s.rows) == pytest.approx(5 * 6 / 2)  # ranks 1..k on every recording


@pytest.mark.parametrize("k, q", [(3, 2.343), (4, 2.569), (5, 2.728), (10, 3.164)])
def test_critical_difference_uses_demsars_table(k, q):
    """Demsar 2006, Table 5(a): q_0.05 of the Nemenyi test; CD = q sqrt(k (k + 1) / (6 N))."""
    n = 8
    rng = np.random.default_rng(k)
    scores = {f"e{i}": {f"r{j}": float(rng.random()) for j in range(n)} for i in range(k)}
    s = paired_statistics(scores)
    assert s.critical_difference == pytest.approx(q * math.sqrt(k * (k + 1) / (6 * n)), abs=2e-3)


# --- properties ---

def test_reordering_rows_or_recordings_changes_nothing():
    scores = _scores(rows=5, recordings=11)
    s = paired_statistics(scores, "total")
    labels = list(scores)[::-1]
    labels.insert(1, labels.pop(3))
    shuffled = {lab: dict(reversed(list(scores[lab].items()))) for lab in labels}
    t = paired_statistics(shuffled, "total")
    assert t.labels == tuple(labels) and t.recordings == s.recordings and t.best == s.best
    for lab in labels:
        moved, before = t.row(lab).to_json(), s.row(lab).to_json()
        assert moved.keys() == before.keys()
        for key, value in before.items():  # the numbers to 1e-12; labels, marks and None (the best row's p) exactly
            if isinstance(value, float):
                assert moved[key] == pytest.approx(value, rel=1e-12), key
            else:
                assert moved[key] == value, key
    assert (t.friedman_statistic, t.friedman_p) == pytest.approx((s.friedman_statistic, s.friedman_p), rel=1e-12)
    order = [s.labels.index(lab) for lab in labels]
    np.testing.assert_allclose(np.array(t.nemenyi_p), np.array(s.nemenyi_p)[np.ix_(order, order)], rtol=1e-12)


def test_a_row_worse_on_every_recording_of_ten_is_significantly_worse():
    rng = np.random.default_rng(11)
    good = {f"r{j}": float(rng.gamma(2.0, 1.0)) for j in range(10)}
    scores = {"good": good, "bad": {r: v * 1.01 + 1e-3 for r, v in good.items()},
              "other": {r: v + 0.5 + float(rng.gamma(2.0, 1.0)) for r, v in good.items()}}
    s = paired_statistics(scores)
    bad = s.row("bad")
    assert s.best == "good" and bad.losses == 10 and bad.wins == bad.ties == 0
    assert bad.p_value < 0.05 and bad.p_holm < 0.05 and not bad.not_worse


@pytest.mark.parametrize("recordings, others, significant", [(5, 1, False), (6, 1, True), (6, 2, False),
                                                             (7, 3, True)])
def test_what_few_recordings_can_show(recordings, others, significant):
    """A row worse on every recording: two-sided Wilcoxon p = 2 / 2^n, times the rows compared with
    the best (Holm's first step): 5 recordings never show it; 6 only against one other row."""
    best = {f"r{j}": 1.0 + j for j in range(recordings)}
    scores = {"best": best, **{f"worse{i}": {r: v + 1 + i for r, v in best.items()} for i in range(others)}}
    row = paired_statistics(scores).row("worse0")
    assert row.p_value == pytest.approx(2 / 2**recordings, rel=1e-12)
    assert row.p_holm == pytest.approx(min(1.0, others * 2 / 2**recordings), rel=1e-12)
    assert row.not_worse is not significant


def test_identical_rows_tie_and_so_do_rows_within_the_tolerance():
    rng = np.random.default_rng(5)
    a = {f"r{j}": float(rng.gamma(2.0, 1.0)) for j in range(8)}
    scores = {"a": a, "b": dict(a), "c": {r: v * (1 + 1e-12) for r, v in a.items()},
              "d": {r: v + 1 for r, v in a.items()}}
    s = paired_statistics(scores)
    assert s.best == "a"
    for lab in ("b", "c"):
        row = s.row(lab)
        assert (row.wins, row.ties, row.losses) == (0, 8, 0) and row.p_value == 1.0 and row.not_worse
    assert s.row("a").rank == s.row("b").rank  # identical scores share their rank
    assert s.row("d").losses == 8 and not s.row("d").not_worse
    assert s.row("a").ci_low < s.row("a").ci_high


def test_a_constant_row_has_a_point_interval():
    scores = {"flat": {f"r{j}": 2.0 for j in range(6)}, "wavy": {f"r{j}": 2.0 + j for j in range(6)}}
    s = paired_statistics(scores)
    assert (s.row("flat").ci_low, s.row("flat").ci_high) == (2.0, 2.0)
    assert s.row("wavy").ci_low < s.row("wavy").mean < s.row("wavy").ci_high


# --- complete cases and too few recordings ---

def test_recordings_without_a_finite_score_are_dropped_and_counted():
    scores = _scores(rows=3, recordings=8)
    scores["est1"]["rec03"] = float("nan")
    del scores["est2"]["rec05"]
    scores["est0"]["rec05"] = None
    scores["failed"] = {r: float("nan") for r in scores["est0"]}
    s = paired_statistics(scores, "total")
    assert len(s.recordings) == 6 and "rec03" not in s.recordings and "rec05" not in s.recordings
    assert [(d.recording, d.without_score) for d in s.dropped] == [("rec03", ("est1",)), ("rec05", ("est0", "est2"))]
    assert s.left_out == ("failed",) and s.labels == ("est0", "est1", "est2")
    text = stats.table_column(RunStatistics((stats.Comparison("total", None, None, s.labels, s),)), "total")[2][0]
    assert "over the 6 recordings every row scored (2 dropped, a row without a score on each: rec03 (est1), " \
           "rec05 (est0, est2))" in text


def test_a_row_that_failed_on_most_recordings_costs_only_itself():
    """Scored on 4 of 8 recordings (at most half), a row is left out of the ranking instead of dropping
    the other four recordings from every row's comparison; scored on 5 of 8, it stays and they drop."""
    scores = _scores(rows=3, recordings=8)
    scores["flaky"] = {r: (1.0 if j < 4 else None) for j, r in enumerate(scores["est0"])}
    s = paired_statistics(scores, "total")
    assert s.left_out == ("flaky",) and len(s.recordings) == 8 and not s.dropped
    text = stats.table_column(RunStatistics((stats.Comparison("total", None, None, s.labels, s),)), "total")[2][0]
    assert "over the 8 recordings every row scored; scored on at most half of them, not ranked: flaky" in text
    scores["flaky"]["rec04"] = 1.0
    s = paired_statistics(scores, "total")
    assert s.left_out == () and len(s.recordings) == 5 and "flaky" in s.labels


@pytest.mark.parametrize("recordings", [1, 2, 4])
def test_fewer_than_five_recordings_give_none_and_a_one_line_reason(recordings):
    scores = _scores(rows=3, recordings=recordings)
    assert paired_statistics(scores) is None
    reason = no_statistics_reason(scores)
    assert "\n" not in reason
    plural = "" if recordings == 1 else "s"
    assert reason == f"{recordings} recording{plural} scored by every row, {MIN_RECORDINGS} needed"


def test_five_complete_recordings_are_enough_and_a_dropped_one_is_named():
    scores = _scores(rows=3, recordings=6)
    assert paired_statistics(scores) is not None and no_statistics_reason(scores) is None
    scores["est2"]["rec01"] = float("inf")
    scores["est1"]["rec04"] = float("nan")
    assert paired_statistics(scores) is None
    assert no_statistics_reason(scores) == ("4 recordings scored by every row, 5 needed (2 dropped, a row without a "
                                            "score on each: rec01 (est2), rec04 (est1))")


def test_bad_input_is_a_value_error_naming_it():
    with pytest.raises(ValueError, match=r"scores\['a'\]\['r1'\]: not a number \('x'\)"):
        paired_statistics({"a": {"r1": "x"}})
    with pytest.raises(ValueError, match="must map recording -> score"):
        paired_statistics({"a": [1.0, 2.0]})


# --- JSON ---

def test_json_round_trip_with_plain_numbers_and_null_for_undefined():
    scores = _scores(rows=4, recordings=7)
    s = paired_statistics(scores, "heading")
    text = json.dumps(s.to_json(), allow_nan=False)
    assert Statistics.from_json(json.loads(text)) == s
    tied = {lab: {f"r{j}": 1.0 for j in range(6)} for lab in ("a", "b", "c")}  # Friedman is 0/0 here
    t = paired_statistics(tied)
    doc = json.loads(json.dumps(t.to_json(), allow_nan=False))
    assert doc["friedman_p"] is None and doc["friedman_statistic"] is None
    assert doc["rows"][0]["p_value"] is None and doc["rows"][1]["p_value"] == 1.0
    assert Statistics.from_json(doc) == t


# --- a run's rows: the table, results.json, the report ---

def _results(recordings: int = 10, labels=("dr", "ekf", "vqf"), mag=(), seed: int = 0) -> list[Result]:
    """Rows as `fusion compare` makes them; "dr" clearly worse than the others everywhere."""
    rng = np.random.default_rng(seed)
    out = []
    for j in range(recordings):
        for i, label in enumerate(labels):
            total = float((8.0 if label == "dr" else 2.0 + 0.1 * i) + rng.gamma(2.0, 0.2))
            rmse = {"total": total, "inclination": total / 3, "heading": total / 2}
            out.append(Result(f"broad/{j:02d}", label, 1000, 0.01, rmse, dict(rmse), scored_samples=1000, coverage=1.0,
                              magnetometer=label in mag))
    return out


def test_table_has_the_interval_column_the_mark_and_the_note():
    results = _results()
    table = format_table(results)
    lines = table.splitlines()
    header = lines[1].split()
    assert header[:7] == ["dataset", "estimator", "total", "inclination", "heading", "total", "95%"]
    run = run_statistics(summary_groups(results), ["total"])
    (c,) = run.of("total")
    means = {line.split()[2]: line for line in lines if line.startswith("mean (10)")}
    for r in c.statistics.rows:
        cell = f"[{r.ci_low:.2f}, {r.ci_high:.2f}]"
        assert cell in means[r.label]
        assert means[r.label].split(cell)[1].startswith(" *") == r.not_worse
    assert c.statistics.row("dr").not_worse is False and "*" not in means["dr"]
    assert float(means["ekf"].split()[3]) == pytest.approx(np.mean([r.rmse_deg["total"] for r in results
                                                                    if r.estimator == "ekf"]), abs=0.006)
    note = lines[-1]
    assert note.startswith("total 95% CI: BCa bootstrap interval of the mean over the 10 recordings every row scored")
    assert f"Friedman p = {c.statistics.friedman_p:.2g}" in note and "*: not significantly worse than" in note
    assert all(line.split()[0].startswith("broad/") for line in lines[7:-1])  # per-recording rows: no cell


def test_table_primary_metric_can_be_inclination():
    results = _results()
    table = format_table(results, primary="inclination")
    assert "inclination 95% CI" in table.splitlines()[1] and table.splitlines()[-1].startswith("inclination 95% CI")
    with pytest.raises(ValueError, match="unknown metric 'tilt'"):
        format_table(results, primary="tilt")


def test_table_with_four_recordings_keeps_its_columns_and_says_why():
    results = _results(recordings=4)
    lines = format_table(results).splitlines()
    assert lines[1].split() == ["dataset", "estimator", "total", "inclination", "heading", "coverage", "us/sample"]
    assert lines[-1] == "no statistics: 4 recordings scored by every row, 5 needed"
    assert sum("no statistics" in line for line in lines) == 1
    assert "no statistics" not in format_table(results[:3])  # one recording: no means, nothing to say


def test_six_d_and_nine_d_rows_are_compared_apart_on_every_metric():
    """Like for like: a 9-D row's inclination is helped by its magnetometer too, so 6-D and 9-D rows
    are ranked and tested apart on every metric; a group of one row is shown, not ranked or tested."""
    results = _results(labels=("dr", "ukf", "ekf", "vqf", "gn"), mag=("ekf", "vqf", "gn"))
    run = run_statistics(summary_groups(results))
    for metric in ("total", "heading", "inclination"):
        assert [(c.imu, c.labels) for c in run.of(metric)] == [("6-D", ("dr", "ukf")), ("9-D", ("ekf", "vqf", "gn"))]
    alone = run_statistics(summary_groups(_results(labels=("dr", "ekf"), mag=("ekf",))))
    assert [(c.imu, c.statistics, c.reason) for c in alone.of("total")] == [
        ("6-D", None, "one row (dr): nothing to compare it with"), ("9-D", None, "one row (ekf): nothing to compare it with")]
    notes = format_table(results).splitlines()[-2:]
    assert notes[0].startswith("total 95% CI (6-D rows)") and notes[1].startswith("total 95% CI (9-D rows)")
    assert "Friedman" not in notes[0] and "Friedman" in notes[1]  # two 6-D rows: no Friedman test


def test_failed_and_low_coverage_rows_drop_their_recording():
    from dataclasses import replace

    results = _results(recordings=7)
    results[4] = replace(results[4], rmse_deg=None, max_deg=None, error="broad/01: estimator 'ekf' failed")
    results[9] = replace(results[9], coverage=0.2)  # broad/03, dr
    (c,) = run_statistics(summary_groups(results), ["total"]).comparisons
    dropped = [(d.recording, d.without_score) for d in c.statistics.dropped]
    assert dropped == [("broad/01", ("ekf",)), ("broad/03", ("dr",))]
    assert len(c.statistics.recordings) == 5


def test_results_json_holds_every_metrics_statistics():
    results = _results()
    doc = json.loads(json.dumps(results_json(results, {}), allow_nan=False))
    assert list(doc["statistics"]) == ["total", "inclination", "heading"]
    run = RunStatistics.from_json(doc["statistics"])
    assert run == run_statistics(summary_groups(results))
    assert run.of("inclination")[0].statistics.row("dr").not_worse is False


def test_report_has_the_statistics_section_and_the_cd_diagrams(tmp_path):
    from fusion.evaluation.report.render import render, write_run

    results = _results(recordings=6, labels=("dr", "ekf", "vqf", "gn"))
    out = tmp_path / "run"
    write_run(out, results_json(results, {"command": "fusion compare (test)"}))
    run = run_statistics(summary_groups(results))
    page, md = (out / "report.html").read_text(), (out / "report.md").read_text()
    assert '<h2 id="statistics">Statistics</h2>' in page and "## Statistics" in md
    for metric in ("total", "inclination", "heading"):
        name = f"summary-cd-{metric}.png"
        assert (out / "figures" / name).stat().st_size > 5000
        assert f'data-file="{name}"' in page and f"figures/{name}" in md
    s = run.of("total")[0].statistics
    for r in s.rows:  # the section's numbers are results.json's
        assert f"| {r.label} | {r.mean:.2f} | [{r.ci_low:.2f}, {r.ci_high:.2f}] | {r.rank:.2f} | " \
               f"{r.wins}/{r.ties}/{r.losses} |" in md
    assert f"Friedman chi-square {s.friedman_statistic:.2f}, p = {s.friedman_p:.2g}" in md
    for name in ("report.html", "report.md"):
        (out / name).unlink()
    for fig in (out / "figures").glob("summary-cd-*.png"):
        fig.unlink()
    render(out)  # `fusion report DIR`: from results.json alone
    assert (out / "report.md").read_text() == md
    assert sorted(p.name for p in (out / "figures").glob("summary-cd-*.png")) == [
        "summary-cd-heading.png", "summary-cd-inclination.png", "summary-cd-total.png"]


def test_report_with_too_few_recordings_says_why():
    from fusion.evaluation.report.render import _markdown

    results = _results(recordings=3)
    doc = results_json(results, {})
    md = _markdown(doc, "", [], [], [], run_statistics(summary_groups(results)), {})
    assert md.count("No statistics: 3 recordings scored by every row, 5 needed.") == 3


def test_cd_figure_draws_every_row_and_needs_three():
    from fusion.evaluation.report.stats_plots import cd_figure

    s = paired_statistics(_scores(rows=4, recordings=8))
    fig = cd_figure(s, "total RMSE")
    texts = [t.get_text() for t in fig.axes[0].texts]
    for r in s.rows:
        assert any(t.startswith(f"{r.label} (") or t.endswith(f") {r.label}") for t in texts), r.label
    assert any(t.startswith("CD = ") for t in texts)
    assert cd_figure(paired_statistics(_scores(rows=2, recordings=8))) is None


def test_report_table_uses_the_runs_primary_metric(tmp_path):
    from fusion.evaluation.report.render import write_run

    results = _results(recordings=6)
    write_run(tmp_path / "a", results_json(results, {"primary": "inclination"}))
    write_run(tmp_path / "b", results_json(results, {"primary": "no such metric"}))  # an older or edited file
    assert (tmp_path / "a" / "table.txt").read_text() == format_table(results, primary="inclination") + "\n"
    assert (tmp_path / "b" / "table.txt").read_text() == format_table(results) + "\n"
    assert "inclination 95% CI" in (tmp_path / "a" / "table.txt").read_text()
