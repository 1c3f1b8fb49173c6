"""The generic CSV, for anyone's IMU: one file per recording, in physical units.

    t,gx,gy,gz,ax,ay,az[,mx,my,mz][,qw,qx,qy,qz][,movement]

t in s, gyro in rad/s, accelerometer in m/s^2, the optional magnetometer in uT (NaN
where there is no sample), all body frame; the optional quaternion is the
ground truth `R_world_body`, scalar first (NaN rows = no truth); the optional `movement`
column (0/1) marks the samples a BROAD-style score uses. A recording's id is its path relative
to the data directory without `.csv` (`mylab/walk`). A `.csv` inside a folder that is a
recording of another format (an ASL `mav0/` folder) belongs to that recording.
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..format_checks import check_file, parse_rows, physical_samples, text_lines, truth_quaternions
from ..types import Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source, recording_id

CSV_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")
CSV_TRUTH = ("qw", "qx", "qy", "qz")
CSV_MAG = ("mx", "my", "mz")


def _header(line: str) -> list[str]:
    return [h.strip().strip("\"'").strip().lower() for h in line.split(",")]


def load_csv(path: str | Path, with_movement: bool = False):
    """Generic CSV in physical units: header `t,gx,gy,gz,ax,ay,az[,mx,my,mz][,qw,qx,qy,qz][,movement]`.

    t in s, gyro in rad/s, accelerometer in m/s^2 (converted to g), magnetometer in uT, all
    body frame; gyro
    row k is the angular rate over (t[k-1], t[k]] (`ImuSamples.gyr_timing` "end", the common
    convention of IMU drivers and of VQF, Madgwick, Mahony and Fusion; a file whose gyro
    rows cover [t[k], t[k+1]) instead can be loaded and then declared with
    `imu.replace(gyr_timing="start")`); the
    optional quaternion is the ground truth `R_world_body`, scalar first (NaN rows = no truth);
    the optional `movement` column (0/1) marks the samples a BROAD-style score uses.
    Returns `(imu, truth)`, or `(imu, truth, movement)` with `with_movement` (movement None
    without the column); truth None without truth columns, or with a warning saying why they are
    unusable (`fusion.format_checks.truth_quaternions`).
    """
    imu, truth, movement, problem = read_csv(path)
    if problem is not None:
        warnings.warn(f"{path}: {problem}; loaded without ground truth", stacklevel=2)
    return (imu, truth, movement) if with_movement else (imu, truth)


def read_csv(path: str | Path) -> tuple:
    """`load_csv`'s `(imu, truth, movement, truth_problem)`: truth_problem says why truth columns
    were not usable (one line, `fusion.types.Recording.truth_problem`), None otherwise."""
    path = Path(path)
    text = text_lines(path)
    header = _header(text[0])
    repeated = sorted({h for h in header if header.count(h) > 1 and h})
    if repeated:
        raise ValueError(f"{path}: the header names column {', '.join(repr(h) for h in repeated)} more than once")
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"{path}: missing CSV columns {', '.join(missing)} (need {','.join(CSV_COLUMNS)}[,{','.join(CSV_TRUTH)}])")
    table = parse_rows(path, text[1:])
    if table.shape[0] < 2 or table.shape[1] != len(header):
        raise ValueError(f"{path}: need at least 2 rows of {len(header)} columns, got shape {table.shape}")
    col = {name: table[:, i] for i, name in enumerate(header)}
    gyr = np.column_stack([col[c] for c in ("gx", "gy", "gz")])
    acc = np.column_stack([col[c] for c in ("ax", "ay", "az")])
    has_truth = all(c in header for c in CSV_TRUTH)
    quat = np.column_stack([col[c] for c in CSV_TRUTH]) if has_truth else np.zeros((len(gyr), 4))
    movement = col["movement"] != 0 if "movement" in col else np.ones(len(gyr), bool)
    mag = np.column_stack([col[c] for c in CSV_MAG]) if all(c in header for c in CSV_MAG) else None
    imu, quat, movement = physical_samples(path, col["t"], gyr, acc, CSV_COLUMNS[1:], "end", quat, movement,
                                           mag=None if mag is None else (mag, "columns mx,my,mz"))
    movement = movement if "movement" in col else None
    if not has_truth:
        return imu, None, movement, None
    quat, problem = truth_quaternions(path, quat, "truth rows (qw,qx,qy,qz)", 1e-3)
    return imu, None if quat is None else Trajectory(imu.t, quat), movement, problem


class CsvFormat(Format):
    kind = "csv"
    describe = ".csv (generic: t,gx,gy,gz,ax,ay,az[,mx,my,mz][,qw,qx,qy,qz][,movement])"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        for path in paths:
            if path.suffix.lower() == ".csv" and path.is_file():
                yield Source(recording_id(root, path), self.kind, path)

    def read(self, source: Source, options: ReadOptions) -> Recording:
        imu, truth, movement, problem = read_csv(source.imu)
        return Recording(source.id, imu, truth, movement=movement, truth_problem=problem)

    def holds(self, source: Source) -> Holds:
        check_file(source.imu)
        with open(source.imu, "rb") as f:
            header = _header(f.readline(65536).decode("utf-8-sig", errors="replace"))
        return Holds(truth=all(c in header for c in CSV_TRUTH), movement="movement" in header,
                     magnetometer=all(c in header for c in CSV_MAG),
                     gyr_timing="end", raw_counts=False)


FORMAT = CsvFormat()
