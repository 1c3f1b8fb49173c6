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


def register(monkeypatch) -> None:
    from fusion import estimators
    monkeypatch.setitem(estimators.ESTIMATORS, "sleepy", Sleepy)
    monkeypatch.setitem(estimators.ESTIMATORS, "killer", Killer)


def marker_pid(path: str | Path) -> int:
    return int(Path(path).read_text())


class RecordingBar:
    """Stands in for the tqdm bar of `fusion.evaluation.runner`: keeps the time of every update."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.updates: list[float] = []
        self.postfixes: list[str] = []
        self.closed_at: float | None = None

    def update(self, n: int = 1) -> None:
        self.updates += [time.monotonic()] * n

    def set_postfix_str(self, text: str) -> None:
        self.postfixes.append(text)

    def close(self) -> None:
        self.closed_at = time.monotonic()


def record_progress(monkeypatch) -> list[RecordingBar]:
    """Replace the runner's progress bar; returns the list the bars of later runs are appended to."""
    from fusion.evaluation import runner

    bars: list[RecordingBar] = []

    def make(total: int, enabled: bool) -> RecordingBar:
        bars.append(RecordingBar(total))
        return bars[-1]

    monkeypatch.setattr(runner, "_progress", make)
    return bars
