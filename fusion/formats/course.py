"""The course recordings: ECE276A pickles and ESE650 `.mat` files, raw ADC counts with VICON truth.

    <data>/ece276a/imu/imuRaw3.p     <data>/ece276a/vicon/viconRot3.p    [<data>/ece276a/cam/cam3.p]
    <data>/ese650/imu/imuRaw3.mat    <data>/ese650/vicon/viconRot3.mat

Each recording's id is its folder relative to the data directory (the data directory's own name
for recordings directly in it) and its number: `ece276a/3`. Layouts (`../shared/data/README.md`):
- ECE276A `imuRawN.p`: float 7 x T; row 0 unix time, rows 1-6 ax ay az wx wy wz, with ax and
  ay already negated by the course (`-raw`); undone here so all formats give the same counts.
- ECE276A-2018 `imuRawN.p`: dict `vals` uint16 6 x T (ax ay az wz wx wy, not negated), `ts` 1 x T.
- ESE650 `imuRawN.mat`: `vals` 6 x T (ax ay az wz wx wy, not negated), `ts` 1 x T.
- VICON `viconRotN.p` / `.mat`: `rots` 3 x 3 x K (world <- body), `ts` 1 x K.

The IMU files become `RawImu` (native ADC counts, order ax ay az wx wy wz, no sign flip), which
`fusion.calibration` turns into `ImuSamples`; VICON files become a `Trajectory`.

Gyro timing (`ImuSamples.gyr_timing`): "start", gyro sample k is the rate over [t[k], t[k+1])
(gyro k, then accelerometer k + 1). The evidence on ece276a 1-9 is
`python benchmarks/timing_evidence.py`, whose figures are in `docs/results.md` ("The course
board's gyro timing"):
- Gyro against accelerometer on the IMU's own clock (gravity in the body frame turns as
  `-w x a`): gyro sample k matches the accelerometer's turn rate a few milliseconds after t[k],
  as a mean over [t[k], t[k+1]] would ("start"; the method is checked on `fusion.sim`).
- Against VICON the pairing is not identifiable by itself: a one-sample gyro shift equals a
  VICON clock shift. With each pairing's own measured clock offset, the estimators' scores
  differ by less than their recording-to-recording spread: ambiguous at the level of the scores.

Pickles can run code when loaded: only open pickle files you trust. As a guard, pickles are
read with a restricted unpickler (`fusion.format_checks.read_pickle`) that only builds numpy arrays
and plain containers and refuses any other class.
"""
from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..calibration import BoardModel, Calibration, calibrate
from ..format_checks import (ADC_LIMIT_COUNTS, field_array, numeric_array, overlap_problem, read_mat, truth_matrices,
                       read_pickle, repair_time, time_row)
from ..types import ImuSamples, RawImu, Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source

IMU_FILE = re.compile(r"imuRaw(\d+)\.(p|mat)$")
COURSE_FILE = re.compile(r"(imuRaw|viconRot|cam)\d+\.(p|mat)$")
SUBFOLDERS = ("imu", "vicon", "cam")

# Canonical channel order ax ay az wx wy wz from the (ax ay az wz wx wy) layout of the
# .mat and 2018 files.
_FROM_AZ_WZ_WX_WY = [0, 1, 2, 4, 5, 3]


def is_course_file(path: Path) -> bool:
    """Whether `path` is named like a course file (imuRawN, viconRotN, camN; .p or .mat)."""
    return bool(COURSE_FILE.match(path.name))


def _raw_imu(t: np.ndarray, counts: np.ndarray, path: Path) -> RawImu:
    if counts.ndim != 2 or counts.shape[1] != 6:
        raise ValueError(f"{path}: IMU values must be a 6 x T array, got shape {counts.shape[::-1]}")
    if counts.shape[0] < 2:
        raise ValueError(f"{path}: {counts.shape[0]} IMU samples; need at least 2")
    if not np.all(np.isfinite(counts)):
        raise ValueError(f"{path}: IMU values contain NaN or Inf")
    if np.abs(counts).max() > ADC_LIMIT_COUNTS:
        raise ValueError(f"{path}: IMU values up to {np.abs(counts).max():.3g} are not ADC counts (|value| <= {ADC_LIMIT_COUNTS})")
    t, counts = repair_time(t, path, counts)
    return RawImu(t, counts, source=str(path), gyr_timing="start")  # the evidence: see the module docstring


def load_imu_pickle(path: str | Path) -> RawImu:
    """ECE276A `imuRawN.p`, either release (7 x T array, or the 2018 dict `vals`/`ts`)."""
    path = Path(path)
    obj = read_pickle(path)
    if isinstance(obj, dict):  # 2018 release: same layout as the .mat files
        vals = field_array(obj, "vals", path)
        if vals.ndim != 2 or vals.shape[0] != 6:
            raise ValueError(f"{path}: 'vals' must be 6 x T, got shape {vals.shape}")
        return _raw_imu(time_row(field_array(obj, "ts", path), vals.shape[1], path), vals[_FROM_AZ_WZ_WX_WY].T, path)
    if not isinstance(obj, np.ndarray):
        raise ValueError(f"{path}: expected a 7 x T array or a dict with 'vals' and 'ts', found {type(obj).__name__}")
    arr = numeric_array(obj, path, "the array")
    if arr.ndim != 2 or arr.shape[0] != 7:
        raise ValueError(f"{path}: expected a 7 x T array (time + 6 channels), got shape {arr.shape}")
    counts = arr[1:].T.copy()
    counts[:, :2] *= -1.0  # this release negated ax and ay; back to native counts
    return _raw_imu(arr[0], counts, path)


def load_imu_mat(path: str | Path) -> RawImu:
    """ESE650 `imuRawN.mat`: `vals` 6 x T (ax ay az wz wx wy), `ts` 1 x T."""
    path = Path(path)
    mat = read_mat(path)
    vals = field_array(mat, "vals", path)
    if vals.ndim != 2 or vals.shape[0] != 6:
        raise ValueError(f"{path}: 'vals' must be 6 x T, got shape {vals.shape}")
    return _raw_imu(time_row(field_array(mat, "ts", path), vals.shape[1], path), vals[_FROM_AZ_WZ_WX_WY].T, path)


def load_imu(path: Path) -> RawImu:
    """Raw counts from a course IMU file, whichever release it comes from."""
    return load_imu_mat(path) if path.suffix == ".mat" else load_imu_pickle(path)


def load_vicon(path: str | Path) -> Trajectory:
    """VICON `viconRotN.p` or `.mat`: `rots` 3 x 3 x K (world <- body), `ts` 1 x K.

    Rows with NaN matrices (tracking gaps) stay NaN in the trajectory; scoring skips them; so do
    matrices that are not rotations (counted in a warning, `fusion.format_checks.truth_matrices`). Raises
    ValueError naming the file when it cannot be read or holds no usable rotation.
    """
    path = Path(path)
    obj = read_mat(path) if path.suffix == ".mat" else read_pickle(path)
    rots = field_array(obj, "rots", path)
    if rots.ndim != 3 or rots.shape[:2] != (3, 3):
        raise ValueError(f"{path}: 'rots' must be 3 x 3 x K, got shape {rots.shape}")
    t = time_row(field_array(obj, "ts", path), rots.shape[2], path)
    matrices = np.moveaxis(rots, 2, 0)  # (K, 3, 3)
    t, matrices = repair_time(t, path, matrices)
    quat, problem = truth_matrices(path, matrices, "'rots' matrices")
    if quat is None:
        raise ValueError(f"{path}: {problem}")
    return Trajectory(t, quat)


def calibrated_samples(raw: RawImu, calib: Calibration, dropouts: bool) -> ImuSamples:
    """`calib.apply(raw)`, with `gyr_valid` from `fusion.checks.dropout_mask` when `dropouts`."""
    imu = calib.apply(raw)
    if dropouts:
        from ..checks import dropout_mask

        imu = imu.replace(gyr_valid=dropout_mask(imu, raw, calib.board))
    return imu


def calibrated_recording(rid: str, raw: RawImu, truth: Trajectory | None, board: BoardModel, dropouts: bool,
                         camera: Path | None = None) -> Recording:
    """A recording of raw counts, calibrated (`fusion.calibration.calibrate`, then
    `calibrated_samples`)."""
    calib = calibrate(raw, board)
    return Recording(rid, calibrated_samples(raw, calib, dropouts), truth, raw, calib, camera=camera)


def _sibling(imu_dir: Path, folder: str, stem: str, number: str, suffix: str) -> Path | None:
    for ext in (suffix, ".p", ".mat"):
        path = imu_dir.parent / folder / f"{stem}{number}{ext}"
        if path.is_file():
            return path
    return None


class CourseFormat(Format):
    kind = "course"
    describe = "imu/imuRawN.p|.mat (course files, with vicon/viconRotN)"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        """`imuRawN.p|.mat` in a folder `imu/` (any folder for a path a user named), with
        `vicon/viconRotN` and `cam/camN` beside it; the first of imuRaw3.p and imuRaw3.mat in
        one folder."""
        seen = set()
        for path in paths:
            match = IMU_FILE.match(path.name)
            if not match or not (root is None or path.parent.name == "imu") or not path.is_file():
                continue
            folder = path.parent.parent
            if root is None:
                prefix = folder.name
            else:
                prefix = root.resolve().name if folder == root else folder.relative_to(root).as_posix()
            number = match.group(1)
            rid = f"{prefix}/{number}"
            if rid in seen:  # imuRaw3.p and imuRaw3.mat in one folder: keep the first
                continue
            seen.add(rid)
            yield Source(rid, self.kind, path,
                         vicon=_sibling(path.parent, "vicon", "viconRot", number, path.suffix),
                         cam=_sibling(path.parent, "cam", "cam", number, path.suffix))

    def read(self, source: Source, options: ReadOptions) -> Recording:
        raw = load_imu(source.imu)
        truth, problem = None, None
        if source.vicon:  # a VICON file that cannot be used costs the truth, not the recording
            try:
                truth = load_vicon(source.vicon)
            except ValueError as exc:
                problem = f"truth unusable: {exc}"
            problem = problem or overlap_problem(truth, raw.t, f"{source.vicon.name}'s")
        rec = calibrated_recording(source.id, raw, None if problem else truth, options.board, options.dropouts,
                                   camera=source.cam)
        return replace(rec, truth_problem=problem) if problem else rec

    def holds(self, source: Source) -> Holds:
        return Holds(truth=source.vicon is not None, movement=False, magnetometer=False, gyr_timing="start",
                     raw_counts=True)


FORMAT = CourseFormat()
