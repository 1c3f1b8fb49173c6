"""The settings of one `fusion compare` / `fusion ablate` run, as one frozen object.

Built once at the edge (the command line, or `run_compare(**options)` / `run_ablate(**options)`),
handed whole to everything below, journalled as itself and read back by itself (`from_json`,
with defaults for the keys an older journal lacks). Each field belongs to one part, in its
metadata:

- `computed`: what the results depend on (the recordings, how they are loaded and scored);
- `written`: what is written, and where;
- `how`: how the run runs (processes, cluster, progress); the only part `--resume` may change.

An option that changes results lives here (its field, whose metadata also holds its command-line
option: `Option`), where it is used, and in its test; the journal round trip
(`tests/test_journal.py`) and the command line (`tests/test_cli.py`) cover every field.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fusion import datasets

from ..scoring.metrics import KINDS, PROTOCOLS

COMPUTED, WRITTEN, HOW = "computed", "written", "how"
API_ONLY = "api-only"  # a field with no option of its own on the command line (see `Option`)
AS_FIELD = "as the field"  # `Option.default`: the option's default is the field's
OPTION_KINDS = ("value", "choices", "switch", "negated", "on_off", "auto_on_off", "append")


@dataclass(frozen=True)
class Option:
    """How a field is given on the command line: `fusion.cli` adds one option per field to
    `fusion compare` and `fusion ablate` (and the loading options to the other commands), from this.

    flag: the option, `--init`; help: its text (argparse's: `%%` for a per cent sign).
    kind: how the option's value becomes the field's:
        `value`: `--flag VALUE`, converted by `type` (None: text; else a converter `fusion.cli`
            names: `int`, `float`, `count` (a whole number >= 0), `seconds` (> 0, finite));
        `choices`: `--flag C`, one of `choices`;
        `switch`: `--flag` (argparse's store_true): True when given, else the field's default;
        `negated`: `--no-thing` (store_true): False when given, else True;
        `on_off`: `--flag on|off`, the field's default shown as its default;
        `auto_on_off`: `--flag auto|on|off`, None, True or False (auto: the field's default, None);
        `append`: `--flag VALUE`, repeatable: the texts given, in order (the field's default when
            none is given).
    metavar: the value's name in `--help`; default: the option's default where it is not the
        field's (`AS_FIELD`: the field's; `--jobs` 0, all cores, where `run_compare`'s default is 1).
    commands: which of compare, ablate and tune offer it (`fusion.cli` offers the loading options,
        dataset to calibration, on every command that reads recordings; `fusion stress` offers
        compare's, but those `fusion.evaluation.sweeps.stress.NOT_OFFERED` names, and its own fields').
    """

    flag: str
    help: str
    kind: str = "value"
    choices: tuple[str, ...] | None = None
    type: str | None = None
    metavar: str | None = None
    default: Any = AS_FIELD
    commands: tuple[str, ...] = ("compare", "ablate")

    def __post_init__(self) -> None:
        if self.kind not in OPTION_KINDS:
            raise ValueError(f"{self.flag}: kind must be one of {', '.join(OPTION_KINDS)}, got {self.kind!r}")

    @property
    def dest(self) -> str:
        """The name argparse stores the option's value under."""
        return self.flag.lstrip("-").replace("-", "_")


def _part(part: str, default: Any, cli: Option | str) -> Any:
    return field(default=default, metadata={"part": part, "cli": cli})


@dataclass(frozen=True)
class RunSettings:
    """One run's options. Each field's metadata holds its part (`part` lists a part's fields) and
    its command-line option (`Option`, whose help says what the field does: `fusion compare --help`).

    Computed: the selection (dataset, data_dir; None: $FUSION_DATA, else ./data), how recordings
    are loaded (calibration, dropouts, mag, imu_topic, truth_topic) and scored (init, protocol,
    align, panorama), timeout_s, repeat. Written: out, json_path, tum, per_recording (always on for
    `run_compare`), primary, command, rerun (a `.rrd` file). How: jobs (None or 0: all cores), progress, scheduler,
    scatter (a Dask cluster: `fusion.evaluation.run.runner.run`), overwrite, resume.
    One field has no option (`API_ONLY`): `command`, the command line recorded in the results
    document, which the command line sets to itself. `fusion tune`'s settings are these and its own
    (`fusion.evaluation.sweeps.tune.TuneSettings`).
    """

    # The keys a run's journalled call holds besides the settings (what kind of run: its estimators,
    # or its grid); any other key that is not a field is an error (`from_json`).
    CALL_KEYS = ("kind", "estimators", "trajectories", "estimator", "params", "preset")

    dataset: str = _part(COMPUTED, "all", Option(
        "--dataset", "'all', comma-separated ids (ece276a/3), folder names (ece276a), bare numbers (3, when "
        "unambiguous), globs ('ece276a/*') or file paths; 'sim' is the built-in simulated recording; identical "
        "recordings in several formats are counted once (default: all)"))
    data_dir: str | None = _part(COMPUTED, None, Option(
        "--data-dir", "folder with recordings (default: $FUSION_DATA, else ./data)"))
    calibration: str | None = _part(COMPUTED, None, Option(
        "--calibration", "apply a calibration file written by 'fusion calibrate' (gyro scale factors, and "
        "per-recording clock offsets if it holds them)", metavar="FILE"))
    init: str | None = _part(COMPUTED, None, Option(
        "--init", "initial orientation: truth (default with ground truth; with --align the aligned truth), accel "
        "(default without), identity", kind="choices", choices=datasets.INIT_MODES))
    protocol: str | None = _part(COMPUTED, None, Option(
        "--protocol", "scoring: full (every sample with truth) or broad (movement phases only, mean heading offset "
        "removed); default: broad for recordings with a movement mask (BROAD trials), else full",
        kind="choices", choices=PROTOCOLS, commands=("compare", "ablate", "tune")))
    align: bool = _part(COMPUTED, False, Option(
        "--align", "for ground truth given in other frames: fit a constant world tilt and a constant body rotation "
        "once per recording from its gyro, accelerometer and truth (never from an estimate), print them, and score "
        "every estimator against the same aligned truth; --init truth then starts from the aligned truth (see "
        "README)", kind="switch", commands=("compare", "ablate", "tune")))
    dropouts: bool = _part(COMPUTED, datasets.DROPOUTS_DEFAULT, Option(
        "--dropouts", "mark detected gyro freezes and ADC-saturated samples invalid so that no estimator integrates "
        "them (default: on; off for ablations)", kind="on_off"))
    mag: bool | None = _part(COMPUTED, None, Option(
        "--mag", "on: use the magnetometer where a recording has one (9-D estimation: heading is observable; BROAD's "
        "protocol then scores the total error without removing a heading offset); off: 6-D, gyro and "
        "accelerometer only; auto (default): on, unless the run mixes estimators that can and cannot use it: then "
        "every row is 6-D, like for like (a note says so)", kind="auto_on_off"))
    imu_topic: str | None = _part(COMPUTED, None, Option(
        "--imu-topic", "ROS bags: the sensor_msgs/Imu topic to read (default: the bag's one Imu topic)",
        metavar="TOPIC"))
    truth_topic: str | None = _part(COMPUTED, None, Option(
        "--truth-topic", "ROS bags: the PoseStamped, TransformStamped or Odometry topic holding the truth (default: "
        "the bag's one topic of those types, if any)", metavar="TOPIC"))
    panorama: bool = _part(COMPUTED, False, Option(
        "--panorama", "also stitch a panorama per estimate (camera frames, or frames rendered from a scene with the "
        "ground truth) and score it against the ground truth's panorama (PSNR, SSIM)", kind="switch",
        commands=("compare",)))
    timeout_s: float | None = _part(COMPUTED, None, Option(
        "--timeout", "stop a job (one recording x one estimator) that runs longer than S seconds; its row says so, "
        "the other rows are computed, and the command exits with status 1", type="seconds", metavar="S"))
    repeat: int = _part(COMPUTED, 1, Option(
        "--repeat", "time each estimate as the least of N runs, each from a fresh estimator (the table's us/sample, "
        "results.json's seconds): the least is what the estimator costs, the others add what else the machine was "
        "doing (Python's timeit documentation, Timer.repeat); the orientations are the last run's, a deterministic "
        "estimator's the same as one run's (default: 1)", type="int", metavar="N"))
    out: str | None = _part(WRITTEN, None, Option(
        "--out", "write results.json, table, figures, report.html and report.md to DIR (re-render later with "
        "`fusion report DIR`); tune: also tuned.json, for `compare --tuned`", metavar="DIR",
        commands=("compare", "ablate", "tune")))
    json_path: str | None = _part(WRITTEN, None, Option(
        "--json", "write the results as JSON (format: docs/json-format.md)", metavar="PATH",
        commands=("compare", "ablate", "tune")))
    tum: bool = _part(WRITTEN, True, Option(
        "--no-tum", "with --out, do not write every estimate and its truth as TUM files under DIR/trajectories (a "
        "few MB per recording and estimator: a BROAD trial's file is about 3 MB)", kind="negated"))
    per_recording: bool = _part(WRITTEN, False, Option(
        "--per-recording", "with --out, also draw each recording's figures for every setting", kind="switch",
        commands=("ablate",)))
    primary: str = _part(WRITTEN, "total", Option(
        "--primary", "the metric whose 95 %% interval and significance mark the table shows (default: total; "
        "inclination for 6-D comparisons)", kind="choices", choices=KINDS))
    command: str | None = _part(WRITTEN, None, API_ONLY)  # the command line is the command line itself
    rerun: str | None = _part(WRITTEN, None, Option(
        "--rerun", "also write a Rerun recording (fusion.evaluation.report.rerun_log): the truth and every estimate as 3-D "
        "bodies on one timeline, the camera frames, sensors, errors, events and the filters' beliefs; open it with "
        "`rerun FILE.rrd` (needs pip install 'fusion[viz]')", metavar="FILE.rrd"))
    jobs: int | None = _part(HOW, 1, Option(
        "--jobs", "worker processes; 0 = all cores (default); results do not depend on it", type="count",
        metavar="N", default=0, commands=("compare", "ablate", "tune")))
    progress: bool = _part(HOW, False, Option("--no-progress", "no progress bar", kind="negated"))
    scheduler: str | None = _part(HOW, None, Option(
        "--scheduler", "run the jobs on a running dask.distributed scheduler's workers instead of local processes, "
        "e.g. tcp://10.0.0.5:8786 (see docs/dask.md)", metavar="ADDRESS", commands=("compare", "ablate", "tune")))
    scatter: bool | None = _part(HOW, None, Option(
        "--scatter", "with --scheduler: load the recordings here and send them to the workers (no shared file "
        "system needed); default: workers read the files themselves when every worker sees them at the same path, "
        "else scatter", kind="switch"))
    overwrite: bool = _part(HOW, False, Option(
        "--overwrite", "with --out: replace the earlier run (or discard the unfinished one) that DIR holds; without "
        "it a folder holding a run is refused (files you put there are kept either way)", kind="switch",
        commands=("compare", "ablate", "tune")))
    resume: bool = _part(HOW, False, Option(  # the command line's value is the folder (`fusion.cli` resumes it)
        "--resume", "continue the unfinished run in the --out folder DIR (stopped by Ctrl-C, SIGTERM, a kill or a "
        "crash): its jobs already done are read back from DIR/.fusion-run/journal.jsonl, the others computed; the "
        "run's other options come from the journal", metavar="DIR", default=None, commands=("compare", "ablate", "tune")))

    def __post_init__(self) -> None:
        if self.primary not in KINDS:
            raise ValueError(f"--primary must be one of {', '.join(KINDS)}, got {self.primary!r}")
        if not (isinstance(self.repeat, int) and self.repeat >= 1):
            raise ValueError(f"--repeat must be a whole number of at least 1, got {self.repeat!r}")
        for name in ("data_dir", "calibration", "out", "json_path", "rerun"):  # paths are kept as text (journalled)
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
        """Read back from `to_json`'s document or a journalled call (an older journal's lacks some
        keys: their defaults), with `how` (fields of the `how` part only) replacing the recorded
        ones. A key that is neither a field nor one of `CALL_KEYS` is an error (written by a newer
        fusion, whose option would change the results)."""
        wrong = sorted(set(how) - set(cls.part(HOW)))
        if wrong:
            raise ValueError(f"--resume changes only how a run runs, not {wrong[0]!r}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(doc) - known - set(cls.CALL_KEYS))
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown key {unknown[0]!r} (written by a newer fusion?)")
        return cls(**{k: v for k, v in doc.items() if k in known}, **how)

    def load_options(self) -> datasets.LoadOptions:
        """How this run loads its recordings (`fusion.selection.load_options`: the calibration file,
        the dropout and magnetometer switches, a ROS bag's topics)."""
        from fusion.selection import load_options

        return load_options(self.calibration, self.dropouts, self.imu_topic, self.truth_topic, self.mag)

    def resolved_data_dir(self) -> Path:
        """The data folder this run reads (`fusion.datasets.data_dir_from`)."""
        return datasets.data_dir_from(self.data_dir)


def resolve_mag(mag: bool | None, entries: Any, sources: Any) -> bool:
    """`--mag` for a run of `entries` (resolved specs) on `sources` (dataset `Source`s or loaded
    recordings): as given when on or off; auto (None, the default) on where every estimator can use
    a magnetometer, and off when the run mixes estimators that can and cannot (`Estimator.magnetometer`;
    trajectory files, whose rows say it themselves, aside) and a selected recording holds one, so that
    every row is 6-D and every ranked group and paired test compares like with like (a note says so,
    and how to get 9-D rows). `--mag on` keeps the mix: the table's imu column marks the 6-D rows, and
    the statistics compare 6-D and 9-D rows apart."""
    if mag is not None:
        return mag
    able = [e.label for e in entries if not e.cls.partial and e.cls.magnetometer]
    blind = [e.label for e in entries if not e.cls.partial and not e.cls.magnetometer]
    if able and blind and any(holds_magnetometer(source) for source in sources):
        from fusion.selection import note

        note(f"{', '.join(blind)} cannot use a magnetometer: every row is 6-D, so that they all compare like for like "
             f"(--mag on gives 9-D rows for {', '.join(able)}, ranked apart from the 6-D ones)")
        return False
    return True


def holds_magnetometer(source: Any) -> bool:
    """Whether a recording holds a magnetometer, as its format says from its file (not loaded); a
    loaded `Recording`'s samples say it themselves."""
    from fusion.formats import FORMATS

    if not isinstance(source, datasets.Source):
        return bool(getattr(source.imu, "has_mag", False))
    try:
        return FORMATS[source.kind].holds(source).magnetometer
    except (ValueError, OSError, KeyError):  # a file that cannot be read says so when it is loaded
        return False
