"""Shared fixtures.

Real-data tests use `data_dir`: the course recordings at `$FUSION_DATA`. Without the
variable they are skipped (a fresh clone has no data); with it set but the files missing
they *fail*, so CI (which sets FUSION_DATA=../shared/data) cannot silently skip them.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def data_dir() -> Path:
    value = os.environ.get("FUSION_DATA")
    if not value:
        pytest.skip("FUSION_DATA is not set: real-recording tests skipped")
    path = Path(value).resolve()
    if not (path / "ece276a" / "imu" / "imuRaw1.p").is_file():
        pytest.fail(f"FUSION_DATA={value} is set but holds no ece276a/imu/imuRaw1.p")
    return path


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
