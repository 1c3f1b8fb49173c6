"""Every file format the toolkit reads, one module each, and their registry.

A format module defines a `fusion.formats.base.Format` with three methods: `find` (its
recordings among the paths of a data directory), `read` (one recording into a checked
`fusion.types.Recording`) and `holds` (what a recording holds: truth, movement mask,
magnetometer, gyro timing, raw counts or physical units). A new format is one module and one
line here, as a new estimator is one line in `fusion.estimators.ESTIMATORS`.

The checks every format shares (bounded sizes before allocation, physical plausibility,
time-stamp repairs) are in `fusion.format_checks`; `fusion.datasets` finds, selects and loads
recordings through this registry.

Order matters only for a path a user names: the first format whose `find` takes it reads it
(an ASL folder's `mav0/imu0/data.csv` is the ASL recording, not a generic CSV).
"""
from __future__ import annotations

from . import asl, broad, course, generic_csv, repoimu, rosbag, sim
from .base import Format, Holds, ReadOptions, Source, recording_id

FORMATS: dict[str, Format] = {
    "course": course.FORMAT,  # ECE276A pickles, ESE650 .mat, with VICON
    "asl": asl.FORMAT,  # EuRoC / TUM-VI folders (mav0/imu0/data.csv)
    "rosbag": rosbag.FORMAT,  # ROS 1 .bag, ROS 2 folders (.db3, .mcap)
    "broad": broad.FORMAT,  # BROAD trials (.hdf5, .mat)
    "repoimu": repoimu.FORMAT,  # RepoIMU .csv (semicolons, two header rows), before the generic CSV
    "csv": generic_csv.FORMAT,  # t,gx,gy,gz,ax,ay,az[,qw,qx,qy,qz][,movement]
    "sim": sim.FORMAT,  # the built-in simulated recording
}

__all__ = ["FORMATS", "Format", "Holds", "ReadOptions", "Source", "recording_id"]
