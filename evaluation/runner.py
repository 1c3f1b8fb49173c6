"""Recordings x estimator settings as independent jobs, serially or in a process pool.

    from fusion import datasets
    from fusion.evaluation.runner import run
    results, infos = run(["dr", "ukf:R=1e-3"], datasets.select("sim"), jobs=2)

A job (`Job`) is one (recording, estimator spec) pair: build, estimate, time, score
(`fusion.evaluation.job.run_one`). It carries everything it needs except the recording: the spec,
the estimator class the spec names (resolved here, in the parent, so a worker never looks a
name up in `fusion.estimators.ESTIMATORS` and 'spawn' runs what the parent registered), and the
recording's index. With `jobs > 1` the jobs run in a `ProcessPoolExecutor` (the 'fork' context
where the platform has it, else 'spawn'). The recordings are handed to each worker once, when it
starts (as dataset `Source`s, which the worker loads the first time a job needs them and keeps,
or as loaded `Recording`s). Results come back in the serial order (recording-major, specs as
given) whatever order the jobs finish in, and hold the same numbers as a serial run: each job
is the same deterministic computation on the same inputs. Only `seconds` (wall time) differs.

State: what a process keeps between jobs (the run's recordings, the ones loaded so far, their
alignments) is one `WorkerState`. A serial run keeps it in a local variable; a pool worker's
initialiser creates one per process and keeps it in `_WORKER`, the module's only mutable
global, which only worker processes set.

With `align`, a recording's alignment (`fusion.evaluation.align`) is fitted from the recording alone
the first time a process needs it and kept with the loaded recording, so every job of that
recording uses it, not a fit of its own (each worker that touches the recording fits it once;
the fit is deterministic, so they agree bit for bit).

Dask: with `scheduler` (the address of a running dask.distributed scheduler) the same jobs run
on that cluster's workers (`_run_dask`), submitted with `pure=False` and `retries`, collected as
they finish; results and their order are again those of a serial run. The workers get the
recordings either as `Source`s, loaded by a task on a worker once per recording (cheap to send;
every worker needs the files at the same absolute path), or loaded here and scattered to every
worker (no shared file system needed; `scatter`). By default the client asks each worker
whether it sees every file (`client.run`) and scatters only if one does not. Jobs, the
recordings and their alignments are tasks of the cluster, so nothing of the run is kept in
module state on a worker.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from fusion import estimators
from fusion.estimators.base import Estimator
from fusion.estimators.params import EstimatorSpec
from fusion.datasets import LoadOptions, Source
from fusion.types import Recording, Trajectory

from .align import Alignment
from .job import Result, aligned, as_specs, expand_all, recording_alignment, resolve, run_one, warn_low_coverage


@dataclass(frozen=True, eq=False)
class RecordingInfo:
    """What the report needs from a recording besides the estimates.

    imu_t: (N,) s, the IMU time stamps every trajectory lives on.
    gyr_valid: (N,) bool, False where the gyro was marked unusable.
    truth: VICON orientations on their own clock (NaN rows in tracking gaps), or None; with
        `--align`, mapped into our frames (`A R_truth B`).
    """

    id: str
    imu_t: np.ndarray
    gyr_valid: np.ndarray
    truth: Trajectory | None


@dataclass(frozen=True)
class Job:
    """One recording x one estimator setting, and how to score it.

    index: the recording's position in the run's items (`WorkerState.recording`).
    spec: the estimator spec; estimator_class: the class it names (`fusion.evaluation.job.resolve`).
    with_info: also return the recording's `RecordingInfo` (for the report's plots).
    panorama_data_dir: when given, also stitch and score a panorama (`fusion.evaluation.panorama`).
    """

    index: int
    spec: EstimatorSpec
    estimator_class: type[Estimator]
    init: str | None = None
    protocol: str | None = None
    with_info: bool = False
    panorama_data_dir: str | None = None
    align: bool = False


class WorkerState:
    """What one process keeps during a run: the run's recordings (`Source`s or `Recording`s), the
    recordings loaded so far and their alignments, each computed once per process."""

    def __init__(self, items: Sequence[Source | Recording], load: LoadOptions = LoadOptions()) -> None:
        self.items = list(items)
        self.load = load
        self._loaded: dict[int, Recording] = {}
        self._alignments: dict[int, Alignment | None] = {}

    def recording(self, index: int) -> Recording:
        if index not in self._loaded:
            item = self.items[index]
            self._loaded[index] = item if isinstance(item, Recording) else self.load.load(item)
        return self._loaded[index]

    def alignment(self, index: int) -> Alignment | None:
        if index not in self._alignments:
            self._alignments[index] = recording_alignment(self.recording(index))
        return self._alignments[index]

    def run(self, job: Job) -> tuple[Result, RecordingInfo | None]:
        """The job's `Result` (and its recording's `RecordingInfo` if asked)."""
        return run_job(job, self.recording(job.index), self.alignment(job.index) if job.align else None)


def run_job(job: Job, rec: Recording, alignment: Alignment | None) -> tuple[Result, RecordingInfo | None]:
    """One job on its (loaded) recording and the recording's alignment (None without `align`):
    the `Result`, and the recording's `RecordingInfo` if the job asks for it."""
    result = run_one(rec, job.spec, job.init, job.protocol, alignment, estimator_class=job.estimator_class)
    rec = aligned(rec, alignment)
    if job.panorama_data_dir is not None:
        from .panorama import panorama_scores

        result = replace(result, panorama=panorama_scores(rec, result.trajectory, data_dir=job.panorama_data_dir))
    info = RecordingInfo(rec.id, rec.imu.t, rec.imu.gyr_valid, rec.truth) if job.with_info else None
    return result, info


_WORKER: WorkerState | None = None  # in a pool worker: its state, set once by `_start_worker`


def quiet_worker() -> None:
    """In a worker process: Ctrl-C goes to the whole process group, but only the parent acts on
    it (it stops the workers, `stop_pool`); SIGTERM kills (a forked worker would otherwise
    inherit the parent's handler)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now: cancel what has not started and terminate the running workers (a job
    can run for minutes; waiting for it would leave it running after an interrupt)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        if proc.is_alive():
            proc.terminate()
    for proc in processes:
        proc.join(timeout=5)
        if proc.is_alive():
            proc.kill()
            proc.join()


def _start_worker(items: Sequence[Source | Recording], load: LoadOptions) -> None:
    """A pool worker's initialiser: signals as `quiet_worker`, and the process's `WorkerState`."""
    global _WORKER
    quiet_worker()
    _WORKER = WorkerState(items, load)


def _run_in_worker(job: Job) -> tuple[Result, RecordingInfo | None]:
    return _WORKER.run(job)


def default_jobs() -> int:
    """All the cores this process may use."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def pool_context() -> multiprocessing.context.BaseContext:
    """'fork' where available (workers inherit the parent's imports), else 'spawn' (jobs carry
    their estimator class, so nothing depends on the child's registry)."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


def run(specs: Iterable[EstimatorSpec | str] | str, items: Sequence[Source | Recording], init: str | None = None,
        jobs: int | None = 1, progress: bool = False, with_info: bool = False, protocol: str | None = None,
        load: LoadOptions = LoadOptions(), panorama_data_dir: str | None = None, align: bool = False,
        scheduler: str | None = None, scatter: bool | None = None) -> tuple[list[Result], list[RecordingInfo]]:
    """Every spec on every recording; results in recording-major order.

    specs: estimator specs or spec texts (`"ukf:R=1e-3"`; `all` expands to the registry,
        `fusion.evaluation.job.expand_all`); each is resolved to its class once here first, so a
        bad name or parameter fails before any work.
    items: dataset `Source`s (loaded lazily, once per process) or loaded `Recording`s.
    jobs: worker processes; None or 0 means all cores; 1 runs in this process.
    with_info: also return one `RecordingInfo` per recording (for plots).
    protocol: scoring protocol (`fusion.evaluation.job.run_one`), None for each recording's default.
    load: how `Source`s are loaded (calibration file, dropout switch).
    panorama_data_dir: when given, also stitch and score a panorama per job (scenes are looked
        up there; see `fusion.evaluation.panorama.panorama_scores`).
    align: score against the truth mapped into our frames by constant rotations fitted once
        per recording (module docstring, `fusion.evaluation.align`), the same for every spec.
    scheduler: the address of a running dask.distributed scheduler (`tcp://10.0.0.5:8786`): the
        jobs run on its workers instead (`jobs` is then not used; see "Dask" in the module
        docstring); None runs locally.
    scatter: with `scheduler`, how workers get the recordings: False ships `Source`s (each
        worker needs the files at the same path), True loads them here and sends the loaded
        recordings, None (default) ships `Source`s if every worker sees every file, else scatters.
    """
    if scatter and not scheduler:
        raise ValueError("--scatter applies to runs on a Dask cluster (--scheduler ADDRESS)")
    specs = expand_all(as_specs(specs))
    items = list(items)
    classes = [resolve(spec) for spec in specs]
    tasks = [Job(i, spec, cls, init, protocol, with_info and j == 0, panorama_data_dir, align)
             for i in range(len(items)) for j, (spec, cls) in enumerate(zip(specs, classes))]
    jobs = default_jobs() if not jobs else int(jobs)
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    jobs = min(jobs, len(tasks)) or 1
    bar = _progress(len(tasks), progress)
    outputs: list[Any] = [None] * len(tasks)
    try:
        if scheduler:
            outputs = _run_dask(tasks, items, scheduler, bar, load, scatter)
        elif jobs == 1:
            state = WorkerState(items, load)
            for n, task in enumerate(tasks):
                bar.set_postfix_str(_label(items, task))
                outputs[n] = state.run(task)
                bar.update()
        else:
            outputs = _run_pool(tasks, items, jobs, bar, load)
    finally:
        bar.close()
    results = [r for r, _ in outputs]
    infos = [info for _, info in outputs if info is not None]
    warn_low_coverage(results)
    return results, infos


def _run_pool(tasks: list[Job], items: list, jobs: int, bar: Any, load: LoadOptions) -> list[Any]:
    outputs: list[Any] = [None] * len(tasks)
    with ProcessPoolExecutor(max_workers=jobs, mp_context=pool_context(), initializer=_start_worker,
                             initargs=(items, load)) as pool:
        futures = {pool.submit(_run_in_worker, task): n for n, task in enumerate(tasks)}
        try:
            for future in as_completed(futures):  # one step of the bar per finished job
                n = futures[future]
                outputs[n] = future.result()  # re-raises a worker's error here
                bar.set_postfix_str(_label(items, tasks[n]))
                bar.update()
        except BaseException:  # a job's error, Ctrl-C, SIGTERM (see `fusion.cli`): no orphaned workers
            stop_pool(pool)
            raise
    return outputs


# --- Dask ---

RETRIES = 2  # extra attempts of a task that raised (a worker's death is counted by the scheduler, see below)
WORKER_WAIT_S = 30.0  # how long to wait for the scheduler's first worker
CONNECT_TIMEOUT_S = 20.0  # how long to try to reach the scheduler


def _run_dask(tasks: list[Job], items: list, scheduler: str, bar: Any, load: LoadOptions,
              scatter: bool | None) -> list[Any]:
    """The jobs on a dask.distributed cluster; outputs in the jobs' order, the bar advanced as
    each job finishes. Every recording becomes one future (a load task on a worker, or the
    loaded recording scattered from here) and, with `align`, one alignment task; each job is a
    task taking them, so a recording is loaded (and aligned) once per run, and a worker that
    needs it fetches it from the worker that has it. A worker that dies mid-job costs a retry:
    the scheduler reruns its tasks elsewhere (up to `distributed.scheduler.allowed-failures`
    deaths per task, 3 by default), recomputing lost recordings from their load task."""
    try:
        from distributed import Client
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
        shared = _recordings_on(client, items, load, scatter, {t.index for t in tasks})
        alignments = {i: client.submit(recording_alignment, shared[i], pure=False, retries=RETRIES)
                      for i in sorted({t.index for t in tasks if t.align})}
        shared += list(alignments.values())
        futures = {client.submit(run_job, task, shared[task.index], alignments.get(task.index), pure=False,
                                 retries=RETRIES): n for n, task in enumerate(tasks)}
        return _collect(client, futures, tasks, items, bar)
    except BaseException:  # a job's error, Ctrl-C, SIGTERM: nothing left running on the cluster
        client.cancel(list(futures) + shared, force=True)
        raise
    finally:
        client.close()


def _collect(client: Any, futures: dict[Any, int], tasks: list[Job], items: list, bar: Any) -> list[Any]:
    from distributed import as_completed as dask_as_completed

    outputs: list[Any] = [None] * len(tasks)
    for future in dask_as_completed(list(futures), loop=client.loop):
        n = futures[future]
        outputs[n] = future.result()  # re-raises a job's error here
        future.release()
        bar.set_postfix_str(_label(items, tasks[n]))
        bar.update()
    return outputs


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
            out.append(client.submit(load.load, item, pure=False, retries=RETRIES))
        else:
            rec = item if isinstance(item, Recording) else load.load(item)
            out.append(client.scatter(rec, broadcast=True, hash=False))
    return out


def _absolute(source: Source) -> Source:
    """The source with absolute file paths (a worker's working folder is not ours)."""
    return replace(source, **{name: Path(path).absolute() for name in ("imu", "vicon", "cam")
                              if (path := getattr(source, name)) is not None})


def _source_paths(sources: list[Source]) -> list[str]:
    return [str(p) for s in sources for p in (s.imu, s.vicon, s.cam) if p is not None]


def _missing_paths(paths: list[str]) -> list[str]:
    """On a worker: the paths it cannot see."""
    return [p for p in paths if not os.path.exists(p)]


def _missing_on_workers(client: Any, sources: list[Source]) -> str:
    """'' when every worker sees every file of `sources`, else which worker misses which file."""
    paths = _source_paths(sources)
    if not paths:
        return ""
    per_worker = client.run(_missing_paths, paths)
    bad = {w: m for w, m in per_worker.items() if m}
    if not bad:
        return ""
    worker, files = next(iter(bad.items()))
    return f"{len(bad)} of {len(per_worker)} workers miss recording files (e.g. {worker}: {files[0]})"


def _label(items: list, job: Job) -> str:
    return f"{items[job.index].id} {job.spec.label}"


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, file=sys.stderr, unit="job", desc="running", leave=False)


def describe_specs(specs: Sequence[EstimatorSpec]) -> dict[str, dict[str, Any]]:
    """For results.json's settings: per label, the class, whether it is causal, and every
    parameter's value after the overrides (defaults included), so a run can be repeated."""
    import dataclasses

    out = {}
    for spec in specs:
        est = estimators.build(spec)
        params = {f.name: getattr(est.params, f.name) for f in dataclasses.fields(est.params)}
        out[spec.label] = {"name": spec.name, "class": type(est).__name__, "causal": bool(type(est).causal),
                           "params": {k: v if isinstance(v, (bool, int, float, str)) or v is None else repr(v)
                                      for k, v in params.items()}}
    return out
