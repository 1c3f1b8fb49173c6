"""The progress bar of a run advances job by job as jobs finish (locally: in this process and
in the process pool), not all at once at the end. Ordered by events, not by the clock: job k
waits until the bar has shown k finished jobs (`cluster_fixtures.Gate`); a bar updated only at
the end would leave it waiting, and the job would fail."""
from __future__ import annotations

import pytest

from fusion.evaluation.run.runner import run
from report_fixtures import recording

import cluster_fixtures


@pytest.mark.parametrize("jobs", [1, 2])
def test_bar_moves_as_each_job_finishes(monkeypatch, tmp_path, jobs):
    cluster_fixtures.register(monkeypatch)
    bars = cluster_fixtures.record_progress(monkeypatch, tmp_path)
    specs = ["gate"] + [f"gate:wait_for={tmp_path / f'updated-{k}'}" for k in range(1, 4)]
    results = run(specs, [recording(300, rid="toy/1")], jobs=jobs, progress=True)
    (bar,) = bars
    assert [r.error for r in results] == [None] * 4  # every job saw the bar move before it ended
    assert bar.total == 4 and len(bar.updates) == 4 and bar.closed_at >= bar.updates[-1]
    assert len(bar.postfixes) == 4 and all(p.startswith("toy/1 gate") for p in bar.postfixes)
