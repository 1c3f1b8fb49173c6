"""A trajectory another program computed, in the table as an estimator (`--trajectory NAME=PATH`).

    fusion compare --estimators ekf --trajectory orbslam=runs/orb/V1_01_easy.tum --dataset euroc/V1_01_easy
    fusion compare --estimators ekf --trajectory mine=runs/mine/ --dataset all
    fusion compare --estimators ukf --trajectory before=runs/last-week --dataset 'broad/*'

PATH is a trajectory file (`fusion.trajectory_files`: TUM or CSV) when one recording is
selected, or a folder holding one file per recording, named by the recording's id:
`runs/mine/ece276a/3.tum` (or `.txt`, `.csv`) for the recording `ece276a/3`.

A folder `fusion compare --out DIR` wrote is read as it is: `DIR` (or `DIR/trajectories`) holds a
folder per recording with a file per estimator, `DIR/trajectories/ece276a/3/ekf.tum`, and the row
NAME reads `NAME.tum` there, or, when there is no such file, the recording's one estimate (a
folder of a run of one estimator; with several, the error lists them). A file `fusion` wrote
says in its header which estimator and recording it holds and whether the estimate used a
magnetometer (`# fusion: estimator=ekf recording=broad/10 imu=9-D`): a 9-D estimate is scored
as 9-D (BROAD's protocol removes no heading offset from it), as its row was.

The file's orientations are put on the recording's IMU time stamps (as the toolkit loads them;
`fusion inspect` prints their span): a file stamp within `SAME_STAMP_S` of an IMU stamp (a file
written on the recording's own stamps, to the precision printed) gives that sample's orientation
as it is; other IMU stamps get the slerp over the file's own stamps, never extrapolated, so IMU
stamps outside the file's span get no orientation and are not scored (the coverage column says
how many were). A file whose span does not overlap the recording's is an error naming it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.trajectory_files import FORMATS, read_trajectory, tum_metadata
from fusion.types import ImuSamples, Trajectory

from ..base import Estimator

SAME_STAMP_S = 1e-6  # a file stamp this close to an IMU stamp is that stamp (a compact TUM file's rounding: <= 5e-7 s)
TRUTH_FILE = "truth.tum"  # beside the estimates in an --out folder: the truth they were scored against


@dataclass(frozen=True)
class TrajectoryFileParams:
    path: str = ""  # a trajectory file, or a folder with one file per recording (module docstring)
    recording: str = ""  # set by `for_recording` in folder mode: the recording whose file to read
    name: str = ""  # the row's name (set by the job that reads it): its file in a folder an --out run wrote


class TrajectoryFile(Estimator):
    """A trajectory read from a file (module docstring); its first row is the file's, not the
    shared initial orientation."""

    Params = TrajectoryFileParams
    partial = True

    def for_recording(self, recording_id: str) -> "TrajectoryFile":
        if not Path(self.params.path).is_dir():
            return self
        return TrajectoryFile(TrajectoryFileParams(self.params.path, recording_id, self.params.name))

    def file(self) -> Path:
        """The trajectory file to read (in folder mode, the recording's: `FOLDER/<id>.tum`, or in a
        folder `fusion compare --out` wrote, `FOLDER[/trajectories]/<id>/NAME.tum`)."""
        folder = Path(self.params.path)
        if not folder.is_dir():
            return folder
        rid = self.params.recording
        if not rid:
            raise ValueError(f"{folder}: a folder of trajectories needs the recording it is read for")
        found = [folder / f"{rid}{suffix}" for suffix in FORMATS]
        for path in found:
            if path.is_file():
                return path
        for root in (folder / "trajectories", folder):  # an --out folder, or its trajectories/ folder
            if (root / rid).is_dir():
                return self._estimate_in(root / rid)
        raise FileNotFoundError(f"{folder}: no trajectory for recording {rid!r} (looked for "
                                f"{', '.join(p.name for p in found)} under {found[0].parent}, and for a folder "
                                f"{rid} as `fusion compare --out` writes under {folder / 'trajectories'})")

    def _estimate_in(self, folder: Path) -> Path:
        """The estimate a recording's folder of an --out folder holds for this row: NAME.tum, else
        its only estimate."""
        name = self.params.name
        if name and (folder / f"{name}.tum").is_file():
            return folder / f"{name}.tum"
        estimates = sorted(p for p in folder.glob("*.tum") if p.name != TRUTH_FILE)
        if len(estimates) == 1:
            return estimates[0]
        listed = ", ".join(p.name for p in estimates) or "no estimate"
        raise FileNotFoundError(f"{folder}: no {name or 'NAME'}.tum (it holds {listed}); name the row after one of "
                                "them, or give that file with one recording selected")

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        path = self.file()
        trajectory = read_trajectory(path)
        quat = np.full((len(imu), 4), np.nan)
        rotation, mask = trajectory.interpolate(imu.t)
        if rotation is None:
            raise ValueError(f"{path}: its time span {trajectory.t[0]:.3f}-{trajectory.t[-1]:.3f} s does not overlap "
                             f"the recording's {imu.t[0]:.3f}-{imu.t[-1]:.3f} s")
        quat[mask] = rotation.as_quat(scalar_first=True)
        same, rows = same_stamps(trajectory.t, imu.t)
        quat[same] = trajectory.quat_wxyz[rows]  # a file on the recording's own stamps: its rows, not a slerp
        diagnostics = {}
        if path.suffix.lower() in (".tum", ".txt") and tum_metadata(path).get("imu") == "9-D":
            diagnostics["magnetometer"] = True  # `fusion.evaluation.run.job.run_one` scores it as 9-D
        return Trajectory(imu.t, quat, diagnostics)


def same_stamps(file_t: np.ndarray, imu_t: np.ndarray,
                tolerance_s: float = SAME_STAMP_S) -> tuple[np.ndarray, np.ndarray]:
    """Which IMU stamps (N,) a file stamp (M,), both increasing, s, matches within `tolerance_s`:
    (N,) bool, and for those the index of the nearest file stamp."""
    j = np.clip(np.searchsorted(file_t, imu_t), 1, max(len(file_t) - 1, 1))
    before = np.clip(j - 1, 0, len(file_t) - 1)
    j = np.clip(j, 0, len(file_t) - 1)
    nearest = np.where(np.abs(file_t[before] - imu_t) <= np.abs(file_t[j] - imu_t), before, j)
    same = np.abs(file_t[nearest] - imu_t) <= tolerance_s
    return same, nearest[same]
