"""Which recordings a command runs on, and how they are loaded: what `--dataset`, `--data-dir`,
`--calibration` and `--dropouts` mean, for every command and for Python callers alike.

    from fusion.selection import load_selected
    recordings = load_selected("sim")  # or ("ece276a/*", "/path/to/data")

Notes (neither errors nor warnings: the simulated recording stands in, identical recordings
were merged) are one line `fusion: note: ...` on stderr.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from . import datasets, gyro_fit
from .types import Recording


def note(text: str) -> None:
    """One line on stderr that is neither an error nor a warning."""
    print(f"fusion: note: {text}", file=sys.stderr)


def select_sources(dataset: str = "all", data_dir: str | os.PathLike | None = None,
                   calibration: str | os.PathLike | None = None) -> list[datasets.Source]:
    """The dataset `Source`s `dataset` names (`fusion.datasets.select`; not loaded yet), identical
    recordings merged (a note says which; `fusion.datasets.merged_ids` records them).

    data_dir: the folder with the recordings (None: `$FUSION_DATA`, else ./data); a folder that
        was asked for (here or in `$FUSION_DATA`) must exist and hold recordings.
    calibration: a calibration file (`fusion.gyro_fit`): warns about recordings its gyro scale
        factors do not apply to.
    """
    user_dir = data_dir or os.environ.get("FUSION_DATA")
    root = datasets.data_dir_from(data_dir)
    if user_dir and root.is_file():
        raise ValueError(f"{root}: data directory is a file; give the folder holding the recordings "
                         f"(or the file itself to --dataset)")
    if user_dir and not root.is_dir():
        raise FileNotFoundError(f"{root}: data directory does not exist")
    if datasets.course_root(root) != root:
        note(f"{root} is a course's {root.name}/ folder; reading recordings from its parent {root.parent}")
    sources = datasets.select(dataset, data_dir)
    if calibration:
        gyro_fit.warn_not_applied(calibration, sources)
    if dataset == "all" and [s.id for s in sources] == [datasets.SIM_ID]:
        if user_dir:
            from .formats import FORMATS

            looked_for = "; ".join(f.describe for kind, f in FORMATS.items() if kind != "sim")
            raise ValueError(f"{root}: no recordings found ({looked_for}); use --dataset sim for the simulated one")
        note(f"no recordings found in {root.resolve()}; running on the built-in simulated recording `sim` "
             "(--data-dir or $FUSION_DATA points at recordings)")
    aligned = [s.id for s in sources if s.kind == "repoimu"]
    if aligned:  # its truth is the Vicon markers' orientation in the Vicon frame (fusion.formats.repoimu)
        note(f"{aligned[0]}{f' and {len(aligned) - 1} more' if len(aligned) > 1 else ''}: RepoIMU's truth is the "
             "markers' orientation in the Vicon frame, not the IMU's: scored through an alignment fitted per "
             "recording, as --align does")
    merged = datasets.describe_merged(sources)
    if merged:
        note(f"identical recordings counted once: {merged}")
    return sources


def load_options(calibration: str | os.PathLike | None = None, dropouts: bool = datasets.DROPOUTS_DEFAULT,
                 imu_topic: str | None = None, truth_topic: str | None = None,
                 mag: bool | None = True) -> datasets.LoadOptions:
    """A calibration file, the dropout switch, a ROS bag's topics (`--imu-topic`, `--truth-topic`;
    None: the one topic of the type) and the magnetometer switch (`--mag`; None, auto: on, which a
    comparison resolves first, `fusion.evaluation.runs`) as the loading options every command uses."""
    topics = dict(imu_topic=imu_topic, truth_topic=truth_topic, mag=mag is not False)
    if not calibration:
        return datasets.LoadOptions(dropouts=dropouts, **topics)
    calib_file = gyro_fit.read(calibration)
    return datasets.LoadOptions(calib_file.board(), dropouts, tuple(sorted(calib_file.clock_offset_s.items())), **topics)


def load_selected(dataset: str = "all", data_dir: str | os.PathLike | None = None,
                  calibration: str | os.PathLike | None = None, dropouts: bool = datasets.DROPOUTS_DEFAULT,
                  progress: bool = False, imu_topic: str | None = None, truth_topic: str | None = None,
                  mag: bool | None = True) -> list[Recording]:
    """The recordings `dataset` names (`select_sources`), loaded and calibrated (`load_options`);
    progress: a progress bar on stderr, one step per recording. A recording whose files cannot be
    read costs only itself: a warning with the loader's one line, and the others are loaded; when
    none can be read, the first one's error is raised."""
    import warnings

    from tqdm import tqdm

    options = load_options(calibration, dropouts, imu_topic, truth_topic, mag)
    loaded, errors = [], []
    for source in tqdm(select_sources(dataset, data_dir, calibration), desc="loading", disable=not progress,
                       file=sys.stderr, leave=False):
        try:
            loaded.append(options.load(source))
        except (ValueError, OSError) as exc:
            errors.append(exc)
    if errors and not loaded:
        raise errors[0]
    for exc in errors:
        warnings.warn(f"{' '.join(str(exc).split())}; skipped (the other recordings go on)", stacklevel=2)
    return loaded


def calibration_settings(calibration: str | os.PathLike | None) -> dict | None:
    """What a calibration file applies (for results.json `settings`), None without one."""
    if not calibration:
        return None
    calib_file = gyro_fit.read(calibration)
    return {"file": str(Path(calibration).resolve()), "gyro_scale_factor": list(calib_file.gyro_scale_factor),
            "clock_offset_s": calib_file.clock_offset_s}
