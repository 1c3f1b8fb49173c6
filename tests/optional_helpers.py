"""What a test may skip, and what it must fail on under CI.

A test is skipped only when something optional is missing on a developer's machine: the real
recordings (`$FUSION_DATA` unset), an optional package (`h5py`, the peers' libraries) or a peer
estimator whose library is not installed (`PeerUnavailable`, which the peers raise when they are
*built* and nowhere else). Under CI (`CI=true`, exported by `.ci/run`, which installs the test
extra with every optional package and points `FUSION_DATA` at the shared recordings) each of these
is a failure instead: a skipped test there would hide a broken set-up.

Nothing here catches an error raised while an estimator *runs*: an ImportError inside `estimate`
is a failure like any other exception.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
from pathlib import Path
from types import ModuleType

import pytest

from fusion import estimators
from fusion.estimators import Estimator
from fusion.estimators.peers.vqf_fusion import PeerUnavailable

COURSE_FILE = Path("ece276a") / "imu" / "imuRaw1.p"  # what a data folder must hold


def under_ci() -> bool:
    """Whether this run is CI (`CI=true`, as `.ci/run` and the common CI services set it)."""
    return os.environ.get("CI") == "true"


def unavailable(reason: str) -> None:
    """Skip the test for something optional that is missing, or fail it under CI."""
    if under_ci():
        pytest.fail(f"{reason}; under CI (CI=true) this fails instead of skipping: CI installs every optional "
                    "package and sets FUSION_DATA")
    pytest.skip(reason)


def optional_module(name: str) -> ModuleType | None:
    """The optional module `name`, or None when it is not installed (a failure under CI).

    Decided by whether the module can be found, not by catching an ImportError: a module that
    is installed but fails to import raises, as any broken dependency should."""
    if importlib.util.find_spec(name.partition(".")[0]) is None:
        if under_ci():
            unavailable(f"optional package {name!r} is not installed")
        return None
    return importlib.import_module(name)


def require_module(name: str) -> ModuleType:
    """The optional module `name`; the test is skipped without it (failed under CI)."""
    module = optional_module(name)
    if module is None:
        unavailable(f"optional package {name!r} is not installed")
    return module


def build_if_available(spec: str) -> Estimator | None:
    """`estimators.build(spec)`, or None for a peer whose library is not installed (a failure
    under CI). Only the construction is guarded: run the estimator outside this call."""
    try:
        return estimators.build(spec)
    except PeerUnavailable as exc:
        if under_ci():
            unavailable(str(exc))
        return None


def build_estimator(spec: str) -> Estimator:
    """`estimators.build(spec)`; the test is skipped for a peer whose library is not installed
    (failed under CI). Only the construction is guarded: run the estimator outside this call."""
    try:
        return estimators.build(spec)
    except PeerUnavailable as exc:
        unavailable(str(exc))
        raise  # not reached: unavailable() skips or fails


def real_data_dir() -> Path:
    """The real recordings at `$FUSION_DATA`: skipped when the variable is unset (a fresh clone
    has no data; failed under CI), failed when it is set but the course recordings are missing."""
    value = os.environ.get("FUSION_DATA")
    if not value:
        unavailable("FUSION_DATA is not set: no real recordings")
    path = Path(value).resolve()
    if not (path / COURSE_FILE).is_file():
        pytest.fail(f"FUSION_DATA={value} is set but holds no {COURSE_FILE.as_posix()}")
    return path
