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
