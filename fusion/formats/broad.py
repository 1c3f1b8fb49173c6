"""Reader for the BROAD benchmark's per-trial files.

BROAD (Berlin Robust Orientation estimation Assessment Dataset; Laidig, Caruso, Cereatti
& Seel, Data 2021) ships one file per trial, `.hdf5` or `.mat`, holding:

    imu_gyr        (N, 3) rad/s, IMU frame
    imu_acc        (N, 3) m/s^2, IMU frame (specific force: +9.81 on the up axis at rest)
    imu_mag        (N, 3) magnetometer, uT (optional; `ImuSamples.mag_ut`)
    opt_quat       (N, 4) w, x, y, z ground truth `R_world_imu`, world z up; NaN rows where
                   the optical tracking was lost
    movement       (N,) bool/0-1: the movement phases, the only samples BROAD scores
    sampling_rate  scalar, Hz (IMU and ground truth share one clock); a file attribute in
                   the published .hdf5 files, a variable in the .mat files

`load_broad` turns one trial into `ImuSamples` (accelerometer in g), a truth `Trajectory`
on the same time stamps `t = k / sampling_rate`, and the movement mask. `.hdf5` needs
h5py (`pip install -e '.[broad]'`, also in `.[peers]`); `.mat` (MATLAB v5) needs only
SciPy, a MATLAB v7.3 `.mat` (an HDF5 file) needs h5py too. Arrays stored transposed
(MATLAB's column-major `3 x N`) are turned batch-first here.

In a data directory, every `.hdf5`/`.h5` file and every `.mat` not named like a course file
(`imuRawN`, `viconRotN`, `camN`) is taken for a trial; its id is its path without the suffix
(`broad/01_undisturbed_slow_rotation_A`).
"""
from __future__ import annotations

import json
import warnings

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..format_checks import MAX_STEP_S, MIN_STEP_S, check_declared, physical_samples, read_isolated, read_mat, truth_quaternions
from ..types import ImuSamples, Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source, recording_id
from .course import is_course_file

SUFFIXES = (".hdf5", ".h5", ".mat")
REQUIRED = ("imu_gyr", "imu_acc", "opt_quat", "sampling_rate")


def _h5py(path: Path):
    try:
        import h5py
    except ImportError:
        raise ImportError(
            f"{path}: reading BROAD .hdf5 (or MATLAB v7.3) files needs h5py: pip install -e '.[broad]' (or pip install h5py)"
        ) from None
    return h5py


def _read_hdf5(path: Path) -> dict[str, np.ndarray]:
    h5py = _h5py(path)
    try:
        with h5py.File(path, "r") as f:
            datasets = [key for key in f.keys() if isinstance(f[key], h5py.Dataset)]
            # Shapes from the header, before reading: a 2 KB file can declare 30 million compressed rows.
            check_declared(path, [(key, f[key].shape or ()) for key in datasets]
                           + [(key, f.attrs.get_id(key).shape or ()) for key in f.attrs.keys()])
            data = {key: np.array(f[key]) for key in datasets}
            # BROAD's published .hdf5 files keep `sampling_rate` as a file attribute, not a dataset.
            for key, value in f.attrs.items():
                if key not in data and not isinstance(value, (str, bytes)):
                    data[key] = np.asarray(value)
            return data
    except OSError as exc:
        raise ValueError(f"{path}: not a readable HDF5 file ({exc})") from None


def read_trial(path: str | Path) -> dict[str, np.ndarray]:
    """The raw arrays of one trial file, by name (no checks beyond readability)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"{path}: not a BROAD trial file (expected {', '.join(SUFFIXES)})")
    if path.suffix.lower() == ".mat":  # MATLAB v7.3 files are HDF5 inside
        return read_mat(path, "MATLAB", v73=_read_hdf5)
    # In a forked child: a corrupt file can crash HDF5's C code (see `read_isolated`).
    return read_isolated(path, _read_hdf5, "BROAD trial")


def is_trial(path: str | Path) -> bool:
    """Whether `path` reads as a BROAD trial (has the required arrays)."""
    try:
        data = read_trial(path)
    except (ValueError, OSError, ImportError):
        return False
    return all(key in data for key in REQUIRED)


def _real(value: Any, key: str, path: Path) -> np.ndarray:
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{path}: {key!r} is not an array of real numbers (dtype {arr.dtype})")
    return arr.astype(float)


def _columns(data: dict[str, Any], key: str, cols: int, n: int | None, path: Path) -> np.ndarray:
    if key not in data:
        raise ValueError(f"{path}: no {key!r} array (found {', '.join(sorted(data)) or 'nothing'})")
    arr = _real(data[key], key, path)
    if arr.ndim == 2 and arr.shape[1] != cols and arr.shape[0] == cols:
        arr = arr.T  # stored column-major (MATLAB): cols x N
    if arr.ndim != 2 or arr.shape[1] != cols or (n is not None and arr.shape[0] != n):
        want = f"({n if n is not None else 'N'}, {cols})"
        raise ValueError(f"{path}: {key!r} must be {want}, got shape {arr.shape}")
    return arr


def load_broad(path: str | Path) -> tuple[ImuSamples, Trajectory | None, np.ndarray]:
    """One BROAD trial: `(imu, truth, movement)` (`read_broad`; an unusable truth is None, with a
    warning saying why)."""
    imu, truth, movement, problem = read_broad(path)
    if problem is not None:
        warnings.warn(f"{path}: {problem}; loaded without ground truth", stacklevel=2)
    return imu, truth, movement


def read_broad(path: str | Path) -> tuple[ImuSamples, Trajectory | None, np.ndarray, str | None]:
    """One BROAD trial: `(imu, truth, movement, truth_problem)`.

    imu: `ImuSamples` on `t = k / sampling_rate` s (k = 0..N-1), gyro rad/s, accelerometer
        in g (`imu_acc / 9.80665`), magnetometer uT (`imu_mag`, when the trial has it), body =
        IMU frame; `gyr_timing` "end" (gyro sample k is the rate over (t[k-1], t[k]], as VQF,
        which BROAD's authors wrote, integrates it).
    truth: `Trajectory` of `opt_quat` (wxyz, `R_world_imu`, z up) on the same stamps, NaN
        rows kept (tracking lost), rows far from unit norm made gaps (`fusion.format_checks.truth_quaternions`);
        None when no row is usable, and truth_problem (one line) says why (None otherwise).
    movement: (N,) bool, the samples BROAD scores (all True if the file has no mask).
    """
    path = Path(path)
    data = read_trial(path)
    gyr = _columns(data, "imu_gyr", 3, None, path)
    n = len(gyr)
    acc = _columns(data, "imu_acc", 3, n, path)
    quat = _columns(data, "opt_quat", 4, n, path)
    if "sampling_rate" not in data:
        raise ValueError(f"{path}: no 'sampling_rate' (neither an array nor a file attribute): the time stamps are unknown")
    rate = _real(data["sampling_rate"], "sampling_rate", path).ravel()
    if rate.size != 1 or not np.isfinite(rate[0]) or rate[0] <= 0:
        raise ValueError(f"{path}: 'sampling_rate' must be one positive number, got {rate}")
    if not 1.0 / MAX_STEP_S <= rate[0] <= 1.0 / MIN_STEP_S:
        raise ValueError(f"{path}: 'sampling_rate' {rate[0]:.6g} Hz is outside [{1 / MAX_STEP_S:g}, {1 / MIN_STEP_S:g}] Hz")
    if "movement" in data:
        movement = np.asarray(data["movement"]).ravel()
        if movement.shape != (n,):
            raise ValueError(f"{path}: 'movement' must have {n} entries, got {movement.size}")
        movement = movement.astype(bool)
    else:
        movement = np.ones(n, bool)
    names = ("imu_gyr x", "imu_gyr y", "imu_gyr z", "imu_acc x", "imu_acc y", "imu_acc z")
    mag = _columns(data, "imu_mag", 3, n, path) if "imu_mag" in data else None
    # BROAD: gyro k covers (t[k-1], t[k]]
    imu, quat, movement = physical_samples(path, np.arange(n) / rate[0], gyr, acc, names, "end", quat, movement,
                                           mag=None if mag is None else (mag, "'imu_mag'"))
    quat, problem = truth_quaternions(path, quat, "'opt_quat' rows (w, x, y, z)", 1e-2)
    return imu, None if quat is None else Trajectory(imu.t, quat), movement, problem


TRIALS_JSON_MAX_BYTES = 1_000_000  # BROAD's lists 39 trials in about 10 kB


def trial_groups(path: str | Path) -> list[str]:
    """The groups BROAD puts the trial at `path` in (`undisturbed`, `rotation`, `attached_magnet`,
    ...), from the `trials.json` beside it (the benchmark's own file: {"trials": {stem: {"groups":
    [...]}}}); [] without one or for a trial it does not list. A `trials.json` that is not that
    is a ValueError naming it."""
    index = Path(path).parent / "trials.json"
    if not index.is_file():
        return []
    if index.stat().st_size > TRIALS_JSON_MAX_BYTES:
        raise ValueError(f"{index}: {index.stat().st_size} bytes, more than BROAD's trials.json could hold "
                         f"({TRIALS_JSON_MAX_BYTES})")
    try:
        doc = json.loads(index.read_text())
        groups = doc["trials"].get(Path(path).stem, {}).get("groups", [])
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError):
        raise ValueError(f"{index}: not BROAD's trials.json ({{\"trials\": {{name: {{\"groups\": [...]}}}}}})") from None
    if not (isinstance(groups, list) and all(isinstance(g, str) for g in groups)):
        raise ValueError(f"{index}: the groups of {Path(path).stem} are not a list of names")
    return groups


def primary_group(path: str | Path) -> str | None:
    """The trial's motion or disturbance group in BROAD's `trials.json` (`rotation`,
    `translation`, `combined`, `tapping`, `attached_magnet`, ...: the groups whose category is
    "motion" or "disturbance"), for leave-one-group-out; None without one."""
    names = trial_groups(path)
    if not names:
        return None
    doc = json.loads((Path(path).parent / "trials.json").read_text())  # read and checked by trial_groups
    categories = {g.get("name"): g.get("category") for g in doc.get("groups", []) if isinstance(g, dict)}
    return next((n for n in names if categories.get(n) in ("motion", "disturbance")), None)


class BroadFormat(Format):
    kind = "broad"
    describe = "BROAD trials (.hdf5/.h5, or a .mat not named like a course file)"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        for path in paths:
            if path.suffix.lower() in SUFFIXES and not is_course_file(path) and path.is_file():
                yield Source(recording_id(root, path), self.kind, path)

    def read(self, source: Source, options: ReadOptions) -> Recording:
        imu, truth, movement, problem = read_broad(source.imu)
        return Recording(source.id, imu, truth, movement=movement, truth_problem=problem)

    def holds(self, source: Source) -> Holds:
        names = set(read_trial(source.imu))  # a trial's arrays are small (some 10 MB): read, not parsed
        return Holds(truth=True, movement="movement" in names, magnetometer="imu_mag" in names, gyr_timing="end",
                     raw_counts=False)


FORMAT = BroadFormat()
