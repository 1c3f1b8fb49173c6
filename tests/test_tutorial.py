"""The tutorial runs: every notebook of docs/tutorial is built from its jupytext source and
executed top to bottom (nbclient, a kernel of this Python), as `python docs/build_tutorial.py`
does. A notebook that raises, or takes longer than `TIMEOUT_S`, fails the test; each one's run
time is printed at the end of the session.

Data: with `$FUSION_DATA` set the notebooks run on the course recordings there, and a variable
pointing at a folder without them *fails* (as the real-data tests do, tests/conftest.py), rather
than quietly teaching on simulated data; without it they run on the built-in `sim` recording,
except under CI (`CI=true`), where that fails too.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest

import fusion

from optional_helpers import real_data_dir, under_ci

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("build_tutorial", ROOT / "docs" / "build_tutorial.py")
build_tutorial = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("build_tutorial", build_tutorial)  # its dataclass looks its module up there
_spec.loader.exec_module(build_tutorial)

NOTEBOOKS = build_tutorial.sources()
# The notebooks are written to run in under two minutes each on a 2-core machine; the limit here
# leaves room for a busy CI runner (their times are printed, see `timings`).
TIMEOUT_S = 200.0


def test_every_notebook_is_found():
    names = [p.stem for p in NOTEBOOKS]
    assert [n[:2] for n in names] == [f"{i:02d}" for i in range(1, len(names) + 1)], names
    assert len(names) >= 7


@pytest.fixture(scope="session")
def tutorial_data() -> str | None:
    """`$FUSION_DATA` (checked to hold the course recordings), or None: the notebooks use `sim`.
    Under CI (`CI=true`) the variable must be set: CI teaches on the real recordings."""
    if not os.environ.get("FUSION_DATA") and not under_ci():
        return None
    return str(real_data_dir())  # fails when the variable names a folder without the recordings


@pytest.fixture(scope="session")
def timings(request):
    """Run time per notebook, printed when the session ends."""
    seen: dict[str, float] = {}
    yield seen
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    if reporter is not None and capture is not None and seen:
        with capture.global_and_fixture_disabled():  # teardown output is captured otherwise
            reporter.write_line("")
            reporter.write_line("tutorial notebooks: " + ", ".join(f"{name} {s:.1f} s" for name, s in seen.items())
                                + f"; total {sum(seen.values()):.0f} s")


@pytest.mark.slow
@pytest.mark.parametrize("source", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(source, tutorial_data, timings, tmp_path, record_property):
    built = build_tutorial.execute(source, TIMEOUT_S, tutorial_data, out_dir=tmp_path)
    timings[source.stem] = built.seconds
    record_property("seconds", round(built.seconds, 1))
    assert built.error is None, built.error
    text = "".join(out.get("text", "") for cell in built.nb.cells if cell.cell_type == "code"
                   for out in cell.get("outputs", []) if out.get("output_type") == "stream")
    # The kernel ran this interpreter's `fusion` (the checkout under test), and the notebook said
    # which recording it used: real data when FUSION_DATA is set, `sim` (announced) otherwise.
    assert f"fusion imported from {Path(fusion.__file__).resolve().parent}" in text
    if tutorial_data:
        assert "NOTE: no recording" not in text and "from " + tutorial_data in text
    else:
        assert "built-in simulated recording" in text
    assert (tmp_path / f"{source.stem}.ipynb").is_file()
    # The figures are the lesson: every notebook shows some (inline PNGs, whatever MPLBACKEND says).
    images = [out for cell in built.nb.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
              if "image/png" in out.get("data", {})]
    assert len(images) >= 2, f"{source.name}: {len(images)} figures"


def test_missing_data_fails_the_notebook(tmp_path):
    """FUSION_DATA pointing at an empty folder stops a notebook with an error, not a fallback to `sim`."""
    built = build_tutorial.execute(NOTEBOOKS[1], TIMEOUT_S, str(tmp_path), out_dir=tmp_path)
    assert built.error is not None and "FileNotFoundError" in built.error and "FUSION_DATA" in built.error
