"""Ablations: the grid of specs, one value == compare, presets checked against the registry,
and the figures of RMSE against each parameter."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.estimators.params import EstimatorSpec
from fusion.evaluation.sweeps import ablate
from fusion.evaluation.report import plots
from fusion.cli import main

from report_fixtures import toy, write_csv_dataset  # noqa: F401 (toy is a fixture)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_csv_dataset(tmp_path_factory.mktemp("ablate") / "data")


def _rows(doc):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in doc["results"]]


def test_grid_specs_order_and_labels():
    specs = ablate.grid_specs("ukf:Q=1e-5", [("R", ["1e-4", "1e-3"]), ("sigma", ["kraft", "julier", "merwe"])])
    assert [s.label for s in specs][:4] == ["ukf:Q=1e-5,R=1e-4,sigma=kraft", "ukf:Q=1e-5,R=1e-4,sigma=julier",
                                             "ukf:Q=1e-5,R=1e-4,sigma=merwe", "ukf:Q=1e-5,R=1e-3,sigma=kraft"]
    assert len(specs) == 6 and specs[0] == EstimatorSpec("ukf", (("Q", "1e-5"), ("R", "1e-4"), ("sigma", "kraft")))
    assert ablate.parse_param("R=1e-4, 1e-3") == ("R", ["1e-4", "1e-3"])
    for bad in ("R", "R=", "=1", "R=1,1"):
        with pytest.raises(ValueError, match="--param"):
            ablate.parse_param(bad)
    with pytest.raises(ValueError, match="both fixed"):
        ablate.grid_specs("ukf:R=1", [("R", ["2"])])


def test_ablate_with_one_value_equals_compare(toy, data, tmp_path):
    assert main(["ablate", "--estimator", "toy", "--param", "g=1.05", "--data-dir", str(data),
                 "--json", str(tmp_path / "a.json"), "--jobs", "1", "--no-progress"]) == 0
    assert main(["compare", "--estimators", "toy:g=1.05", "--data-dir", str(data),
                 "--json", str(tmp_path / "c.json"), "--jobs", "1", "--no-progress"]) == 0
    a, c = (json.loads((tmp_path / f"{x}.json").read_text()) for x in "ac")
    assert _rows(a) == _rows(c) and len(a["results"]) == 2
    assert a["settings"]["estimator_details"] == c["settings"]["estimator_details"]
    assert a["settings"]["params"] == {"g": ["1.05"]} and a["settings"]["kind"] == "ablate"


def test_grid_ablation_writes_parameter_plots(toy, data, tmp_path, capsys):
    out = tmp_path / "abl"
    code = main(["ablate", "--estimator", "toy", "--param", "g=0.9,1,1.1", "--param", "mode=plain,rough",
                 "--data-dir", str(data), "--out", str(out), "--jobs", "2", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    doc = json.loads((out / "results.json").read_text())
    labels = list(dict.fromkeys(r["estimator"] for r in doc["results"]))
    assert labels == [f"toy:g={g},mode={m}" for g in ("0.9", "1", "1.1") for m in ("plain", "rough")]
    assert len(doc["results"]) == 12
    names = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert names == ["ablation-bars.png", "ablation-grid.png", "ablation-params.png", "ablation-sweep.png",
                     "summary-rmse.png", "summary-speed.png"]  # no per-recording figures without --per-recording
    # RMSE vs each parameter: one panel per parameter, one line per value of the other
    fig = plots.param_figure(doc["results"])
    panels = [ax for ax in fig.axes if ax.get_lines()]
    assert [len(ax.get_lines()) for ax in panels] == [2, 3]
    gain_line = panels[0].get_lines()[0]  # mode=plain, against g
    np.testing.assert_allclose(gain_line.get_xdata(), [0.9, 1.0, 1.1])
    means = [np.mean([r["rmse_deg"]["total"] for r in doc["results"] if r["estimator"] == f"toy:g={g},mode=plain"])
             for g in ("0.9", "1", "1.1")]
    np.testing.assert_allclose(gain_line.get_ydata(), means)
    assert means[1] < means[0] and means[1] < means[2]  # the unscaled gyro is best
    grid = plots.grid_figure(doc["results"])
    assert grid.axes[0].images[0].get_array().shape == (3, 2)
    bars = plots.bars_figure(doc["results"])
    assert len(bars.axes[0].patches) == 6 * 3
    table = (out / "table.txt").read_text()
    assert "toy:g=1.1,mode=rough" in table


def test_preset_runs_and_unregistered_estimator_is_a_clear_error(toy, data, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(ablate.PRESETS, "toy-gain", ["dr", "toy:g=0.95", "toy:g=1.05"])
    monkeypatch.setitem(ablate.PRESETS, "needs-ghost", ["dr", "ghost:R=1"])
    assert main(["ablate", "--preset", "toy-gain", "--data-dir", str(data), "--json", str(tmp_path / "p.json"),
                 "--jobs", "1", "--no-progress"]) == 0
    doc = json.loads((tmp_path / "p.json").read_text())
    assert [r["estimator"] for r in doc["results"]][:3] == ["dr", "toy:g=0.95", "toy:g=1.05"]
    assert doc["settings"]["preset"] == "toy-gain"
    capsys.readouterr()
    assert main(["ablate", "--preset", "needs-ghost", "--data-dir", str(data), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "preset 'needs-ghost' needs estimator(s) ghost, not registered here" in err and err.count("\n") == 1
    assert main(["ablate", "--preset", "nope", "--data-dir", str(data), "--no-progress"]) == 1
    assert "unknown preset 'nope'; available: ukf-vs-dr, sigma" in capsys.readouterr().err


def test_shipped_presets_are_well_formed():
    from fusion import estimators
    from fusion.estimators.params import parse_specs

    assert {"ukf-vs-dr", "sigma", "accel-update", "smoother-solvers", "motion-weight"} <= set(ablate.PRESETS)
    for name, texts in ablate.PRESETS.items():
        specs = [s for t in texts for s in parse_specs(t)]
        assert len(specs) == len(texts) >= 2, name
        assert len({s.label for s in specs}) == len(specs), name
        if all(s.name in estimators.ESTIMATORS for s in specs):  # names and values valid here
            assert [s.label for s in ablate.preset_specs(name)] == [s.label for s in specs]


@pytest.mark.parametrize("argv, message", [
    (["--estimator", "toy", "--param", "nope=1,2"], "unknown parameter 'nope'; valid: g, gain, mode"),
    (["--estimator", "toy", "--param", "mode=plain,wobbly"], "'wobbly' is not one of plain, rough"),
    (["--estimator", "toy", "--param", "g=-1"], "gain must be positive"),
    (["--estimator", "toy"], "needs at least one --param"),
    (["--preset", "sigma", "--estimator", "toy"], "either --preset"),
    (["--estimator", "toy,dr", "--param", "g=1"], "name one estimator"),
])
def test_bad_ablations_are_one_line(toy, data, capsys, argv, message):
    assert main(["ablate", *argv, "--data-dir", str(data), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
