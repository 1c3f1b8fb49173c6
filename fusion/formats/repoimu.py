"""Reader for RepoIMU's recordings, as published (Szczesna et al., "Reference Data Set for Accuracy
Evaluation of Orientation Estimation Algorithms for Inertial Motion Capture Systems", ICCVG 2016;
https://github.com/agnieszkaszczesna/RepoIMU).

Two kinematic sets: a T-stick (`TStick/TStick_Test02_Trial1.csv`) and a three-segment pendulum, one
file per segment (`Pendulum/Pendulum_Test02a_Trial1_Segment_1.csv`). Each is a semicolon-separated
text file with two header rows, the quantity and its component:

    Time (s);Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;IMU Magnetometer;;;
    ;W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z;
    0.08;1;0;1.6232e-035;0;-0.071594;0.21157;9.7958;0.002314;-0.00634;0.001322;-0.33533;0.19856;-0.88708

time in s, the Vicon orientation as a quaternion w, x, y, z, the accelerometer in m/s^2 and the
gyroscope in rad/s (the units as published, read as they are), then the magnetometer. Six pendulum
files (`Pendulum_Test02*`) use another header, the time's unit in a second row of units, and write
some numbers with a decimal comma:

    Time;Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;IMU Magnetometer;;;
    s;W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z;
    0,006;1;-8,00E-05;...

Both forms are read (`header_form`); the field separator is the semicolon, so a comma in a number
is its decimal mark. Its traps, handled here:

- rows where the markers were not seen hold an all-zero quaternion: truth gaps (NaN rows), not a
  rotation; the static files hold nothing else and are read without truth (`Recording.truth_problem`);
- a few rows hold a quaternion far from unit norm (|q| 0.006-0.95 in seven pendulum files): truth
  gaps too, counted in a warning (`fusion.format_checks.truth_quaternions`);
- some rows repeat the previous row's time stamp (in some files with other data on the second
  row): dropped (the first row of each stamp kept), and their count said in a warning, which
  `fusion inspect` prints with the recording;
- the pendulum's rows come every 6 ms (163 Hz) while its IMU's values change at about 50 Hz (gyro),
  49 Hz (magnetometer) and 25 Hz (accelerometer): each row repeats a sensor's last sample until the
  next arrives. The rows are kept as published, and a warning gives each sensor's rate
  (`fusion.checks.value_rate_hz`; `fusion inspect` too): measured on the pendulum (`docs/results.md`,
  "RepoIMU's held samples"), keeping them scores every estimator as well as, or better than,
  keeping only the rows where the gyro (or any sensor) changed;
- the T-stick's gyro saturates at about +-7.3 rad/s (420 deg/s; Test05: 600-850 samples per sign):
  the flat tops are found from the data (`fusion.checks.FlatTopDetector`) and reported (`fusion
  inspect`, the report's events), not marked invalid: integrating the clipped reading scores every
  estimator far better than holding the orientation across it (`docs/results.md`, "RepoIMU's
  clipped gyro");
- the Vicon orientation is the marker body's in the Vicon frame, neither the IMU's axes nor an
  up-pointing world: its recordings say so (`Recording.truth_needs_alignment`), and every run
  scores them through an alignment (`fusion.evaluation.scoring.align` fits the constant world tilt and
  IMU-to-marker rotation from the recording's own gyro, accelerometer and truth), as `--align` does. With
  a magnetometer the world rotation also turns the Vicon frame to magnetic north, fitted from the
  field and the truth alone (the same for every estimator), so a 9-D row's heading error is its own
  and not the room's (`docs/align.md`);
- the magnetometer reads about 1: the Xsens MTx sensor used reports the field in arbitrary units
  normalised to its strength where it was calibrated. The toolkit keeps magnetometers in uT, so
  such values (a median norm of 0.2-5) are multiplied by `FIELD_UT`, a typical Earth field
  strength in central Europe (IGRF: 49-50 uT); the estimators use the field's direction, which
  this does not change. Values already in uT are read as they are.

A recording's id is its path below the data directory without `.csv`
(`repoimu/pendulum/Pendulum_Test02a_Trial1_Segment_1`, as `fusion data fetch repoimu` lays them out).
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from ..format_checks import check_file, parse_rows, physical_samples, text_lines, truth_quaternions
from ..types import Recording, Trajectory
from .base import Format, Holds, ReadOptions, Source, recording_id

HEADER_FIRST_CELLS = ("time (s)", "time")  # the two header forms' first cell; the second is "vicon orientation"
COLUMNS = 14  # t; qw qx qy qz; ax ay az; gx gy gz; mx my mz
FIELD_UT = 50.0  # uT per normalised unit of the magnetometer (see the module docstring)
NORMALISED_FIELD = (0.2, 5.0)  # a median magnetometer norm in this range is in normalised units


def header_form(first_row: str) -> str | None:
    """Which of RepoIMU's header forms a file's first row is: "time (s)" (`Time (s);Vicon Orientation;...`
    with a row of components after it) or "time" (`Time;Vicon Orientation;...` with a row of units),
    None for another file."""
    cells = [c.strip().lower() for c in first_row.split(";")]
    if len(cells) >= 2 and cells[0] in HEADER_FIRST_CELLS and cells[1] == "vicon orientation":
        return cells[0]
    return None


def is_repoimu(path: str | Path) -> bool:
    """Whether a file starts with one of RepoIMU's header rows."""
    try:
        with open(path, "rb") as f:
            first = f.readline(4096).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    return header_form(first) is not None


def load_repoimu(path: str | Path) -> tuple:
    """One RepoIMU file: `(imu, truth, repeated)` (`read_repoimu`; a file without usable truth gives
    None, with a warning saying why)."""
    imu, truth, repeated, problem = read_repoimu(path)
    if problem is not None:
        warnings.warn(f"{path}: {problem}; loaded without ground truth", stacklevel=2)
    return imu, truth, repeated


def read_repoimu(path: str | Path) -> tuple:
    """One RepoIMU file: `(imu, truth, repeated, truth_problem)`.

    imu: `ImuSamples` (gyro rad/s, accelerometer in g from m/s^2, magnetometer uT, IMU frame,
        `gyr_timing` "end"); truth: `Trajectory` of the Vicon quaternions (w, x, y, z, the marker
        body in the Vicon frame: use `--align`), NaN rows where the file holds an all-zero
        quaternion or one far from unit norm, or None (a static file); repeated: the number of
        rows dropped for repeating a time stamp; truth_problem: why truth is None (one line), or None.
    """
    path = Path(path)
    lines = text_lines(path)
    if len(lines) < 3 or header_form(lines[0]) is None:
        raise ValueError(f"{path}: not a RepoIMU file (its first row must start with 'Time (s);Vicon Orientation' or "
                         "'Time;Vicon Orientation')")
    # the header rows end in ';', data rows may too; ';' separates fields, so a ',' is a decimal mark
    rows = [line.strip().rstrip(";").replace(",", ".") for line in lines[2:]]
    table = parse_rows(path, rows, delimiter=";")
    if table.shape[1] != COLUMNS:
        raise ValueError(f"{path}: {table.shape[1]} columns, RepoIMU files have {COLUMNS} (time; Vicon w,x,y,z; "
                         "acceleration x,y,z; gyroscope x,y,z; magnetometer x,y,z)")
    t = table[:, 0]
    repeated = np.zeros(len(t), bool)
    repeated[1:] = t[1:] == t[:-1]
    n_repeated = int(repeated.sum())
    if n_repeated:
        warnings.warn(f"{path}: {n_repeated} rows repeat the previous row's time stamp; dropped (the first row of "
                      "each stamp kept)", stacklevel=2)
        table = table[~repeated]
        t = table[:, 0]
    quat = table[:, 1:5]  # all-zero rows (markers not seen) become gaps in `truth_quaternions`
    mag = table[:, 11:14]
    with np.errstate(invalid="ignore"):
        norm = np.nanmedian(np.linalg.norm(mag, axis=1))
    if NORMALISED_FIELD[0] <= norm <= NORMALISED_FIELD[1]:
        mag = mag * FIELD_UT
    names = ("gyroscope x", "gyroscope y", "gyroscope z", "acceleration x", "acceleration y", "acceleration z")
    imu, quat = physical_samples(path, t, table[:, 8:11], table[:, 5:8], names, "end", quat,
                                 mag=None if mag is None else (mag, "magnetometer columns"))
    _warn_held(path, imu)
    quat, problem = truth_quaternions(path, quat, "Vicon orientation rows (w, x, y, z)", 1e-2)
    return imu, None if quat is None else Trajectory(imu.t, quat), n_repeated, problem


def _warn_held(path: Path, imu) -> None:
    """A warning naming each sensor whose values are held over rows (`fusion.checks.held_sensors`),
    with its rate: the rows are kept as published (module docstring)."""
    from ..checks import check_timing, held_sensors, imu_sensors

    timing = check_timing(imu.t, sensors=imu_sensors(imu))
    held = held_sensors(timing)
    if held:
        warnings.warn(f"{path}: rows at {timing.rate_hz:.0f} Hz hold the IMU's values: "
                      + ", ".join(f"the {name} changes at {rate:.0f} Hz" for name, rate in held.items())
                      + " (rows kept as published)", stacklevel=3)


class RepoImuFormat(Format):
    kind = "repoimu"
    describe = "RepoIMU .csv (Time (s);Vicon Orientation;... or Time;Vicon Orientation;...: semicolon-separated, two header rows)"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        for path in paths:
            if path.suffix.lower() == ".csv" and path.is_file() and is_repoimu(path):
                yield Source(recording_id(root, path), self.kind, path)

    def read(self, source: Source, options: ReadOptions) -> Recording:
        imu, truth, _, problem = read_repoimu(source.imu)
        return Recording(source.id, imu, truth, truth_problem=problem, truth_needs_alignment=True)

    def holds(self, source: Source) -> Holds:
        check_file(source.imu)
        return Holds(truth=True, movement=False, magnetometer=True, gyr_timing="end", raw_counts=False)


FORMAT = RepoImuFormat()
