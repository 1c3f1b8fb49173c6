"""Whole runs, as the `fusion` commands do them: select and load recordings, run, score, and
write what was asked for (a `--json` document, an `--out` folder). The command line
(`fusion.cli`) parses arguments and calls one function of this module per command; from
Python the same run is two lines:

    from fusion.evaluation.runs import run_compare
    run = run_compare("dr,ukf", "sim", jobs=1)

`run.table` is what `fusion compare` prints, `run.results` the rows (`fusion.evaluation.job.Result`),
`run.document` the results document (README, "`--json` format"). Recordings are chosen and loaded
as `fusion.selection` says (`dataset`, `data_dir`, `calibration`, `dropouts`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from fusion import datasets
from fusion.checks import RecordingCheck
from fusion.estimators.params import EstimatorSpec
from fusion.selection import calibration_settings, load_options, load_selected, select_sources

from . import ablate
from .compare import format_table, results_json
from .job import Result, as_specs, expand_all
from .report import OutputFolder, git_commit, write_run
from .runner import describe_specs, run

PathLike = str | os.PathLike


@dataclass(frozen=True, eq=False)
class Run:
    """A finished `run_compare`/`run_ablate`.

    results: one row per recording x estimator, recording-major.
    table: the table `fusion compare` prints (`fusion.evaluation.compare.format_table`).
    document: the results document written to `json_path` and `out` (None when neither was asked for).
    report: the written `report.html` (None without `out`).
    """

    results: list[Result]
    table: str
    document: dict[str, Any] | None = None
    report: Path | None = None


def run_compare(estimators: str | Sequence[str | EstimatorSpec] = "all", dataset: str = "all",
                data_dir: PathLike | None = None, *, init: str | None = None, protocol: str | None = None,
                align: bool = False, dropouts: bool = datasets.DROPOUTS_DEFAULT, calibration: PathLike | None = None,
                jobs: int | None = 1, progress: bool = False, panorama: bool = False,
                json_path: PathLike | None = None, out: PathLike | None = None, command: str | None = None,
                scheduler: str | None = None, scatter: bool | None = None) -> Run:
    """`fusion compare`: every estimator on every recording `dataset` names.

    estimators: spec text (`"dr,ukf:R=1e-3"`, `"all"`) or a list of specs.
    init, protocol, align: as `fusion.evaluation.compare.compare`.
    jobs: worker processes (None or 0: all cores); results do not depend on it.
    scheduler: run the jobs on the dask.distributed cluster at this address instead
        (`tcp://10.0.0.5:8786`); scatter: how its workers get the recordings
        (`fusion.evaluation.runner.run`: False ships paths, True loaded recordings, None decides).
    panorama: also stitch and score a panorama per row (`fusion.evaluation.panorama.panorama_scores`).
    json_path: write the results document there; out: write the report folder there (locked before
        any computation, written through a staging folder: `fusion.evaluation.report.OutputFolder`).
    command: the command line recorded in the document's settings (default: this call).
    """
    text = estimators if isinstance(estimators, str) else ",".join(
        s if isinstance(s, str) else s.label for s in estimators)
    specs = expand_all(as_specs(estimators))
    settings = {"kind": "compare", "estimators": text}
    command = command or f"run_compare({text!r}, {dataset!r})"
    return _execute(specs, settings, dataset, data_dir, command, init=init, protocol=protocol, align=align,
                    dropouts=dropouts, calibration=calibration, jobs=jobs, progress=progress, panorama=panorama,
                    json_path=json_path, out=out, per_recording=True, scheduler=scheduler, scatter=scatter)


def run_ablate(estimator: str | None = None, params: Sequence[str | tuple[str, Sequence[str]]] = (),
               preset: str | None = None, dataset: str = "all", data_dir: PathLike | None = None, *,
               per_recording: bool = False, init: str | None = None, protocol: str | None = None,
               align: bool = False, dropouts: bool = datasets.DROPOUTS_DEFAULT, calibration: PathLike | None = None,
               jobs: int | None = 1, progress: bool = False, json_path: PathLike | None = None,
               out: PathLike | None = None, command: str | None = None, scheduler: str | None = None,
               scatter: bool | None = None) -> Run:
    """`fusion ablate`: one estimator over a grid of parameter values, or a preset
    (`fusion.evaluation.ablate`).

    estimator: the estimator to sweep, possibly with fixed parameters (`"ukf:Q=1e-5"`).
    params: the grid, as `"R=1e-4,1e-3"` texts or `("R", ["1e-4", "1e-3"])` pairs.
    preset: a name in `fusion.evaluation.ablate.PRESETS` (instead of estimator and params).
    per_recording: with `out`, also draw each recording's figures for every setting.
    Other arguments as `run_compare`.
    """
    if bool(preset) == bool(estimator):
        raise ValueError("ablate: give either --preset NAME or --estimator NAME with --param NAME=V1,V2,...")
    if preset:
        if params:
            raise ValueError("ablate: --param applies to --estimator, not to --preset")
        specs = ablate.preset_specs(preset)
        settings = {"kind": "ablate", "preset": preset, "estimators": ",".join(s.label for s in specs)}
    else:
        if not params:
            raise ValueError("ablate: --estimator needs at least one --param NAME=V1,V2,...")
        grid = [ablate.parse_param(p) if isinstance(p, str) else (p[0], list(p[1])) for p in params]
        specs = ablate.grid_specs(estimator, grid)
        settings = {"kind": "ablate", "estimator": estimator, "params": dict(grid),
                    "estimators": ",".join(s.label for s in specs)}
    command = command or f"run_ablate({estimator!r}, {list(params)!r}, {preset!r}, {dataset!r})"
    return _execute(specs, settings, dataset, data_dir, command, init=init, protocol=protocol, align=align,
                    dropouts=dropouts, calibration=calibration, jobs=jobs, progress=progress, panorama=False,
                    json_path=json_path, out=out, per_recording=per_recording, scheduler=scheduler,
                    scatter=scatter)


def _execute(specs: list[EstimatorSpec], settings: dict[str, Any], dataset: str, data_dir: PathLike | None,
             command: str, *, out: PathLike | None, **options: Any) -> Run:
    """Run and write; an `out` folder is taken (locked) before computing."""
    if not out:
        return _execute_in(None, specs, settings, dataset, data_dir, command, **options)
    with OutputFolder(out) as folder:
        return _execute_in(folder, specs, settings, dataset, data_dir, command, **options)


def _execute_in(folder: OutputFolder | None, specs: list[EstimatorSpec], settings: dict[str, Any], dataset: str,
                data_dir: PathLike | None, command: str, *, init: str | None, protocol: str | None, align: bool,
                dropouts: bool, calibration: PathLike | None, jobs: int | None, progress: bool, panorama: bool,
                json_path: PathLike | None, per_recording: bool, scheduler: str | None,
                scatter: bool | None) -> Run:
    sources = select_sources(dataset, data_dir, calibration)
    root = datasets.data_dir_from(data_dir)
    results, infos = run(specs, sources, init, jobs=jobs, progress=progress, load=load_options(calibration, dropouts),
                         panorama_data_dir=str(root) if panorama else None,
                         with_info=folder is not None and per_recording, protocol=protocol, align=align,
                         scheduler=scheduler, scatter=scatter)
    table = format_table(results, align=align)
    sweep = ablate.sweep_summary([r.to_json() for r in results]) if settings.get("kind") == "ablate" else None
    if sweep:
        table += "\n\n" + ablate.format_sweep(sweep)
    if not (json_path or folder):
        return Run(results, table)
    settings = {"command": command, **settings, "dataset": dataset,
                "data_dir": str(root.resolve()),
                "merged": datasets.merged_ids(sources),
                "dropouts": "on" if dropouts else "off",
                "calibration": calibration_settings(calibration),
                "init": init or ("default (the aligned truth where available, else accel)" if align
                                 else "default (truth where available, else accel)"),
                "align": bool(align),
                "protocol": protocol or "default (broad for recordings with a movement mask, else full)",
                "estimator_details": describe_specs(specs),
                "git_commit": git_commit()}
    doc = results_json(results, settings)
    if sweep:
        doc["sweep"] = sweep  # README, "`--json` format"
    if json_path:
        Path(json_path).write_text(json.dumps(doc, indent=2) + "\n")
    report = None
    if folder is not None:
        report = write_run(folder, doc, results, infos, jobs=jobs, progress=progress, per_recording=per_recording)
    return Run(results, table, doc, report)


@dataclass(frozen=True, eq=False)
class Inspection:
    """A finished `run_inspect`: one `fusion.checks.RecordingCheck` per recording, the text
    `fusion inspect` prints, and the figures written (with `out`)."""

    checks: list[RecordingCheck]
    text: str
    figures: list[Path]


def run_inspect(dataset: str = "all", data_dir: PathLike | None = None, *, calibration: PathLike | None = None,
            dropouts: bool = datasets.DROPOUTS_DEFAULT, progress: bool = False, json_path: PathLike | None = None,
            out: PathLike | None = None, command: str | None = None) -> Inspection:
    """`fusion inspect`: the sensor checks of every recording `dataset` names
    (`fusion.checks.check_recording`); json_path: write them as JSON; out: a figure per recording."""
    from fusion.checks import check_recording, format_check

    recordings = load_selected(dataset, data_dir, calibration, dropouts, progress)
    checks = [check_recording(rec) for rec in recordings]
    if json_path:
        doc = {"command": command or f"run_inspect({dataset!r})", "recordings": [c.to_json() for c in checks]}
        Path(json_path).write_text(json.dumps(doc, indent=2) + "\n")
    figures = []
    if out:
        from .inspect_plots import plot_check

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
              command: str | None = None) -> CalibrationRun:
    """`fusion calibrate`: fit per-axis gyro scale factors against the truth (`fusion.gyro_fit`).

    out: the calibration file to write; clock_offset: also store each recording's clock offset.
    leave_one_out: first score `estimators` on each recording with the scales fitted on the
        others (`fusion.evaluation.loo`); align applies to those scores only.
    """
    from fusion import gyro_fit

    recordings = load_selected(dataset, data_dir, calibration, dropouts, progress)
    lines, folds = [], []
    if leave_one_out:
        from .loo import format_folds, leave_one_out as folds_of

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

