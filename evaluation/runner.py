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
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
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
        rec = self.recording(job.index)
        alignment = self.alignment(job.index) if job.align else None
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
        load: LoadOptions = LoadOptions(), panorama_data_dir: str | None = None, align: bool = False
        ) -> tuple[list[Result], list[RecordingInfo]]:
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
    """
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
        if jobs == 1:
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
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                for future in done:
                    n = futures[future]
                    outputs[n] = future.result()  # re-raises a worker's error here
                    bar.set_postfix_str(_label(items, tasks[n]))
                    bar.update()
        except BaseException:  # a job's error, Ctrl-C, SIGTERM (see `fusion.cli`): no orphaned workers
            stop_pool(pool)
            raise
    return outputs


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
