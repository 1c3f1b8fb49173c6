"""Shared fixtures.

Real-data tests use `data_dir`: the course recordings at `$FUSION_DATA`. Without the
variable they are skipped (a fresh clone has no data), except under CI (`CI=true`, which
`.ci/run` exports), where that is a failure; with the variable set but the files missing they
*fail*, so CI (which sets FUSION_DATA=../shared/data) cannot silently skip them. The rules are
`optional_helpers.real_data_dir`'s.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from optional_helpers import real_data_dir


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return real_data_dir()


# --- fuzzing statistics (tests/test_fuzz_loaders.py), printed at the end for the CI log --------

_FUZZ_STATS = pytest.StashKey[dict]()


@pytest.fixture(scope="session")
def fuzz_stats(request) -> dict:
    """Counts of generated broken-file cases and of the tracebacks they caused."""
    return request.config.stash.setdefault(_FUZZ_STATS, {"cases": 0, "tracebacks": 0})


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    stats = config.stash.get(_FUZZ_STATS, None)
    if stats:
        terminalreporter.write_line(
            f"fuzz: {stats['cases']} cases, {stats['tracebacks']} tracebacks "
            f"(loaded {stats.get('ok', 0)}, repaired with a warning {stats.get('warn', 0)}, rejected {stats.get('error', 0)})")
