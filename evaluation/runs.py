"""Whole runs, as the `fusion` commands do them: select and load recordings, run, score, and
write what was asked for (a `--json` document, an `--out` folder). The command line
(`fusion.cli`) parses arguments and calls one function of this module per command; from
Python the same run is two lines:

    from fusion.evaluation.runs import run_compare
    run = run_compare("dr,ukf", "sim", jobs=1)

(`run_stress`, `fusion stress`: the same, each recording also under controlled sensor faults:
`fusion.evaluation.sweeps.stress`.)

`run.table` is what `fusion compare` prints, `run.results` the rows (`fusion.evaluation.run.job.Result`,
without trajectories: see `fusion.evaluation.run.runner`), `run.document` the results document
(`docs/json-format.md`). Recordings are chosen and loaded as `fusion.selection` says
(`dataset`, `data_dir`, `calibration`, `dropouts`).

With an output folder (`out`), every finished job is journalled there as it ends
(`fusion.evaluation.run.journal`), so that a run stopped at any point continues with
`run_resume(out)` (`fusion compare --resume DIR`), computing only the jobs not yet done.
"""
from __future__ import annotations

import json
import os
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from fusion import datasets
from fusion.checks import RecordingCheck
from fusion.estimators import ResolvedSpec, resolve_all, resolve_trajectory
from fusion.estimators.params import EstimatorSpec, parse_specs
from fusion.selection import calibration_settings, load_selected, note, select_sources

from .compare import format_table, results_json, versions
from .report.render import git_commit, write_run
from .run.job import JobOutput, Result
from .run.journal import Journal, fingerprint, job_key
from .run.output import OutputFolder
from .run.runner import job_cells, run, source_paths
from .run.settings import COMPUTED, WRITTEN, RunSettings, resolve_mag
from .sweeps import ablate, stress
from .sweeps.stress import StressSettings

PathLike = str | os.PathLike


@dataclass(frozen=True, eq=False)
class Run:
    """A finished `run_compare`/`run_ablate`.

    results: one row per recording x estimator, recording-major (a failed job's row has `error`).
    table: the table `fusion compare` prints (`fusion.evaluation.compare.format_table`).
    document: the results document written to `json_path` and `out` (None when neither was asked for).
    report: the written `report.html` (None without `out`).
    """

    results: list[Result]
    table: str
    document: dict[str, Any] | None = None
    report: Path | None = None

    @property
    def failed(self) -> list[Result]:
        """The rows whose job failed (each `error` is one line naming the estimator and recording)."""
        return [r for r in self.results if r.error is not None]


def run_compare(estimators: str | Sequence[str | EstimatorSpec | ResolvedSpec] = "all", dataset: str = "all",
                data_dir: PathLike | None = None, *, trajectories: Sequence[tuple[str, PathLike]] = (),
                tuned: PathLike | None = None, **options: Any) -> Run:
    """`fusion compare`: every estimator on every recording `dataset` names.

    estimators: spec text (`"dr,ukf:R=1e-3"`, `"all"`) or a list of specs.
    trajectories: (name, path) pairs: trajectories other programs wrote, in the table as rows
        named `name` (`fusion.estimators.adapters.trajectory_file`: a file with one recording selected, or a
        folder with one file per recording).
    tuned: a tuned-settings file (`fusion tune --out DIR`'s tuned.json): each estimator it holds runs
        with its tuned setting (`fusion.evaluation.sweeps.tune.apply_tuned`).
    options: the run's settings, `fusion.evaluation.run.settings.RunSettings`' fields (its docstring
        lists them, each one's option help says what it does: `fusion compare --help`). With `out`
        the report folder is locked before any computation and written through a staging folder
        (`fusion.evaluation.run.output.OutputFolder`), each job journalled as it ends; a folder that
        holds another run is refused unless `overwrite`; `resume` continues the unfinished run
        there (`run_resume` repeats its call for you).
    """
    settings = RunSettings(dataset=dataset, data_dir=data_dir, **{**options, "per_recording": True})
    if tuned:
        from .sweeps.tune import apply_tuned

        specs = parse_specs(estimators) if isinstance(estimators, str) else list(estimators)
        estimators = ",".join(s.label if isinstance(s, EstimatorSpec) else s for s in apply_tuned(specs, tuned))
    with _heartbeat(settings.progress):
        entries = resolve_all(estimators) + [resolve_trajectory(name, path) for name, path in trajectories]
    text = estimators if isinstance(estimators, str) else ",".join(e.label for e in entries if not e.cls.partial)
    kind = {"kind": "compare", "estimators": text,
            "trajectories": [[name, str(Path(path).resolve())] for name, path in trajectories]}
    if settings.command is None:
        settings = replace(settings, command=f"run_compare({text!r}, {dataset!r})")
    return _execute(entries, kind, {"kind": "compare", "estimators": text}, settings)


def run_ablate(estimator: str | None = None, params: Sequence[str | tuple[str, Sequence[str]]] = (),
               preset: str | None = None, dataset: str = "all", data_dir: PathLike | None = None, *,
               tuned: PathLike | None = None, **options: Any) -> Run:
    """`fusion ablate`: one estimator over a grid of parameter values, or a preset
    (`fusion.evaluation.sweeps.ablate`).

    estimator: the estimator to sweep, possibly with fixed parameters (`"ukf:Q=1e-5"`).
    params: the grid, as `"R=1e-4,1e-3"` texts or `("R", ["1e-4", "1e-3"])` pairs.
    preset: a name in `fusion.evaluation.sweeps.ablate.PRESETS` (instead of estimator and params).
    tuned: a tuned-settings file (`fusion tune --out DIR`'s tuned.json): the swept estimator runs
        with its tuned setting for every parameter the grid does not sweep.
    options: as `run_compare` (`RunSettings`' fields); `per_recording`: with `out`, also draw each
        recording's figures (and, with `tum`, write its TUM files) for every setting.
    """
    settings = RunSettings(dataset=dataset, data_dir=data_dir, **options)
    if bool(preset) == bool(estimator):
        raise ValueError("ablate: give either --preset NAME or --estimator NAME with --param NAME=V1,V2,...")
    grid: list[tuple[str, list[str]]] = []
    if preset:
        if params or tuned:
            raise ValueError("ablate: --param and --tuned apply to --estimator, not to --preset")
        specs = ablate.preset_specs(preset)
        document = {"kind": "ablate", "preset": preset}
    else:
        if not params:
            raise ValueError("ablate: --estimator needs at least one --param NAME=V1,V2,...")
        grid = [ablate.parse_param(p) if isinstance(p, str) else (p[0], list(p[1])) for p in params]
        if tuned:
            from .sweeps.tune import apply_tuned

            (base,) = apply_tuned(parse_specs(estimator), tuned)
            swept = {name for name, _ in grid}
            estimator = EstimatorSpec(base.name, tuple(p for p in base.overrides if p[0] not in swept)).label
        specs = ablate.grid_specs(estimator, grid)
        document = {"kind": "ablate", "estimator": estimator, "params": dict(grid)}
    with _heartbeat(settings.progress):
        entries = resolve_all(specs)
    document["estimators"] = ",".join(e.label for e in entries)
    kind = {"kind": "ablate", "estimator": estimator, "params": grid, "preset": preset}
    if settings.command is None:
        settings = replace(settings, command=f"run_ablate({estimator!r}, {list(params)!r}, {preset!r}, {dataset!r})")
    return _execute(entries, kind, document, settings)


def run_stress(estimators: str | Sequence[str | EstimatorSpec | ResolvedSpec] = "all", dataset: str = "all",
               data_dir: PathLike | None = None, *, faults: Sequence[str] | None = None, **options: Any) -> Run:
    """`fusion stress`: every estimator on every recording `dataset` names, clean and under each
    fault at each severity (`fusion.evaluation.sweeps.stress`, `fusion.faults`).

    estimators: as `run_compare`'s.
    faults: `--fault` texts, "KIND=L1,L2,..." or "KIND" (its documented severities); None: every kind
        at its five documented severities.
    options: as `run_compare`'s (`RunSettings`' fields, but panorama and per_recording). The rows
        carry their `fault`; `run.document` adds `stress` (the dose-response) and `robustness`; the
        table is the clean rows' (`format_table`), then the dose-response and the robustness summary.
    """
    for name in stress.NOT_OFFERED:
        if name in options and options[name] != getattr(RunSettings(), name):
            raise ValueError(f"stress: {name} is not offered (a stress run draws no per-recording figures and "
                             "writes no trajectories)")
    settings = StressSettings(dataset=dataset, data_dir=data_dir, faults=faults,
                              **{k: v for k, v in options.items() if k not in stress.NOT_OFFERED})
    with _heartbeat(settings.progress):
        entries = resolve_all(estimators)
    text = estimators if isinstance(estimators, str) else ",".join(e.label for e in entries)
    the_plan = settings.plan()
    kind = {"kind": "stress", "estimators": text, "faults": list(settings.faults) if settings.faults else None}
    document = {"kind": "stress", "estimators": text, "faults": {k: list(levels) for k, levels in the_plan}}
    if settings.command is None:
        settings = replace(settings, command=f"run_stress({text!r}, {dataset!r}, faults={faults!r})")
    return _execute(entries, kind, document, settings)


def _settings_class(call: dict[str, Any]) -> type[RunSettings]:
    """The settings class a journalled call reads back with: a stress run's has its faults."""
    return stress.StressSettings if call.get("kind") == "stress" else RunSettings


def run_resume(out: PathLike, **how: Any) -> Run:
    """`fusion compare --resume DIR` / `fusion ablate --resume DIR`: continue the unfinished run in
    `out` with the call recorded in its journal; `how` may change only how it runs (jobs, progress,
    scheduler, scatter) and where the results document goes (json_path). The jobs already
    journalled are not computed again."""
    header = Journal.read_header(Path(out))
    call = dict(header["call"])
    json_path = how.pop("json_path", None)
    recorded = {**call, "data_dir": header["data_dir"], "calibration": header.get("calibration"),
                "command": header["command"], "out": os.fspath(out), "json_path": json_path}
    settings = _settings_class(call).from_json(recorded, resume=True, **how)
    options = {f: getattr(settings, f) for f in RunSettings.__dataclass_fields__ if f not in ("dataset", "data_dir")}
    kind = call.pop("kind")
    if kind == "stress":
        for name in stress.NOT_OFFERED:
            options.pop(name)
        return run_stress(call["estimators"], settings.dataset, settings.data_dir, faults=call.get("faults"),
                          **options)
    if kind == "compare":
        options.pop("per_recording")
        trajectories = [tuple(pair) for pair in call.get("trajectories", [])]
        return run_compare(call["estimators"], settings.dataset, settings.data_dir, trajectories=trajectories,
                           **options)
    grid = [(name, values) for name, values in call["params"]]
    return run_ablate(call["estimator"], grid, call["preset"], settings.dataset, settings.data_dir, **options)


# The fields of `RunSettings` that a run's journal records in its call: what is computed and what is
# written, but the paths (data_dir and calibration are recorded resolved beside the call; the
# folder is where the journal is; json_path and command are given again on resume or kept apart).
JOURNALLED = tuple(f for f in RunSettings.part(COMPUTED) + RunSettings.part(WRITTEN)
                   if f not in ("data_dir", "calibration", "out", "json_path", "command"))


def _journal_call(kind: dict[str, Any], settings: RunSettings) -> dict[str, Any]:
    """The call a run's journal records: what kind of run (and its estimators or grid), and the
    journalled settings."""
    return {**kind, **{name: getattr(settings, name) for name in JOURNALLED}}


def _execute(entries: list[ResolvedSpec], kind: dict[str, Any], document: dict[str, Any], s: RunSettings) -> Run:
    """Select, run (journalled into `s.out`), score, and write; an `out` folder is taken (locked)
    before computing. kind: what the journal records besides the settings; document: what the
    results document's settings record besides them."""
    if s.resume and not s.out:
        raise ValueError("--resume needs the output folder of the run to continue")
    sources = select_sources(s.dataset, s.data_dir, s.calibration)
    s = replace(s, mag=resolve_mag(s.mag, entries, sources))
    files = [e for e in entries if e.cls.partial and not Path(e.params.path).is_dir()]
    if files and len(sources) != 1:
        raise ValueError(f"--trajectory {files[0].label}={files[0].params.path}: a file is one recording's "
                         f"trajectory, and --dataset {s.dataset!r} selects {len(sources)}; select one, or give a "
                         "folder with one file per recording")
    root = s.resolved_data_dir()
    load = s.load_options()  # a bad calibration file fails here, before the output folder is touched
    faults = stress.variants(s.plan(), sources, s.mag) if isinstance(s, StressSettings) else None
    if faults is not None:
        stress.check_variants(s.plan(), faults)
    series_wanted = (s.per_recording or bool(s.rerun)) and faults is None  # a stress run draws its own
    if s.rerun:  # before any work: the package is installed, the file name is a .rrd in a folder
        from .report.rerun_log import check_path, require

        require()
        check_path(s.rerun)
    if not s.out:
        parts = _Parts() if s.rerun and faults is None else None  # the estimates for the .rrd, kept in memory
        results = run(entries, sources, s, series=parts is not None, on_done=parts.record if parts else None,
                      faults=faults)
        return _finish(None, parts, entries, sources, results, document, s, range(len(results)))
    with OutputFolder(s.out) as folder:
        if not s.resume and not s.overwrite and folder.holds_run():
            raise ValueError(f"{folder.path}: holds an earlier run (results.json); give --overwrite to replace it, "
                             "or choose another output folder (nothing was changed)")
        call = _journal_call(kind, s)
        header = {"call": call, "data_dir": str(root.resolve()),
                  "calibration": str(Path(s.calibration).resolve()) if s.calibration else None, "command": s.command,
                  "jobs_total": len(job_cells(len(sources), len(entries), faults)), "versions": versions(),
                  "git_commit": git_commit()}
        journal = Journal.resume(folder.path) if s.resume else Journal.start(folder.path, header, replace=s.overwrite)
        try:
            if s.resume:
                _check_resumable(journal, header)
            keys = _job_keys(entries, sources, load, s, faults)
            done = {n: Result.from_json(journal.done[key].row) for n, key in enumerate(keys) if key in journal.done}
            if s.resume:
                note(f"resuming {folder.path}: {len(done)} of {len(keys)} jobs done, {len(keys) - len(done)} to run")

            def record(n: int, output: JobOutput) -> None:
                journal.record(keys[n], output.result.to_json(), output.result.error, _series_part(output))

            results = run(entries, sources, s, series=series_wanted, done=done, on_done=record, faults=faults)
            return _finish(folder, journal, entries, sources, results, document, s, keys)
        finally:
            journal.close()


@contextmanager
def _heartbeat(enabled: bool, first_s: float = 2.0, every_s: float = 4.0) -> Iterator[None]:
    """Say so on stderr while the estimators are being built, if that takes a while: the first
    build on a new installation compiles the filters' and smoothers' kernels (numba, cached on disk
    afterwards), which takes tens of seconds during which nothing else would be printed."""
    import threading
    import time

    if not enabled:
        yield
        return
    done = threading.Event()
    start = time.monotonic()

    def beat() -> None:
        if done.wait(first_s):
            return
        note("preparing the estimators: the first run on this installation compiles their kernels (once; "
             "cached afterwards)")
        while not done.wait(every_s):
            note(f"still compiling ({time.monotonic() - start:.0f} s)")

    thread = threading.Thread(target=beat, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()


def _job_keys(entries: list[ResolvedSpec], sources: list, load: Any, s: RunSettings,
              faults: Sequence[Sequence[Any]] | None = None) -> list[str]:
    """Each job's journal key (recording-major, as `fusion.evaluation.run.runner.run` numbers them:
    `job_cells`); a stress run's key holds its fault."""
    options = {"init": s.init, "protocol": s.protocol, "align": s.align, "panorama": s.panorama}
    prints = [fingerprint(source_paths(src), what=src.id) for src in sources]
    return [job_key(dataset=sources[i].id, files=prints[i], estimator=entries[j].label, origin=entries[j].describe(),
                    load=repr(load), **options, **({} if fault is None else {"fault": fault.to_json()}))
            for i, fault, j in job_cells(len(sources), len(entries), faults)]


def _same_call(call: dict[str, Any]) -> dict[str, Any]:
    """A journalled call as compared on resume: its own keys, and the settings with the defaults of
    those an older journal lacks."""
    settings = _settings_class(call).from_json(call)
    return {**json.loads(json.dumps(call)), **{name: getattr(settings, name) for name in JOURNALLED}}


def _check_resumable(journal: Journal, header: dict[str, Any]) -> None:
    """A resumed run must be the run that was started; a change of code is worth a warning."""
    import warnings

    before = journal.header
    for key in ("call", "data_dir", "calibration"):
        now, then = header[key], before.get(key)
        if key == "call":
            now, then = _same_call(now), _same_call(then or {})
        if json.loads(json.dumps(now)) != then:
            raise ValueError(f"{journal.path}: was started with another {key} ({before.get(key)!r}); resume it with "
                             "--resume DIR alone, or write this run to another folder")
    if (before.get("git_commit"), before.get("versions")) != (header["git_commit"], header["versions"]):
        warnings.warn(f"{journal.folder}: resumed with other code or packages than it was started with "
                      f"(commit {header['git_commit']}, was {before.get('git_commit')}); rows computed before and "
                      "after may differ", stacklevel=3)


def _finish(folder: OutputFolder | None, journal: Journal | None, entries: list[ResolvedSpec], sources: list,
            results: list[Result], document: dict[str, Any], s: RunSettings, keys: Sequence[str] = ()) -> Run:
    """The table, the results document and the report folder of a finished run."""
    if document.get("kind") == "stress":
        return _finish_stress(folder, journal, entries, sources, results, document, s)
    table = format_table(results, align=s.align or None, primary=s.primary)  # None: where a row was aligned
    sweep = (ablate.sweep_summary([r.to_json() for r in results], groups=_trial_groups(sources))
             if document.get("kind") == "ablate" else None)
    if sweep:
        table += "\n\n" + ablate.format_sweep(sweep)
    if s.rerun:
        _write_rerun(journal, entries, sources, results, list(keys), s)
        note(f"wrote {s.rerun}; watch it with: rerun {s.rerun} (Rerun's viewer: pip install 'fusion[viz]'; "
             "--web-viewer for a browser)")
    if not (s.json_path or folder):
        return Run(results, table)
    doc = results_json(results, _settings_document(document, sources, entries, s))
    if sweep:
        doc["sweep"] = sweep  # docs/json-format.md
    if s.json_path:
        Path(s.json_path).write_text(json.dumps(doc, indent=2) + "\n")
    report = None
    if folder is not None:
        series = (_series(journal, entries, len(sources), results, list(keys), folder.staging, s.tum)
                  if s.per_recording else None)
        report = write_run(folder, doc, series, journal, jobs=s.jobs, progress=s.progress)
        journal.remove()
    return Run(results, table, doc, report)


def _settings_document(document: dict[str, Any], sources: list, entries: list[ResolvedSpec],
                       s: RunSettings) -> dict[str, Any]:
    """The results document's `settings`: the command, what `document` says of the run, and the settings."""
    root = s.resolved_data_dir()
    return {"command": s.command, **document, "dataset": s.dataset,
            "data_dir": str(root.resolve()),
            "merged": datasets.merged_ids(sources),
            "dropouts": "on" if s.dropouts else "off",
            "calibration": calibration_settings(s.calibration),
            "init": s.init or ("default (the aligned truth where available, else accel)" if s.align
                               else "default (truth where available, else accel)"),
            "align": bool(s.align), "primary": s.primary,
            "protocol": s.protocol or "default (broad for recordings with a movement mask, else full)",
            "estimator_details": {e.label: e.describe() for e in entries},
            "git_commit": git_commit()}


def _finish_stress(folder: OutputFolder | None, journal: Journal | None, entries: list[ResolvedSpec], sources: list,
                   results: list[Result], document: dict[str, Any], s: RunSettings) -> Run:
    """A stress run's table (the clean rows', then the dose-response and the robustness summary), its
    results document (every row with its fault; `stress`, `robustness`; the statistics and the
    per-dataset means of the clean rows) and its report folder and Rerun recording."""
    rows = [r.to_json() for r in results]
    clean = [r for r in results if not r.fault or r.fault["kind"] == stress.NONE]
    summary = stress.stress_summary(rows, s.primary)
    robust = stress.robustness(summary)
    table = (format_table(clean, align=s.align or None, primary=s.primary) + "\n\n"
             + stress.format_stress(summary, robust))
    if s.rerun:
        from .report.rerun_log import write_stress

        write_stress(s.rerun, summary, _first_recording(sources, results, s), data_dir=s.resolved_data_dir())
    if not (s.json_path or folder):
        return Run(results, table)
    doc = results_json(clean, _settings_document(document, sources, entries, s))
    doc.update(results=rows, stress=summary, robustness=robust)
    if s.json_path:
        Path(s.json_path).write_text(json.dumps(doc, indent=2) + "\n")
    report = None
    if folder is not None:
        report = write_run(folder, doc, None, journal, jobs=s.jobs, progress=s.progress)
        journal.remove()
    return Run(results, table, doc, report)


def _first_recording(sources: list, results: list[Result], s: RunSettings) -> Any:
    """The first recording of a run that could be read, loaded again (what `--rerun` shows the faults
    on), or None."""
    readable = {r.dataset for r in results if r.readable}
    source = next((src for src in sources if src.id in readable), None)
    return None if source is None else s.load_options().load(source)


def _series_part(output: JobOutput) -> dict[str, np.ndarray] | None:
    """What a job adds to its recording's series (`fusion.evaluation.run.series.job_part`), with its
    recording's arrays under `rec_` names when it brings them; None without plot data."""
    part = dict(output.part or {})
    part.update({f"rec_{k}": v for k, v in (output.recording_part or {}).items()})
    return part or None


class _Parts:
    """The series parts of a run without an output folder, in memory by job number (what a journal
    keeps on disk): for `--rerun` alone."""

    def __init__(self) -> None:
        self._parts: dict[int, dict[str, np.ndarray]] = {}

    def record(self, n: int, output: JobOutput) -> None:
        self._parts[n] = _series_part(output) or {}

    def load_part(self, n: int) -> dict[str, np.ndarray]:
        return self._parts[n]


def _write_rerun(parts: Any, entries: list[ResolvedSpec], sources: list, results: list[Result], keys: list,
                 s: RunSettings) -> None:
    """The Rerun recording of a run (`s.rerun`, `fusion.evaluation.report.rerun_log`): each recording loaded
    again (its sensors, events and camera) beside its series from the jobs' parts."""
    from .report.rerun_log import write

    load = s.load_options()
    per = len(entries)
    recordings = (load.load(source) for i, source in enumerate(sources) if results[i * per].readable)
    write(s.rerun, zip(recordings, _series(parts, entries, len(sources), results, keys, Path(), tum=False)),
          data_dir=s.resolved_data_dir())


def _trial_groups(sources: list) -> dict[str, list[str]]:
    """Recording id -> its BROAD groups (`fusion.formats.broad.trial_groups`), for the recordings
    with a `trials.json` beside them; a malformed one is a warning and no groups."""
    import warnings

    from fusion.formats.broad import trial_groups

    out = {}
    for source in sources:
        if getattr(source, "imu", None) is None:
            continue
        try:
            groups = trial_groups(source.imu)
        except (ValueError, OSError) as exc:
            warnings.warn(f"{exc}; the sweep is not summarised per group", stacklevel=2)
            return {}
        if groups:
            out[source.id] = groups
    return out


def _series(journal: Journal, entries: list[ResolvedSpec], recordings: int, results: list[Result],
            keys: list[str], stage: Path, tum: bool = True) -> Iterator[Any]:
    """Each readable recording's series, assembled from its jobs' parts in the journal, one at a time (so
    that at most one recording's plot data is in memory); on the way (`tum`), each estimate and the
    truth it was scored against are written as TUM files into `stage/trajectories/<recording>/`,
    to the precision the data carry, each with a header naming the estimator, the recording and
    whether it used a magnetometer (`fusion.trajectory_files.write_tum`, compact)."""
    from fusion.trajectory_files import write_tum

    from .run import series

    per = len(entries)
    for i in range(recordings):
        if not results[i * per].readable:  # its files could not be read: nothing ran, nothing to draw
            continue
        shown = [j for j in range(per) if results[i * per + j].ran]
        first = journal.load_part(keys[i * per])  # the recording's arrays come with its first job
        parts = [first if j == 0 else journal.load_part(keys[i * per + j]) for j in shown]
        recording = {k[4:]: v for k, v in first.items() if k.startswith("rec_")}
        if tum:
            rid = str(recording["id"])
            folder = stage / "trajectories" / rid
            folder.mkdir(parents=True, exist_ok=True)
            if "truth_at_imu" in recording:
                truth = next((r.truth for r in results[i * per:(i + 1) * per] if r.truth), None)
                write_tum(folder / "truth.tum", recording["imu_t"], recording["truth_at_imu"], compact=True,
                          metadata={"estimator": "truth", "recording": rid, **({"truth": truth} if truth else {})})
            for j, part in zip(shown, parts):
                row = results[i * per + j]
                write_tum(folder / f"{entries[j].label.replace('/', '_')}.tum", recording["imu_t"], part["quat_wxyz"],
                          compact=True, metadata={"estimator": row.estimator, "recording": rid,
                                                  "imu": "9-D" if row.magnetometer else "6-D"})
        yield series.assemble(recording, [entries[j].label for j in shown], [bool(entries[j].cls.causal) for j in shown],
                              parts)


@dataclass(frozen=True, eq=False)
class PanoramaRun:
    """A finished `run_panorama`: the recording and estimator, the estimate's panorama
    (`fusion.evaluation.panorama.recording.Panorama`), its scores (`panorama.panorama_scores`), the image
    written, where its frames come from (`panorama.frames_origin`), and `text`, what
    `fusion panorama` prints."""

    recording_id: str
    estimator: str
    panorama: Any
    scores: dict[str, float]
    out: Path
    frames: str = ""

    @property
    def text(self) -> str:
        s = self.scores
        lines = [f"{self.recording_id} {self.estimator}: {self.panorama.frames_used} frames "
                 f"({self.panorama.frames_skipped} skipped) -> {self.out}",
                 *([f"frames: {self.frames}"] if self.frames else []),
                 f"PSNR {s['psnr_db']:.2f} dB, SSIM {s['ssim']:.4f} against the ground-truth panorama; "
                 f"covered {s['covered_fraction']:.3f} of the sphere"]
        if np.isfinite(s["scene_psnr_db"]):
            lines.append(f"PSNR {s['scene_psnr_db']:.2f} dB, SSIM {s['scene_ssim']:.4f} against the scene")
        return "\n".join(lines)


def run_panorama(dataset: str, estimator: str | EstimatorSpec | ResolvedSpec, out: PathLike, *,
                 data_dir: PathLike | None = None, init: str | None = None, size: str = "1920x960",
                 rate_hz: float = 10.0, scene: Any = None, blend: str = "feather", reference: bool = False,
                 calibration: PathLike | None = None, dropouts: bool = datasets.DROPOUTS_DEFAULT,
                 progress: bool = False, imu_topic: str | None = None, truth_topic: str | None = None,
                 mag: bool = True) -> PanoramaRun:
    """`fusion panorama`: estimate one recording's orientations with one estimator, stitch its
    frames (its camera's, or frames rendered from a scene with the truth:
    `fusion.evaluation.panorama.recording.reference_panorama`)
    into a panorama, score it and write the image to `out` (.png/.jpg).

    dataset: names exactly one recording (`fusion.selection.load_selected`); estimator: one spec text.
    size: the panorama's "WIDTHxHEIGHT" in px; rate_hz: the rendered frames' rate.
    reference: write the estimate, the ground truth's panorama and their difference, stacked.
    """
    import cv2

    from .run.job import run_one
    from .panorama.recording import (PanoramaGrid, check_options, comparison_image, estimate_panorama, frames_origin,
                           reference_panorama)

    check_options(out, rate_hz)  # before any work: the image format and the frame rate
    recordings = load_selected(dataset, data_dir, calibration, dropouts, progress, imu_topic, truth_topic, mag)
    if len(recordings) != 1:
        raise ValueError(f"--dataset {dataset!r} names {len(recordings)} recordings; panorama takes one")
    (recording,) = recordings
    with _heartbeat(progress):
        entries = resolve_all(estimator)
    if len(entries) != 1:
        raise ValueError(f"--estimator {estimator!r}: give exactly one estimator")
    if reference and recording.truth is None:
        raise ValueError(f"{recording.id}: --reference needs ground truth, and this recording has none")
    width, _, height = size.partition("x")
    try:
        grid = PanoramaGrid(int(width), int(height))
    except ValueError as exc:
        raise ValueError(f"--size {size!r}: expected WIDTHxHEIGHT in px, e.g. 1920x960 ({exc})") from exc
    trajectory = run_one(recording, entries[0], init).trajectory
    options = dict(data_dir=datasets.data_dir_from(data_dir), scene=scene, grid=grid, blend=blend, rate_hz=rate_hz)
    pano, scores = estimate_panorama(recording, trajectory, progress=progress, **options)
    image = pano.bgr()
    if reference:
        image = comparison_image(pano, reference_panorama(recording, **options).truth)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image):
        raise ValueError(f"{out}: could not write the image (use a .png or .jpg name)")
    frames = frames_origin(recording, data_dir=options["data_dir"], scene=scene, rate_hz=rate_hz)
    return PanoramaRun(recording.id, entries[0].label, pano, scores, out, frames)


@dataclass(frozen=True, eq=False)
class Inspection:
    """A finished `run_inspect`: one `fusion.checks.RecordingCheck` per recording, the text
    `fusion inspect` prints, and the figures written (with `out`)."""

    checks: list[RecordingCheck]
    text: str
    figures: list[Path]


def run_inspect(dataset: str = "all", data_dir: PathLike | None = None, *, calibration: PathLike | None = None,
            dropouts: bool = datasets.DROPOUTS_DEFAULT, progress: bool = False, json_path: PathLike | None = None,
            out: PathLike | None = None, command: str | None = None, imu_topic: str | None = None,
            truth_topic: str | None = None, mag: bool = True) -> Inspection:
    """`fusion inspect`: the sensor checks of every recording `dataset` names
    (`fusion.checks.check_recording`); json_path: write them as JSON; out: a figure per recording."""
    from fusion.checks import check_recording, format_check

    recordings = load_selected(dataset, data_dir, calibration, dropouts, progress, imu_topic, truth_topic, mag)
    checks = [check_recording(rec) for rec in recordings]
    if json_path:
        doc = {"command": command or f"run_inspect({dataset!r})", "recordings": [c.to_json() for c in checks]}
        Path(json_path).write_text(json.dumps(doc, indent=2) + "\n")
    figures = []
    if out:
        from .report.inspect_plots import plot_check

        folder = Path(out)
        folder.mkdir(parents=True, exist_ok=True)
        for rec, check in zip(recordings, checks):
            path = folder / f"inspect_{rec.id.replace('/', '_')}.png"
            plot_check(rec, check, path)
            figures.append(path)
    text = "\n\n".join(format_check(c) for c in checks)
    return Inspection(checks, "\n".join([text, *(f"wrote {p}" for p in figures)]), figures)


@dataclass(frozen=True, eq=False)
class CalibrationRun:
    """A finished `run_calibrate`: the fit (`fusion.gyro_fit.GyroFit`), the leave-one-out folds (empty
    without), the text `fusion calibrate` prints and the file written (None: the text ends with
    the file's contents instead)."""

    fit: Any
    folds: list
    text: str
    written: Path | None


def run_calibrate(dataset: str = "all", data_dir: PathLike | None = None, *, out: PathLike | None = None,
              clock_offset: bool = False, leave_one_out: bool = False, estimators: str = "dr",
              init: str | None = None, align: bool = False, calibration: PathLike | None = None,
              dropouts: bool = datasets.DROPOUTS_DEFAULT, progress: bool = False,
              command: str | None = None, imu_topic: str | None = None, truth_topic: str | None = None,
              mag: bool = True) -> CalibrationRun:
    """`fusion calibrate`: fit per-axis gyro scale factors against the truth (`fusion.gyro_fit`).

    out: the calibration file to write; clock_offset: also store each recording's clock offset.
    leave_one_out: first score `estimators` on each recording with the scales fitted on the
        others (`fusion.evaluation.sweeps.loo`); align applies to those scores only.
    """
    from fusion import gyro_fit

    recordings = load_selected(dataset, data_dir, calibration, dropouts, progress, imu_topic, truth_topic, mag)
    lines, folds = [], []
    if leave_one_out:
        from .sweeps.loo import format_folds, leave_one_out as folds_of

        folds = folds_of([estimators], recordings, init=init, progress=progress, align=align)
        lines += [format_folds(folds), "", format_table([r for f in folds for r in f.results], align=align)]
    elif align:
        raise ValueError("calibrate: --align applies to the scores of --leave-one-out (the fit itself assumes "
                         "the truth's frames are the IMU's)")
    result = gyro_fit.fit_recordings(recordings)
    lines.append(f"fit on {len(result.fitted_on)} recordings ({result.samples} samples): gyro_scale_factor "
                 + ", ".join(f"{x:.4f}" for x in result.gyro_scale_factor)
                 + " (sensitivity vs nominal " + ", ".join(f"{100 * (x - 1):+.1f} %" for x in result.sensitivity_ratio)
                 + f"); misalignment {', '.join(f'{x:+.2f}' for x in result.misalignment_deg)} deg; "
                 f"residual {result.residual_rms_deg_s:.2f} deg/s")
    if clock_offset:
        lines += [f"  clock offset {rid}: truth lags by {off * 1e3:+.1f} ms" for rid, off in result.clock_offset_s.items()]
    command = command or f"run_calibrate({dataset!r})"
    if out:
        gyro_fit.write(out, result, with_clock_offset=clock_offset, command=command)
        lines.append(f"wrote {out}")
    else:
        lines.append(gyro_fit.to_json_text(result, with_clock_offset=clock_offset, command=command).rstrip("\n"))
    return CalibrationRun(result, folds, "\n".join(lines), Path(out) if out else None)

