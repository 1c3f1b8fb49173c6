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
unit quaternions, increasing stamps repaired with a warning: `fusion.format_checks`).

A TUM file `fusion compare --out` writes (`write_tum(..., compact=True)`) says in a comment what
it holds, `# fusion: estimator=ekf recording=broad/10 imu=9-D` (`tum_metadata` reads it back),
and carries the precision the data carry rather than every digit of a double: the time to its own
resolution when it is 1 us or coarser, else to 1 us (`time_decimals`), quaternions to 1e-7
(`QUAT_DECIMALS`). Read back on the recording's stamps, such a file gives the estimate to 1e-7
(`fusion.estimators.adapters.trajectory_file` matches stamps within 1 us).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .format_checks import parse_rows, repair_time, text_lines, unit_quaternions
from .types import Trajectory

import shlex
from typing import Mapping

FORMATS = {".tum": "tum", ".txt": "tum", ".csv": "csv"}
METADATA_PREFIX = "# fusion:"  # a TUM comment line of `key=value` words (`tum_metadata`)
QUAT_DECIMALS = 7  # a compact TUM file's quaternion components: 1e-7, a rotation of about 1e-5 deg
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


def write_tum(path: str | Path, t: np.ndarray, quat_wxyz: np.ndarray, *, metadata: Mapping[str, str] | None = None,
              compact: bool = False) -> None:
    """Write (N,) s and (N, 4) scalar-first quaternions as a TUM file (positions zero); rows with a
    NaN are left out.

    metadata: `key=value` words for the `# fusion:` comment line (`tum_metadata` reads them back).
    compact: the precision the data carry (module docstring: the time to `time_decimals`, the
        quaternions to `QUAT_DECIMALS`), about half the size; otherwise every number in full
        double precision (`%.17g`: reads back bit for bit).
    """
    t = np.asarray(t, dtype=float)
    quat = np.asarray(quat_wxyz, dtype=float)
    keep = np.isfinite(t) & np.all(np.isfinite(quat), axis=1)
    with open(path, "w", encoding="ascii") as out:
        if metadata:
            words = (f"{k}={v}" if v and not any(c.isspace() or c in "'\"\\" for c in v)
                     else f'{k}="{_escaped(v)}"' for k, v in ((k, str(v)) for k, v in metadata.items()))
            out.write(f"{METADATA_PREFIX} {' '.join(words)}\n")
        out.write("# t tx ty tz qx qy qz qw (written by fusion: R_world_body, scalar last, positions not estimated)\n")
        if compact:
            table = np.column_stack([t, quat[:, [1, 2, 3, 0]]])[keep]
            q = f"%.{QUAT_DECIMALS}f"
            np.savetxt(out, table, fmt=f"%.{time_decimals(t[keep])}f 0 0 0 {q} {q} {q} {q}")
        else:
            np.savetxt(out, np.column_stack([t, np.zeros((len(t), 3)), quat[:, [1, 2, 3, 0]]])[keep], fmt="%.17g")


def _escaped(text: str) -> str:
    """Text inside double quotes as `shlex.split` reads it back."""
    return text.replace("\\", "\\\\").replace('"', '\\"')


def time_decimals(t: np.ndarray) -> int:
    """Decimals of the time in a compact TUM file: the stamps' own decimal resolution when it is
    1 us or coarser (stamps in 3.5 ms steps from 0, as BROAD's, get 4 decimals and read back to a
    double's rounding), else 1 us (6 decimals: the Unix stamps of a float64 hold no more than
    0.24 us anyway)."""
    t = np.asarray(t, dtype=float)
    slack = 2 * np.spacing(np.abs(t))  # numpy's decimal rounding itself is off by an ulp or so
    for decimals in range(6):
        if np.all(np.abs(np.round(t, decimals) - t) <= slack):
            return decimals
    return 6


def tum_metadata(path: str | Path) -> dict[str, str]:
    """The `key=value` words of a TUM file's `# fusion:` comment line (`write_tum`'s metadata),
    {} when it has none (a file another program wrote)."""
    out: dict[str, str] = {}
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line.lstrip().startswith("#"):
                break  # the comments come first
            if line.startswith(METADATA_PREFIX):
                try:
                    words = shlex.split(line[len(METADATA_PREFIX):])
                except ValueError:
                    words = []
                out.update(w.split("=", 1) for w in words if "=" in w)
    return out
