"""The examples users read run as written: the usage block of the library modules' docstrings
and the README's "Python API" section (on `sim`, the built-in simulated recording). Each gives
the rows it promises, and every score equals the README's step-by-step API (build, estimate,
score) on the same recording."""
from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import io
import re
import textwrap
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def docstring_example(module_name: str) -> str:
    """The first indented block of a module's docstring (the usage example)."""
    doc = importlib.import_module(module_name).__doc__
    block = re.search(r"\n\n((?:    .*\n)+)", doc)
    assert block, f"{module_name}: no indented example in its docstring"
    return textwrap.dedent(block.group(1))


@pytest.fixture
def no_data(monkeypatch, tmp_path):
    """No data directory: `sim` is the only recording."""
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)


@functools.cache
def step_by_step_rmse(spec: str) -> dict[str, float]:
    """The README's step-by-step API on `sim`: what every example below must reproduce."""
    from fusion import datasets, estimators
    from fusion.datasets import initial_orientation
    from fusion.evaluation.scoring.metrics import score

    recording = datasets.load("sim")
    trajectory = estimators.build(spec).estimate(recording.imu, initial_orientation(recording))
    return score(recording.truth, trajectory).rmse_deg


def assert_rows(results, specs: list[str]) -> None:
    """One row per spec on `sim`, in order, each scoring what the step-by-step API scores
    (the same deterministic computation: equal to rounding)."""
    assert [(r.dataset, r.estimator) for r in results] == [("sim", spec) for spec in specs]
    for r in results:
        expected = step_by_step_rmse(r.estimator)
        assert r.rmse_deg == pytest.approx(expected, rel=1e-12), r.estimator
        assert r.samples == r.scored_samples > 10_000 and r.coverage == 1.0  # sim: 3 min at 100 Hz, all scored


def test_runner_docstring_example_runs(no_data):
    namespace: dict = {}
    exec(docstring_example("fusion.evaluation.run.runner"), namespace)
    results = namespace["results"]
    assert_rows(results, ["dr", "ukf:R=1e-3"])
    assert all(r.trajectory is None and r.error is None for r in results)  # rows, not trajectories


def run_example(module: str) -> dict:
    namespace: dict = {}
    with contextlib.redirect_stderr(io.StringIO()):
        exec(docstring_example(module), namespace)
    return namespace


def test_compare_docstring_example_runs(no_data):
    assert_rows(run_example("fusion.evaluation.compare")["results"], ["dr", "ukf:R=1e-3"])


def test_job_docstring_example_runs(no_data):
    assert_rows([run_example("fusion.evaluation.run.job")["result"]], ["ukf:R=1e-3"])


def test_runs_docstring_example_runs(no_data):
    run = run_example("fusion.evaluation.runs")["run"]
    assert_rows(run.results, ["dr", "ukf"])
    rows = [line.split() for line in run.table.splitlines()]
    assert [row[:2] for row in rows if row[:1] == ["sim"]] == [["sim", "dr"], ["sim", "ukf"]]


def test_selection_docstring_example_runs(no_data):
    from fusion import datasets

    recordings = run_example("fusion.selection")["recordings"]
    assert [r.id for r in recordings] == ["sim"]
    reference = datasets.load("sim").imu
    np.testing.assert_array_equal(recordings[0].imu.t, reference.t)
    np.testing.assert_array_equal(recordings[0].imu.gyr_rad_s, reference.gyr_rad_s)
    np.testing.assert_array_equal(recordings[0].imu.acc_g, reference.acc_g)


def test_run_compare_is_the_cli_in_two_lines(no_data, capsys):
    from fusion.cli import main
    from fusion.evaluation.runs import run_compare

    run = run_compare("dr,ekf", "sim")
    assert main(["compare", "--estimators", "dr,ekf", "--dataset", "sim", "--no-progress", "--jobs", "1"]) == 0
    cli_table = capsys.readouterr().out
    number = re.compile(r"\s+\d+\.\d+$")  # us/sample differs between runs
    assert [number.sub("", line) for line in run.table.splitlines()] == \
           [number.sub("", line) for line in cli_table.rstrip("\n").splitlines()]
    assert [r.estimator for r in run.results] == ["dr", "ekf"] and run.document is None and run.report is None


def test_readme_python_api_runs(no_data, capsys):
    section = README.read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 2
    for block in blocks:
        exec(block, {})
    printed = capsys.readouterr().out.splitlines()
    expected = step_by_step_rmse("ekf")
    assert ast.literal_eval(printed[0]) == pytest.approx(expected, rel=1e-12)  # the first block's print
    assert printed[1].startswith("RMSE in degrees")
    rows = {tuple(line.split()[:2]): line.split()[2:5] for line in printed[2:] if line.startswith("sim ")}
    assert list(rows) == [("sim", "dr"), ("sim", "ekf")]
    assert rows["sim", "ekf"] == [f"{expected[k]:.2f}" for k in ("total", "inclination", "heading")]  # the table's 2 decimals
