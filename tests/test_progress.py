"""The progress bar of a run advances job by job as jobs finish (locally: in this process and
in the process pool), not all at once at the end."""
from __future__ import annotations

import time

import pytest

from fusion.evaluation.runner import run
from report_fixtures import recording

import cluster_fixtures


@pytest.fixture
def sleepy(monkeypatch):
    cluster_fixtures.register(monkeypatch)
    return cluster_fixtures.record_progress(monkeypatch)


@pytest.mark.parametrize("jobs", [1, 2])
def test_bar_moves_as_each_job_finishes(sleepy, jobs):
    bars = sleepy
    recs = [recording(300, seed=k, rid=f"toy/{k}") for k in range(3)]
    start = time.monotonic()
    results, _ = run(["sleepy:s=0.3", "sleepy:s=0.31"], recs, jobs=jobs, progress=True)
    (bar,) = bars
    assert len(results) == 6 and bar.total == 6
    assert len(bar.updates) == 6 and bar.updates == sorted(bar.updates)
    # 6 jobs of 0.3 s on `jobs` processes finish in 6 / jobs waves: the first update comes after
    # the first wave, long before the last job finishes (a bar updated only at the end would
    # show all six within milliseconds)
    waves = 6 // jobs
    assert bar.updates[0] - start >= 0.25
    assert bar.updates[-1] - bar.updates[0] >= 0.3 * (waves - 1) - 0.1
    assert bar.closed_at >= bar.updates[-1]
    assert len(bar.postfixes) == 6 and all(p.startswith("toy/") for p in bar.postfixes)
