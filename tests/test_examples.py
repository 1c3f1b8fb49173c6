"""The examples users read run as written: the usage block of the library modules' docstrings
and the README's "Python API" section (on `sim`, the built-in simulated recording)."""
from __future__ import annotations

import contextlib
import importlib
import io
import re
import textwrap
from pathlib import Path

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


def test_runner_docstring_example_runs(no_data):
    namespace: dict = {}
    exec(docstring_example("fusion.evaluation.runner"), namespace)
    results = namespace["results"]
    assert [(r.dataset, r.estimator) for r in results] == [("sim", "dr"), ("sim", "ukf:R=1e-3")]
    assert all(r.rmse_deg["total"] > 0 for r in results)
    assert all(r.trajectory is None and r.error is None for r in results)  # rows, not trajectories


@pytest.mark.parametrize("module, name", [("fusion.evaluation.compare", "results"), ("fusion.evaluation.job", "result"),
                                          ("fusion.evaluation.runs", "run"), ("fusion.selection", "recordings")])
def test_library_docstring_examples_run(no_data, module, name):
    namespace: dict = {}
    with contextlib.redirect_stderr(io.StringIO()):
        exec(docstring_example(module), namespace)
    assert namespace[name]


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
    printed = capsys.readouterr().out
    assert "'inclination'" in printed and "RMSE in degrees" in printed and re.search(r"\nsim +ekf +\d", printed)
