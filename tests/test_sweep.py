"""The BROAD sweep: the `broad-sweep` preset's grid, the best common setting (TAGP) and the
per-recording best read from an ablation's rows, and their place in the printed table,
results.json, the report and its figure."""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from fusion.cli import main
from fusion.evaluation.sweeps import ablate
from fusion.evaluation.report import plots
from fusion.estimators.params import parse_specs

from report_fixtures import toy, write_csv_dataset  # noqa: F401 (toy is a fixture)


def _row(dataset, label, total, coverage=1.0):
    return {"dataset": dataset, "estimator": label, "rmse_deg": {"total": total, "inclination": 0.0, "heading": 0.0},
            "coverage": coverage}


def test_sweep_summary_common_best_and_per_recording_best():
    # a is best on r1, b on r2; b has the lower mean (2.5 vs 3.0); c is never best
    errors = {("r1", "a"): 1.0, ("r2", "a"): 5.0, ("r1", "b"): 2.0, ("r2", "b"): 3.0, ("r1", "c"): 4.0, ("r2", "c"): 4.0}
    rows = [_row(d, lab, e) for (d, lab), e in errors.items()]
    rows.append(_row("r3", "a", 0.0, coverage=0.1))  # low coverage: left out as from the means
    s = ablate.sweep_summary(rows)
    assert s["best_common"] == {"estimator": "b", "mean_rmse_deg": 2.5}
    assert s["per_recording"] == [
        {"dataset": "r1", "best_estimator": "a", "best_rmse_deg": 1.0, "common_rmse_deg": 2.0},
        {"dataset": "r2", "best_estimator": "b", "best_rmse_deg": 3.0, "common_rmse_deg": 3.0}]
    assert s["mean_best_per_recording_deg"] == 2.0 and s["settings"] == 3 and s["recordings"] == 2
    text = ablate.format_sweep(s)
    assert "best common setting (lowest mean over all recordings): b  mean 2.50" in text
    assert ablate.sweep_summary([_row("r1", "a", 1.0)]) is None  # one setting: nothing to choose


def test_sweep_summary_per_broad_group():
    """BROAD's TAGP per group: the best common setting over each group's trials only."""
    errors = {("r1", "a"): 1.0, ("r2", "a"): 5.0, ("r3", "a"): 2.0,
              ("r1", "b"): 2.0, ("r2", "b"): 3.0, ("r3", "b"): 2.5}
    rows = [_row(d, lab, e) for (d, lab), e in errors.items()]
    groups = {"r1": ["all_trials", "undisturbed"], "r2": ["all_trials", "disturbed"], "r3": ["all_trials", "undisturbed"]}
    s = ablate.sweep_summary(rows, groups=groups)
    assert s["best_common"]["estimator"] == "b"  # 2.5 against 2.67 over all three
    assert s["groups"] == [
        {"group": "all_trials", "recordings": 3, "best_estimator": "b", "mean_rmse_deg": 2.5},
        {"group": "undisturbed", "recordings": 2, "best_estimator": "a", "mean_rmse_deg": 1.5},
        {"group": "disturbed", "recordings": 1, "best_estimator": "b", "mean_rmse_deg": 3.0}]
    assert s["trial_groups"] == groups
    assert "undisturbed       2    1.50  a" in ablate.format_sweep(s)
    assert "groups" not in ablate.sweep_summary(rows)  # without trials.json: no group lines


def test_trial_groups_read_broads_trials_json(tmp_path):
    from fusion.formats.broad import trial_groups

    trial = tmp_path / "36_disturbed_attached_magnet_5cm.hdf5"
    assert trial_groups(trial) == []  # no trials.json beside it
    (tmp_path / "trials.json").write_text(json.dumps(
        {"trials": {trial.stem: {"groups": ["all_trials", "disturbed", "attached_magnet"]}}}))
    assert trial_groups(trial) == ["all_trials", "disturbed", "attached_magnet"]
    assert trial_groups(tmp_path / "99_unknown.hdf5") == []
    (tmp_path / "trials.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"trials\.json: not BROAD's trials\.json"):
        trial_groups(trial)


def test_broad_sweep_preset_is_the_ekf_grid():
    specs = ablate.preset_specs("broad-sweep")
    assert len(specs) == 30 and {s.name for s in specs} == {"ekf"}
    combos = [tuple(v for _, v in s.overrides) for s in specs]
    assert combos == list(itertools.product(*ablate.BROAD_SWEEP.values()))
    assert [k for k, _ in specs[0].overrides] == ["Q", "R", "tauc"]
    assert ("3e-4", "3e-5", "0.1") in combos  # EKFParams' defaults are in the grid
    from fusion import estimators
    first = estimators.build(specs[-1]).params
    assert (first.process_noise_rad2_s, first.acc_noise_g2_s, first.disturbance_corr_s) == (1e-3, 1e-3, 0.5)


def test_ablate_prints_and_writes_the_sweep(toy, tmp_path, capsys):
    data = write_csv_dataset(tmp_path / "data", count=2, n=400)
    out = tmp_path / "abl"
    code = main(["ablate", "--estimator", "toy", "--param", "g=0.9,1,1.1", "--param", "mode=plain,rough",
                 "--data-dir", str(data), "--out", str(out), "--jobs", "1", "--no-progress"])
    printed = capsys.readouterr().out
    assert code == 0
    doc = json.loads((out / "results.json").read_text())
    sweep = doc["sweep"]
    assert sweep == ablate.sweep_summary(doc["results"])
    labels = list(dict.fromkeys(r["estimator"] for r in doc["results"]))
    mean = {lab: np.mean([r["rmse_deg"]["total"] for r in doc["results"] if r["estimator"] == lab]) for lab in labels}
    assert sweep["best_common"]["estimator"] == min(labels, key=mean.get)
    assert sweep["best_common"]["estimator"].startswith("toy:g=1,")  # the unscaled gyro
    assert [p["dataset"] for p in sweep["per_recording"]] == ["lab/rec1", "lab/rec2"]
    assert ablate.format_sweep(sweep) in printed
    assert ablate.format_sweep(sweep) in (out / "table.txt").read_text()
    assert "## Sweep" in (out / "report.md").read_text() and "Sweep" in (out / "report.html").read_text()
    assert (out / "figures" / "ablation-sweep.png").is_file()
    # the figure: one panel per parameter, each point the minimum of the mean over the others
    fig = plots.sweep_figure(doc["results"])
    panels = [ax for ax in fig.axes if ax.get_lines()]
    assert len(panels) == 2
    g_line = panels[0].get_lines()[0]
    np.testing.assert_allclose(g_line.get_xdata(), [0.9, 1.0, 1.1])
    np.testing.assert_allclose(g_line.get_ydata(), [min(mean[f"toy:g={g},mode={m}"] for m in ("plain", "rough"))
                                                    for g in ("0.9", "1", "1.1")])
    star = panels[0].get_lines()[1]
    assert star.get_ydata()[0] == pytest.approx(sweep["best_common"]["mean_rmse_deg"])
    assert plots.sweep_figure([r for r in doc["results"] if "mode=plain" in r["estimator"]]) is None  # one parameter
    assert parse_specs(sweep["best_common"]["estimator"])[0].name == "toy"
