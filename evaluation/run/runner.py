"""Recordings x estimators as independent jobs: in this process, on a pool of worker processes, or on
a dask.distributed cluster. The one job runner of `fusion compare` and `fusion ablate`.

    from fusion import datasets
    from fusion.evaluation.run.runner import run
    results = run(["dr", "ukf:R=1e-3"], datasets.select("sim"), jobs=2)

(the keywords are `fusion.evaluation.run.settings.RunSettings`' fields; a caller holding a run's
settings passes them whole: `run(specs, sources, settings)`).

A job (`fusion.evaluation.run.job.Job`) is one (recording, estimator) pair: build, estimate, time,
score (`fusion.evaluation.run.job.run_job`); in a stress run (`faults`), one (recording, fault,
estimator) triple, the fault (`fusion.faults.Fault`) applied to the loaded recording in the process
that runs the job (`WorkerState.faulted`: each recording is still loaded once per process). It
carries indices only: into the run's recordings (dataset `Source`s, loaded the first time a process
needs them and kept, or loaded `Recording`s) and into its resolved specs
(`fusion.estimators.ResolvedSpec`, resolved once, in the parent, so a bad name or parameter fails
before any work). Results come back in the serial order
(recording-major, estimators as given) whatever order the jobs finish in, and hold the same
numbers as a serial run: each job is the same deterministic computation on the same inputs. Only
`seconds` (wall time) differs.

Memory: a job sends back its row (`Result.summary`: scores, timings, coverage), and its plot data
only when the run draws figures (`series`), which the caller writes to disk as each job ends
(`on_done`) and does not keep. So a sweep of hundreds of jobs holds hundreds of rows, not
hundreds of trajectories. `keep=True` returns whole results instead (trajectories, per-sample
errors: for a few jobs, from Python).

State: what a process keeps between jobs (the run's recordings, the ones loaded so far, their
alignments) is one `WorkerState`. A serial run keeps it in a local variable; a pool worker's
initialiser creates one per process and keeps it in `_WORKER`, the module's only mutable global,
which only worker processes set. The pool (`fusion.evaluation.run.pool.WorkerPool`) forks its workers
where the platform can (they inherit the recordings and the resolved specs); its workers die
with the parent however the parent ends, and a job past `timeout_s` is stopped and becomes a
failed row. A run with a user's estimator (`runs_user_code`) runs in worker processes even with
jobs=1: its code may end the process it runs in (`os._exit`, a segfault in a library it calls),
which costs that job's row (`fusion.evaluation.run.pool.WorkerDied`), not the run; `sys.exit` and a
KeyboardInterrupt it raises itself are rows too (`fusion.evaluation.run.job.run_one`).

With `align` (and for a recording whose truth is in frames of its own, `Recording.truth_needs_alignment`),
a recording's alignment (`fusion.evaluation.scoring.align`) is fitted from the recording alone
the first time a process needs it and kept with the loaded recording, so every job of that
recording uses it (each worker that touches the recording fits it once; the fit is
deterministic, so they agree bit for bit).

A recording that cannot be scored costs only itself: one whose files cannot be read becomes an
`Unreadable` when it is loaded, and each of its jobs a row saying so without running anything; one
without usable truth, or (with `align`) without an alignment it can be scored through, runs its
estimators unscored. Their rows carry the reason (`Result.not_scored`); only when no selected
recording can be read at all does the run end with an error.

Dask: with `scheduler` (the address of a running dask.distributed scheduler) the same jobs run on
that cluster's workers (`_run_dask`), submitted with `pure=False` and `retries`, collected as they
finish, each released once its output is handed on: the client holds rows, as the pool does.
The workers get the recordings either as `Source`s, loaded by a task on a worker once per
recording (cheap to send; every worker needs the files at the same absolute path), or loaded here
and scattered to every worker (no shared file system needed; `scatter`). By default the client
asks each worker whether it sees every file (`client.run`) and scatters only if one does not.
"""
from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from fusion.datasets import LoadOptions, Source
from fusion.estimators import ResolvedSpec, resolve_all
from fusion.estimators.params import EstimatorSpec
from fusion.types import Recording

from ..scoring.align import Alignment
from .job import (UNREADABLE, Job, JobOutput, Result, Unreadable, aligns, checked_alignment, failed, run_job,
                  truth_system, warn_low_coverage)
from .pool import TaskTimeout, WorkerDied, WorkerPool, default_jobs
from .settings import RunSettings

# docs/dask.md's worker environment, as a dask configuration: dask's nanny starts each worker with
# MALLOC_TRIM_THRESHOLD_=65536 (freed memory handed back at once, so the smoothers' large arrays are
# paged in again every iteration) and one BLAS/OpenMP thread; this unsets them. For a LocalCluster
# started from Python: `with dask.config.set(WORKER_ENVIRON): LocalCluster(...)`.
WORKER_ENVIRON = {"distributed.nanny.pre-spawn-environ": {
    name: None for name in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}}


class WorkerState:
    """What one process keeps during a run: the run's recordings (`Source`s or `Recording`s) and
    resolved specs, the recordings loaded so far, their alignments and their truth on the IMU
    stamps, each computed once per process."""

    def __init__(self, items: Sequence[Source | Recording], entries: Sequence[ResolvedSpec],
                 load: LoadOptions = LoadOptions()) -> None:
        self.items = list(items)
        self.entries = list(entries)
        self.load = load
        self._loaded: dict[int, Loaded] = {}
        self._alignments: dict[int, tuple[Alignment | None, str | None]] = {}
        self._truth_at_imu: dict[tuple[int, bool], Any] = {}
        self._faulted: dict[tuple[int, Any], Recording] = {}  # the last few (recording, fault): `faulted`

    def recording(self, index: int) -> Recording | Unreadable:
        return self.loaded(index).recording

    def loaded(self, index: int) -> "Loaded":
        if index not in self._loaded:
            item = self.items[index]
            self._loaded[index] = Loaded(item) if isinstance(item, Recording) else load_recording(self.load, item)
        return self._loaded[index]

    def alignment(self, index: int) -> tuple[Alignment | None, str | None]:
        """The recording's alignment and why it cannot be scored through it (`checked_alignment`)."""
        if index not in self._alignments:
            rec = self.recording(index)
            self._alignments[index] = (None, None) if isinstance(rec, Unreadable) else checked_alignment(rec)
        return self._alignments[index]

    def truth_at_imu(self, index: int, align: bool) -> Callable | None:
        """A callable giving the recording's (aligned) truth on its IMU stamps, computed on the
        first call and kept; None without truth."""
        from ..scoring import consistency
        from .job import aligned

        rec = self.recording(index)
        if isinstance(rec, Unreadable) or rec.truth is None:
            return None

        def compute() -> Any:
            key = (index, align)
            if key not in self._truth_at_imu:
                shown = aligned(rec, self.alignment(index)[0] if align else None)
                self._truth_at_imu[key] = consistency.truth_on(shown.truth, shown.imu.t)
            return self._truth_at_imu[key]

        return compute

    def faulted(self, index: int, fault: Any) -> Recording:
        """The loaded recording under `fault` (`fusion.faults.apply`, with the run's dropout switch),
        kept for the next jobs: a stress run's jobs come recording x fault x estimator, so the
        estimators of one fault follow each other; only the last `FAULTED_KEPT` are kept (a
        recording under every fault would not fit in memory)."""
        key = (index, fault)
        if key not in self._faulted:
            from fusion.faults import apply

            while len(self._faulted) >= FAULTED_KEPT:
                self._faulted.pop(next(iter(self._faulted)))
            self._faulted[key] = apply(self.recording(index), fault, self.load.dropouts)
        return self._faulted[key]

    def run(self, job: Job) -> JobOutput:
        rec = self.recording(job.recording)
        align = not isinstance(rec, Unreadable) and aligns(rec, job.settings.align)
        alignment, problem = self.alignment(job.recording) if align else (None, None)
        truth_at_imu = self.truth_at_imu(job.recording, align)
        if job.fault is not None and not job.fault.clean and not isinstance(rec, Unreadable):
            try:
                rec = self.faulted(job.recording, job.fault)
            except ValueError as exc:  # a fault that does not fit the recording: one line, its row
                return fault_failed(job, rec, self.entries[job.estimator], exc)
            truth_at_imu = _truth_on_stamps(rec, alignment) if job.series else None
        output = run_job(job, rec, self.entries[job.estimator], alignment, truth_at_imu, problem)
        return output.after(self.loaded(job.recording).warnings)


FAULTED_KEPT = 2  # faulted recordings a process keeps (`WorkerState.faulted`)


def _truth_on_stamps(rec: Recording, alignment: Alignment | None) -> Callable | None:
    """A callable giving a (faulted) recording's aligned truth on its own IMU stamps, None without truth."""
    from ..scoring import consistency
    from .job import aligned

    if rec.truth is None:
        return None
    shown = aligned(rec, alignment)
    return lambda: consistency.truth_on(shown.truth, shown.imu.t)


def fault_failed(job: Job, rec: Recording, entry: ResolvedSpec, exc: Exception) -> JobOutput:
    """The row of a job whose fault cannot be applied to its recording (`fusion.faults.apply` raised)."""
    row = failed(rec.id, entry.label, len(rec.imu), f"{rec.id}: estimator {entry.label!r}: {exc}")
    return JobOutput(replace(row, fault=job.fault.to_json()))


def job_cells(recordings: int, estimators: int, faults: Sequence[Sequence[Any]] | None = None
              ) -> list[tuple[int, Any, int]]:
    """A run's jobs in their order, as (recording index, fault, estimator index): recording-major,
    then each of the recording's faults (`faults[i]`; None: one job per estimator, without a fault),
    then the estimators as given. Job n of a run is `job_cells(...)[n]`."""
    return [(i, fault, j) for i in range(recordings) for fault in (faults[i] if faults is not None else (None,))
            for j in range(estimators)]


@dataclass(frozen=True, eq=False)
class Loaded:
    """A recording as a process loaded it (`load_recording`): the recording, or `Unreadable`, and the
    warnings its loader raised (their texts: shown once by the process that runs the run, as a job's
    are, however many processes load it)."""

    recording: Recording | Unreadable
    warnings: tuple[str, ...] = ()


def load_recording(load: LoadOptions, source: Source) -> Loaded:
    """The recording, loaded as `load` says, or `Unreadable` with the loader's one-line message
    (`ValueError`, `FileNotFoundError` and other `OSError`s: a file that cannot be read costs only
    its recording), with the loader's warnings. An `ImportError` (an optional package a format
    needs) still ends the run."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            recording = load.load(source)
        except (ValueError, OSError) as exc:
            recording = Unreadable(source.id, " ".join(str(exc).split()))
    return Loaded(recording, tuple(dict.fromkeys(str(w.message) for w in caught)))


_WORKER: WorkerState | None = None  # in a pool worker: its state, set once by `_start_worker`


def _start_worker(state: WorkerState) -> None:
    global _WORKER
    _WORKER = state


def _run_in_worker(job: Job) -> JobOutput:
    return _WORKER.run(job)


def run(specs: Iterable[EstimatorSpec | ResolvedSpec | str] | str, items: Sequence[Source | Recording],
        settings: RunSettings | None = None, *, keep: bool = False, series: bool = False,
        done: Mapping[int, Result] | None = None, on_done: Callable[[int, JobOutput], None] | None = None,
        faults: Sequence[Sequence[Any]] | None = None, **options: Any) -> list[Result]:
    """Every estimator on every recording; results in recording-major order (job n is recording
    n // len(specs) with spec n % len(specs); with `faults`, `job_cells(...)[n]`).

    specs: estimator specs, spec texts (`"ukf:R=1e-3"`; `all` expands to the registry) or resolved
        specs (`fusion.estimators.resolve_all`, which resolves the others here, once).
    items: dataset `Source`s (loaded lazily, once per process) or loaded `Recording`s.
    settings: the run's `fusion.evaluation.run.settings.RunSettings`; `options`, its fields as keywords
        (`run(specs, items, jobs=2, align=True)`), replace the given settings' own (or the
        defaults'). Of them the runner reads:
        init, protocol, align (`fusion.evaluation.run.job.run_one`; with `align` a recording's alignment
        is fitted once per process, module docstring); panorama: also stitch and score a panorama
        per job, its scenes looked up under data_dir (`fusion.evaluation.panorama.recording.panorama_scores`);
        calibration, dropouts, mag, imu_topic, truth_topic: how `Source`s are loaded
        (`RunSettings.load_options`);
        jobs: worker processes; None or 0 means all cores; 1 runs in this process, unless `timeout_s`
        or a user's estimator (`runs_user_code`) asks for one worker process;
        timeout_s: stop a job that runs longer (its row then says so);
        scheduler: the address of a running dask.distributed scheduler (`tcp://10.0.0.5:8786`): the
        jobs run on its workers instead (`jobs` is then not used; see "Dask" in the module
        docstring); None runs locally;
        scatter: with `scheduler`, how workers get the recordings: False ships `Source`s (each
        worker needs the files at the same path), True loads them here and sends the loaded
        recordings, None (default) ships `Source`s if every worker sees every file, else scatters;
        progress: a progress bar on stderr. The selection (dataset) and what is written (out,
        json_path, ...) are the caller's.
    keep: return whole results (trajectories, per-sample errors) instead of rows.
    series: each job also sends its plot data, handed to `on_done` (the first estimator's job of a
        recording also its recording's: `JobOutput.recording_part`).
    done: rows already known (a resumed run), by job number: not computed again.
    on_done: called here, in this process, with (job number, `JobOutput`) as each job ends (a
        failed job included: its row has an `error`).
    faults: per recording, the `fusion.faults.Fault`s to run it under (`fusion stress`), each with
        every estimator; a job's fault is applied where it runs, its row records it (`Result.fault`).
        None: each recording as loaded.
    """
    if settings is not None and not isinstance(settings, RunSettings):
        raise TypeError(f"run: settings must be a RunSettings (or give its fields as keywords), got {settings!r}")
    s = RunSettings(**options) if settings is None else replace(settings, **options)
    scheduler, scatter, timeout_s = s.scheduler, s.scatter, s.timeout_s
    if scatter and not scheduler:
        raise ValueError("--scatter applies to runs on a Dask cluster (--scheduler ADDRESS)")
    if timeout_s is not None and not timeout_s > 0:
        raise ValueError(f"--timeout must be a positive number of seconds, got {timeout_s}")
    entries = resolve_all(specs)
    items = list(items)
    done = dict(done or {})
    truths = [truth_system(item) for item in items]
    if s.panorama:  # the scenes' folder as this process sees it (a worker's $FUSION_DATA is not ours)
        s = replace(s, data_dir=str(s.resolved_data_dir()))
    load = s.load_options()
    if faults is not None and len(faults) != len(items):
        raise ValueError(f"run: faults must give one list per recording ({len(items)}), got {len(faults)}")
    tasks = {n: Job(i, j, s, series, j == 0, keep, truths[i], fault)
             for n, (i, fault, j) in enumerate(job_cells(len(items), len(entries), faults))}
    todo = [n for n in tasks if n not in done]
    jobs = default_jobs() if not s.jobs else int(s.jobs)
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    jobs = min(jobs, len(todo)) or 1
    bar = _progress(len(tasks), s.progress)
    bar.update(len(tasks) - len(todo))
    results: dict[int, Result] = dict(done)

    shown: set[str] = set()

    def finished(n: int, output: JobOutput) -> None:
        results[n] = output.result
        for message in output.warnings:  # each once per run, here, where the user reads them
            if message not in shown:
                shown.add(message)
                warnings.warn(message, stacklevel=2)
        if on_done is not None:
            on_done(n, output)
        fault = tasks[n].fault
        bar.set_postfix_str(f"{items[tasks[n].recording].id}{f' {fault.label}' if fault is not None else ''} "
                            f"{entries[tasks[n].estimator].label}")
        bar.update()

    try:
        if scheduler:
            _run_dask([(n, tasks[n]) for n in todo], items, entries, scheduler, load, scatter, finished)
        elif jobs == 1 and timeout_s is None and not any(runs_user_code(e) for e in entries):
            state = WorkerState(items, entries, load)
            for n in todo:
                finished(n, state.run(tasks[n]))
        else:
            with WorkerPool(jobs, _start_worker, (WorkerState(items, entries, load),), timeout_s) as pool:
                for k, outcome in pool.imap_unordered(_run_in_worker, [(tasks[n],) for n in todo]):
                    n = todo[k]
                    rec, entry = items[tasks[n].recording], entries[tasks[n].estimator]
                    fault = tasks[n].fault
                    stamp = {} if fault is None else {"fault": fault.to_json()}
                    if isinstance(outcome.error, (TaskTimeout, WorkerDied)):
                        finished(n, JobOutput(replace(failed(rec.id, entry.label, 0,
                                                             f"{rec.id}: estimator {entry.label!r}: {outcome.error}"),
                                                      **stamp)))
                    elif isinstance(outcome.error, (SystemExit, KeyboardInterrupt)):  # a worker ignores Ctrl-C: not
                        # the user's; raised outside `run_one`'s guard (which makes them rows), e.g. by a user's __del__
                        finished(n, JobOutput(replace(failed(rec.id, entry.label, 0, f"{rec.id}: estimator "
                                                             f"{entry.label!r}: its worker process stopped on "
                                                             f"{outcome.error!r}"), **stamp)))
                    else:
                        finished(n, outcome.result())  # re-raises a worker's error (a recording that
                        # cannot be loaded: one line naming its file) here
    finally:
        bar.close()
    out = [results[n] for n in sorted(tasks)]
    if out and not any(r.readable for r in out):  # nothing ran: that is an error, not a table of reasons
        reasons = list(dict.fromkeys(r.not_scored[len(UNREADABLE) + 2:] for r in out))
        raise ValueError(reasons[0] if len(reasons) == 1 else
                         f"none of the {len(items)} selected recordings can be read: {reasons[0]} (and "
                         f"{len(reasons) - 1} more)")
    warn_low_coverage(out)
    return out


def runs_user_code(entry: ResolvedSpec) -> bool:
    """A user's estimator (a file, a module, an entry point; not a trajectory file, which our code
    reads). A run with one runs its jobs in worker processes, even with jobs=1: a user's code that
    ends its process (`os._exit`) or crashes the interpreter (a segfault in compiled code it
    calls) then costs its row, not the run."""
    return entry.user and getattr(entry.origin, "kind", None) != "trajectory"


# --- Dask ---

RETRIES = 2  # extra attempts of a task that raised (a worker's death is counted by the scheduler, see below)
WORKER_WAIT_S = 30.0  # how long to wait for the scheduler's first worker
CONNECT_TIMEOUT_S = 20.0  # how long to try to reach the scheduler


def _given(value: Any) -> Any:
    """A value as a Dask task's result (recomputable from the graph if the worker holding it dies)."""
    return value


def _dask_job(job: Job, loaded: Loaded, entry: ResolvedSpec,
              fitted: tuple[Alignment | None, str | None] | None) -> JobOutput:
    """A job as a task on a Dask worker (the recording and its alignment are tasks of their own)."""
    from ..scoring import consistency
    from .job import aligned

    rec = loaded.recording
    alignment, problem = fitted or (None, None)
    if job.fault is not None and not job.fault.clean and not isinstance(rec, Unreadable):
        from fusion.faults import apply

        try:
            rec = apply(rec, job.fault, job.settings.dropouts)
        except ValueError as exc:
            return fault_failed(job, rec, entry, exc)
    truth_at_imu = None
    if not isinstance(rec, Unreadable) and rec.truth is not None and not problem:
        shown = aligned(rec, alignment)
        truth_at_imu = lambda: consistency.truth_on(shown.truth, shown.imu.t)  # noqa: E731
    return run_job(job, rec, entry, alignment, truth_at_imu, problem).after(loaded.warnings)


def _fit_alignment(loaded: Loaded, align: bool) -> tuple[Alignment | None, str | None]:
    """A Dask task: `checked_alignment` of a loaded recording that `aligns`; (None, None) for others."""
    rec = loaded.recording
    return checked_alignment(rec) if not isinstance(rec, Unreadable) and aligns(rec, align) else (None, None)


def _run_dask(tasks: list[tuple[int, Job]], items: list, entries: list[ResolvedSpec], scheduler: str,
              load: LoadOptions, scatter: bool | None, finished: Callable[[int, JobOutput], None]) -> None:
    """The jobs on a dask.distributed cluster, each output handed to `finished` as it arrives.
    Every recording becomes one future (a load task on a worker, or the loaded recording
    scattered from here) and, with `align`, one alignment task; every estimator spec one task;
    each job is a task taking them, so a recording is loaded (and aligned) once per run, and a
    worker that needs it fetches it from the worker that has it. A worker that dies mid-job costs a retry: the scheduler reruns
    its tasks elsewhere (up to `distributed.scheduler.allowed-failures` deaths per task, 3 by
    default), recomputing lost recordings from their load task."""
    try:
        from distributed import Client
        from distributed import as_completed as dask_as_completed
    except ImportError:
        raise ImportError("--scheduler needs dask.distributed: pip install 'dask[distributed]'") from None
    try:
        client = Client(scheduler, set_as_default=False, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"--scheduler {scheduler}: cannot connect ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]})") from None
    futures: dict[Any, int] = {}
    shared: list[Any] = []
    try:
        try:
            client.wait_for_workers(1, timeout=WORKER_WAIT_S)
        except TimeoutError:
            raise ValueError(f"--scheduler {scheduler}: no worker connected within {WORKER_WAIT_S:.0f} s") from None
        needed = {job.recording for _, job in tasks}
        shared = _recordings_on(client, items, load, scatter, needed)
        align = tasks[0][1].settings.align if tasks else False  # (one run: one setting)
        alignments = {i: client.submit(_fit_alignment, shared[i], align, pure=False, retries=RETRIES)
                      for i in sorted({job.recording for _, job in tasks})}
        # each spec as a task of its own (not scattered): a worker that dies with its result costs a
        # recomputation, where scattered data would be lost with the last worker that held it
        specs = {j: client.submit(_given, entries[j], pure=False, retries=RETRIES)
                 for j in sorted({job.estimator for _, job in tasks})}
        shared += list(alignments.values()) + list(specs.values())
        futures = {client.submit(_dask_job, job, shared[job.recording], specs[job.estimator],
                                 alignments.get(job.recording), pure=False, retries=RETRIES): n for n, job in tasks}
        for future in dask_as_completed(list(futures), loop=client.loop):
            n = futures.pop(future)
            output = future.result()  # re-raises a task's error here
            future.release()
            finished(n, output)
    except BaseException:  # a job's error, Ctrl-C, SIGTERM: nothing left running on the cluster
        client.cancel(list(futures) + shared, force=True)
        raise
    finally:
        client.close()


def _recordings_on(client: Any, items: list, load: LoadOptions, scatter: bool | None, needed: set[int]) -> list[Any]:
    """One future per item: a load task on a worker for a `Source` whose files every worker
    sees (or all of them, `scatter=False`), else the recording loaded here and scattered to every
    worker (so that losing one worker loses no copy)."""
    sources = [_absolute(item) if isinstance(item, Source) else item for item in items]
    if scatter is None:
        missing = _missing_on_workers(client, [s for s in sources if isinstance(s, Source)])
        scatter = bool(missing)
        if missing:
            from fusion.selection import note

            note(f"sending loaded recordings to the workers (--scatter): {missing}")
    out: list[Any] = []
    for i, item in enumerate(sources):
        if i not in needed:
            out.append(None)
        elif isinstance(item, Source) and not scatter:
            out.append(client.submit(load_recording, load, item, pure=False, retries=RETRIES))
        else:
            rec = Loaded(item) if isinstance(item, Recording) else load_recording(load, item)
            out.append(client.scatter(rec, broadcast=True, hash=False))
    return out


def _absolute(source: Source) -> Source:
    """The source with absolute file paths (a worker's working folder is not ours)."""
    return replace(source, **{name: Path(path).absolute() for name in ("imu", "vicon", "cam")
                              if (path := getattr(source, name)) is not None})


def source_paths(source: Source) -> list[Path]:
    """The files (or folders) a recording is read from."""
    return [Path(p) for p in (source.imu, source.vicon, source.cam) if p is not None]


def _missing_paths(paths: list[str]) -> list[str]:
    """On a worker: the paths it cannot see."""
    return [p for p in paths if not os.path.exists(p)]


def _missing_on_workers(client: Any, sources: list[Source]) -> str:
    """'' when every worker sees every file of `sources`, else which worker misses which file."""
    paths = [str(p) for s in sources for p in source_paths(s)]
    if not paths:
        return ""
    per_worker = client.run(_missing_paths, paths)
    bad = {w: m for w, m in per_worker.items() if m}
    if not bad:
        return ""
    worker, files = next(iter(bad.items()))
    return f"{len(bad)} of {len(per_worker)} workers miss recording files (e.g. {worker}: {files[0]})"


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, file=sys.stderr, unit="job", desc="running", leave=False)
