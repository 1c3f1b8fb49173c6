"""Orientation trajectories as files: what another program (C++, MATLAB, a ROS node) wrote, and
what `fusion compare --out` writes for evo.

    TUM   `t tx ty tz qx qy qz qw` per line, space-separated, `#` comments: t in s, the
          position (m; zeros where there is none) and the orientation scalar LAST
          (Sturm et al., "A benchmark for the evaluation of RGB-D SLAM systems", IROS 2012; the
          format evo reads and writes, `evo_ape tum ...`). Read by extension `.tum` or `.txt`.
    CSV   a header `t,qw,qx,qy,qz` then one row per sample, scalar FIRST (as everywhere in
          this toolkit). Read by extension `.csv`.

The orientation is `R_world_body` (body to world), as the TUM format's pose is the body's pose
in the world. A trajectory read back is checked like a recording's truth (bounded size, numbers,
unit quaternions, increasing stamps repaired with a warning: `fusion.loaders`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .loaders import parse_rows, repair_time, text_lines, unit_quaternions
from .types import Trajectory

FORMATS = {".tum": "tum", ".txt": "tum", ".csv": "csv"}
CSV_HEADER = ("t", "qw", "qx", "qy", "qz")
NORM_TOLERANCE = 1e-3  # a written quaternion's norm may differ from 1 by rounding; more is another layout


def read_trajectory(path: str | Path) -> Trajectory:
    """A trajectory file (TUM or CSV, module docstring) as a `Trajectory` (scalar-first
    `R_world_body`); one line naming the file for anything it cannot read."""
    path = Path(path)
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise ValueError(f"{path}: a trajectory file must be .tum or .txt (TUM: t tx ty tz qx qy qz qw) or .csv "
                         "(t,qw,qx,qy,qz)")
    lines = text_lines(path)
    if kind == "tum":
        rows = [line.replace(",", " ") for line in lines if line.strip() and not line.lstrip().startswith("#")]
        table = parse_rows(path, rows, delimiter=None)
        if table.shape[1] != 8:
            raise ValueError(f"{path}: TUM rows have 8 columns (t tx ty tz qx qy qz qw), these have {table.shape[1]}")
        t, quat = table[:, 0], table[:, [7, 4, 5, 6]]
    else:
        header = tuple(h.strip().lower() for h in lines[0].split(","))
        if header != CSV_HEADER:
            raise ValueError(f"{path}: a trajectory CSV starts with the header {','.join(CSV_HEADER)}, got {lines[0][:80]!r}")
        table = parse_rows(path, lines[1:])
        t, quat = table[:, 0], table[:, 1:5]
    t, quat = repair_time(t, path, quat, sampling=False)
    unit = unit_quaternions(path, quat, "its orientations", NORM_TOLERANCE)
    if unit is None:
        raise ValueError(f"{path}: no finite orientation")
    return Trajectory(t, unit)


def write_tum(path: str | Path, t: np.ndarray, quat_wxyz: np.ndarray) -> None:
    """Write (N,) s and (N, 4) scalar-first quaternions as a TUM file (positions zero, every
    number in full double precision: `%.17g` reads back bit for bit); rows with a NaN are left out."""
    t = np.asarray(t, dtype=float)
    quat = np.asarray(quat_wxyz, dtype=float)
    keep = np.isfinite(t) & np.all(np.isfinite(quat), axis=1)
    table = np.column_stack([t, np.zeros((len(t), 3)), quat[:, [1, 2, 3, 0]]])[keep]
    with open(path, "w", encoding="ascii") as out:
        out.write("# t tx ty tz qx qy qz qw (written by fusion: R_world_body, scalar last, positions not estimated)\n")
        np.savetxt(out, table, fmt="%.17g")
