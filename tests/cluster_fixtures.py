"""Test-only estimators for the parallel-run tests (`tests/test_dask.py`): one that takes a
fixed time per job (to watch a progress bar move) and one that kills the Dask worker running
it on its first attempt (to check that a dead worker costs a retry, not a row). Both return
dead reckoning, so their rows are deterministic."""
from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.estimators.base import Estimator
from fusion.estimators.dr import DeadReckoning
from fusion.types import ImuSamples, Trajectory


@dataclass(frozen=True)
class SleepyParams:
    sleep_s: float = field(default=0.3, metadata={"alias": "s"})


class Sleepy(Estimator):
    """Dead reckoning after sleeping `sleep_s` seconds."""

    Params = SleepyParams

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        time.sleep(self.params.sleep_s)
        return DeadReckoning().estimate(imu, init_quat_wxyz)


@dataclass(frozen=True)
class KillerParams:
    marker: str = ""


class Killer(Estimator):
    """Dead reckoning; but inside a Dask worker, if the file `marker` does not exist yet, it
    creates it and kills its own worker process (SIGKILL: no clean-up, as a crashed or
    OOM-killed machine). Outside a worker it never kills (a serial run is the reference)."""

    Params = KillerParams

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        from distributed import get_worker

        try:
            get_worker()
            in_worker = True
        except ValueError:
            in_worker = False
        if in_worker and self.params.marker:
            try:
                fd = os.open(self.params.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                fd = None
            if fd is not None:
                os.write(fd, str(os.getpid()).encode())
                os.close(fd)
                os.kill(os.getpid(), signal.SIGKILL)
        return DeadReckoning().estimate(imu, init_quat_wxyz)


@dataclass(frozen=True)
class GateParams:
    started: str = ""  # a folder: write `started-<pid>-<n>` (holding the pid) there when a job starts
    wait_for: str = ""  # a path: wait until it exists before finishing
    limit_s: float = 120.0  # give up waiting after this long (a failure, never a pass)


class Gate(Estimator):
    """Dead reckoning, after announcing that it started (`started`) and waiting for a file to
    appear (`wait_for`): tests order events by files, not by sleeping and hoping."""

    Params = GateParams

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        if self.params.started:
            folder = Path(self.params.started)
            n = len(list(folder.glob(f"started-{os.getpid()}-*")))
            # written under another name and renamed: a reader never sees the file empty
            partial = folder / f".partial-{os.getpid()}-{n}"
            partial.write_text(str(os.getpid()))
            os.replace(partial, folder / f"started-{os.getpid()}-{n}")
        if self.params.wait_for:
            deadline = time.monotonic() + self.params.limit_s
            while not Path(self.params.wait_for).exists():
                if time.monotonic() > deadline:
                    raise RuntimeError(f"gate: {self.params.wait_for} did not appear within {self.params.limit_s} s")
                time.sleep(0.01)
        return DeadReckoning().estimate(imu, init_quat_wxyz)


def started_pids(folder: Path) -> list[int]:
    """The pids of the processes that started a `Gate` job announcing itself in `folder`."""
    return sorted({int(p.read_text()) for p in Path(folder).glob("started-*")})


def wait_until(condition, what: str, limit_s: float = 120.0) -> None:
    """Wait for an event (a file, a process's end); fail, naming it, if it never happens."""
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {limit_s} s")
        time.sleep(0.02)


def alive(pid: int) -> bool:
    """Whether process `pid` exists and is not a zombie (Linux: /proc)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def register(monkeypatch) -> None:
    from fusion import estimators
    monkeypatch.setitem(estimators.ESTIMATORS, "sleepy", Sleepy)
    monkeypatch.setitem(estimators.ESTIMATORS, "killer", Killer)
    monkeypatch.setitem(estimators.ESTIMATORS, "gate", Gate)


def marker_pid(path: str | Path) -> int:
    return int(Path(path).read_text())


class RecordingBar:
    """Stands in for the tqdm bar of `fusion.evaluation.run.runner`: keeps the time of every update,
    and with `folder` writes `updated-<count>` there at each (for `Gate` jobs to wait on)."""

    def __init__(self, total: int, folder: Path | None = None) -> None:
        self.total = total
        self.folder = folder
        self.updates: list[float] = []
        self.postfixes: list[str] = []
        self.closed_at: float | None = None

    def update(self, n: int = 1) -> None:
        self.updates += [time.monotonic()] * n
        if self.folder is not None and n:
            (self.folder / f"updated-{len(self.updates)}").write_text("")

    def set_postfix_str(self, text: str) -> None:
        self.postfixes.append(text)

    def close(self) -> None:
        self.closed_at = time.monotonic()


def record_progress(monkeypatch, folder: Path | None = None) -> list[RecordingBar]:
    """Replace the runner's progress bar; returns the list the bars of later runs are appended to."""
    from fusion.evaluation.run import runner

    bars: list[RecordingBar] = []

    def make(total: int, enabled: bool) -> RecordingBar:
        bars.append(RecordingBar(total, folder))
        return bars[-1]

    monkeypatch.setattr(runner, "_progress", make)
    return bars


TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent

# Runs `fusion` (or, with "--library", `run_ablate(**json)`) with the test-only estimators registered.
_MAIN = ("import json, sys; sys.path.insert(0, sys.argv[1]); import pytest, cluster_fixtures, report_fixtures; "
         "mp = pytest.MonkeyPatch(); cluster_fixtures.register(mp); report_fixtures.register(mp)\n"
         "if sys.argv[2] == '--library':\n"
         "    from fusion.evaluation.runs import run_ablate; run_ablate(**json.loads(sys.argv[3])); sys.exit(0)\n"
         "from fusion.cli import main; sys.exit(main(sys.argv[2:]))")


def fusion_process(*argv: str, **popen):
    """A `fusion ...` process (or `--library JSON`: a Python caller of `run_ablate`) that knows the
    test-only estimators."""
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-c", _MAIN, str(TESTS), *argv], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **popen)
