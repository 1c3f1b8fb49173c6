"""The settings of one `fusion compare` / `fusion ablate` run, as one frozen object.

Built once at the edge (the command line, or `run_compare(**options)` / `run_ablate(**options)`),
handed whole to everything below, journalled as itself and read back by itself (`from_json`,
with defaults for the keys an older journal lacks). Each field belongs to one part, in its
metadata:

- `computed`: what the results depend on (the recordings, how they are loaded and scored);
- `written`: what is written, and where;
- `how`: how the run runs (processes, cluster, progress); the only part `--resume` may change.

An option that changes results lives here (its field), where it is used, and in its test; the
journal round trip (`tests/test_journal.py`) covers every field.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fusion import datasets

COMPUTED, WRITTEN, HOW = "computed", "written", "how"


def _part(part: str, default: Any) -> Any:
    return field(default=default, metadata={"part": part})


@dataclass(frozen=True)
class RunSettings:
    """One run's options (`fusion compare --help` describes each).

    Computed: dataset (the selection), data_dir (None: $FUSION_DATA, else ./data), calibration (a
    `fusion calibrate` file), init (`truth`, `accel`, `identity`; None: each recording's default),
    protocol (`full`, `broad`; None: each recording's default), align (score against the aligned
    truth), dropouts (mask detected gyro freezes), mag (use the magnetometer where there is one),
    imu_topic / truth_topic (a ROS bag's topics), panorama (stitch and score a panorama per row),
    timeout_s (stop a job that runs longer; its row says so).
    Written: out (the report folder), json_path (the results document), tum (TUM files of every
    estimate under out/trajectories), per_recording (per-recording figures; always for compare),
    primary (the metric whose interval and significance mark the table shows: `total`,
    `inclination`, `heading`), command (the command line recorded in the document).
    How: jobs (worker processes; None or 0: all cores), progress, scheduler / scatter (a Dask
    cluster: `fusion.evaluation.runner.run`), overwrite (replace the run `out` holds), resume
    (continue the unfinished run in `out`).
    """

    dataset: str = _part(COMPUTED, "all")
    data_dir: str | None = _part(COMPUTED, None)
    calibration: str | None = _part(COMPUTED, None)
    init: str | None = _part(COMPUTED, None)
    protocol: str | None = _part(COMPUTED, None)
    align: bool = _part(COMPUTED, False)
    dropouts: bool = _part(COMPUTED, datasets.DROPOUTS_DEFAULT)
    mag: bool = _part(COMPUTED, True)
    imu_topic: str | None = _part(COMPUTED, None)
    truth_topic: str | None = _part(COMPUTED, None)
    panorama: bool = _part(COMPUTED, False)
    timeout_s: float | None = _part(COMPUTED, None)
    out: str | None = _part(WRITTEN, None)
    json_path: str | None = _part(WRITTEN, None)
    tum: bool = _part(WRITTEN, True)
    per_recording: bool = _part(WRITTEN, False)
    primary: str = _part(WRITTEN, "total")
    command: str | None = _part(WRITTEN, None)
    jobs: int | None = _part(HOW, 1)
    progress: bool = _part(HOW, False)
    scheduler: str | None = _part(HOW, None)
    scatter: bool | None = _part(HOW, None)
    overwrite: bool = _part(HOW, False)
    resume: bool = _part(HOW, False)

    def __post_init__(self) -> None:
        from .metrics import KINDS

        if self.primary not in KINDS:
            raise ValueError(f"--primary must be one of {', '.join(KINDS)}, got {self.primary!r}")
        for name in ("data_dir", "calibration", "out", "json_path"):  # paths are kept as text (journalled)
            value = getattr(self, name)
            if isinstance(value, os.PathLike):
                object.__setattr__(self, name, os.fspath(value))

    @classmethod
    def part(cls, name: str) -> tuple[str, ...]:
        """The names of the fields of one part (`computed`, `written`, `how`), in order."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.metadata["part"] == name)

    def to_json(self) -> dict[str, Any]:
        """Every field, as the journal records it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, doc: dict[str, Any], **how: Any) -> "RunSettings":
        """Read back from `to_json`'s document (or an older journal's call, which lacks some keys:
        their defaults), with `how` (fields of the `how` part only) replacing the recorded ones."""
        wrong = sorted(set(how) - set(cls.part(HOW)))
        if wrong:
            raise ValueError(f"--resume changes only how a run runs, not {wrong[0]!r}")
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in doc.items() if k in known}, **how)

    def load_options(self) -> datasets.LoadOptions:
        """How this run loads its recordings (`fusion.selection.load_options`: the calibration file,
        the dropout and magnetometer switches, a ROS bag's topics)."""
        from fusion.selection import load_options

        return load_options(self.calibration, self.dropouts, self.imu_topic, self.truth_topic, self.mag)

    def resolved_data_dir(self) -> Path:
        """The data folder this run reads (`fusion.datasets.data_dir_from`)."""
        return datasets.data_dir_from(self.data_dir)
