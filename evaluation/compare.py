"""Run estimators over recordings and score them: the library behind `fusion compare`.

    from fusion.evaluation.compare import compare
    results = compare(["dr", "ukf:R=1e-3"], [fusion.datasets.load("ece276a/1")])

Every (recording, estimator) pair is one job: build the estimator from its spec, time
`estimate` on the recording's calibrated samples from the shared initial orientation, score
it against the truth when there is one. Results come back in a stable order: recordings as
given, estimators as given within each recording.
"""
from __future__ import annotations

import platform
import time
import warnings
from dataclasses import dataclass, replace
from typing import Any, Iterable

import numpy as np

from fusion import estimators
from fusion.estimators.params import EstimatorSpec, parse_specs
from fusion.datasets import initial_orientation
from fusion.types import Recording, Trajectory

from .align import Alignment, fit_alignment
from .metrics import KINDS, MIN_COVERAGE, Score, score


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


def _as_specs(specs: Iterable[EstimatorSpec | str]) -> list[EstimatorSpec]:
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


def run_one(recording: Recording, spec: EstimatorSpec, init: str | None = None, protocol: str | None = None,
            align: bool | Alignment | None = False) -> Result:
    """One job: estimate, time, score (`protocol` None: the recording's default).

    align: score against the truth mapped into our frames (`fusion.evaluation.align`): True fits the
        recording's alignment here; an `Alignment` (fitted once per recording by the caller)
        is used as given. The initial orientation then comes from the aligned truth
        (`init` None or "truth"), so every estimator starts in our frames.
    """
    alignment = None
    if isinstance(align, Alignment):
        alignment = align
    elif align:
        alignment = recording_alignment(recording)
    recording = aligned(recording, alignment)
    estimator = estimators.build(spec)
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


def compare(specs: Iterable[EstimatorSpec | str], recordings: Iterable[Recording], init: str | None = None,
            progress: bool = False, protocol: str | None = None, jobs: int | None = 1,
            align: bool = False) -> list[Result]:
    """Every estimator on every recording, in a stable order (recording-major).

    specs: estimator specs or spec texts (`"ukf:R=1e-3"`, `"all"`).
    recordings: loaded `Recording`s, or dataset `Source`s (loaded once per worker).
    init: `truth`, `accel`, `identity`, or None for each recording's default.
    progress: show a progress bar on stderr.
    protocol: scoring protocol, "full" or "broad" (`fusion.evaluation.metrics`), or None for each
        recording's default (`default_protocol`).
    jobs: worker processes (None or 0: all cores); the results do not depend on it
        (see `fusion.evaluation.runner`).
    align: score against the truth mapped into our frames by constant world and body rotations
        fitted once per recording from its IMU and truth (`fusion.evaluation.align`), the same for
        every estimator; each result's `alignment` holds them.
    """
    from .runner import run

    results, _ = run(expand_all(_as_specs(specs)), list(recordings), init, jobs=jobs, progress=progress,
                     protocol=protocol, align=align)
    return results


def versions() -> dict[str, str]:
    """Versions of Python and the packages that shape the numbers."""
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for package in ("fusion", "numpy", "scipy", "filterpy", "vqf", "ahrs", "imufusion"):
        try:
            out[package] = md.version(package)
        except md.PackageNotFoundError:
            out[package] = "not installed"
    return out


def recording_alignments(results: list[Result]) -> list[dict[str, Any]]:
    """One entry per recording of an `--align` run: `{"dataset": id, **alignment}`, in run order."""
    out: dict[str, dict[str, Any]] = {}
    for r in results:
        if r.alignment and r.dataset not in out:
            out[r.dataset] = {"dataset": r.dataset, **r.alignment}
    return list(out.values())


def results_json(results: list[Result], settings: dict[str, Any]) -> dict[str, Any]:
    """The document `--json` writes: `results`, `alignments` (one per recording, empty without
    `--align`), `settings`, `versions`."""
    return {"results": [r.to_json() for r in results], "alignments": recording_alignments(results),
            "settings": settings, "versions": versions()}


ALIGN_NOTE = ("after --align: truth mapped into our frames as A R_truth B, A = R_ourworld_truthworld and "
              "B = R_truthbody_imubody fitted once per recording from its gyro, accelerometer and truth, "
              "the same for every estimator")


def dataset_group(dataset: str) -> str:
    """The folder a recording id belongs to: "ece276a/3" -> "ece276a", "broad/06_..." -> "broad";
    "other" for ids without one (`sim`, files at the top of the data directory)."""
    return dataset.rsplit("/", 1)[0] if "/" in dataset else "other"


def summary_groups(results: list[Result]) -> list[tuple[str | None, list[Result]]]:
    """The results split into the groups their means are taken over.

    One group (named None) when every scored recording comes from one folder; else one group
    per folder (`ece276a`, `broad`, ...) in run order: recordings of different sensors, scored
    under different protocols, are never averaged together.
    """
    groups = list(dict.fromkeys(dataset_group(r.dataset) for r in results if r.rmse_deg))
    if len(groups) <= 1:
        return [(None, list(results))]
    return [(g, [r for r in results if dataset_group(r.dataset) == g]) for g in groups]


def format_table(results: list[Result], align: bool | None = None) -> str:
    """A readable table: first a mean row per estimator over the recordings that have ground
    truth (per folder when they come from several, see `summary_groups`), then one row per recording x estimator (RMSE in degrees), recordings without ground
    truth last; with alignment, the fitted rotations after it.

    align: whether the run used `--align` (None: whether any result carries an alignment).
    """
    if align is None:
        align = any(r.alignment for r in results)
    header = ["dataset", "estimator", "total", "inclination", "heading", "coverage", "us/sample"]
    rows = []
    for r in results:
        rmse = [f"{r.rmse_deg[k]:.2f}" for k in KINDS] if r.rmse_deg else ["-"] * 3
        rows.append([r.dataset, r.estimator, *rmse, format_coverage(r), f"{r.us_per_sample:.1f}"])
    labels = list(dict.fromkeys(r.estimator for r in results))
    means = []
    if len({r.dataset for r in results}) >= 2:
        for group, members in summary_groups(results):
            for label in labels:
                mine = [r for r in members if r.estimator == label]
                scored = [r for r in mine if r.in_means]
                if not mine:
                    continue
                mean = [f"{np.mean([r.rmse_deg[k] for r in scored]):.2f}" for k in KINDS] if scored else ["-"] * 3
                us = np.mean([r.us_per_sample for r in mine])
                name = f"mean ({len(scored)})" if group is None else f"mean {group} ({len(scored)})"
                means.append([name, label, *mean, "", f"{us:.1f}"])
    if any(r.panorama for r in results):
        header += ["pano PSNR dB", "SSIM"]
        for row, r in zip(rows, results):
            p = r.panorama or {}
            row += [f"{p.get('psnr_db', float('nan')):.2f}", f"{p.get('ssim', float('nan')):.3f}"]
        means = [row + ["", ""] for row in means]
    widths = [max(len(str(row[i])) for row in [header, *rows, *means]) for i in range(len(header))]

    def line(row: list[str]) -> str:
        return "  ".join(str(c).ljust(w) if i < 2 else str(c).rjust(w) for i, (c, w) in enumerate(zip(row, widths)))

    out = ["RMSE in degrees (total = geodesic angle; inclination = gravity direction; heading = twist about world z); "
           + (ALIGN_NOTE if align else "no alignment"),
           line(header), line(["-" * w for w in widths])]
    scored_rows = [row for row, r in zip(rows, results) if r.rmse_deg]
    unscored_rows = [row for row, r in zip(rows, results) if not r.rmse_deg]
    if means:
        out += [line(r) for r in means]
        out.append(line(["-" * w for w in widths]))
    out += [line(r) for r in scored_rows]
    if unscored_rows:
        if scored_rows or means:
            out += [f"without ground truth (not scored): {len({r.dataset for r in results if not r.rmse_deg})} recordings"]
        out += [line(r) for r in unscored_rows]
    if any(r.low_coverage for r in results):
        out += [LOW_COVERAGE_NOTE]
    if any(r.alignment for r in results):
        out += ["", format_alignments(results)]
    return "\n".join(out)


LOW_COVERAGE_NOTE = (f"LOW: scored on less than {MIN_COVERAGE:.0%} of the recording (the truth covers too little of it); "
                     "left out of the means")


def format_coverage(r: Result) -> str:
    """`98.5%` (scored samples / samples the protocol scores), `0.0% LOW` below `MIN_COVERAGE`, `-` without."""
    if r.coverage is None:
        return "-"
    return f"{100 * r.coverage:.1f}%" + (" LOW" if r.low_coverage else "")


def warn_low_coverage(results: list[Result]) -> None:
    """One warning per row scored on less than `MIN_COVERAGE` of its recording."""
    for r in results:
        if r.low_coverage:
            warnings.warn(f"{r.dataset}, {r.estimator}: scored on {r.scored_samples} of the recording's samples "
                          f"({100 * r.coverage:.2g}% < {MIN_COVERAGE:.0%}: the truth covers too little of it); "
                          "flagged and left out of the means", stacklevel=2)


def format_alignments(results: list[Result]) -> str:
    """The fitted rotations of an `--align` run, one row per recording: rotation vectors
    (axis * angle) and angles, deg, and the fit's diagnostics."""
    header = ["dataset", "world A (x, y, z)", "|A|", "body B (x, y, z)", "|B|", "rate pairs", "residual deg/s",
              "|g| g"]
    rows = []
    for a in recording_alignments(results):
        w, b = a["world_deg"], a["body_deg"]
        rows.append([a["dataset"], " ".join(f"{x:+7.2f}" for x in w), f"{np.linalg.norm(w):.2f}",
                     " ".join(f"{x:+7.2f}" for x in b), f"{np.linalg.norm(b):.2f}", str(a.get("rate_pairs", "-")),
                     _maybe(a.get("rate_residual_deg_s"), ".2f"), _maybe(a.get("gravity_g"), ".3f")])
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = ["Alignment per recording, deg (rotation vectors: A = R_ourworld_truthworld, a tilt only; "
             "B = R_truthbody_imubody; truth in our frames = A R_truth B)"]
    lines += ["  ".join(c.ljust(w) if i < 1 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
              for row in [header, ["-" * w for w in widths], *rows]]
    return "\n".join(lines)


def _maybe(value: Any, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)
