"""Finding recordings in a data directory, selecting them by id, and loading them.

A data directory is laid out like the course releases, possibly nested:

    <data>/ece276a/imu/imuRaw3.p     <data>/ece276a/vicon/viconRot3.p    [<data>/ece276a/cam/cam3.p]
    <data>/ese650/imu/imuRaw3.mat    <data>/ese650/vicon/viconRot3.mat
    <data>/mylab/walk.csv            (generic CSV, see `fusion.loaders.load_csv`)
    <data>/broad/01_undisturbed_slow_rotation_A.hdf5   (BROAD trial, .hdf5 or .mat, see `fusion.broad`)

Each recording gets an id: its folder relative to the data directory (or, for recordings
directly in it, the data directory's own name) plus its number, e.g. `ece276a/3`; a CSV
file's or BROAD trial's id is its path without the suffix. A `.mat` file that is not a
course file (imuRawN/viconRotN/camN) is taken for a BROAD trial. The built-in simulated recording is always `sim`.

The data directory is `--data-dir`, else `$FUSION_DATA`, else `./data`. A course's `imu/`
(or `vicon/`, `cam/`) folder given as the data directory stands for its parent.

The same session may be present in several formats (`ece276a/3`, `ese650/3` and the IMU-only
`ece276a-2018/3` hold identical raw samples). `select` counts each recording once: course
recordings whose loaded time stamps and counts are bit-identical are merged (`merge_identical`,
a hash of the loaded arrays: some 0.1 s for 27 files), keeping the id with ground truth; the
kept `Source` lists the others in `aliases`. CSV files and BROAD trials are not hashed (they
are not raw counts of the course board and would need a full load; each file counts as one).
"""
from __future__ import annotations

import fnmatch
import hashlib
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import loaders
from .calibration import BoardModel, calibrate
from .types import Recording

SIM_ID = "sim"
_IMU_FILE = re.compile(r"imuRaw(\d+)\.(p|mat)$")
_COURSE_FILE = re.compile(r"(imuRaw|viconRot|cam)\d+\.(p|mat)$")
_BROAD_SUFFIXES = (".hdf5", ".h5", ".mat")


@dataclass(frozen=True)
class Source:
    """Where one recording's files are. `kind` is "course", "csv", "broad" or "sim"."""

    id: str
    kind: str
    imu: Path | None = None
    vicon: Path | None = None
    cam: Path | None = None
    aliases: tuple[str, ...] = ()  # ids of identical recordings merged into this one (`merge_identical`)


COURSE_SUBFOLDERS = ("imu", "vicon", "cam")


def data_dir_from(arg: str | os.PathLike | None = None) -> Path:
    """`arg`, else `$FUSION_DATA`, else `./data`."""
    return Path(arg or os.environ.get("FUSION_DATA") or "data")


def course_root(root: Path) -> Path:
    """`root`, or its parent when `root` is a course's `imu/`, `vicon/` or `cam/` folder (ids
    are `<folder>/<N>`, so they need the folder above)."""
    return root.parent if root.name in COURSE_SUBFOLDERS and root.is_dir() else root


def _natural_key(text: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def _sibling(imu_dir: Path, folder: str, stem: str, number: str, suffix: str) -> Path | None:
    for ext in (suffix, ".p", ".mat"):
        path = imu_dir.parent / folder / f"{stem}{number}{ext}"
        if path.is_file():
            return path
    return None


def discover(data_dir: str | os.PathLike | None = None) -> dict[str, Source]:
    """Every recording below `data_dir`, by id, in natural order; `sim` always last.

    A missing directory is not an error (a fresh clone has none): only `sim` is found.
    """
    root = course_root(data_dir_from(data_dir))
    found: dict[str, Source] = {}
    if root.is_dir():
        for path in sorted(root.rglob("*")):
            if not path.is_file():
                continue
            match = _IMU_FILE.match(path.name)
            if match and path.parent.name == "imu":
                folder = path.parent.parent.relative_to(root).as_posix()
                prefix = root.resolve().name if folder == "." else folder
                number, suffix = match.group(1), path.suffix
                rid = f"{prefix}/{number}"
                if rid in found:  # imuRaw3.p and imuRaw3.mat in one folder: keep the first
                    continue
                found[rid] = Source(
                    rid, "course", path,
                    vicon=_sibling(path.parent, "vicon", "viconRot", number, suffix),
                    cam=_sibling(path.parent, "cam", "cam", number, suffix),
                )
            elif path.suffix.lower() == ".csv":
                rid = path.relative_to(root).with_suffix("").as_posix()
                found[rid] = Source(rid, "csv", path)
            elif path.suffix.lower() in _BROAD_SUFFIXES and not _COURSE_FILE.match(path.name):
                rid = path.relative_to(root).with_suffix("").as_posix()
                found[rid] = Source(rid, "broad", path)
    ordered = {k: found[k] for k in sorted(found, key=_natural_key)}
    ordered[SIM_ID] = Source(SIM_ID, "sim")
    return ordered


def select(selection: str, data_dir: str | os.PathLike | None = None, dedupe: bool = True) -> list[Source]:
    """Sources for `all`, a comma list of ids, folder names (`ece276a`: every recording in it),
    bare numbers (`3`, when one recording has it after merging identical ones), globs
    (`ece276a/*`), paths to files, or paths to folders (every recording found below them).

    `all` means every real recording found, or `sim` when there is none. Raises with the
    list of available ids when a name matches nothing. dedupe: merge identical recordings
    (`merge_identical`), so that each is counted once.
    """
    available = discover(data_dir)
    real = [s for rid, s in available.items() if rid != SIM_ID]
    chosen: list[Source] = []
    for token in (tok.strip() for tok in selection.split(",")):
        if not token:
            continue
        if token == "all":
            matches = real or [available[SIM_ID]]
        elif token in available:
            matches = [available[token]]
        elif any(ch in token for ch in "*?["):
            matches = [s for rid, s in available.items() if fnmatch.fnmatchcase(rid, token)]
        elif token.isdigit():
            matches = merge_identical([s for rid, s in available.items() if rid.rsplit("/", 1)[-1] == token])
            if len(matches) > 1:
                raise ValueError(f"dataset {token!r} is ambiguous: {', '.join(s.id for s in matches)} "
                                 "(different recordings); give the id")
        elif any(rid.startswith(token.rstrip("/") + "/") for rid in available):
            matches = [s for rid, s in available.items() if rid.startswith(token.rstrip("/") + "/")]
        elif Path(token).is_file():
            matches = [_source_for_file(Path(token))]
        elif Path(token).is_dir():
            matches = [s for rid, s in discover(token).items() if rid != SIM_ID]
        else:
            matches = []
        if not matches:
            root = data_dir_from(data_dir)
            names = ", ".join(available) if len(available) <= 30 else ", ".join(list(available)[:30]) + ", ..."
            raise ValueError(f"dataset {token!r} not found in {root} (available: {names})")
        chosen.extend(s for s in matches if s not in chosen)
    if not chosen:
        raise ValueError(f"dataset selection {selection!r} names no recording")
    return merge_identical(chosen) if dedupe else chosen


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
    match = _IMU_FILE.match(path.name)
    if path.suffix.lower() == ".csv":
        return Source(path.with_suffix("").as_posix(), "csv", path)
    if path.suffix.lower() in _BROAD_SUFFIXES and not _COURSE_FILE.match(path.name):
        return Source(path.with_suffix("").as_posix(), "broad", path)
    if match:
        number = match.group(1)
        return Source(
            f"{path.parent.parent.name}/{number}", "course", path,
            vicon=_sibling(path.parent, "vicon", "viconRot", number, path.suffix),
            cam=_sibling(path.parent, "cam", "cam", number, path.suffix),
        )
    raise ValueError(f"{path}: not a recording this toolkit reads (imuRawN.p/.mat, .csv, or a BROAD .hdf5/.mat trial)")


def load_imu(path: Path):
    """Raw counts from a course IMU file, whichever release it comes from."""
    return loaders.load_imu_mat(path) if path.suffix == ".mat" else loaders.load_imu_pickle(path)


DROPOUTS_DEFAULT = True  # detected gyro freezes and ADC saturation are sensor faults: never integrate them


def calibrated_samples(raw, calib, dropouts: bool = DROPOUTS_DEFAULT):
    """`calib.apply(raw)`, with `gyr_valid` from `fusion.checks.dropout_mask` when `dropouts`."""
    imu = calib.apply(raw)
    if dropouts:
        from .checks import dropout_mask

        imu = imu.replace(gyr_valid=dropout_mask(raw, calib.board))
    return imu


def load_source(source: Source, board: BoardModel = BoardModel(), dropouts: bool = DROPOUTS_DEFAULT,
                truth_offset_s: float = 0.0) -> Recording:
    """Read and calibrate one recording.

    dropouts: the one switch of dropout handling: mark detected gyro freezes and saturated
        samples invalid (`ImuSamples.gyr_valid`, see `fusion.checks`); off for ablations.
    truth_offset_s: a measured clock offset (truth stamp minus IMU stamp, s, see
        `fusion.checks.clock_offset`); the truth's stamps are moved by `-truth_offset_s`.
    """
    if source.kind == "sim":
        from .sim import simulate

        # The simulated hardware is the nominal board (with the sim's own sensitivity errors);
        # `board` is the user's model of it, used only to calibrate, as for a real file.
        raw, truth = simulate()
        calib = calibrate(raw, board)
        return Recording(SIM_ID, calibrated_samples(raw, calib, dropouts), _shift(truth, truth_offset_s), raw, calib)
    if source.kind == "csv":
        imu, truth, movement = loaders.load_csv(source.imu, with_movement=True)
        return Recording(source.id, loaders.invalidate_gaps(imu), _shift(truth, truth_offset_s), movement=movement)
    if source.kind == "broad":
        from .broad import load_broad

        imu, truth, movement = load_broad(source.imu)
        return Recording(source.id, imu, _shift(truth, truth_offset_s), movement=movement)
    raw = load_imu(source.imu)
    calib = calibrate(raw, board)
    truth = loaders.load_vicon(source.vicon) if source.vicon else None
    if truth is not None and not (truth.t[0] < raw.t[-1] and raw.t[0] < truth.t[-1]):
        raise ValueError(f"{source.vicon}: VICON time span does not overlap the IMU file {source.imu}")
    # Gyro samples before a time gap are marked invalid too (see `fusion.loaders`, time stamps).
    imu = loaders.invalidate_gaps(calibrated_samples(raw, calib, dropouts))
    return Recording(source.id, imu, _shift(truth, truth_offset_s), raw, calib, camera=source.cam)


def _shift(truth, offset_s: float):
    if truth is None or offset_s == 0.0:
        return truth
    from .types import Trajectory

    return Trajectory(truth.t - offset_s, truth.quat_wxyz, truth.diagnostics)


def load(dataset_id: str, data_dir: str | os.PathLike | None = None, board: BoardModel = BoardModel(),
         dropouts: bool = DROPOUTS_DEFAULT) -> Recording:
    """One recording by id (e.g. `ece276a/3`, `sim`) or path."""
    (source,) = select(dataset_id, data_dir)[:1]
    return load_source(source, board, dropouts)


@dataclass(frozen=True)
class LoadOptions:
    """How recordings are loaded, in one picklable value (worker processes load their own).

    board: the sensor model (a calibration file's gyro scale factors go here).
    dropouts: mark detected gyro freezes and saturation invalid (see `load_source`).
    truth_offsets_s: per recording id, a measured truth clock offset, s.
    """

    board: BoardModel = BoardModel()
    dropouts: bool = DROPOUTS_DEFAULT
    truth_offsets_s: tuple[tuple[str, float], ...] = ()

    def load(self, source: Source) -> Recording:
        return load_source(source, self.board, self.dropouts, dict(self.truth_offsets_s).get(source.id, 0.0))


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
