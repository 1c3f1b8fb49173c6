"""One job: one recording x one estimator spec, estimated, timed and scored, and the `Result`
it gives. The layer below `fusion.evaluation.runner` (which schedules jobs) and
`fusion.evaluation.compare` (which runs them and formats their tables).

    from fusion import datasets
    from fusion.evaluation.job import run_one
    result = run_one(datasets.load("sim"), "ukf:R=1e-3")
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace
from typing import Any, Iterable

import numpy as np

from fusion import estimators
from fusion.estimators.base import Estimator
from fusion.estimators.params import EstimatorSpec, make_params, parse_specs
from fusion.datasets import initial_orientation
from fusion.types import Recording, Trajectory

from .align import Alignment, fit_alignment
from .metrics import MIN_COVERAGE, Score, score


@dataclass(frozen=True, eq=False)
class Result:
    """One recording x estimator. `rmse_deg`/`max_deg` are None without ground truth.

    scored_samples, coverage: how many samples were scored and their fraction of what the
    protocol scores (`fusion.evaluation.metrics.Score.coverage`); None without ground truth (or
    from an older results.json). Below `MIN_COVERAGE` the row is flagged and left out of means.
    """

    dataset: str
    estimator: str
    samples: int
    seconds: float
    rmse_deg: dict[str, float] | None
    max_deg: dict[str, float] | None
    trajectory: Trajectory | None = None
    score: Score | None = None
    panorama: dict[str, float] | None = None  # with --panorama: `fusion.evaluation.panorama.panorama_scores`
    alignment: dict[str, Any] | None = None  # with --align: the recording's `fusion.evaluation.align.Alignment.to_json`
    scored_samples: int | None = None
    coverage: float | None = None

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

    def to_json(self) -> dict[str, Any]:
        """The row of `results.json` (the keys are a documented format: see README; `panorama`
        only with `--panorama`; `alignment` null unless the row was scored with `--align`)."""
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
        }
        if self.panorama is not None:
            row["panorama"] = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in self.panorama.items()}
        return row


def as_specs(specs: Iterable[EstimatorSpec | str] | str) -> list[EstimatorSpec]:
    """Estimator specs from specs or spec texts (`["dr", "ukf:R=1e-3,Q=1e-5"]`, or one text)."""
    if isinstance(specs, str):
        specs = [specs]
    out: list[EstimatorSpec] = []
    for spec in specs:
        out.extend(parse_specs(spec) if isinstance(spec, str) else [spec])
    return out


def expand_all(specs: list[EstimatorSpec]) -> list[EstimatorSpec]:
    """Replace the name `all` with every registered estimator (registry order).

    `all` leaves out peers whose optional library is not installed (with a warning);
    naming such a peer explicitly is an error that says what to install.
    """
    out: list[EstimatorSpec] = []
    for spec in specs:
        if spec.name != "all":
            out.append(spec)
            continue
        missing = []
        for name in estimators.ESTIMATORS:
            try:
                estimators.build(EstimatorSpec(name))
            except ImportError:
                missing.append(name)
                continue
            out.append(EstimatorSpec(name, spec.overrides))
        if missing:
            warnings.warn(f"'all' leaves out {', '.join(missing)}: optional packages not installed "
                          f"(pip install -e '.[peers]')", stacklevel=2)
    return out


def default_protocol(recording: Recording) -> str:
    """"broad" for recordings that carry a movement mask (BROAD trials), else "full"."""
    return "broad" if recording.movement is not None else "full"


def recording_alignment(recording: Recording) -> Alignment | None:
    """The recording's alignment (`fusion.evaluation.align.fit_alignment`), None without truth; errors
    name the recording."""
    if recording.truth is None:
        return None
    try:
        return fit_alignment(recording.imu, recording.truth)
    except ValueError as exc:
        raise ValueError(f"{recording.id}: {exc}") from None


def aligned(recording: Recording, alignment: Alignment | None) -> Recording:
    """The recording with its truth mapped into our frames, `A R_truth B` (a new `Recording`)."""
    if alignment is None or recording.truth is None:
        return recording
    return replace(recording, truth=alignment.apply(recording.truth))


def resolve(spec: EstimatorSpec | str) -> type[Estimator]:
    """The estimator class a spec names, from the registry `fusion.estimators.ESTIMATORS`; the spec
    is built once here, so a bad name or parameter is an error before any work."""
    if isinstance(spec, str):
        (spec,) = parse_specs(spec)
    estimators.build(spec)
    return estimators.ESTIMATORS[spec.name]


def build(spec: EstimatorSpec, estimator_class: type[Estimator] | None = None) -> Estimator:
    """A fresh estimator for `spec`: of `estimator_class` when given (resolved by the caller,
    `resolve`; a worker process then never looks the name up), else from the registry."""
    if estimator_class is None:
        return estimators.build(spec)
    return estimator_class(make_params(estimator_class.Params, spec.overrides, owner=spec.name))


def run_one(recording: Recording, spec: EstimatorSpec | str, init: str | None = None, protocol: str | None = None,
            align: bool | Alignment | None = False, estimator_class: type[Estimator] | None = None) -> Result:
    """One job: estimate, time, score (`protocol` None: the recording's default).

    spec: an estimator spec or its text (`"ukf:R=1e-3"`).
    estimator_class: the class `spec` names, when the caller resolved it (`resolve`); None looks it
        up in the registry.
    align: score against the truth mapped into our frames (`fusion.evaluation.align`): True fits the
        recording's alignment here; an `Alignment` (fitted once per recording by the caller)
        is used as given. The initial orientation then comes from the aligned truth
        (`init` None or "truth"), so every estimator starts in our frames.
    """
    if isinstance(spec, str):
        (spec,) = parse_specs(spec)
    alignment = None
    if isinstance(align, Alignment):
        alignment = align
    elif align:
        alignment = recording_alignment(recording)
    recording = aligned(recording, alignment)
    estimator = build(spec, estimator_class)
    q0 = initial_orientation(recording, init)
    start = time.perf_counter()
    # Parameters far outside their range (`ekf:Q=1e308`, `gn:sa=1e-300`) overflow inside a filter:
    # numpy's floating-point warnings are silenced here and the result judged by its finiteness,
    # and a numerical exception becomes one line naming the estimator and the recording.
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
            trajectory = estimator.estimate(recording.imu, q0)
    except (ArithmeticError, np.linalg.LinAlgError) as exc:
        raise ValueError(f"{recording.id}: estimator {spec.label!r} failed numerically ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]}); check its parameter values") from None
    seconds = time.perf_counter() - start
    if not np.all(np.isfinite(trajectory.quat_wxyz)):
        raise ValueError(f"{recording.id}: estimator {spec.label!r} produced non-finite orientations "
                         "(diverged or overflowed; check its parameter values)")
    protocol = protocol or default_protocol(recording)
    result_score = None
    if recording.truth is not None:
        try:
            result_score = score(recording.truth, trajectory, protocol, recording.movement)
        except ValueError as exc:
            raise ValueError(f"{recording.id}, {spec.label}: {exc}") from None
    return Result(
        recording.id, spec.label, len(recording.imu), seconds,
        result_score.rmse_deg if result_score else None,
        result_score.max_deg if result_score else None,
        trajectory, result_score, alignment=alignment.to_json() if alignment else None,
        scored_samples=result_score.samples if result_score else None,
        coverage=result_score.coverage if result_score else None,
    )


def warn_low_coverage(results: list[Result]) -> None:
    """One warning per row scored on less than `MIN_COVERAGE` of its recording."""
    for r in results:
        if r.low_coverage:
            warnings.warn(f"{r.dataset}, {r.estimator}: scored on {r.scored_samples} of the recording's samples "
                          f"({100 * r.coverage:.2g}% < {MIN_COVERAGE:.0%}: the truth covers too little of it); "
                          "flagged and left out of the means", stacklevel=2)
