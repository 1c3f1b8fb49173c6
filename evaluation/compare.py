"""Run estimators over recordings and score them: the library behind `fusion compare`.

    from evaluation.compare import compare
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

import estimators
from estimators.params import EstimatorSpec, parse_specs
from fusion.datasets import initial_orientation
from fusion.types import Recording, Trajectory

from .align import Alignment, fit_alignment
from .metrics import KINDS, Score, score


@dataclass(frozen=True, eq=False)
class Result:
    """One recording x estimator. `rmse_deg`/`max_deg` are None without ground truth."""

    dataset: str
    estimator: str
    samples: int
    seconds: float
    rmse_deg: dict[str, float] | None
    max_deg: dict[str, float] | None
    trajectory: Trajectory | None = None
    score: Score | None = None
    panorama: dict[str, float] | None = None  # with --panorama: `evaluation.panorama.panorama_scores`
    alignment: dict[str, Any] | None = None  # with --align: the recording's `evaluation.align.Alignment.to_json`

    @property
    def us_per_sample(self) -> float:
        return 1e6 * self.seconds / max(self.samples, 1)

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
    """The recording's alignment (`evaluation.align.fit_alignment`), None without truth; errors
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

    align: score against the truth mapped into our frames (`evaluation.align`): True fits the
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
    trajectory = estimator.estimate(recording.imu, q0)
    seconds = time.perf_counter() - start
    if not np.all(np.isfinite(trajectory.quat_wxyz)):
        raise ValueError(f"{recording.id}: estimator {spec.label!r} produced non-finite orientations")
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
    )


def compare(specs: Iterable[EstimatorSpec | str], recordings: Iterable[Recording], init: str | None = None,
            progress: bool = False, protocol: str | None = None, jobs: int | None = 1,
            align: bool = False) -> list[Result]:
    """Every estimator on every recording, in a stable order (recording-major).

    specs: estimator specs or spec texts (`"ukf:R=1e-3"`, `"all"`).
    recordings: loaded `Recording`s, or dataset `Source`s (loaded once per worker).
    init: `truth`, `accel`, `identity`, or None for each recording's default.
    progress: show a progress bar on stderr.
    protocol: scoring protocol, "full" or "broad" (`evaluation.metrics`), or None for each
        recording's default (`default_protocol`).
    jobs: worker processes (None or 0: all cores); the results do not depend on it
        (see `evaluation.runner`).
    align: score against the truth mapped into our frames by constant world and body rotations
        fitted once per recording from its IMU and truth (`evaluation.align`), the same for
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


def format_table(results: list[Result], align: bool | None = None) -> str:
    """A readable table: one row per recording x estimator, RMSE in degrees, and a mean row
    per estimator over the recordings that have ground truth; with alignment, the fitted
    rotations after it.

    align: whether the run used `--align` (None: whether any result carries an alignment).
    """
    if align is None:
        align = any(r.alignment for r in results)
    header = ["dataset", "estimator", "total", "inclination", "heading", "us/sample"]
    rows = []
    for r in results:
        rmse = [f"{r.rmse_deg[k]:.2f}" for k in KINDS] if r.rmse_deg else ["-"] * 3
        rows.append([r.dataset, r.estimator, *rmse, f"{r.us_per_sample:.1f}"])
    labels = list(dict.fromkeys(r.estimator for r in results))
    means = []
    for label in labels:
        scored = [r for r in results if r.estimator == label and r.rmse_deg]
        mine = [r for r in results if r.estimator == label]
        if len({r.dataset for r in results}) < 2:
            continue
        mean = [f"{np.mean([r.rmse_deg[k] for r in scored]):.2f}" for k in KINDS] if scored else ["-"] * 3
        us = np.mean([r.us_per_sample for r in mine])
        means.append([f"mean ({len(scored)})", label, *mean, f"{us:.1f}"])
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
    out += [line(r) for r in rows]
    if means:
        out.append(line(["-" * w for w in widths]))
        out += [line(r) for r in means]
    if any(r.alignment for r in results):
        out += ["", format_alignments(results)]
    return "\n".join(out)


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
