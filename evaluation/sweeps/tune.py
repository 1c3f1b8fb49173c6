"""Tuning every estimator by one protocol, and judging it out of sample (`fusion tune`).

Each estimator's tunable parameters and their ranges are declared beside its parameters
(`fusion.estimators.search.Tunable`, in the field's metadata); every estimator, ours, the peers
and a user's, is tuned the same way:

- the candidates: the grid preset (the product of each parameter's `grid` values, with the
  library default), or, with `search="tpe"`, `budget` settings proposed by Optuna's TPE sampler
  (Bergstra et al., "Algorithms for Hyper-Parameter Optimization", NeurIPS 2011), seeded;
- the objective of a setting on a set of recordings: the mean over them of its RMSE (`metric`:
  total, inclination or heading), the criterion of BROAD's "trial-agnostic good parameters"
  (Laidig et al., "BROAD - A Benchmark for Robust Inertial Orientation Estimation", Data 6(7):72,
  2021, sec. 4.2), with a failed or unscored row counting as infinitely bad;
- what is reported, per estimator: the library default, the best common setting over all
  recordings (in sample: chosen and judged on the same recordings), each recording's own best
  (an upper bound, in sample), and the honest figure: out of sample, each recording scored with the
  setting chosen without it (leave one recording out, `by="recording"`; leave one group out,
  `by="group"`: BROAD's motion or disturbance group, a folder of another dataset; or chosen on
  `train` and scored on `test`), with the setting each fold chose.

A grid's scores are computed once per (setting, recording) and reused by every fold. With TPE each
fold runs its own study on its training recordings only (so that the held-out recording never
guides the search), and one study on all recordings gives the common setting; each trial's
sampler is seeded with `seed` and the number of trials completed before it, so that a study
continued with `--resume` proposes what an uninterrupted one would. Scores of (setting,
recording) pairs already computed are never computed again, within a run or, through the
journal of an `--out` folder, after a stop. Results do not depend on `jobs`.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from fusion import datasets
from fusion.estimators import ResolvedSpec, resolve, resolve_all
from fusion.estimators.params import EstimatorSpec
from fusion.estimators.search import Tunable, alias_of, search_space
from fusion.selection import note, select_sources

from ..run.job import Result
from ..run.settings import API_ONLY, COMPUTED, HOW, Option, RunSettings
from ..scoring.metrics import KINDS, MIN_COVERAGE
from .loo import Fold

PathLike = str | os.PathLike

TUNED_FORMAT = "fusion-tuned-settings"
SEARCHES = ("grid", "tpe")
FOLDS = ("recording", "group")


def _own(default: Any, cli: Option | str) -> Any:
    return field(default=default, metadata={"part": COMPUTED, "cli": cli})


_TUNE = ("tune",)


@dataclass(frozen=True)
class TuneSettings(RunSettings):
    """Everything a `fusion tune` run depends on: the `RunSettings` it reads (the recordings, how
    they are loaded and scored, how the run runs) and its own fields below, each with its
    command-line option in its metadata (`fusion.cli` adds tune's options from them, as compare's).
    Journalled as itself (`JOURNALLED`); `--resume` may change only how it runs (`jobs`, `progress`,
    `scheduler`, a dask.distributed scheduler's address to run the jobs on, as `fusion compare
    --scheduler`).

    Loading and scoring (`dataset`, `data_dir`, `calibration`, `init`, `protocol`, `dropouts`, `mag`,
    `align`) as `fusion compare`: with `align`, every candidate is scored against the truth mapped
    into our frames by the rotations fitted once per recording (`fusion.evaluation.scoring.align`),
    for a dataset whose truth is given in other frames. A `RunSettings` field tuning does not read
    (a ROS bag's topics, panoramas, ...) is an error away from its default. Where the results go
    (`out`, `json_path`, `overwrite`, `resume`, `command`) is `run_tune`'s to say.
    """

    CALL_KEYS = ()  # the journal records the settings alone (`run_tune`)
    # What the journal and the results document record, in this order: tune's own fields and the
    # `RunSettings` fields it reads.
    JOURNALLED = ("estimators", "dataset", "train", "test", "metric", "by", "search", "budget", "seed", "data_dir",
                  "calibration", "init", "protocol", "dropouts", "mag", "align")

    estimators: str = _own("all", API_ONLY)  # spec text (`"madgwick,mahony"`, `"all"`); a parameter fixed in a spec is not tuned
    train: str | None = _own(None, Option(
        "--train", "choose the setting on these recordings (with --test: instead of folds over --dataset)",
        metavar="SEL", commands=_TUNE))
    test: str | None = _own(None, Option(
        "--test", "score the chosen setting on these recordings", metavar="SEL", commands=_TUNE))
    metric: str = _own("total", Option(
        "--metric", "the RMSE minimised and reported (default: total)", kind="choices", choices=KINDS,
        commands=_TUNE))
    by: str = _own("recording", Option(
        "--by", "the folds over --dataset: leave one recording out (default), or one group out (BROAD's motion or "
        "disturbance group; another dataset's folder)", kind="choices", choices=FOLDS, commands=_TUNE))
    search: str = _own("grid", Option(
        "--search", "grid: the grid preset each estimator declares (default); tpe: Optuna's seeded TPE sampler "
        "with --budget trials per study", kind="choices", choices=SEARCHES, commands=_TUNE))
    budget: int = _own(30, Option("--budget", "TPE trials per study (default: 30)", type="int", metavar="N",
                                  commands=_TUNE))
    seed: int = _own(0, Option("--seed", "TPE's seed (default: 0)", type="int", metavar="N", commands=_TUNE))

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.metric not in KINDS:
            raise ValueError(f"tune: --metric must be one of {', '.join(KINDS)}, got {self.metric!r}")
        if self.by not in FOLDS:
            raise ValueError(f"tune: --by must be one of {', '.join(FOLDS)}, got {self.by!r}")
        if self.search not in SEARCHES:
            raise ValueError(f"tune: --search must be one of {', '.join(SEARCHES)}, got {self.search!r}")
        if not (isinstance(self.budget, int) and 1 <= self.budget <= 10_000):
            raise ValueError(f"tune: --budget must be a whole number from 1 to 10000, got {self.budget!r}")
        if (self.train is None) != (self.test is None):
            raise ValueError("tune: --train and --test go together (choose on one selection, score on the other)")
        for f in dataclasses.fields(RunSettings):  # what tuning does not read must stay as it is
            if f.name not in self.JOURNALLED and f.metadata["part"] != HOW and f.name not in _WHERE \
                    and getattr(self, f.name) != f.default:
                option = f.metadata["cli"]
                flag = option.flag if isinstance(option, Option) else f.name
                raise ValueError(f"tune: {flag} is not supported here; use it with fusion compare")

    def to_json(self) -> dict[str, Any]:
        """The fields that decide the results (`JOURNALLED`; not how the run runs)."""
        return {name: getattr(self, name) for name in self.JOURNALLED}


# Where the results go: `run_tune`'s own arguments, not settings of the tuning.
_WHERE = ("out", "json_path", "command")


@dataclass(frozen=True)
class EstimatorTuning:
    """What tuning found for one estimator (scores: mean RMSE in degrees over the recordings named).

    space: the tuned parameters (alias -> `Tunable`); default: the library default's mean;
    common: the best common setting over all recordings and its mean (in sample); per_recording:
    the mean of each recording's own best (in sample, an upper bound); out_of_sample: the mean over
    the test recordings of the setting each fold chose, and `chosen`: fold name -> setting;
    scores_default / scores_tuned: recording id -> RMSE of the default and of the out-of-sample
    choice; evaluated: how many settings were scored.
    """

    estimator: str
    space: dict[str, Tunable]
    default: float
    common_setting: dict[str, float]
    common: float
    per_recording: float
    out_of_sample: float
    chosen: dict[str, dict[str, float]]
    scores_default: dict[str, float]
    scores_tuned: dict[str, float]
    evaluated: int

    def to_json(self) -> dict[str, Any]:
        return {"estimator": self.estimator,
                "space": {k: {"low": t.low, "high": t.high, "log": t.log, "grid": list(t.grid)}
                          for k, t in self.space.items()},
                "default_deg": _finite(self.default), "common_setting": self.common_setting,
                "common_deg": _finite(self.common), "per_recording_best_deg": _finite(self.per_recording),
                "out_of_sample_deg": _finite(self.out_of_sample), "chosen": self.chosen,
                "scores_default_deg": {k: _finite(v) for k, v in self.scores_default.items()},
                "scores_tuned_deg": {k: _finite(v) for k, v in self.scores_tuned.items()},
                "test_datasets": scores_per_dataset(self), "settings_evaluated": self.evaluated}


def scores_per_dataset(tuning: EstimatorTuning) -> list[dict[str, Any]]:
    """The out-of-sample scores per dataset of the test recordings (their folder,
    `fusion.evaluation.compare.dataset_group`, in test order): `{"dataset", "recordings",
    "default_deg", "tuned_deg"}`, each the mean over that dataset's test recordings (null when a
    row there failed)."""
    from ..compare import dataset_group

    folders: dict[str, list[str]] = {}
    for rid in tuning.scores_tuned:
        folders.setdefault(dataset_group(rid), []).append(rid)
    return [{"dataset": folder, "recordings": len(ids),
             "default_deg": _finite(_mean({rid: tuning.scores_default[rid] for rid in ids})),
             "tuned_deg": _finite(_mean({rid: tuning.scores_tuned[rid] for rid in ids}))} for folder, ids in folders.items()]


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def value_text(value: float, tunable: Tunable) -> str:
    """A setting's value as spec text: whole numbers for counts, else 4 significant digits (the
    value used is the one the text gives, so a label reproduces its row exactly)."""
    return str(int(round(value))) if tunable.integer else f"{value:.4g}"


def candidate_spec(entry: ResolvedSpec, setting: dict[str, float]) -> EstimatorSpec:
    """The spec of `entry` with `setting` (alias -> value) added to its own overrides."""
    space = tunable_space(entry)
    return EstimatorSpec(entry.spec.name, entry.spec.overrides
                         + tuple((alias, value_text(v, space[alias])) for alias, v in setting.items()))


def tunable_space(entry: ResolvedSpec, mag: bool = True) -> dict[str, Tunable]:
    """alias -> `Tunable` of the parameters `entry` tunes: its declared space less the parameters
    its spec fixes (and, without the magnetometer, `mag` False, those that act on it alone)."""
    params_cls = entry.cls.Params
    fixed = {name for name, _ in entry.spec.overrides}
    out = {}
    for name, tunable in search_space(params_cls).items():
        alias = alias_of(params_cls, name)
        if alias not in fixed and name not in fixed and (mag or not tunable.magnetometer):
            out[alias] = tunable
    return out


def grid_settings(entry: ResolvedSpec, mag: bool = True) -> list[dict[str, float]]:
    """The grid preset's settings (alias -> value), the library default (`{}`) first."""
    space = tunable_space(entry, mag)
    names = [alias for alias, t in space.items() if t.grid]
    out: list[dict[str, float]] = [{}]
    for values in (itertools.product(*(space[a].grid for a in names)) if names else ()):
        setting = dict(zip(names, map(float, values)))
        if not _is_default(entry, setting):  # a grid point that is the default setting is the first entry already
            out.append(setting)
    return out


def _defaults(entry: ResolvedSpec) -> dict[str, float]:
    """alias -> the value `entry` runs with (its default, or its spec's), for its tunable parameters."""
    params_cls = entry.cls.Params
    return {alias_of(params_cls, name): float(getattr(entry.params, name)) for name in search_space(params_cls)}


def _is_default(entry: ResolvedSpec, setting: dict[str, float]) -> bool:
    """Whether `setting` is what `entry` runs with anyway (then it is the default's row, `{}`)."""
    current = _defaults(entry)
    return all(math.isclose(v, current[a], rel_tol=1e-12) for a, v in setting.items())


def folds_of(sources: Sequence[Any], by: str) -> list[Fold]:
    """Leave-one-out folds over `sources` (`Source`s, in order): one recording, or one group
    (`group_of`) held out at a time."""
    ids = [s.id for s in sources]
    if len(ids) < 2:
        raise ValueError(f"tune: folds need at least two recordings, the selection has {len(ids)}")
    if by == "recording":
        return [Fold(rid, tuple(i for i in ids if i != rid), (rid,)) for rid in ids]
    groups: dict[str, list[str]] = {}
    for s in sources:
        groups.setdefault(group_of(s), []).append(s.id)
    if len(groups) < 2:
        raise ValueError(f"tune: --by group needs recordings of two groups or more; all are in {next(iter(groups))!r}")
    return [Fold(g, tuple(i for i in ids if i not in members), tuple(members)) for g, members in groups.items()]


def group_of(source: Any) -> str:
    """A recording's group for leave-one-group-out: BROAD's motion or disturbance group
    (`fusion.formats.broad.primary_group`), else its dataset (the id's first folder)."""
    from fusion.formats.broad import primary_group

    imu = getattr(source, "imu", None)
    group = primary_group(imu) if imu is not None else None
    return group or source.id.split("/")[0]


class Scores:
    """RMSE rows of (spec label, recording id), each computed once (`runner.run` on the pool), and
    journalled into an `--out` folder's run journal as it ends."""

    def __init__(self, sources: Sequence[Any], settings: TuneSettings, journal: Any = None) -> None:
        self.sources = {s.id: s for s in sources}
        self.settings = settings
        # the runner's settings: how recordings are loaded and scored, and how the jobs run
        self.run_settings = RunSettings(init=settings.init, protocol=settings.protocol,
                                        calibration=settings.calibration, dropouts=settings.dropouts, mag=settings.mag,
                                        align=settings.align, jobs=settings.jobs, progress=settings.progress,
                                        scheduler=settings.scheduler)
        self.load = self.run_settings.load_options()
        self.journal = journal
        self.rows: dict[tuple[str, str], Result] = {}
        self._prints: dict[str, str] = {}

    def _key(self, label: str, rid: str, describe: dict[str, Any]) -> str:
        """A row's journal key: the recording and its files' contents (a recording changed since a
        stop is computed again), the estimator, and how it is loaded and scored."""
        from ..run.journal import fingerprint, job_key
        from ..run.runner import source_paths

        if rid not in self._prints:
            self._prints[rid] = fingerprint(source_paths(self.sources[rid]), what=rid)
        s = self.settings
        aligned = {"align": True} if s.align else {}  # (keys of unaligned rows as before: older journals resume)
        return job_key(kind="tune", dataset=rid, files=self._prints[rid], estimator=label, origin=describe,
                       load=repr(self.load), init=s.init, protocol=s.protocol, **aligned)

    def evaluate(self, specs: Sequence[EstimatorSpec], ids: Sequence[str]) -> dict[tuple[str, str], Result]:
        """The rows of every spec on every recording in `ids` (computing those not known yet)."""
        from ..run.runner import run

        entries = resolve_all(list(specs))
        missing_ids = [rid for rid in ids if any((e.label, rid) not in self.rows for e in entries)]
        if self.journal is not None:
            for e in entries:
                for rid in missing_ids:
                    key = self._key(e.label, rid, e.describe())
                    if key in self.journal.done:
                        self.rows[(e.label, rid)] = Result.from_json(self.journal.done[key].row)
        todo_entries = [e for e in entries if any((e.label, rid) not in self.rows for rid in ids)]
        todo_ids = [rid for rid in ids if any((e.label, rid) not in self.rows for e in todo_entries)]
        if todo_entries and todo_ids:
            items = [self.sources[rid] for rid in todo_ids]
            done = {n: self.rows[(e.label, rid)] for n, (rid, e) in
                    enumerate(itertools.product(todo_ids, todo_entries)) if (e.label, rid) in self.rows}

            def record(n: int, output: Any) -> None:
                rid, e = todo_ids[n // len(todo_entries)], todo_entries[n % len(todo_entries)]
                self.rows[(e.label, rid)] = output.result
                if self.journal is not None:
                    self.journal.record(self._key(e.label, rid, e.describe()), output.result.to_json(),
                                        output.result.error, None)

            run(todo_entries, items, self.run_settings, done=done, on_done=record)
        return {(e.label, rid): self.rows[(e.label, rid)] for e in entries for rid in ids}

    def score(self, row: Result) -> float:
        """A row's RMSE in the tuned metric; inf for a failed or unscored row."""
        if row.error is not None or not row.in_means:
            return math.inf
        value = row.rmse_deg[self.settings.metric]
        return float(value) if math.isfinite(value) else math.inf


def _mean(scores: Mapping[str, float]) -> float:
    """The mean of recording id -> RMSE as every table takes it: across datasets the mean of the
    per-dataset means (`fusion.evaluation.scoring.stats.mean_across_datasets`); inf if one is inf."""
    from ..scoring.stats import mean_across_datasets

    return mean_across_datasets(scores)


def _search_grid(entry: ResolvedSpec, scores: Scores, folds: list[Fold], all_ids: list[str]) -> EstimatorTuning:
    """Every grid setting on every recording, once; each fold chooses from its training scores."""
    settings = grid_settings(entry, scores.settings.mag)
    specs = [candidate_spec(entry, s) for s in settings]
    ids = sorted(set(all_ids) | {rid for f in folds for rid in f.test})
    rows = scores.evaluate(specs, ids)
    labels = [resolve(spec).label for spec in specs]
    table = {(k, rid): scores.score(rows[(label, rid)]) for k, label in enumerate(labels) for rid in ids}

    def best(train: Sequence[str]) -> int:  # the lowest mean; on a tie the earlier setting (the default first)
        return int(np.argmin([_mean({rid: table[(k, rid)] for rid in train}) for k in range(len(settings))]))

    return _tuning(entry, settings, table, best(all_ids), {f.name: best(f.train) for f in folds}, folds, all_ids,
                   scores.settings.mag)


def _search_tpe(entry: ResolvedSpec, scores: Scores, folds: list[Fold], all_ids: list[str],
                storage: Any) -> EstimatorTuning:
    """One seeded TPE study on all recordings (the common setting) and one per fold on its
    training recordings; each fold's best is then scored on its test recordings."""
    settings: list[dict[str, float]] = [{}]
    table: dict[tuple[int, str], float] = {}

    def scored(setting: dict[str, float], ids: Sequence[str]) -> float:
        setting = {} if _is_default(entry, setting) else setting
        if setting not in settings:
            settings.append(setting)
        k = settings.index(setting)
        spec = candidate_spec(entry, setting)
        rows = scores.evaluate([spec], ids)
        label = resolve(spec).label
        for rid in ids:
            table[(k, rid)] = scores.score(rows[(label, rid)])
        return _mean({rid: table[(k, rid)] for rid in ids})

    test_ids = [rid for f in folds for rid in f.test]
    scored({}, sorted(set(all_ids) | set(test_ids)))  # the default everywhere
    common = _run_study(entry, f"{entry.label}/all", all_ids, scores.settings, storage, scored)
    chosen = {}
    for fold in folds:
        best = _run_study(entry, f"{entry.label}/{fold.name}", fold.train, scores.settings, storage, scored)
        scored(best, fold.test)
        chosen[fold.name] = settings.index({} if _is_default(entry, best) else best)
    common = {} if _is_default(entry, common) else common
    return _tuning(entry, settings, table, settings.index(common), chosen, folds, all_ids, scores.settings.mag)


def _tuning(entry: ResolvedSpec, settings: list[dict[str, float]], table: dict[tuple[int, str], float],
            common: int, chosen: dict[str, int], folds: list[Fold], all_ids: list[str], mag: bool) -> EstimatorTuning:
    """The figures of `EstimatorTuning` from a table of (setting index, recording id) -> RMSE, the
    common setting's index and each fold's chosen index."""
    test_ids = [rid for f in folds for rid in f.test]
    tuned = {rid: table[(chosen[f.name], rid)] for f in folds for rid in f.test}
    per_recording = {rid: min(v for (_, r), v in table.items() if r == rid) for rid in all_ids}
    return EstimatorTuning(
        estimator=entry.label, space=tunable_space(entry, mag), default=_mean({rid: table[(0, rid)] for rid in test_ids}),
        common_setting=settings[common], common=_mean({rid: table[(common, rid)] for rid in all_ids}),
        per_recording=_mean(per_recording), out_of_sample=_mean(tuned),
        chosen={name: settings[k] for name, k in chosen.items()},
        scores_default={rid: table[(0, rid)] for rid in test_ids}, scores_tuned=tuned, evaluated=len(settings))


def _run_study(entry: ResolvedSpec, name: str, ids: Sequence[str], settings: TuneSettings, storage: Any,
               scored: Callable[[dict[str, float], Sequence[str]], float]) -> dict[str, float]:
    """A TPE study of `settings.budget` trials on `ids`; returns its best setting. Its first trial
    is the library default (where it lies in the range), as in the grid; each later trial's
    sampler is seeded with the seed and the number of trials completed before it (module
    docstring); a trial a stop left running is marked failed and proposed again."""
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    space = tunable_space(entry, settings.mag)
    study = optuna.create_study(study_name=name, storage=storage, direction="minimize", load_if_exists=True)
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        study._storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
    default = {a: v for a, v in _defaults(entry).items() if a in space}
    if not study.trials and all(space[a].low <= v <= space[a].high for a, v in default.items()):
        study.enqueue_trial(default)
    while len(complete := study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))) < settings.budget:
        study.sampler = optuna.samplers.TPESampler(seed=settings.seed + len(complete))
        trial = study.ask()
        setting = {}
        for alias, t in space.items():
            value = (trial.suggest_int(alias, int(t.low), int(t.high), log=t.log) if t.integer
                     else trial.suggest_float(alias, t.low, t.high, log=t.log))
            setting[alias] = float(value_text(value, t))
        value = scored(setting, ids)
        study.tell(trial, value if math.isfinite(value) else 1e300)
    best = min(complete, key=lambda t: (t.value, t.number))
    return {alias: float(value_text(best.params[alias], space[alias])) for alias in space}


@dataclass(frozen=True, eq=False)
class TuneRun:
    """A finished `run_tune`: one `EstimatorTuning` per estimator, the text `fusion tune` prints,
    the results document (rows: each estimator's default and its out-of-sample choice per test
    recording) and the report written (None without `out`)."""

    tunings: list[EstimatorTuning]
    table: str
    document: dict[str, Any]
    report: Path | None = None


def run_tune(estimators: str = "all", dataset: str = "all", *, out: PathLike | None = None,
             json_path: PathLike | None = None, overwrite: bool = False, resume: bool = False,
             command: str | None = None, **settings: Any) -> TuneRun:
    """`fusion tune`: every estimator in `estimators` tuned on the recordings `dataset` selects by
    one protocol (module docstring; the other keywords are `TuneSettings`' fields).

    out: write results.json, table.txt, report.html/md, tuned.json (for `compare --tuned`) and the
        Optuna journal there, journalling every score as it is computed (`resume` continues a
        stopped run: then only `jobs` and `progress` may be given); json_path: the results document.
    """
    from ..run.journal import Journal
    from ..run.output import OutputFolder
    from ..report.render import git_commit

    if resume:
        if not out:
            raise ValueError("--resume needs the output folder of the run to continue")
        header = Journal.read_header(Path(out))
        call = header["call"]
        if call.get("kind") != "tune":
            raise ValueError(f"{out}: holds an unfinished `fusion {call.get('kind')}` run; resume it with that command")
        how = {k: v for k, v in settings.items() if k in ("jobs", "progress", "scheduler")}
        if set(settings) - set(how):
            raise ValueError(f"--resume continues the run recorded in {out}: give it with --jobs, --scheduler or "
                             "--no-progress only")
        config = TuneSettings.from_json(call["settings"], **how)
        command = header["command"]
    else:
        for name in ("data_dir", "calibration"):  # journalled as absolute paths: --resume from anywhere
            if settings.get(name) is not None:
                settings[name] = str(Path(settings[name]).resolve())
        config = TuneSettings(estimators=estimators, dataset=dataset, **settings)
    command = command or f"run_tune({config.estimators!r}, {config.dataset!r})"
    entries = resolve_all(config.estimators)
    split = None
    if config.train is not None:
        train = select_sources(config.train, config.data_dir, config.calibration)
        test = select_sources(config.test, config.data_dir, config.calibration)
        split = [[s.id for s in train], [s.id for s in test]]
        sources = list({s.id: s for s in train + test}.values())
    else:
        sources = select_sources(config.dataset, config.data_dir, config.calibration)
    config = _sensors(config, entries, sources)
    if not out:
        scores = Scores(sources, config)
        folds, all_ids = _folds(config, entries, scores, split)
        tunings = _tune_all(entries, scores, folds, all_ids, None)
        return _finish(config, entries, scores, tunings, folds, command, json_path)
    with OutputFolder(out) as folder:
        if not resume and not overwrite and folder.holds_run():
            raise ValueError(f"{folder.path}: holds an earlier run (results.json); give --overwrite to replace it, "
                             "or choose another output folder (nothing was changed)")
        header = {"call": {"kind": "tune", "settings": config.to_json()}, "command": command,
                  "versions": _versions(), "git_commit": git_commit()}
        journal = Journal.resume(folder.path) if resume else Journal.start(folder.path, header, replace=overwrite)
        try:
            if resume:
                note(f"resuming {folder.path}: {len(journal.done)} scores computed before")
            storage = _optuna_storage(journal.run_dir) if config.search == "tpe" else None
            scores = Scores(sources, config, journal)
            folds, all_ids = _folds(config, entries, scores, split)
            tunings = _tune_all(entries, scores, folds, all_ids, storage)
            return _finish(config, entries, scores, tunings, folds, command, json_path, (folder, journal))
        finally:
            journal.close()


def _sensors(config: TuneSettings, entries: list[ResolvedSpec], sources: Sequence[Any]) -> TuneSettings:
    """The tuning's magnetometer switch: `--mag auto` resolved as `fusion compare` does (like for like,
    `resolve_mag`), and off, with a note naming the parameters left out of the search, when no selected
    recording holds a magnetometer: a search over what the data cannot exercise chooses nothing."""
    from ..run.settings import holds_magnetometer, resolve_mag

    mag = resolve_mag(config.mag, entries, sources)
    if mag and not any(holds_magnetometer(s) for s in sources):
        unused = [f"{e.label}: {', '.join(a for a in tunable_space(e, True) if a not in tunable_space(e, False))}"
                  for e in entries if not e.cls.partial and len(tunable_space(e, True)) > len(tunable_space(e, False))]
        if unused:
            note("tune: the recordings hold no magnetometer: its parameters are left out of the search ("
                 + "; ".join(unused) + ")")
        mag = False
    return replace(config, mag=mag)


def _folds(config: TuneSettings, entries: list[ResolvedSpec], scores: Scores,
           split: list[list[str]] | None) -> tuple[list[Fold], list[str]]:
    """The folds and the recordings tuned on (`all_ids`), over the recordings that can be scored: each
    estimator's default is run on every selected recording first (the first candidate of every
    search), and a recording whose rows were not scored (`Result.not_scored`: no truth, its files
    unreadable, ...) or were scored on too little of it (`Result.low_coverage`) is left out of the
    folds, with a note naming it and why. split: the ids of `--train` and `--test`, or None for folds
    over `--dataset`."""
    ids = list(scores.sources)
    rows = scores.evaluate([candidate_spec(e, {}) for e in entries if not e.cls.partial], ids)
    reasons = {rid: r.not_scored for (_, rid), r in rows.items() if r.not_scored}
    reasons.update({rid: f"its truth covers {100 * r.coverage:.2g}% of what is scored (at least {MIN_COVERAGE:.0%})"
                    for (_, rid), r in rows.items() if r.low_coverage and rid not in reasons})
    if reasons:
        note(f"tune: {len(reasons)} of {len(ids)} recordings cannot be scored and are left out: "
             + "; ".join(f"{rid}: {why}" for rid, why in reasons.items()))
    if split is None:
        kept = [s for s in scores.sources.values() if s.id not in reasons]
        return folds_of(kept, config.by), [s.id for s in kept]
    train_ids, test_ids = ([rid for rid in ids if rid not in reasons] for ids in split)
    if not train_ids or not test_ids:
        raise ValueError(f"tune: no recording of --{'train' if not train_ids else 'test'} can be scored")
    return [Fold("train", tuple(train_ids), tuple(test_ids))], train_ids


OPTUNA_JOURNAL = "optuna-journal.log"


def _optuna_storage(run_dir: Path) -> Any:
    """Optuna's journal storage in the run's folder (its file is kept with the results)."""
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    return JournalStorage(JournalFileBackend(str(run_dir / OPTUNA_JOURNAL)))


def _versions() -> dict[str, str]:
    from ..compare import versions

    return versions()


def _tune_all(entries: list[ResolvedSpec], scores: Scores, folds: list[Fold], all_ids: list[str],
              storage: Any) -> list[EstimatorTuning]:
    out = []
    for n, entry in enumerate(entries, 1):
        if entry.cls.partial:
            raise ValueError(f"tune: {entry.label} is a trajectory file: nothing to tune")
        if scores.settings.progress:
            space = tunable_space(entry, scores.settings.mag)
            what = (f"{len(grid_settings(entry, scores.settings.mag))} settings" if scores.settings.search == "grid"
                    else f"{scores.settings.budget} trials a study")
            note(f"tuning {entry.label} ({n} of {len(entries)}): {', '.join(space) or 'nothing to tune'}; {what}")
        if scores.settings.search == "tpe" and tunable_space(entry, scores.settings.mag):
            if storage is None:
                import optuna

                storage = optuna.storages.InMemoryStorage()
            out.append(_search_tpe(entry, scores, folds, all_ids, storage))
        else:
            out.append(_search_grid(entry, scores, folds, all_ids))
    return out


def _setting_text(setting: dict[str, float]) -> str:
    return ",".join(f"{k}={v:g}" for k, v in setting.items()) or "default"


def tuned_statistics(tunings: Sequence[dict[str, Any]], metric: str) -> tuple[Any, dict[str, str], str]:
    """The statistics of the tuned rows (`EstimatorTuning.to_json`'s, each estimator's out-of-sample
    scores per test recording), as a comparison's table shows them
    (`fusion.evaluation.scoring.stats.paired_statistics`): the statistics (None with too few
    recordings), per estimator the cells "[lo, hi]*  W/T/L  Holm p", and the note under the table."""
    from ..scoring.stats import no_statistics_reason, paired_statistics

    scores = {t["estimator"]: dict(t["scores_tuned_deg"]) for t in tunings}
    stats = paired_statistics(scores, metric=metric) if len(scores) >= 2 else None
    cells = {}
    for label in scores:
        row = stats.row(label) if stats is not None else None
        if row is None:
            cells[label] = f"{'':>17}  {'':>8}  {'':>7}"
            continue
        ci = f"[{row.ci_low:.2f}, {row.ci_high:.2f}]" if row.ci_low is not None else "[-, -]"
        p, wtl = ("best", "-") if row.p_holm is None else (f"{row.p_holm:.3f}", f"{row.wins}/{row.ties}/{row.losses}")
        cells[label] = f"{ci:>16}{'*' if row.not_worse else ' '}  {wtl:>8}  {p:>7}"
    if len(scores) < 2:
        note = "one estimator: its tuned row is compared with nothing"
    elif stats is None:
        note = f"no statistics: {no_statistics_reason(scores)}"
    else:
        friedman = f"; Friedman p = {stats.friedman_p:.2g}" if stats.friedman_p is not None else ""
        note = (f"{metric} 95% CI: {stats.ci_method} bootstrap interval of the tuned row's mean over the "
                f"{len(stats.recordings)} test recordings every row scored; W/T/L and Holm p: paired against the best "
                f"tuned row ({stats.best}; Wilcoxon signed-rank, Holm-corrected); *: not significantly worse than it"
                f"{friedman}")
    return stats, cells, note


def format_tuning(tunings: Sequence[EstimatorTuning], config: TuneSettings, folds: Sequence[Fold]) -> str:
    """The table `fusion tune` prints: per estimator, its default, best common setting and
    per-recording best (both in sample), and the out-of-sample figure, in degrees, with the tuned
    rows' statistics (`tuned_statistics`: interval, wins/ties/losses and Holm p against the best)."""
    how = (f"chosen on {config.train}, scored on {config.test}" if config.train is not None
           else f"leave one {config.by} out, {len(folds)} folds")
    search = ("the grid preset" if config.search == "grid"
              else f"TPE, {config.budget} trials per study, seed {config.seed}")
    width = max([len(t.estimator) for t in tunings] + [9])
    aligned = ("; against the truth aligned per recording (--align: constant world and body rotations fitted from "
               "the gyro, accelerometer and truth)" if config.align else "")
    _, cells, note = tuned_statistics([t.to_json() for t in tunings], config.metric)
    lines = [f"{config.metric} RMSE (deg), mean over the test recordings; {how}; search: {search}{aligned}",
             f"{'estimator':<{width}}  {'default':>8}  {'common*':>8}  {'per-rec*':>8}  {'tuned':>8}  "
             f"{'95% CI (tuned)':>17}  {'W/T/L':>8}  {'Holm p':>7}  {'settings':>8}  common setting"]
    for t in tunings:
        lines.append(f"{t.estimator:<{width}}  {t.default:8.2f}  {t.common:8.2f}  {t.per_recording:8.2f}  "
                     f"{t.out_of_sample:8.2f}  {cells[t.estimator]}  {t.evaluated:8d}  {_setting_text(t.common_setting)}")
    lines.append("* in sample (chosen and judged on the recordings tuned on): the best common setting over them, "
                 "and each one's own best (an upper bound); default, tuned: over the test recordings, tuned out of "
                 "sample (each scored with the setting chosen without it)")
    lines.append(note)
    return "\n".join(lines + _per_dataset_lines(tunings, folds, width))


def _per_dataset_lines(tunings: Sequence[EstimatorTuning], folds: Sequence[Fold], width: int) -> list[str]:
    """Under `format_tuning`'s table: the default and tuned scores per dataset of the test
    recordings (`scores_per_dataset`) when they come from two or more; and a note when test recordings
    were also tuned on (`--train` and `--test` overlapping: their "tuned" is in sample)."""
    out = []
    parts = {t.estimator: scores_per_dataset(t) for t in tunings}
    if any(len(p) >= 2 for p in parts.values()):
        name = max([len(d["dataset"]) for p in parts.values() for d in p] + [7])
        out += ["", "per dataset of the test recordings (mean over its recordings):",
                f"{'estimator':<{width}}  {'dataset':<{name}}  {'recs':>4}  {'default':>8}  {'tuned':>8}"]
        for label, p in parts.items():
            out += [f"{label:<{width}}  {d['dataset']:<{name}}  {d['recordings']:4d}  {_cell(d['default_deg'])}  "
                    f"{_cell(d['tuned_deg'])}" for d in p]
    overlap = sorted({rid for f in folds for rid in set(f.train) & set(f.test)})
    if overlap:
        out.append(f"note: {len(overlap)} test recording{'s were' if len(overlap) > 1 else ' was'} also tuned on "
                   f"({', '.join(overlap[:3])}{', ...' if len(overlap) > 3 else ''}): "
                   f"{'their' if len(overlap) > 1 else 'its'} tuned scores are in sample")
    return out


def _cell(value: float | None) -> str:
    return f"{value:8.2f}" if value is not None else f"{'failed':>8}"


def _finish(config: TuneSettings, entries: list[ResolvedSpec], scores: Scores, tunings: list[EstimatorTuning],
            folds: list[Fold], command: str, json_path: PathLike | None,
            held: tuple[Any, Any] | None = None) -> TuneRun:
    """The rows, table and document of a finished tuning, written where asked (held: the `--out`
    folder and its journal, taken by `run_tune`)."""
    from ..compare import results_json
    from ..report.render import git_commit, write_run

    rows = _rows(entries, scores, tunings, folds)
    table = format_tuning(tunings, config, folds)
    details = {}
    for entry, tuning in zip(entries, tunings):
        details[entry.label] = entry.describe()
        if tuning.space:
            details[f"{entry.label} tuned"] = {**entry.describe(), "tuned": tuning.chosen}
    settings = {"command": command, "kind": "tune", **config.to_json(), "estimator_details": details,
                "git_commit": git_commit()}
    doc = results_json(rows, settings)
    doc["tune"] = {"folds": [{"name": f.name, "train": list(f.train), "test": list(f.test)} for f in folds],
                   "estimators": [t.to_json() for t in tunings], "table": table}
    if json_path:
        Path(json_path).write_text(json.dumps(doc, indent=2) + "\n")
    report = None
    if held is not None:
        import shutil

        folder, journal = held
        stage = folder.staging
        (stage / TUNED_FILE).write_text(json.dumps(tuned_document(entries, tunings, config), indent=2) + "\n")
        if (journal.run_dir / OPTUNA_JOURNAL).is_file():
            shutil.copyfile(journal.run_dir / OPTUNA_JOURNAL, stage / OPTUNA_JOURNAL)
        report = write_run(folder, doc, None, journal, jobs=config.jobs, progress=config.progress)
        journal.remove()
    return TuneRun(tunings, table, doc, report)


def _rows(entries: list[ResolvedSpec], scores: Scores, tunings: list[EstimatorTuning],
          folds: list[Fold]) -> list[Result]:
    """Per test recording (in fold order), each estimator's row with its default and with its
    out-of-sample choice (labelled `NAME tuned`), as the rows of a comparison."""
    out = []
    for fold in folds:
        for rid in fold.test:
            for entry, tuning in zip(entries, tunings):
                tuned = resolve(candidate_spec(entry, tuning.chosen[fold.name])).label
                default = resolve(candidate_spec(entry, {})).label
                out.append(scores.rows[(default, rid)])
                if tuning.space:  # an estimator with nothing to tune has no second row
                    out.append(replace(scores.rows[(tuned, rid)], estimator=f"{entry.label} tuned"))
    return out


TUNED_FILE = "tuned.json"


def tuned_document(entries: list[ResolvedSpec], tunings: list[EstimatorTuning], config: TuneSettings) -> dict[str, Any]:
    """tuned.json: each estimator's best common setting, as `compare --tuned FILE` reads it."""
    return {"format": TUNED_FORMAT, "version": 1, "metric": config.metric, "dataset": config.train or config.dataset,
            "estimators": {e.label: {"spec": e.spec.name,
                                     "overrides": [list(p) for p in candidate_spec(e, t.common_setting).overrides],
                                     "common_deg": _finite(t.common), "out_of_sample_deg": _finite(t.out_of_sample)}
                           for e, t in zip(entries, tunings)}}


def read_tuned(path: PathLike) -> dict[str, EstimatorSpec]:
    """tuned.json (`tuned_document`): estimator label -> its tuned spec; one line naming the file
    and the problem otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such tuned-settings file (`fusion tune --out DIR` writes "
                                f"DIR/{TUNED_FILE})")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("format") != TUNED_FORMAT:
            raise TypeError("format")
        out = {}
        for label, item in doc["estimators"].items():
            pairs = tuple((str(k), str(v)) for k, v in item["overrides"])
            out[str(label)] = EstimatorSpec(str(item["spec"]), pairs)
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a tuned-settings file written by `fusion tune` ({type(exc).__name__})") from None
    return out


def apply_tuned(specs: Sequence[EstimatorSpec], path: PathLike) -> list[EstimatorSpec]:
    """`specs` with each one that `path` (tuned.json) holds replaced by its tuned spec (same name,
    the tuned overrides after its own); a note names those the file does not hold."""
    tuned = read_tuned(path)
    out, untouched = [], []
    for spec in specs:
        if spec.label in tuned:
            extra = tuple(p for p in tuned[spec.label].overrides if p not in spec.overrides)
            out.append(EstimatorSpec(spec.name, spec.overrides + extra))
        else:
            out.append(spec)
            untouched.append(spec.label)
    if untouched:
        note(f"--tuned {path}: no tuned setting for {', '.join(untouched)} (run with its defaults)")
    return out
