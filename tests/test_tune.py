"""`fusion tune`: one protocol for every estimator, judged out of sample.

The fold logic is pinned on a table of made-up scores (a held-out recording that would pick
another setting must not); the runs on real recordings check that a stopped tuning resumed
equals an uninterrupted one, that the TPE search is seeded and independent of `--jobs`, and
that `compare --tuned` runs the setting the tuning chose.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import pytest

from fusion.cli import main
from fusion.estimators import resolve
from fusion.evaluation.run import journal as journal_mod
from fusion.evaluation.sweeps import tune
from fusion.evaluation.run.job import Result

COURSE = "ece276a/1,ece276a/2,ece276a/3"


@dataclass
class FakeSource:
    id: str


class TableScores:
    """A `tune.Scores` stand-in: (estimator label, recording) -> RMSE from a function of the spec."""

    def __init__(self, rmse, settings=tune.TuneSettings()):
        self.rmse = rmse  # (overrides dict, recording id) -> deg
        self.settings = settings
        self.rows = {}

    def evaluate(self, specs, ids):
        out = {}
        for spec in specs:
            label = resolve(spec).label
            for rid in ids:
                value = self.rmse(dict(spec.overrides), rid)
                row = Result(rid, label, 100, 0.0, {"total": value, "inclination": value, "heading": value},
                             {"total": value, "inclination": value, "heading": value}, coverage=1.0)
                self.rows[(label, rid)] = out[(label, rid)] = row
        return out

    score = tune.Scores.score


def test_a_fold_chooses_from_its_training_recordings_only():
    """Madgwick's gain: 0.3 is best on recording c alone (by far), 0.033 on a and b. Leaving c out
    must choose 0.033 for c even though 0.3 has the best mean over all three."""
    def rmse(overrides, rid):
        beta = float(overrides.get("beta", 0.033))
        if rid == "c":
            return 1.0 if beta == 0.3 else 50.0
        return 2.0 if beta == 0.033 else 3.0

    entry = resolve("madgwick")
    ids = ["a", "b", "c"]
    folds = tune.folds_of([FakeSource(i) for i in ids], "recording")
    result = tune._search_grid(entry, TableScores(rmse), folds, ids)
    assert result.common_setting == {"beta": 0.3}  # in sample: (3 + 3 + 1) / 3 beats (2 + 2 + 50) / 3
    assert result.chosen["c"] == {}  # out of sample, chosen on a and b: the default, beta = 0.033
    assert result.chosen["a"] == result.chosen["b"] == {"beta": 0.3}  # c in the training set outweighs
    assert result.scores_tuned == {"a": 3.0, "b": 3.0, "c": 50.0}
    assert math.isclose(result.out_of_sample, 56 / 3)
    assert math.isclose(result.common, 7 / 3)
    assert math.isclose(result.per_recording, (2 + 2 + 1) / 3)  # each recording's own best
    assert math.isclose(result.default, (2 + 2 + 50) / 3)
    assert result.evaluated == len(tune.grid_settings(entry))


def test_a_failed_row_is_never_chosen():
    def rmse(overrides, rid):
        return math.nan if overrides.get("beta") == "0.3" else 2.0 + float(overrides.get("beta", 0.033))

    entry = resolve("madgwick")
    ids = ["a", "b"]
    result = tune._search_grid(entry, TableScores(rmse), tune.folds_of([FakeSource(i) for i in ids], "recording"), ids)
    assert result.common_setting == {"beta": 0.01}
    assert all(setting != {"beta": 0.3} for setting in result.chosen.values())


def test_grid_settings_start_with_the_default_and_honour_fixed_parameters():
    space = tune.tunable_space(resolve("mahony"))
    n_kp, n_ki = len(space["kp"].grid), len(space["ki"].grid)
    default_in_grid = 1.0 in space["kp"].grid and 0.3 in space["ki"].grid  # ahrs' defaults kp = 1, ki = 0.3
    grid = tune.grid_settings(resolve("mahony"))
    assert grid[0] == {} and len(grid) == 1 + n_kp * n_ki - default_in_grid
    assert len({tuple(sorted(s.items())) for s in grid}) == len(grid)
    fixed = tune.grid_settings(resolve("mahony:ki=0.01"))
    assert fixed[0] == {} and all(set(s) == {"kp"} for s in fixed[1:])
    assert len(fixed) == 1 + n_kp - (1.0 in space["kp"].grid)
    assert tune.grid_settings(resolve("dr")) == [{}]


def test_group_folds_hold_out_whole_groups(data_dir):
    from fusion.selection import select_sources

    sources = select_sources("broad/*", data_dir)
    folds = tune.folds_of(sources, "group")
    names = {f.name for f in folds}
    assert {"rotation", "translation", "attached_magnet"} <= names
    for fold in folds:
        assert not set(fold.train) & set(fold.test)
        assert {tune.group_of(s) for s in sources if s.id in fold.test} == {fold.name}
    assert sorted(r for f in folds for r in f.test) == sorted(s.id for s in sources)


def test_settings_reject_bad_values():
    with pytest.raises(ValueError, match="--metric"):
        tune.TuneSettings(metric="yaw")
    with pytest.raises(ValueError, match="--train and --test go together"):
        tune.TuneSettings(train="broad/*")
    with pytest.raises(ValueError, match="unknown key 'bogus'"):
        tune.TuneSettings.from_json({"bogus": 1})
    assert tune.TuneSettings.from_json({"metric": "heading"}).to_json()["metric"] == "heading"


def _tune(out: Path, *extra: str, data_dir: Path) -> tuple[int, str]:
    code = main(["tune", "--estimators", "vqf-basic,madgwick", "--dataset", COURSE, "--data-dir", str(data_dir),
                 "--mag", "off", "--no-progress", "--jobs", "1", "--out", str(out), *extra])
    return code, (out / "results.json").read_text() if (out / "results.json").exists() else ""


def test_a_stopped_tuning_resumed_equals_an_uninterrupted_one(data_dir, tmp_path, monkeypatch, capsys):
    code, _ = _tune(tmp_path / "whole", data_dir=data_dir)
    assert code == 0
    whole = json.loads((tmp_path / "whole" / "results.json").read_text())

    real = journal_mod.Journal.record
    calls = []

    def stop_after_ten(self, *args, **kwargs):
        if len(calls) == 10:
            raise KeyboardInterrupt
        calls.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(journal_mod.Journal, "record", stop_after_ten)
    code, _ = _tune(tmp_path / "stopped", data_dir=data_dir)
    assert code == 130 and not (tmp_path / "stopped" / "results.json").exists()
    assert "--resume" in capsys.readouterr().err
    monkeypatch.setattr(journal_mod.Journal, "record", real)
    assert main(["tune", "--resume", str(tmp_path / "stopped"), "--no-progress", "--jobs", "2"]) == 0
    resumed = json.loads((tmp_path / "stopped" / "results.json").read_text())
    assert resumed["tune"]["estimators"] == whole["tune"]["estimators"]
    assert [(r["dataset"], r["estimator"], r["rmse_deg"]) for r in resumed["results"]] == \
           [(r["dataset"], r["estimator"], r["rmse_deg"]) for r in whole["results"]]


def test_tpe_is_seeded_and_independent_of_jobs(data_dir, tmp_path):
    docs = []
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        assert main(["tune", "--estimators", "madgwick", "--dataset", COURSE, "--data-dir", str(data_dir),
                     "--mag", "off", "--search", "tpe", "--budget", "4", "--seed", "3", "--no-progress",
                     "--jobs", jobs, "--out", str(out)]) == 0
        docs.append(json.loads((out / "results.json").read_text())["tune"]["estimators"])
        assert (out / tune.OPTUNA_JOURNAL).is_file()
    assert docs[0] == docs[1]
    (madgwick,) = docs[0]
    assert set(madgwick["chosen"]) == {"ece276a/1", "ece276a/2", "ece276a/3"}
    # each of the 4 studies (all recordings, 3 folds) starts from the default, then 3 proposals
    assert 1 + 3 <= madgwick["settings_evaluated"] <= 1 + 4 * 3


def test_compare_tuned_runs_the_chosen_setting(data_dir, tmp_path, capsys):
    out = tmp_path / "tuned"
    assert main(["tune", "--estimators", "vqf-basic", "--dataset", COURSE, "--data-dir", str(data_dir), "--mag", "off",
                 "--no-progress", "--jobs", "1", "--out", str(out)]) == 0
    table = (out / "table.txt").read_text()
    assert "common setting" in table and "## Tuning" in (out / "report.md").read_text()
    assert main(["report", str(out), "--no-progress", "--jobs", "1"]) == 0  # re-rendered from results.json alone
    assert (out / "table.txt").read_text() == table and (out / "tuned.json").is_file()
    doc = json.loads((out / "tuned.json").read_text())
    pairs = doc["estimators"]["vqf-basic"]["overrides"]
    assert pairs and all(k in ("tauAcc", "tauMag") for k, _ in pairs)
    capsys.readouterr()
    assert main(["compare", "--estimators", "vqf-basic,dr", "--dataset", COURSE, "--data-dir", str(data_dir),
                 "--mag", "off", "--no-progress", "--jobs", "1", "--tuned", str(out / "tuned.json"),
                 "--json", str(tmp_path / "c.json")]) == 0
    err = capsys.readouterr().err
    assert "no tuned setting for dr" in err
    rows = json.loads((tmp_path / "c.json").read_text())["results"]
    label = "vqf-basic:" + ",".join(f"{k}={v}" for k, v in pairs)
    assert {r["estimator"] for r in rows} == {label, "dr"}
    common = doc["estimators"]["vqf-basic"]["common_deg"]
    mean = sum(r["rmse_deg"]["total"] for r in rows if r["estimator"] == label) / 3
    assert math.isclose(mean, common, rel_tol=1e-12)


def test_a_broken_tuned_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "tuned.json"
    bad.write_text('{"format": "something else"}')
    assert main(["compare", "--estimators", "dr", "--dataset", "sim", "--no-progress", "--tuned", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fusion: error: {bad}: not a tuned-settings file written by `fusion tune` (TypeError)"]


def test_ablate_tuned_fixes_what_the_grid_does_not_sweep(data_dir, tmp_path, capsys):
    tuned = tmp_path / "tuned.json"
    tuned.write_text(json.dumps({"format": tune.TUNED_FORMAT, "version": 1, "metric": "total", "dataset": "x",
                                 "estimators": {"vqf-basic": {"spec": "vqf-basic", "overrides": [["tauAcc", "2"],
                                                                                                 ["tauMag", "20"]]}}}))
    assert main(["ablate", "--estimator", "vqf-basic", "--param", "tauMag=3,9", "--dataset", "ece276a/1",
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1", "--tuned", str(tuned),
                 "--json", str(tmp_path / "a.json")]) == 0
    labels = [r["estimator"] for r in json.loads((tmp_path / "a.json").read_text())["results"]]
    assert labels == ["vqf-basic:tauAcc=2,tauMag=3", "vqf-basic:tauAcc=2,tauMag=9"]  # the grid's tauMag wins
    capsys.readouterr()
    assert main(["ablate", "--preset", "sigma", "--dataset", "sim", "--no-progress", "--tuned", str(tuned)]) == 1
    assert "--tuned apply to --estimator" in capsys.readouterr().err


def test_a_6d_dataset_tunes_no_magnetometer_parameter_and_the_table_tests_the_tuned_rows(data_dir, capsys):
    """On the course recordings (no magnetometer), the magnetometer's parameters are left out of the
    search, with a note naming them (a setting the data cannot exercise is not "chosen"); the table
    carries the tuned rows' interval, wins/ties/losses and Holm p, as a comparison's does."""
    import re

    code = main(["tune", "--estimators", "ekf,madgwick", "--dataset", "ece276a/1,ece276a/2,ece276a/3,ece276a/4,ece276a/5",
                 "--data-dir", str(data_dir), "--no-progress", "--jobs", "1"])
    out, err = capsys.readouterr()
    assert code == 0, err
    (line,) = [ln for ln in err.splitlines() if "hold no magnetometer" in ln]
    assert line.endswith("its parameters are left out of the search (ekf: Rm)")
    assert "Rm=" not in out and "95% CI (tuned)" in out and "W/T/L" in out and "Holm p" in out
    cells = {m[0]: m for m in re.findall(r"^(\S+) .*?\[([\d.]+), ([\d.]+)\](\*?)\s+(\S+)\s+(\S+)", out, re.M)}
    assert set(cells) == {"ekf", "madgwick"}
    (best,) = [label for label, c in cells.items() if c[5] == "best"]
    other = next(label for label in cells if label != best)
    assert sum(map(int, cells[other][4].split("/"))) == 5  # wins/ties/losses over the five test recordings
    assert float(cells[other][5]) <= 1.0 and cells[best][3] == "*"
    assert f"against the best tuned row ({best}; Wilcoxon signed-rank, Holm-corrected)" in out
