"""Finding recordings in a data directory, selecting them by id, and loading them.

A data directory holds recordings of every format in `fusion.formats` (one module each, and
the registry `FORMATS`), possibly nested:

    <data>/ece276a/imu/imuRaw3.p     <data>/ece276a/vicon/viconRot3.p    [<data>/ece276a/cam/cam3.p]
    <data>/ese650/imu/imuRaw3.mat    <data>/ese650/vicon/viconRot3.mat
    <data>/mylab/walk.csv            (generic CSV, see `fusion.formats.generic_csv`)
    <data>/broad/01_undisturbed_slow_rotation_A.hdf5   (BROAD trial, .hdf5 or .mat, see `fusion.formats.broad`)
    <data>/repoimu/tstick/TStick_Test02_Trial1.csv     (RepoIMU, see `fusion.formats.repoimu`)

Each recording gets an id: for the course files, their folder relative to the data directory
(or, for recordings directly in it, the data directory's own name) plus their number, e.g.
`ece276a/3`; for a file of another format, its path without the suffix; for a format that is
a folder, the folder's path. A `.mat` file that is not a course file (imuRawN/viconRotN/camN)
is taken for a BROAD trial; files inside a folder that is itself a recording belong to it. The
built-in simulated recording is always `sim`.

The data directory is `--data-dir`, else `$FUSION_DATA`, else `./data`. A public dataset's name
(`broad/*`, `repoimu/pendulum/*`) that the data directory does not hold is looked up in the cache
`fusion data fetch` fills (`fusion.fetch`); when it is not there either, the error says which fetch
to run. A course's `imu/`
(or `vicon/`, `cam/`) folder given as the data directory stands for its parent.

The same session may be present in several formats (`ece276a/3`, `ese650/3` and the IMU-only
`ece276a-2018/3` hold identical raw samples). `select` counts each recording once: course
recordings whose loaded time stamps and counts are bit-identical are merged (`merge_identical`,
a hash of the loaded arrays: some 0.1 s for 27 files), keeping the id with ground truth; the
kept `Source` lists the others in `aliases`. Recordings of other formats are not hashed (they
are not raw counts of the course board and would need a full load; each counts as one).

Loading (`LoadOptions.load`, `load_source`) reads a recording through its format's `read`,
then, the same for every format: marks the gyro samples standing for time gaps invalid
(`fusion.format_checks.invalidate_gaps`) and, with `dropouts`, those of gyro freezes found in the data
(`fusion.checks.dropout_mask`; a format in raw counts does that in its calibration, with
saturation); drops the magnetometer when `mag` is off; and moves the truth by a measured clock
offset.
"""
from __future__ import annotations

import fnmatch
import hashlib
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .calibration import BoardModel, Calibration
from .formats import FORMATS, Source
from .formats import course
from .formats.course import load_imu
from .formats.sim import SIM_ID
from .format_checks import invalidate_gaps
from .types import ImuSamples, RawImu, Recording, Trajectory

__all__ = ["COURSE_SUBFOLDERS", "DROPOUTS_DEFAULT", "INIT_MODES", "SIM_ID", "LoadOptions", "Source", "calibrated_samples",
           "course_root", "data_dir_from", "describe_merged", "discover", "fingerprint", "initial_orientation", "load",
           "load_imu", "load_source", "merge_identical", "merged_ids", "select"]

COURSE_SUBFOLDERS = course.SUBFOLDERS


def data_dir_from(arg: str | os.PathLike | None = None) -> Path:
    """`arg`, else `$FUSION_DATA`, else `./data`."""
    return Path(arg or os.environ.get("FUSION_DATA") or "data")


def course_root(root: Path) -> Path:
    """`root`, or its parent when `root` is a course's `imu/`, `vicon/` or `cam/` folder (ids
    are `<folder>/<N>`, so they need the folder above)."""
    return root.parent if root.name in COURSE_SUBFOLDERS and root.is_dir() else root


def _natural_key(text: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def _found(root: Path | None, paths: list[Path]) -> list[Source]:
    """Every format's recordings among `paths` (`Format.find`), in registry order; a recording
    inside a folder that is itself a recording (an ASL `mav0/`, a rosbag2 folder) belongs to it
    and is left out."""
    sources = [s for fmt in FORMATS.values() for s in fmt.find(root, paths)]
    folders = {s.imu for s in sources if s.imu is not None and s.imu.is_dir()}
    return [s for s in sources if s.imu is None or not folders.intersection(s.imu.parents)]


def discover(data_dir: str | os.PathLike | None = None) -> dict[str, Source]:
    """Every recording below `data_dir`, by id, in natural order; `sim` always last.

    A missing directory is not an error (a fresh clone has none): only `sim` is found.
    """
    root = course_root(data_dir_from(data_dir))
    found: dict[str, Source] = {}
    if root.is_dir():
        for source in _found(root, [root, *sorted(root.rglob("*"))]):  # root: a folder that is one recording
            found.setdefault(source.id, source)
    ordered = {k: found[k] for k in sorted(found, key=_natural_key)}
    ordered[SIM_ID] = Source(SIM_ID, "sim")
    return ordered


def select(selection: str, data_dir: str | os.PathLike | None = None, dedupe: bool = True) -> list[Source]:
    """Sources for `all`, a comma list of ids, folder names (`ece276a`: every recording in it),
    bare numbers (`3`, when one recording has it after merging identical ones), globs
    (`ece276a/*`), paths to files, or paths to folders (every recording found below them).

    `all` means every real recording found, or `sim` when there is none. Ids, folder names and globs
    match regardless of case, on every platform (`repoimu/pendulum/*` selects `repoimu/Pendulum/...`),
    an exact match first. Raises, listing the folders found and what they hold, when a name matches
    nothing. dedupe: merge identical recordings (`merge_identical`), so that each is counted once.
    """
    available = discover(data_dir)
    real = [s for rid, s in available.items() if rid != SIM_ID]
    folded = {rid.casefold(): s for rid, s in available.items()}
    chosen: list[Source] = []
    for token in (tok.strip() for tok in selection.split(",")):
        if not token:
            continue
        key = token.casefold()
        prefix = key.rstrip("/") + "/"
        if token == "all":
            matches = real or [available[SIM_ID]]
        elif token in available:
            matches = [available[token]]
        elif key in folded:
            matches = [folded[key]]
        elif any(ch in token for ch in "*?["):
            matches = [s for rid, s in folded.items() if fnmatch.fnmatchcase(rid, key)]
        elif token.isdigit():
            matches = merge_identical([s for rid, s in available.items() if rid.rsplit("/", 1)[-1] == token])
            if len(matches) > 1:
                raise ValueError(f"dataset {token!r} is ambiguous: {', '.join(s.id for s in matches)} "
                                 "(different recordings); give the id")
        elif any(rid.startswith(prefix) for rid in folded):
            matches = [s for rid, s in folded.items() if rid.startswith(prefix)]
        elif Path(token).is_file():
            matches = [_source_for_file(Path(token))]
        elif Path(token).is_dir():
            matches = [s for rid, s in discover(token).items() if rid != SIM_ID]
        else:
            matches = []
        if not matches:
            matches = _fetched(token, data_dir)
        if not matches:
            root = data_dir_from(data_dir)
            raise ValueError(f"dataset {token!r} not found in {root} (available: {available_text(available)})"
                             f"{_fetch_hint(token)}")
        chosen.extend(s for s in matches if s not in chosen)
    if not chosen:
        raise ValueError(f"dataset selection {selection!r} names no recording")
    return merge_identical(chosen) if dedupe else chosen


def available_text(available: dict[str, Source], limit: int = 12) -> str:
    """What a data folder holds, for the error of a selection that matches nothing: each folder of
    recordings with its count and an id as an example (`broad/* (14, e.g. broad/01_...)`), then the
    recordings directly in it; `limit` entries at most, then how many more."""
    folders: dict[str, list[str]] = {}
    for rid in available:
        folders.setdefault(rid.rsplit("/", 1)[0] + "/*" if "/" in rid else rid, []).append(rid)
    parts = [f"{name} ({len(ids)}, e.g. {ids[0]})" if len(ids) > 1 or name.endswith("/*") else name
             for name, ids in folders.items()]
    return ", ".join(parts[:limit]) + (f", and {len(parts) - limit} more folders" if len(parts) > limit else "")


def _public_name(token: str) -> str | None:
    """The public dataset (`fusion.fetch.DATASETS`) a selection token starts with, if any."""
    from .fetch import DATASETS

    name = token.split("/", 1)[0].lower()
    return name if name in DATASETS else None


def _fetched(token: str, data_dir: str | os.PathLike | None) -> list[Source]:
    """The recordings `token` names in the cache `fusion data fetch` fills by default, for a
    public dataset's name (`broad/*`) that the data directory does not hold."""
    name = _public_name(token)
    if name is None:
        return []
    from .fetch import cache_dir

    cache = cache_dir()
    if not (cache / name).is_dir() or cache.resolve() == course_root(data_dir_from(data_dir)).resolve():
        return []
    try:
        return select(token, cache, dedupe=False)
    except ValueError:
        return []


def _fetch_hint(token: str) -> str:
    name = _public_name(token)
    return f"; fetch it with: fusion data fetch {name}" if name else ""


def fingerprint(source: Source) -> str | None:
    """A hash of a course recording's loaded time stamps and raw counts (identical for the same
    session in any release), or None for other kinds and unreadable files (their error comes
    when they are loaded)."""
    if source.kind != "course" or source.imu is None:
        return None
    try:
        raw = load_imu(source.imu)
    except (ValueError, OSError):
        return None
    digest = hashlib.sha1(np.ascontiguousarray(raw.t, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(raw.counts, dtype=np.float64).tobytes())
    return digest.hexdigest()


def merge_identical(sources: list[Source]) -> list[Source]:
    """`sources` with identical recordings (same `fingerprint`) counted once, in order.

    Of a group, the one with ground truth (then with camera frames, then the first) is kept, at
    its own position, with the others' ids (and aliases) in its `aliases`.
    """
    if sum(s.kind == "course" for s in sources) < 2:
        return list(sources)
    groups: dict[str, list[Source]] = {}
    keys = []
    for s in sources:
        key = fingerprint(s) or f"unique:{s.id}"
        keys.append(key)
        groups.setdefault(key, []).append(s)
    out = []
    for s, key in zip(sources, keys):
        group = groups[key]
        best = min(group, key=lambda g: (g.vicon is None, g.cam is None))
        if s is not best:
            continue
        others = [a for g in group if g is not best for a in (g.id, *g.aliases)]
        out.append(replace(best, aliases=tuple(dict.fromkeys([*best.aliases, *others]))) if others else best)
    return out


def merged_ids(sources: list[Source]) -> dict[str, list[str]]:
    """{kept id: [merged ids]} for the sources that absorbed identical recordings."""
    return {s.id: list(s.aliases) for s in sources if s.aliases}


def describe_merged(sources: list[Source]) -> str:
    """One line saying which ids were merged, compact when whole folders match by number:
    `ece276a/1-9 also found as ece276a-2018/N, ese650/N (identical samples; counted once)`."""
    merged = merged_ids(sources)
    if not merged:
        return ""
    patterns: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    singles = []
    for kept, others in merged.items():
        folder, _, number = kept.rpartition("/")
        folders = tuple(o.rpartition("/")[0] for o in others)
        if number.isdigit() and all(o.rpartition("/")[2] == number for o in others):
            patterns.setdefault((folder, folders), []).append(number)
        else:
            singles.append(f"{kept} = {', '.join(others)}")
    parts = []
    for (folder, folders), numbers in patterns.items():
        if len(numbers) == 1:
            parts.append(f"{folder}/{numbers[0]} = {', '.join(f'{f}/{numbers[0]}' for f in folders)}")
        else:
            parts.append(f"{folder}/N = {', '.join(f'{f}/N' for f in folders)} for N = {_ranges(numbers)}")
    return "; ".join(parts + singles)


def _ranges(numbers: list[str]) -> str:
    values = sorted(int(n) for n in numbers)
    runs: list[list[int]] = []
    for v in values:
        if runs and v == runs[-1][-1] + 1:
            runs[-1].append(v)
        else:
            runs.append([v])
    return ",".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)


def _source_for_file(path: Path) -> Source:
    found = _found(None, [path])
    if found:
        return found[0]
    kinds = "; ".join(fmt.describe for kind, fmt in FORMATS.items() if kind != "sim")
    raise ValueError(f"{path}: not a recording this toolkit reads ({kinds})")


DROPOUTS_DEFAULT = True  # detected gyro freezes and ADC saturation are sensor faults: never integrate them


def calibrated_samples(raw: RawImu, calib: Calibration, dropouts: bool = DROPOUTS_DEFAULT) -> ImuSamples:
    """`calib.apply(raw)`, with `gyr_valid` from `fusion.checks.dropout_mask` when `dropouts`."""
    return course.calibrated_samples(raw, calib, dropouts)


def load_source(source: Source, board: BoardModel = BoardModel(), dropouts: bool = DROPOUTS_DEFAULT,
                truth_offset_s: float = 0.0, imu_topic: str | None = None, truth_topic: str | None = None) -> Recording:
    """Read and calibrate one recording (`LoadOptions` says what the arguments mean).

    truth_offset_s: a measured clock offset (truth stamp minus IMU stamp, s, see
        `fusion.checks.clock_offset`); the truth's stamps are moved by `-truth_offset_s`.
    """
    return _load(source, LoadOptions(board, dropouts, imu_topic=imu_topic, truth_topic=truth_topic), truth_offset_s)


def _load(source: Source, options: "LoadOptions", truth_offset_s: float) -> Recording:
    fmt = FORMATS.get(source.kind)
    if fmt is None:
        raise ValueError(f"{source.id}: unknown recording kind {source.kind!r} (known: {', '.join(FORMATS)})")
    rec = fmt.read(source, options)
    # Gyro samples before a time gap are marked invalid (see `fusion.format_checks`, time stamps).
    imu = invalidate_gaps(rec.imu)
    if options.dropouts and rec.raw is None:  # recordings in physical units: gyro freezes found from the data
        from .checks import dropout_mask  # (raw counts: the format's calibration does it, with saturation)

        imu = imu.replace(gyr_valid=dropout_mask(imu))
    if not options.mag and imu.mag_ut is not None:  # --mag off: 6-D estimation
        imu = imu.replace(mag_ut=None)
    truth = _shift(rec.truth, truth_offset_s)
    return rec if imu is rec.imu and truth is rec.truth else replace(rec, imu=imu, truth=truth)


def _shift(truth: Trajectory | None, offset_s: float) -> Trajectory | None:
    if truth is None or offset_s == 0.0:
        return truth
    return Trajectory(truth.t - offset_s, truth.quat_wxyz, truth.diagnostics)


def load(dataset_id: str, data_dir: str | os.PathLike | None = None, board: BoardModel = BoardModel(),
         dropouts: bool = DROPOUTS_DEFAULT) -> Recording:
    """One recording by id (e.g. `ece276a/3`, `sim`) or path."""
    (source,) = select(dataset_id, data_dir)[:1]
    return load_source(source, board, dropouts)


@dataclass(frozen=True)
class LoadOptions:
    """How recordings are loaded, in one picklable value (worker processes load their own).

    board: the sensor model of recordings in raw counts (a calibration file's gyro scale
        factors go here).
    dropouts: the one switch of dropout handling: mark detected gyro freezes and saturated
        samples invalid (`ImuSamples.gyr_valid`, see `fusion.checks`); off for ablations.
    truth_offsets_s: per recording id, a measured truth clock offset, s (see `load_source`).
    imu_topic, truth_topic: the topics of a ROS bag to read the IMU and the truth from (None:
        the one topic of the type, see `fusion.formats.rosbag`); other formats ignore them.
    mag: use the magnetometer of recordings that have one (`ImuSamples.mag_ut`; `--mag off`
        drops it: 6-D estimation).
    """

    board: BoardModel = BoardModel()
    dropouts: bool = DROPOUTS_DEFAULT
    truth_offsets_s: tuple[tuple[str, float], ...] = ()
    imu_topic: str | None = None
    truth_topic: str | None = None
    mag: bool = True

    def load(self, source: Source) -> Recording:
        """Read one recording through its format (`fusion.formats.FORMATS`), checked and calibrated."""
        return _load(source, self, dict(self.truth_offsets_s).get(source.id, 0.0))


INIT_MODES = ("truth", "accel", "identity")


def initial_orientation(recording: Recording, mode: str | None = None) -> np.ndarray:
    """(4,) quat_wxyz every estimator starts from, at `recording.imu.t[0]`.

    - `truth`: the ground truth at the first IMU sample inside its span (the default with truth);
    - `accel`: tilt from the accelerometer averaged over the first rest, zero yaw (the default without);
    - `identity`: what the course reports did.
    """
    from scipy.spatial.transform import Rotation

    mode = mode or ("truth" if recording.truth is not None else "accel")
    if mode == "identity":
        return np.array([1.0, 0.0, 0.0, 0.0])
    if mode == "truth":
        if recording.truth is None:
            raise ValueError(f"{recording.id}: --init truth needs ground truth, and this recording has none")
        rot, mask = recording.truth.interpolate(recording.imu.t)
        if rot is None:
            raise ValueError(f"{recording.id}: no IMU sample falls inside the ground truth's span")
        return rot[0].as_quat(scalar_first=True)
    if mode == "accel":
        calib = recording.calibration
        stop = calib.rest_start[1] if calib is not None else min(len(recording.imu), 50)
        up_body = recording.imu.acc_g[:stop].mean(axis=0)
        # The rotation taking the measured up direction (body) to world z, with no yaw.
        rot, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up_body])
        yaw = rot.as_euler("ZYX")[0]
        return (Rotation.from_euler("Z", -yaw) * rot).as_quat(scalar_first=True)
    raise ValueError(f"unknown --init {mode!r}; use one of {', '.join(INIT_MODES)}")
