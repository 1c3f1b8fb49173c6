"""Leave-one-recording-out scoring of the VICON gyro calibration (`fusion calibrate --leave-one-out`).

For each recording with ground truth: fit the gyro scale factors on all the *other* recordings
(`fusion.gyro_fit.leave_one_out`), re-calibrate the held-out recording with them, run the
estimators on it and score it. No recording is ever scored with a calibration fitted on itself.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from fusion import gyro_fit
from fusion.types import Recording

from ..compare import Result, compare


@dataclass(frozen=True)
class Fold:
    """One fold: choose (or fit) on `train`, score on `test` (recording ids). The folds of
    `fusion tune` (`fusion.evaluation.sweeps.tune.folds_of`) and of the leave-one-out calibration."""

    name: str
    train: tuple[str, ...]
    test: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class CalibrationFold:
    """One fold of the leave-one-out gyro calibration: the `Fold` (one recording held out), the
    fit on its training recordings and the results on the held-out one."""

    fold: Fold
    fit: gyro_fit.GyroFit
    results: list[Result]

    @property
    def held_out(self) -> str:
        return self.fold.name


def leave_one_out(specs: Iterable, recordings: list[Recording], init: str | None = None,
                  progress: bool = False, align: bool = False) -> list[CalibrationFold]:
    specs = list(specs)
    by_id = {r.id: r for r in recordings}
    folds = []
    for held, fitted in gyro_fit.leave_one_out(recordings):
        if held in fitted.fitted_on:  # the whole point: never fit on the scored recording
            raise RuntimeError(f"leave-one-out fold for {held} was fitted on it")
        rec = gyro_fit.with_gyro_scale(by_id[held], fitted.gyro_scale_factor)
        fold = Fold(held, tuple(fitted.fitted_on), (held,))
        folds.append(CalibrationFold(fold, fitted, compare(specs, [rec], init=init, progress=progress, align=align)))
    return folds


def format_folds(folds: list[CalibrationFold]) -> str:
    lines = ["Leave-one-out gyro scale factors (fitted on the other recordings; sensitivity ratio = 1 / factor):",
             f"{'held out':<12} {'factor x':>9} {'factor y':>9} {'factor z':>9}   sensitivity vs nominal (x, y, z)"]
    for f in folds:
        s = f.fit.gyro_scale_factor
        r = f.fit.sensitivity_ratio
        lines.append(f"{f.held_out:<12} {s[0]:9.4f} {s[1]:9.4f} {s[2]:9.4f}   "
                     + ", ".join(f"{100 * (x - 1):+.1f} %" for x in r))
    return "\n".join(lines)
