"""One job: one recording x one estimator, estimated, timed and scored, and the `Result` it gives.
The layer below `fusion.evaluation.run.runner` (which schedules jobs on processes or a cluster).

    from fusion import datasets
    from fusion.evaluation.run.job import run_one
    result = run_one(datasets.load("sim"), "ukf:R=1e-3")

`run_one` is the single-job API: it returns the whole result (trajectory and per-sample errors)
and raises on failure. A run's jobs go through `run_job` instead, which returns the row only
(`Result.summary`: scores, timings, coverage; what a sweep of hundreds of jobs can keep in
memory), the job's plot data when asked (`fusion.evaluation.run.series.job_part`), and turns a
failure into a row that says what went wrong, so the other rows are still computed.
"""
from __future__ import annotations

import contextlib
import signal
import threading
import time
import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fusion.datasets import initial_orientation
from fusion.estimators import ResolvedSpec, resolve
from fusion.estimators.adapters import user
from fusion.estimators.params import EstimatorSpec
from fusion.estimators.adapters.trajectory_file import TrajectoryFile
from fusion.types import Recording, Trajectory

from ..scoring.align import Alignment, fit_alignment
from ..scoring.metrics import MIN_COVERAGE, Score, score
from .settings import RunSettings


@dataclass(frozen=True, eq=False)
class Result:
    """One recording x estimator. `rmse_deg`/`max_deg` are None without ground truth.

    scored_samples, coverage: how many samples were scored and their fraction of what the
    protocol scores (`fusion.evaluation.scoring.metrics.Score.coverage`); None without ground truth (or
    from an older results.json). Below `MIN_COVERAGE` the row is flagged and left out of means.
    trajectory, score: the estimate and its per-sample errors (`run_one`); None in a run's rows.
    error: why the job failed (its estimator raised, returned garbage, ran too long); None if it
        did not. A failed row has no scores.
    magnetometer: the estimate used a magnetometer (9-D); False for 6-D (gyro and accelerometer).
    protocol: the scoring protocol the row was scored with ("full" or "broad"; None without
        truth, or unknown). With "broad" a 6-D row's mean heading offset was removed before
        scoring (`fusion.evaluation.scoring.metrics.score`), a 9-D row's was not.
    truth: what the recording's truth is (`truth_system`: "VICON", "optical motion capture
        (BROAD)", ...), None without truth or unknown.
    Both are the recording's, the same for all its rows: results.json keeps them once per
    recording (`fusion.evaluation.compare.recording_facts`), not in the rows.
    traceback: a failed row whose user code raised: the traceback of the user's own frames
        (`fusion.estimators.adapters.user.failure_site`); None otherwise.
    not_scored: why the row's recording was not scored, one line starting with one of
        `NOT_SCORED` ("cannot be read": its files could not be read and no estimator ran; "no truth",
        "truth unusable": `fusion.types.Recording.truth_problem`; "alignment undetermined",
        "alignment poor": with `--align`, `fusion.evaluation.scoring.align.Alignment.problem`); the same for
        every row of a recording; None for a scored row and a failed one. A fact about the data: the
        run goes on, and its exit status does not change.
    fault: the sensor fault the recording was run under (`fusion stress`: `fusion.faults.Fault.to_json`,
        {"kind", "severity", "unit"}; kind "none" for the clean run); None outside a stress run.
    """

    dataset: str
    estimator: str
    samples: int
    seconds: float
    rmse_deg: dict[str, float] | None
    max_deg: dict[str, float] | None
    trajectory: Trajectory | None = None
    score: Score | None = None
    panorama: dict[str, float] | None = None  # with --panorama: `fusion.evaluation.panorama.recording.panorama_scores`
    alignment: dict[str, Any] | None = None  # with --align: the recording's `fusion.evaluation.scoring.align.Alignment.to_json`
    scored_samples: int | None = None
    coverage: float | None = None
    error: str | None = None
    magnetometer: bool = False
    protocol: str | None = None
    truth: str | None = None
    traceback: str | None = None
    not_scored: str | None = None
    fault: dict[str, Any] | None = None

    @property
    def readable(self) -> bool:
        """The row's recording could be read (its estimator ran, or failed)."""
        return not (self.not_scored or "").startswith(UNREADABLE)

    @property
    def ran(self) -> bool:
        """The estimator ran to its end on the recording: not failed, the recording readable (its
        time means something)."""
        return self.error is None and self.readable

    @property
    def heading_offset_removed(self) -> bool:
        """The row's mean heading offset was removed before scoring: a 6-D estimate scored with
        BROAD's protocol (a row whose protocol is unknown, from an older results.json: a
        recording of the `broad` folder)."""
        return bool(self.rmse_deg) and self.scored_protocol == "broad" and not self.magnetometer

    @property
    def scored_protocol(self) -> str:
        """`protocol`, or when unknown the default of a recording of its folder ("broad" for the
        `broad` folder, else "full")."""
        return self.protocol or ("broad" if self.dataset.split("/")[0] == "broad" else "full")

    @property
    def us_per_sample(self) -> float:
        return 1e6 * self.seconds / max(self.samples, 1)

    @property
    def low_coverage(self) -> bool:
        """Scored on less than `MIN_COVERAGE` of the recording (flagged, left out of means)."""
        return self.coverage is not None and self.coverage < MIN_COVERAGE

    @property
    def in_means(self) -> bool:
        return bool(self.rmse_deg) and not self.low_coverage

    def summary(self) -> "Result":
        """The row without its arrays (trajectory, per-sample errors)."""
        return replace(self, trajectory=None, score=None)

    def to_json(self) -> dict[str, Any]:
        """The row of `results.json` (the keys are a documented format: docs/json-format.md; `panorama`
        only with `--panorama`; `alignment` null unless the row was scored with `--align`;
        `error` only on a failed row, `traceback` only on a failed row whose user code raised,
        `not_scored` only on a row of a recording that was not scored, `fault` only on a stress run's
        row; `protocol` and `truth` go into the document's `recordings`, once per recording)."""
        row = {
            "dataset": self.dataset,
            "estimator": self.estimator,
            "samples": self.samples,
            "seconds": self.seconds,
            "rmse_deg": self.rmse_deg,
            "max_deg": self.max_deg,
            "scored_samples": self.scored_samples,
            "coverage": self.coverage,
            "alignment": self.alignment,
            "magnetometer": self.magnetometer,
        }
        if self.panorama is not None:
            row["panorama"] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in self.panorama.items()}
        if self.error is not None:
            row["error"] = self.error
        if self.traceback is not None:
            row["traceback"] = self.traceback
        if self.not_scored is not None:
            row["not_scored"] = self.not_scored
        if self.fault is not None:
            row["fault"] = self.fault
        return row

    @classmethod
    def from_json(cls, r: dict[str, Any]) -> "Result":
        """A results.json row (as `to_json` wrote it, with its recording's `protocol` and `truth` when
        given) as a `Result` without arrays."""
        return cls(r["dataset"], r["estimator"], r["samples"], r["seconds"], r["rmse_deg"], r["max_deg"],
                   panorama=r.get("panorama"), alignment=r.get("alignment"), scored_samples=r.get("scored_samples"),
                   coverage=r.get("coverage"), error=r.get("error"), magnetometer=bool(r.get("magnetometer", False)),
                   protocol=r.get("protocol"), truth=r.get("truth"), traceback=r.get("traceback"),
                   not_scored=r.get("not_scored"), fault=r.get("fault"))


def default_protocol(recording: Recording) -> str:
    """"broad" for recordings that carry a movement mask (BROAD trials), else "full"."""
    return "broad" if recording.movement is not None else "full"


# Why a recording was not scored (`Result.not_scored` starts with one of these). The reasons are facts
# about the data, not failures: such a recording costs only itself.
UNREADABLE = "cannot be read"  # its files: the loader's one line (no estimator ran)
NO_TRUTH = "no truth"  # the file holds none (a course test recording, a static RepoIMU file)
TRUTH_UNUSABLE = "truth unusable"  # `fusion.format_checks.usable_truth`, `overlap_problem`
ALIGNMENT_UNDETERMINED = "alignment undetermined"  # `fusion.evaluation.scoring.align.fit_alignment` raised
ALIGNMENT_POOR = "alignment poor"  # `fusion.evaluation.scoring.align.Alignment.problem`
NOT_SCORED = (UNREADABLE, NO_TRUTH, TRUTH_UNUSABLE, ALIGNMENT_UNDETERMINED, ALIGNMENT_POOR)


@dataclass(frozen=True)
class Unreadable:
    """A recording whose files could not be read: its id and why (the loader's one line, naming the
    file). Its jobs become rows `unreadable_row`, not failures."""

    id: str
    why: str


def unreadable_row(recording: Unreadable, label: str) -> Result:
    """The row of an estimator on a recording that could not be read: not run, not scored."""
    return Result(recording.id, label, 0, 0.0, None, None, not_scored=f"{UNREADABLE}: {recording.why}")


def no_truth_reason(recording: Recording) -> str:
    """Why a recording without truth is not scored: its `truth_problem`, or that its file holds none."""
    return recording.truth_problem or f"{NO_TRUTH} (its files hold none)"


def without_truth(recording: Recording, why: str) -> Recording:
    """The recording with its truth set aside, `why` (one line) recorded as its `truth_problem`: its
    estimators still run (from the accelerometer's tilt), unscored."""
    return replace(recording, truth=None, truth_problem=why)


def recording_alignment(recording: Recording) -> Alignment | None:
    """The recording's alignment (`fusion.evaluation.scoring.align.fit_alignment`), None without truth; errors
    name the recording."""
    if recording.truth is None:
        return None
    try:
        return fit_alignment(recording.imu, recording.truth)
    except ValueError as exc:
        raise ValueError(f"{recording.id}: {ALIGNMENT_UNDETERMINED}: {exc}") from None


def aligns(recording: Recording, align: bool) -> bool:
    """Whether the recording is scored through an alignment: `--align` asked for it, or its truth is in
    frames of its own (`Recording.truth_needs_alignment`)."""
    return align or recording.truth_needs_alignment


def checked_alignment(recording: Recording) -> tuple[Alignment | None, str | None]:
    """The recording's alignment and, when the recording cannot be scored through it, why (one line
    starting "alignment undetermined" or "alignment poor", `Alignment.problem`); `(None, None)`
    without truth."""
    if recording.truth is None:
        return None, None
    try:
        alignment = fit_alignment(recording.imu, recording.truth)
    except ValueError as exc:
        return None, f"{ALIGNMENT_UNDETERMINED}: {' '.join(str(exc).split())}"
    problem = alignment.problem()
    return alignment, f"{ALIGNMENT_POOR}: {problem}" if problem else None


def aligned(recording: Recording, alignment: Alignment | None) -> Recording:
    """The recording with its truth mapped into our frames, `A R_truth B` (a new `Recording`)."""
    if alignment is None or recording.truth is None:
        return recording
    return replace(recording, truth=alignment.apply(recording.truth))


class EstimatorError(ValueError):
    """An estimator's failure: one line naming the recording, the estimator, what it raised and
    where (str), and for a user's code the traceback of its own frames (`traceback`, or None)."""

    def __init__(self, message: str, traceback: str | None = None) -> None:
        super().__init__(message)
        self.traceback = traceback


TRACEBACK_NOTE = "its traceback: --verbose, or the row's \"traceback\" in results.json (--out or --json)"


class _Signals:
    """While an estimator runs in the main thread: notes whether SIGINT or SIGTERM really arrived,
    so that a KeyboardInterrupt the estimator's code raises itself is told from the user's Ctrl-C
    (a real signal still stops the run: the previous handler is called as before). Off the main
    thread, or where the signal is ignored or left to its default (a pool worker), nothing is
    installed: a KeyboardInterrupt there can only be the code's own."""

    def __init__(self) -> None:
        self.arrived = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> "_Signals":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous = signal.getsignal(sig)
                if callable(previous):
                    self._previous[sig] = previous
                    signal.signal(sig, self._note)
        return self

    def _note(self, signum: int, frame: Any) -> None:
        self.arrived = True
        self._previous[signum](signum, frame)

    def __exit__(self, *exc: Any) -> bool:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        return False


_WARMED: set[tuple] = set()  # (estimator class, parameters, sensors) already run once in this process
WARM_UP_SAMPLES = 200
WARMED_MODULES = ("fusion.estimators.",)  # the estimators warmed up: the toolkit's own (their modules' prefix)


def warm_up(entry: ResolvedSpec, recording: Recording, q0: np.ndarray) -> None:
    """Run one of our estimators once, untimed, on the first `WARM_UP_SAMPLES` samples of the
    recording, the first time this process meets it (per parameters and sensors): numba compiles
    (or loads from its cache) every kernel on its first call with given argument types, and
    the kernels the filters' constructors do not load themselves would otherwise be compiled
    inside the timed estimate (the first row's us/sample 100 times the second's). The results
    do not change: a fresh estimator is built for the timed run. Only the toolkit's own
    estimators (`WARMED_MODULES`) are warmed up: other code (a user's, a test's) may have effects
    of its own; nor are trajectory files."""
    if entry.user or len(recording.imu) < 2 or not entry.cls.__module__.startswith(WARMED_MODULES):
        return
    key = (entry.cls, repr(entry.params), recording.imu.has_mag, recording.imu.gyr_timing)
    if key in _WARMED:
        return
    _WARMED.add(key)
    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            entry.build().for_recording(recording.id).estimate(recording.imu.window(0, WARM_UP_SAMPLES), q0)
    except Exception:  # a recording too short for it, say: the timed run reports what matters
        pass


def _build(entry: ResolvedSpec) -> Any:
    """A fresh estimator of the spec; a trajectory file's knows its row's name (the file an --out
    folder holds for it: `fusion.estimators.adapters.trajectory_file`)."""
    if entry.cls is TrajectoryFile and not entry.params.name:
        return TrajectoryFile(replace(entry.params, name=entry.label))
    return entry.build()


def _failure(where: str, exc: BaseException, entry: ResolvedSpec) -> EstimatorError:
    """An exception an estimator raised, as one line: what, and where in the user's code (the
    innermost frame of it; the traceback of its frames goes with the error)."""
    site, trace = user.failure_site(exc, entry.origin)
    at = f" at {site}" if site else ""
    if isinstance(exc, SystemExit):
        what = (f"raised SystemExit({exc.code!r}) (what sys.exit does){at}: an estimator returns its orientations "
                "or raises an exception, it does not end the process")
    elif isinstance(exc, KeyboardInterrupt):
        what = f"raised KeyboardInterrupt{at} (its own code, not a Ctrl-C)"
    else:
        what = f"raised {type(exc).__name__}: {' '.join(str(exc).split())[:300]}{at}"
    return EstimatorError(f"{where} {what}" + (f"; {TRACEBACK_NOTE}" if trace else ""), trace)


def run_one(recording: Recording, spec: ResolvedSpec | EstimatorSpec | str, init: str | None = None,
            protocol: str | None = None, align: bool | Alignment | None = False, repeat: int = 1) -> Result:
    """One job: estimate, time, score (`protocol` None: the recording's default). Raises ValueError
    (naming the recording and the estimator; an `EstimatorError` with the user's traceback when a
    user's code raised) when the estimator fails.

    spec: a resolved spec (`fusion.estimators.resolve`), a spec, or its text (`"ukf:R=1e-3"`).
    align: score against the truth mapped into our frames (`fusion.evaluation.scoring.align`): True fits the
        recording's alignment here (`checked_alignment`: one it cannot be scored through leaves the
        row unscored, saying why), as False does for a recording whose truth is in frames of its own
        (`Recording.truth_needs_alignment`); an `Alignment` (fitted once per recording by the caller)
        is used as given. The initial orientation then comes from the aligned truth (`init` None or
        "truth"), so every estimator starts in our frames.

    Whatever the estimator raises ends this job only: an exception, and also SystemExit
    (`sys.exit` in its code) and a KeyboardInterrupt its code raises itself, become the
    ValueError; a real Ctrl-C (SIGINT) or SIGTERM while it runs still stops the caller.
    The time is that of `estimate` alone: our estimators are warmed up first (`warm_up`). With
    `repeat`, the estimate is run that many times, each from a fresh estimator, and the time is the
    least of theirs (Python's timeit documentation, `Timer.repeat`: the others add what else the
    machine was doing); the trajectory is the last run's.
    """
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    entry = spec if isinstance(spec, ResolvedSpec) else resolve(spec)
    alignment = align if isinstance(align, Alignment) else None
    if alignment is None and aligns(recording, bool(align)):
        alignment, problem = checked_alignment(recording)
        if problem:
            recording = without_truth(recording, problem)
    recording = aligned(recording, alignment)
    q0 = initial_orientation(recording, init)
    warm_up(entry, recording, q0)
    # Parameters far outside their range (`ekf:Q=1e308`, `gn:R=1e-300`) overflow inside a filter:
    # numpy's floating-point warnings are silenced here and the result judged by its finiteness,
    # and a numerical exception becomes one line naming the estimator and the recording.
    where = f"{recording.id}: estimator {entry.label!r}"
    signals = _Signals()
    try:
        with signals, np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"), \
                warnings.catch_warnings(record=True) if entry.user else contextlib.nullcontext([]) as caught:
            if entry.user:
                warnings.simplefilter("always")
            seconds = float("inf")
            for _ in range(repeat):
                estimator = _build(entry).for_recording(recording.id)
                start = time.perf_counter()
                trajectory = estimator.estimate(recording.imu, q0)
                seconds = min(seconds, time.perf_counter() - start)
            if entry.user and not entry.cls.partial:  # a user's estimator's output is checked (`fusion.estimators.adapters.user`)
                trajectory = Trajectory(trajectory.t, user.check_output(trajectory.quat_wxyz, len(recording.imu)),
                                        trajectory.diagnostics)
    except KeyboardInterrupt as exc:  # Terminated (SIGTERM) included
        if signals.arrived:
            raise  # the user's Ctrl-C (or a SIGTERM): the run stops
        raise _failure(where, exc, entry) from None
    except SystemExit as exc:
        raise _failure(where, exc, entry) from None
    except (ArithmeticError, np.linalg.LinAlgError) as exc:
        if user.failure_site(exc, entry.origin)[0]:  # raised in the user's code: where
            raise _failure(where, exc, entry) from None
        raise ValueError(f"{where} failed numerically ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]}); check its parameter values") from None
    except ValueError as exc:
        if not entry.user:
            raise
        if user.failure_site(exc, entry.origin)[0]:  # the user's own ValueError, not our check of its output
            raise _failure(where, exc, entry) from None
        raise ValueError(f"{where}: {' '.join(str(exc).split())[:300]}") from None
    except Exception as exc:
        if not entry.user:
            raise
        raise _failure(where, exc, entry) from None
    for warning in caught:  # a user's estimator's warnings, named: which estimator, which recording
        if issubclass(warning.category, ResourceWarning):
            continue  # the garbage collector's, about whatever it collected then (ignored by Python's defaults too)
        warnings.warn_explicit(f"{where}: {warning.message}", warning.category, warning.filename, warning.lineno)
    if not entry.cls.partial and not np.all(np.isfinite(trajectory.quat_wxyz)):
        raise ValueError(f"{where} produced non-finite orientations (diverged or overflowed; check its parameter "
                         "values)")
    protocol = protocol or default_protocol(recording)
    nine_d = (bool(trajectory.diagnostics.get("magnetometer", False)) if entry.cls.partial and trajectory.diagnostics
              else bool(entry.cls.magnetometer and recording.imu.has_mag))
    result_score = None
    if recording.truth is not None:
        try:
            result_score = score(recording.truth, trajectory, protocol, recording.movement, partial=entry.cls.partial,
                                 nine_d=nine_d)
        except ValueError as exc:
            raise ValueError(f"{recording.id}, {entry.label}: {exc}") from None
        if entry.user:
            slip = user.convention_slip(
                result_score.rmse_deg["total"],
                lambda q: score(recording.truth, Trajectory(trajectory.t, q), protocol, recording.movement,
                                partial=entry.cls.partial, nine_d=nine_d).rmse_deg["total"],
                trajectory.quat_wxyz)
            if slip:
                raise ValueError(f"{where}: {slip}")
    return Result(
        recording.id, entry.label, len(recording.imu), seconds,
        result_score.rmse_deg if result_score else None,
        result_score.max_deg if result_score else None,
        trajectory, result_score, alignment=alignment.to_json() if alignment else None,
        scored_samples=result_score.samples if result_score else None,
        coverage=result_score.coverage if result_score else None, magnetometer=nine_d,
        protocol=protocol if result_score else None, truth=truth_system(recording) if result_score else None,
        not_scored=None if result_score else no_truth_reason(recording),
    )


# What a recording's truth is, by its format (`fusion.formats`), for captions and notes: "the error
# against VICON" is wrong for BROAD, whose truth is another optical system.
TRUTH_SYSTEMS = {"course": "VICON", "broad": "optical motion capture (BROAD)", "sim": "simulated truth"}
GENERIC_TRUTH = "ground truth"


def truth_system(recording: Any, kind: str | None = None) -> str:
    """What the truth of a recording (a `Recording` or a dataset `Source`) is, for text:
    `TRUTH_SYSTEMS` by its format (`kind`, a `Source`'s own when not given), else "ground truth".
    A loaded `Recording` carries no format: the course board's raw counts say VICON, an id in a
    `broad` folder BROAD, `sim` the simulation."""
    kind = kind or getattr(recording, "kind", None)
    if kind is None:
        from fusion.datasets import SIM_ID

        rid = str(getattr(recording, "id", ""))
        kind = ("sim" if rid == SIM_ID else "course" if getattr(recording, "raw", None) is not None
                else "broad" if rid.split("/")[0] == "broad" else None)
    return TRUTH_SYSTEMS.get(kind, GENERIC_TRUTH)


@dataclass(frozen=True)
class Job:
    """One recording x one estimator of a run, and what to return.

    recording, estimator: indices into the run's recordings and resolved specs.
    settings: the run's `fusion.evaluation.run.settings.RunSettings`; a job reads what decides its row
        (init, protocol, align, repeat; panorama: also stitch and score a panorama
        (`fusion.evaluation.panorama.recording`) with the scenes under data_dir, which the runner resolves).
    series: also return the job's plot data (`fusion.evaluation.run.series.job_part`), and with
        `with_recording` its recording's (`series.recording_part`).
    keep: return the whole `Result` (trajectory and per-sample errors) instead of its summary.
    truth: what the recording's truth is (`truth_system` of its `Source`), for the row; None: from
        the loaded recording.
    fault: a `fusion.faults.Fault` the recording is run under (`fusion stress`; the runner applies it
        to the loaded recording, `fusion.faults.apply`, and the row records it), or None: as loaded.
    """

    recording: int
    estimator: int
    settings: RunSettings = RunSettings()
    series: bool = False
    with_recording: bool = False
    keep: bool = False
    truth: str | None = None
    fault: Any = None


@dataclass(frozen=True, eq=False)
class JobOutput:
    """What a job sends back: its row, its plot data when asked (None otherwise), and the warnings
    it raised (their texts, each once), which the process that runs the run shows: a worker's
    stderr is not always the user's (a Dask worker's never is)."""

    result: Result
    part: dict[str, np.ndarray] | None = None
    recording_part: dict[str, np.ndarray] | None = None
    warnings: tuple[str, ...] = ()

    def after(self, earlier: tuple[str, ...]) -> "JobOutput":
        """The output with `earlier` warnings (its recording's loader's) before its own."""
        return replace(self, warnings=tuple(dict.fromkeys(earlier + self.warnings))) if earlier else self


def run_job(job: Job, rec: Recording | Unreadable, entry: ResolvedSpec, alignment: Alignment | None,
            truth_at_imu: Any = None, problem: str | None = None) -> JobOutput:
    """`run_one` as a run's job: a failure becomes a row with its `error` (one line naming the
    estimator and the recording) instead of an exception; the row is a summary unless `job.keep`;
    the warnings raised are returned (`JobOutput.warnings`), not shown. A recording that could not be
    read (`Unreadable`) gives its row (`unreadable_row`) without running anything.

    truth_at_imu: a callable giving the truth on the IMU stamps (for a filter's consistency plot
        data; the caller keeps it once per recording), or None.
    problem: why the recording cannot be scored through its `alignment` (`checked_alignment`): its
        truth is set aside and the estimator runs unscored; None otherwise.
    With `job.fault`, `rec` is the recording under that fault (the runner applies it), and the row
    records the fault (`Result.fault`).
    """
    output = _run_job(job, rec, entry, alignment, truth_at_imu, problem)
    if job.fault is None:
        return output
    return replace(output, result=replace(output.result, fault=job.fault.to_json()))


def _run_job(job: Job, rec: Recording | Unreadable, entry: ResolvedSpec, alignment: Alignment | None,
             truth_at_imu: Any = None, problem: str | None = None) -> JobOutput:
    from . import series

    if isinstance(rec, Unreadable):
        return JobOutput(unreadable_row(rec, entry.label))
    if problem:
        rec, truth_at_imu = without_truth(rec, problem), None
    with warnings.catch_warnings(record=True) as caught:  # shown by the process that runs the run
        warnings.simplefilter("always")
        shown = aligned(rec, alignment)
        recording_part = series.recording_part(shown, truth_at_imu) if job.series and job.with_recording else None
        try:
            s = job.settings
            result = run_one(rec, entry, s.init, s.protocol, alignment, s.repeat)
            if s.panorama:
                from ..panorama.recording import panorama_scores

                result = replace(result, panorama=panorama_scores(shown, result.trajectory, data_dir=s.data_dir))
            if job.truth and result.truth:
                result = replace(result, truth=job.truth)
            part = series.job_part(result.trajectory, result.score, truth_at_imu) if job.series else None
            output = JobOutput(result if job.keep else result.summary(), part, recording_part)
        except ValueError as exc:  # run_one's messages name the recording and the estimator
            output = JobOutput(failed(rec.id, entry.label, len(rec.imu), str(exc), getattr(exc, "traceback", None)),
                               None, recording_part)
        except Exception as exc:  # an estimator's own bug outside `estimate`: a row, not an abort
            output = JobOutput(failed(rec.id, entry.label, len(rec.imu),
                                      f"{rec.id}: estimator {entry.label!r} raised {type(exc).__name__}: "
                                      f"{' '.join(str(exc).split())[:300]}"), None, recording_part)
    return replace(output, warnings=tuple(dict.fromkeys(str(w.message) for w in caught)))


def failed(dataset: str, label: str, samples: int, message: str, traceback: str | None = None) -> Result:
    """The row of a job that failed: no scores, its error (and the user's traceback, if any)."""
    return Result(dataset, label, samples, 0.0, None, None, error=message, traceback=traceback)


def warn_low_coverage(results: list[Result]) -> None:
    """One warning per row scored on less than `MIN_COVERAGE` of its recording."""
    for r in results:
        if r.low_coverage:
            warnings.warn(f"{r.dataset}, {r.estimator}: scored on {r.scored_samples} of the recording's samples "
                          f"({100 * r.coverage:.2g}% < {MIN_COVERAGE:.0%}: the truth covers too little of it); "
                          "flagged and left out of the means", stacklevel=2)
