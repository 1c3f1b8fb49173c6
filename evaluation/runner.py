"""Recordings x estimator settings as independent jobs, serially or in a process pool.

    results, infos = run(["dr", "ukf:R=1e-3"], datasets.select("all"), jobs=2)

A job is one (recording, estimator spec) pair: build, estimate, time, score
(`evaluation.compare.run_one`). With `jobs > 1` the jobs run in a `ProcessPoolExecutor`
(the 'fork' context where the platform has it, else 'spawn'). The recordings are handed to
each worker once, when it starts (as dataset `Source`s, which the worker loads the first
time a job needs them and keeps, or as loaded `Recording`s); a job itself only carries two
indices. Results come back in the serial order (recording-major, specs as given) whatever
order the jobs finish in, and hold the same numbers as a serial run: each job is the same
deterministic computation on the same inputs. Only `seconds` (wall time) differs.

With `align`, a recording's alignment (`evaluation.align`) is fitted from the recording alone
the first time a process needs it and kept with the loaded recording, so every job of that
recording uses it, not a fit of its own (each worker that touches the recording fits it once;
the fit is deterministic, so they agree bit for bit).
"""
from __future__ import annotations

import multiprocessing
import os
import sys
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

import estimators
from estimators.params import EstimatorSpec
from fusion.datasets import LoadOptions, Source
from fusion.types import Recording, Trajectory

from .align import Alignment
from .compare import Result, aligned, recording_alignment, run_one


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


# Per process: the recordings of the current run and the ones loaded so far.
_ITEMS: list[Source | Recording] = []
_CACHE: dict[int, Recording] = {}
_ALIGNMENTS: dict[int, Alignment | None] = {}
_LOAD = LoadOptions()


def _init_worker(items: Sequence[Source | Recording], registry: dict[str, type] | None, load: LoadOptions = LoadOptions()) -> None:
    global _ITEMS, _LOAD
    _ITEMS = list(items)
    _LOAD = load
    _CACHE.clear()
    _ALIGNMENTS.clear()
    if registry is not None:  # under 'spawn' the child starts from the default registry
        estimators.ESTIMATORS.clear()
        estimators.ESTIMATORS.update(registry)


def _recording(index: int) -> Recording:
    rec = _CACHE.get(index)
    if rec is None:
        item = _ITEMS[index]
        rec = item if isinstance(item, Recording) else _LOAD.load(item)
        _CACHE[index] = rec
    return rec


def _alignment(index: int) -> Alignment | None:
    if index not in _ALIGNMENTS:
        _ALIGNMENTS[index] = recording_alignment(_recording(index))
    return _ALIGNMENTS[index]


def _job(index: int, spec: EstimatorSpec, init: str | None, protocol: str | None, with_info: bool,
         panorama_data_dir: str | None = None, align: bool = False) -> tuple[Result, RecordingInfo | None]:
    rec = _recording(index)
    alignment = _alignment(index) if align else None
    result = run_one(rec, spec, init, protocol, alignment)
    rec = aligned(rec, alignment)
    if panorama_data_dir is not None:
        from .panorama import panorama_scores

        result = replace(result, panorama=panorama_scores(rec, result.trajectory, data_dir=panorama_data_dir))
    info = RecordingInfo(rec.id, rec.imu.t, rec.imu.gyr_valid, rec.truth) if with_info else None
    return result, info


def default_jobs() -> int:
    """All the cores this process may use."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def pool_context() -> multiprocessing.context.BaseContext:
    """'fork' where available (workers inherit imports and the registry), else 'spawn'."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


def run(specs: Sequence[EstimatorSpec], items: Sequence[Source | Recording], init: str | None = None,
        jobs: int | None = 1, progress: bool = False, with_info: bool = False, protocol: str | None = None,
        load: LoadOptions = LoadOptions(), panorama_data_dir: str | None = None, align: bool = False
        ) -> tuple[list[Result], list[RecordingInfo]]:
    """Every spec on every recording; results in recording-major order.

    specs: expanded estimator specs (no `all`); each is built once here first, so a bad
        name or parameter fails before any work.
    items: dataset `Source`s (loaded lazily, once per process) or loaded `Recording`s.
    jobs: worker processes; None or 0 means all cores; 1 runs in this process.
    with_info: also return one `RecordingInfo` per recording (for plots).
    protocol: scoring protocol (`evaluation.compare.run_one`), None for each recording's default.
    load: how `Source`s are loaded (calibration file, dropout switch).
    panorama_data_dir: when given, also stitch and score a panorama per job (scenes are looked
        up there; see `evaluation.panorama.panorama_scores`).
    align: score against the truth mapped into our frames by constant rotations fitted once
        per recording (module docstring, `evaluation.align`), the same for every spec.
    """
    specs = list(specs)
    items = list(items)
    for spec in specs:
        estimators.build(spec)
    tasks = [(i, s, init, protocol, with_info and j == 0, panorama_data_dir, align)
             for i in range(len(items)) for j, s in enumerate(specs)]
    jobs = default_jobs() if not jobs else int(jobs)
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    jobs = min(jobs, len(tasks)) or 1
    bar = _progress(len(tasks), progress)
    outputs: list[Any] = [None] * len(tasks)
    try:
        if jobs == 1:
            _init_worker(items, None, load)
            for n, task in enumerate(tasks):
                bar.set_postfix_str(_label(items, task))
                outputs[n] = _job(*task)
                bar.update()
        else:
            outputs = _run_pool(tasks, items, jobs, bar, load)
    finally:
        bar.close()
        _CACHE.clear()
        _ALIGNMENTS.clear()
    results = [r for r, _ in outputs]
    infos = [info for _, info in outputs if info is not None]
    return results, infos


def _run_pool(tasks: list[tuple], items: list, jobs: int, bar: Any, load: LoadOptions) -> list[Any]:
    ctx = pool_context()
    registry = None if ctx.get_start_method() == "fork" else dict(estimators.ESTIMATORS)
    outputs: list[Any] = [None] * len(tasks)
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_init_worker,
                             initargs=(items, registry, load)) as pool:
        futures = {pool.submit(_job, *task): n for n, task in enumerate(tasks)}
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_EXCEPTION)
                for future in done:
                    n = futures[future]
                    outputs[n] = future.result()  # re-raises a worker's error here
                    bar.set_postfix_str(_label(items, tasks[n]))
                    bar.update()
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    return outputs


def _label(items: list, task: tuple) -> str:
    return f"{items[task[0]].id} {task[1].label}"


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
