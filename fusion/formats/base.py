"""What every format module provides: the `Source` of a recording, what it `Holds`, and the
`Format` interface (find, read, holds) that `fusion.formats.FORMATS` registers."""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from ..calibration import BoardModel
from ..types import GyrTiming, Recording


class ReadOptions(Protocol):
    """What a format's `read` may use of `fusion.datasets.LoadOptions` (see there)."""

    board: BoardModel
    dropouts: bool
    imu_topic: str | None
    truth_topic: str | None


@dataclass(frozen=True)
class Source:
    """Where one recording's files are, not yet read.

    id: the recording's id (see `fusion.datasets`).
    kind: its format, a key of `fusion.formats.FORMATS` ("course", "csv", "broad", "asl",
        "rosbag", "sim").
    imu: the recording's file, or its folder for formats that are folders (an ASL `mav0/`
        folder, a rosbag2 folder); None for the simulated recording.
    vicon, cam: the course files' VICON and camera files (None for other formats).
    aliases: ids of identical recordings merged into this one (`fusion.datasets.merge_identical`).
    """

    id: str
    kind: str
    imu: Path | None = None
    vicon: Path | None = None
    cam: Path | None = None
    aliases: tuple[str, ...] = ()


@dataclass(frozen=True)
class Holds:
    """What a recording holds, as its file says (before it is loaded).

    truth: a ground-truth orientation. movement: a movement mask (the samples a benchmark
    scores). magnetometer: magnetometer samples (the file holds them, whether or not the toolkit
    reads them). gyr_timing: which interval a gyro sample covers (`fusion.types.ImuSamples`).
    raw_counts: the IMU comes as the course board's ADC counts, calibrated by the toolkit (so a
    calibration file's gyro scale factors apply); False for files in physical units.
    """

    truth: bool
    movement: bool
    magnetometer: bool
    gyr_timing: GyrTiming
    raw_counts: bool


class Format(ABC):
    """One file format: how its recordings are found, read and described.

    A new format is a module with a subclass of this and one line in `fusion.formats.FORMATS`.
    `read` checks what it reads with the shared checks of `fusion.format_checks` (bounded sizes
    before allocation, physical plausibility, time-stamp repairs) and raises `ValueError` or
    `FileNotFoundError` naming the file, in one line, for anything it cannot read.
    """

    kind: str  # the registry key, stored in `Source.kind`
    describe: str  # what the files look like, for messages: "imuRawN.p/.mat (course files)"

    @abstractmethod
    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        """The recordings among `paths`.

        root: the data directory the ids are relative to (see `recording_id`), or None for a
            path a user named (its id is the path as given).
        paths: files and folders below `root`, sorted (every one, not only this format's), or
            the one path a user named.
        """

    @abstractmethod
    def read(self, source: Source, options: ReadOptions) -> Recording:
        """Read, check and (for raw counts) calibrate one recording."""

    @abstractmethod
    def holds(self, source: Source) -> Holds:
        """What the recording holds, from its file's header or structure (not a full read)."""


def recording_id(root: Path | None, path: Path, strip_suffix: bool = True) -> str:
    """The id of a recording at `path`: its path relative to `root` (the data directory's own
    name when it is `root` itself or outside it), or the path as given when `root` is None;
    without the file suffix when `strip_suffix`."""
    if root is not None:
        if path == root or root not in path.parents:
            return path.resolve().name
        path = path.relative_to(root)
    return (path.with_suffix("") if strip_suffix else path).as_posix()
