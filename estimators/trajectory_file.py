"""A trajectory another program computed, in the table as an estimator (`--trajectory NAME=PATH`).

    fusion compare --estimators ekf --trajectory orbslam=runs/orb/V1_01_easy.tum --dataset euroc/V1_01_easy
    fusion compare --estimators ekf --trajectory mine=runs/mine/ --dataset all

PATH is a trajectory file (`fusion.trajectory_files`: TUM or CSV) when one recording is
selected, or a folder holding one file per recording, named by the recording's id:
`runs/mine/ece276a/3.tum` (or `.txt`, `.csv`) for the recording `ece276a/3`. (An `--out` folder
holds one folder per recording with a file per estimator, `DIR/trajectories/ece276a/3/ekf.tum`:
name one of those files with one recording selected.)

The file's orientations are put on the recording's IMU time stamps (as the toolkit loads them;
`fusion inspect` prints their span) by slerp over the file's own stamps: never extrapolated, so
IMU stamps outside the file's span get no orientation and are not scored (the coverage column
says how many were). A file whose span does not overlap the recording's is an error naming it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.trajectory_files import FORMATS, read_trajectory
from fusion.types import ImuSamples, Trajectory

from .base import Estimator


@dataclass(frozen=True)
class TrajectoryFileParams:
    path: str = ""  # a trajectory file, or a folder with one file per recording (module docstring)
    recording: str = ""  # set by `for_recording` in folder mode: the recording whose file to read


class TrajectoryFile(Estimator):
    """A trajectory read from a file (module docstring); its first row is the file's, not the
    shared initial orientation."""

    Params = TrajectoryFileParams
    partial = True

    def for_recording(self, recording_id: str) -> "TrajectoryFile":
        if not Path(self.params.path).is_dir():
            return self
        return TrajectoryFile(TrajectoryFileParams(self.params.path, recording_id))

    def file(self) -> Path:
        """The trajectory file to read (in folder mode, the recording's)."""
        folder = Path(self.params.path)
        if not folder.is_dir():
            return folder
        if not self.params.recording:
            raise ValueError(f"{folder}: a folder of trajectories needs the recording it is read for")
        found = [folder / f"{self.params.recording}{suffix}" for suffix in FORMATS]
        for path in found:
            if path.is_file():
                return path
        raise FileNotFoundError(f"{folder}: no trajectory for recording {self.params.recording!r} (looked for "
                                f"{', '.join(p.name for p in found)} under {found[0].parent})")

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        path = self.file()
        trajectory = read_trajectory(path)
        rotation, mask = trajectory.interpolate(imu.t)
        if rotation is None:
            raise ValueError(f"{path}: its time span {trajectory.t[0]:.3f}-{trajectory.t[-1]:.3f} s does not overlap "
                             f"the recording's {imu.t[0]:.3f}-{imu.t[-1]:.3f} s")
        quat = np.full((len(imu), 4), np.nan)
        quat[mask] = rotation.as_quat(scalar_first=True)
        return Trajectory(imu.t, quat)
