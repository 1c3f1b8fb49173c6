"""EuRoC and TUM-VI folders (the ASL dataset format): IMU and motion-capture truth as CSV files.

    <data>/euroc/V1_01_easy/mav0/imu0/data.csv                        IMU
    <data>/euroc/V1_01_easy/mav0/imu0/sensor.yaml                     its T_BS (optional)
    <data>/euroc/V1_01_easy/mav0/state_groundtruth_estimate0/data.csv  truth (EuRoC), or
    <data>/tumvi/dataset-room1_512_16/mav0/mocap0/data.csv            truth (TUM-VI), or
    <data>/euroc/V1_01_easy/mav0/vicon0/data.csv                      truth (EuRoC's raw VICON)
    each truth folder with its sensor.yaml (T_BS, optional)

Burri et al., "The EuRoC micro aerial vehicle datasets", IJRR 35(10), 2016; Schubert et al.,
"The TUM VI benchmark for evaluating visual-inertial odometry", IROS 2018. The folder holding
`mav0/` is one recording; its id is that folder's path (`euroc/V1_01_easy`), and the CSV files
inside belong to it (they are not generic CSV recordings).

`imu0/data.csv`: a header line `#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]`, then
one row per sample: integer nanoseconds, the angular rate (rad/s) and the specific force (m/s^2)
of the IMU S, in its own frame. Gyro timing "end" (`ImuSamples.gyr_timing`, the common
convention: the sample stamped t is the rate up to t). The stamps (IMU and truth alike) become
float64 seconds since the first IMU stamp, subtracted as integers (`fusion.format_checks.seconds_since`:
unix times in ns would lose 0.24 us to float64 otherwise).

Truth (the first present of `state_groundtruth_estimate0`, `mocap0`, `vicon0`): `#timestamp`
(ns) and `q_RS_w, q_RS_x, q_RS_y, q_RS_z`, the orientation of the truth's sensor frame S in the
world frame R (scalar first), among other columns (positions, velocities, biases: not read).

Frames: every `sensor.yaml` holds `T_BS`, a 4 x 4 row-major matrix that maps coordinates in
the sensor frame S into the body frame B (p_B = T_BS p_S: the sensor's pose in the body
frame). When the truth's sensor is not the IMU (EuRoC's `vicon0` tracks a marker frame), the
IMU's orientation in the world is R_RI = R_RS_truth * R_BS_truth^-1 * R_BS_imu (rotation parts
only; SciPy `Rotation` composition); a missing `sensor.yaml` or `T_BS` counts as identity.
The files are read with PyYAML (an OpenCV-style first line `%YAML:1.0` is skipped); the
truth is `R_world_body` of the IMU in the file's world frame R (z up in EuRoC and TUM-VI).
"""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..format_checks import (check_file, matrices_to_quat, one_line, overlap_problem, parse_rows, physical_samples,
                       repair_time, seconds_since, text_lines, truth_quaternions)
from ..types import Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source, recording_id

IMU_COLUMNS = ("w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z")
TRUTH_COLUMNS = ("q_RS_w", "q_RS_x", "q_RS_y", "q_RS_z")
TRUTH_FOLDERS = ("state_groundtruth_estimate0", "mocap0", "vicon0")  # the first present is the truth
YAML_MAX_BYTES = 1024**2  # a sensor.yaml is a few hundred bytes
NS_STEP_RANGE = (1e4, 1e9)  # plausible median step of nanosecond stamps: 100 kHz .. 1 Hz


def _table(path: Path, needed: tuple[str, ...]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """`(stamps_ns, columns)` of an ASL CSV file (header `#timestamp [ns],name [unit],...`): the
    integer `#timestamp` column and the columns `needed` (after it) by name, as floats."""
    lines = text_lines(path)
    header = [h.strip().lstrip("#").split("[")[0].strip() for h in lines[0].split(",")]
    missing = [c for c in ("timestamp", *needed) if c not in header]
    if missing or header[0] != "timestamp":
        raise ValueError(f"{path}: missing ASL columns {', '.join(missing) or 'timestamp (first)'} (need "
                         f"#timestamp [ns],{','.join(needed)})")
    rows = [line for line in lines[1:] if line.strip()]
    table = parse_rows(path, rows)
    if table.shape[0] < 2 or table.shape[1] != len(header):
        raise ValueError(f"{path}: need at least 2 rows of {len(header)} columns, got shape {table.shape}")
    try:  # as integers: a float64 holds unix times in ns only to 256 ns
        stamps = np.array([row.split(",", 1)[0].strip() for row in rows]).astype(np.int64)
    except (ValueError, OverflowError) as exc:
        raise ValueError(f"{path}: the #timestamp column must hold integer nanoseconds ({one_line(exc)})") from None
    return stamps, {name: table[:, header.index(name)] for name in needed}


def _seconds(stamps_ns: np.ndarray, origin_ns: int, path: Path) -> np.ndarray:
    """Nanosecond stamps as float64 seconds since `origin_ns`; refused when their steps say
    they are not nanoseconds."""
    with np.errstate(over="ignore"):
        step = float(np.median(np.diff(stamps_ns.astype(float))))
    if step > 0 and not NS_STEP_RANGE[0] <= step <= NS_STEP_RANGE[1]:
        raise ValueError(f"{path}: the #timestamp column steps by {step:.3g} (median); ASL time stamps are integer "
                         f"nanoseconds (a 200 Hz IMU steps by 5e6)")
    sec, nsec = np.divmod(stamps_ns, 1_000_000_000)
    return seconds_since(sec, nsec, divmod(int(origin_ns), 1_000_000_000))


def sensor_rotation(path: Path) -> Rotation | None:
    """The rotation part of `T_BS` in a `sensor.yaml` (S -> B), None without file or `T_BS`."""
    if not path.exists():
        return None
    check_file(path)
    if path.stat().st_size > YAML_MAX_BYTES:
        raise ValueError(f"{path}: {path.stat().st_size} bytes, not a sensor.yaml (limit {YAML_MAX_BYTES})")
    try:
        import yaml
    except ImportError:
        raise ImportError(f"{path}: reading ASL sensor.yaml files needs PyYAML: pip install pyyaml") from None
    text = path.read_bytes().decode("utf-8", errors="replace")
    if text.startswith("%YAML:"):  # OpenCV's FileStorage writes this non-standard directive
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not a readable YAML file ({one_line(exc)})") from None
    if not isinstance(doc, dict) or "T_BS" not in doc:
        return None
    t_bs = doc["T_BS"]
    data = t_bs.get("data") if isinstance(t_bs, dict) else t_bs
    if not isinstance(data, list) or len(data) != 16 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                                 for x in data):
        what = f"{type(data).__name__} of {len(data)}" if isinstance(data, list) else type(data).__name__
        raise ValueError(f"{path}: T_BS must hold 16 numbers (a 4 x 4 matrix, row-major) in 'data', got a {what}")
    matrix = np.array(data, dtype=float).reshape(4, 4)
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{path}: T_BS holds NaN or Inf")
    return Rotation.from_quat(matrices_to_quat(matrix[None, :3, :3], path), scalar_first=True)[0]


def read_imu(mav0: Path):
    """`(imu, path, origin_ns)`: the IMU samples of an ASL folder's `imu0/data.csv` (physical
    units, through `fusion.format_checks.physical_samples`), their time in s since `origin_ns`, the
    first stamp."""
    path = mav0 / "imu0" / "data.csv"
    stamps, cols = _table(path, IMU_COLUMNS)
    gyr = np.column_stack([cols[c] for c in IMU_COLUMNS[:3]])
    acc = np.column_stack([cols[c] for c in IMU_COLUMNS[3:]])
    (imu,) = physical_samples(path, _seconds(stamps, stamps[0], path), gyr, acc, IMU_COLUMNS, "end")
    return imu, path, int(stamps[0])


def truth_folder(mav0: Path) -> Path | None:
    """The folder of the truth (the first of `TRUTH_FOLDERS` with a data.csv), or None."""
    return next((mav0 / f for f in TRUTH_FOLDERS if (mav0 / f / "data.csv").is_file()), None)


def read_truth(mav0: Path, origin_ns: int) -> tuple[Trajectory | None, str | None]:
    """`(truth, problem)`: the IMU's orientation `R_world_imu` from the truth's data.csv and the two
    T_BS (see the module docstring), its time in s since `origin_ns`, rows far from unit norm made
    gaps; `(None, None)` without a truth folder; `(None, why)` when its rows are unusable
    (`fusion.format_checks.truth_quaternions`)."""
    folder = truth_folder(mav0)
    if folder is None:
        return None, None
    path = folder / "data.csv"
    stamps, cols = _table(path, TRUTH_COLUMNS)
    quat = np.column_stack([cols[c] for c in TRUTH_COLUMNS])
    t, quat = repair_time(_seconds(stamps, origin_ns, path), path, quat)
    quat, problem = truth_quaternions(path, quat, "q_RS_w, q_RS_x, q_RS_y, q_RS_z rows", 1e-2)
    if quat is None:
        return None, problem
    truth_b_s = sensor_rotation(folder / "sensor.yaml")
    imu_b_s = sensor_rotation(mav0 / "imu0" / "sensor.yaml")
    if truth_b_s is not None or imu_b_s is not None:
        ok = np.all(np.isfinite(quat), axis=1)
        r_world_imu = Rotation.from_quat(quat[ok], scalar_first=True)
        if truth_b_s is not None:
            r_world_imu = r_world_imu * truth_b_s.inv()  # R_RS * R_SB = R_RB
        if imu_b_s is not None:
            r_world_imu = r_world_imu * imu_b_s  # R_RB * R_BI = R_RI
        quat = quat.copy()
        quat[ok] = r_world_imu.as_quat(scalar_first=True)
    return Trajectory(t, quat), None


class AslFormat(Format):
    kind = "asl"
    describe = "EuRoC / TUM-VI folders (mav0/imu0/data.csv)"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        """The folders holding `mav0/imu0/data.csv` (for a path a user named: that file)."""
        for path in paths:
            if path.name == "data.csv" and path.parent.name == "imu0" and path.parent.parent.name == "mav0" \
                    and path.is_file():
                mav0 = path.parent.parent
                yield Source(recording_id(root, mav0.parent, strip_suffix=False), self.kind, mav0)

    def read(self, source: Source, options: ReadOptions) -> Recording:
        imu, _, origin_ns = read_imu(source.imu)
        try:  # a truth folder that cannot be read costs the truth, not the recording
            truth, problem = read_truth(source.imu, origin_ns)
        except ValueError as exc:
            truth, problem = None, f"truth unusable: {' '.join(str(exc).split())}"
        if truth is not None:
            problem = overlap_problem(truth, imu.t, f"the {truth_folder(source.imu).name} folder's")
        return Recording(source.id, imu, None if problem else truth, truth_problem=problem)

    def holds(self, source: Source) -> Holds:
        return Holds(truth=truth_folder(source.imu) is not None, movement=False, magnetometer=False, gyr_timing="end",
                     raw_counts=False)


FORMAT = AslFormat()
