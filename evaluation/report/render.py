"""Output folders of `fusion compare --out DIR` / `fusion ablate --out DIR`, and their report.

    DIR/results.json     the document `--json` writes (results, settings, versions)
    DIR/table.txt        the table the command printed
    DIR/command.txt      the exact command, and how to re-render
    DIR/series/NNN.npz   per recording, the time series the figures need (`fusion.evaluation.run.series`)
    DIR/figures/*.png    per recording: Euler angles over the truth, errors, smoother cost, and per
                         filter with a covariance its consistency (`plots.consistency_figure`);
                         summary: RMSE heat maps, accuracy vs speed; ablations: RMSE vs parameter;
                         stress runs: a dose-response figure per fault and the robustness grid
    DIR/report.html      one page, readable offline: the summary figures embedded (base64 PNG), the
                         per-recording ones linked from figures/ and loaded as the reader scrolls
    DIR/report.md        the same for a repository (links to figures/)
    DIR/trajectories/    every estimate and the truth it was scored against, as TUM files (evo)
    DIR/journal.jsonl    every job's row, as the run journalled them (`fusion.evaluation.run.journal`)

Only files the toolkit wrote are ever replaced or removed: they are listed in
`DIR/.fusion-manifest.json`; a run holds `DIR/.fusion.lock` (flock) and writes into a staging
folder that is moved in at the end, results.json last (`fusion.evaluation.run.output.OutputFolder`).

`render(DIR)` (the command `fusion report DIR`) rebuilds table, figures and both reports
from results.json and series/ alone: no estimator runs, and the estimators need not even
be installed. Figures are drawn in a process pool, one job per recording.
"""
from __future__ import annotations

import base64
import html
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from ..compare import (ALIGNMENT_HEADER, IMU_NOTE, LOW_COVERAGE_NOTE, Result, across_datasets, alignment_cells,
                      dataset_group, format_coverage, format_table, heading_offset_note, not_scored_recordings, sensors,
                      shows_imu, summary_groups)
from ..run import series as series_io
from ..run.job import GENERIC_TRUTH, TRUTH_SYSTEMS
from ..run.output import LOCK, MANIFEST, RESULTS, STAGING_PREFIX, OutputFolder, _atomic_text, read_manifest  # noqa: F401
from ..scoring.metrics import KINDS
from ..scoring.stats import Comparison, RunStatistics, dropped_text, run_statistics

# What `render` (`fusion report DIR`) writes afresh; everything else in the folder (results.json,
# series/, trajectories/, journal.jsonl, command.txt, the user's own files) it leaves as it is.
RENDERED = ("table.txt", "report.md", "report.html", "figures/")

# --- writing a run ---

def git_commit() -> str:
    """The commit of the code that ran (with `+dirty` for local changes), or 'unknown'."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                              timeout=5)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=5)
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def write_run(out_dir: "str | Path | OutputFolder", doc: dict[str, Any], series: Iterable[Any] | None = None,
              journal: Any = None, jobs: int | None = 1, progress: bool = False) -> Path:
    """Write results.json, the series and the report of a run; returns report.html's path.

    out_dir: the folder, or an `OutputFolder` already held (`fusion compare --out` takes it
        before computing, so that a second run on the same folder is refused at once).
    doc: the results.json document (`fusion.evaluation.compare.results_json`).
    series: one `fusion.evaluation.run.series.RecordingSeries` per recording, in run order (each is
        written as soon as it is produced, so an iterator keeps one in memory), or None for a run
        without per-recording figures.
    journal: the run's `fusion.evaluation.run.journal.Journal`, committed with the other files.

    Everything is written into a staging folder first and moved in at the end (`OutputFolder`),
    results.json last; files the toolkit did not write are never removed.
    """
    if not isinstance(out_dir, OutputFolder):
        with OutputFolder(out_dir) as folder:
            return write_run(folder, doc, series, journal, jobs, progress)
    folder, stage = out_dir, out_dir.staging
    out = folder.path
    _atomic_text(stage / RESULTS, json.dumps(doc, indent=2) + "\n")
    command = doc.get("settings", {}).get("command", "")
    (stage / "command.txt").write_text(f"{command}\n# re-render the report from this folder without recomputing:\n"
                                       f"fusion report {out}\n")
    if series is not None:
        series_dir = stage / "series"
        series_dir.mkdir(exist_ok=True)
        for n, recording_series in enumerate(series):
            series_io.save(series_dir / f"{n:03d}.npz", recording_series)
    if journal is not None:
        journal.finish(stage)
    _render_into(stage, stage, jobs, progress)
    folder.commit()
    return out / "report.html"


# --- rendering ---

def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=fig.dpi)


def _render_recording(series_path: str, fig_dir: str, truths: dict[str, str] | None = None
                      ) -> tuple[list[tuple[str, str]], list[dict[str, Any]]]:
    """Draw one recording's figures. Returns (caption, file name) pairs of its figures, and one
    entry per filter that reports a covariance for the "Filter consistency" section: dataset,
    estimator, caption, file and the `fusion.evaluation.scoring.consistency.Summary` as a dict.
    truths: what each recording's truth is (`truth_names`), for the captions."""
    import dataclasses

    from ..scoring import consistency
    from . import plots

    s = series_io.load(Path(series_path))
    truth = (truths or {}).get(s.id) or truth_name(s.id)
    stem = f"rec-{Path(series_path).stem}-{plots.slug(s.id)}"
    out = []
    for suffix, make, caption in (
        ("euler", plots.euler_figure, f"Euler angles (ZYX) over the truth ({truth})"),
        ("error", plots.error_figure, "error over time"),
        ("events", plots.event_error_figure, "total error against time around the events (no truth, gyro invalid, "
                                             "rests, freezes, magnetic disturbances, movement phases: shaded; the "
                                             "longest zoomed) and where each estimator's flags switched on"),
        ("loss", plots.loss_figure, "smoother cost per iteration"),
    ):
        fig = make(s) if make is plots.loss_figure else make(s, truth=truth)
        if fig is None:
            continue
        name = f"{stem}-{suffix}.png"
        _save(fig, Path(fig_dir) / name)
        out.append((f"{s.id}: {caption}", name))
    beliefs = []
    names: set[str] = set()
    for e, belief in sorted(s.beliefs.items()):
        label = s.labels[e]
        name = f"{stem}-consistency-{plots.slug(label)}.png"
        if name in names:  # two labels with the same slug
            name = f"{stem}-consistency-{e}-{plots.slug(label)}.png"
        names.add(name)
        summary = consistency.summarize(belief)
        _save(plots.consistency_figure(s, e, summary=summary, truth=truth), Path(fig_dir) / name)
        caption = (f"{s.id}, {label}: attitude error against the truth ({truth}) about each body axis and the "
                   "filter's +-3 sigma "
                   "(deg); NIS of the accelerometer updates and its chi-square(3) 95 % band; samples without an "
                   "accelerometer update (skipped, gated or invalid), with the chi-square guard, with a rest update"
                   + ("; gyro-bias estimate (deg/s)" if belief.bias_rad_s is not None else ""))
        beliefs.append({"dataset": s.id, "estimator": label, "file": name, "caption": caption,
                        "summary": dataclasses.asdict(summary)})
    return out, beliefs


def _render_summary(doc: dict[str, Any], fig_dir: str) -> list[tuple[str, str]]:
    from . import plots

    rows = doc["results"]
    causal = {label: d.get("causal", True) for label, d in doc["settings"].get("estimator_details", {}).items()}
    figures: list[tuple[str, str, Callable]] = [
        ("RMSE per estimator and recording", "summary-rmse.png", lambda: plots.summary_rmse_figure(rows)),
        ("accuracy vs speed", "summary-speed.png", lambda: plots.speed_figure(rows, causal)),
    ]
    if doc["settings"].get("kind") == "ablate":
        figures = [
            ("mean RMSE per setting", "ablation-bars.png", lambda: plots.bars_figure(rows)),
            ("sweep: mean total RMSE against each parameter, the minimum over the other parameters",
             "ablation-sweep.png", lambda: plots.sweep_figure(rows)),
            ("mean total RMSE against each parameter", "ablation-params.png", lambda: plots.param_figure(rows)),
            ("mean total RMSE over the parameter grid", "ablation-grid.png", lambda: plots.grid_figure(rows)),
        ] + figures
    out = []
    for caption, name, make in figures:
        fig = make()
        if fig is not None:
            _save(fig, Path(fig_dir) / name)
            out.append((caption, name))
    return out


def _render_statistics(statistics: dict[str, Any], doc: dict[str, Any], fig_dir: str) -> dict[tuple, tuple[str, str]]:
    """The critical-difference diagram of every comparison with three rows or more
    (`fusion.evaluation.report.stats_plots.cd_figure`): (metric, group, imu) -> (caption, file name),
    `summary-cd-<metric>.png` (`summary-cd-<metric>-<group and imu>.png` when a metric has several)."""
    from . import plots
    from .stats_plots import cd_figure

    run = RunStatistics.from_json(statistics)
    order = list(dict.fromkeys(r["estimator"] for r in doc["results"]))
    colors = {label: plots.color(i) for i, label in enumerate(order)}
    out = {}
    for c in run.comparisons:
        fig = None if c.statistics is None else cd_figure(c.statistics, f"{c.metric} RMSE", colors)
        if fig is None:
            continue
        name = f"summary-cd-{c.metric}" + (f"-{plots.slug(c.name)}" if len(run.of(c.metric)) > 1 else "") + ".png"
        _save(fig, Path(fig_dir) / name)
        out[(c.metric, c.group, c.imu)] = (f"critical-difference diagram, {c.metric} RMSE"
                                           + (f" ({c.name})" if c.name else ""), name)
    return out


def render(out_dir: str | Path, jobs: int | None = 1, progress: bool = False) -> Path:
    """(Re)build table.txt, figures/, report.html and report.md from results.json and series/
    (in a staging folder, moved in at the end: see `OutputFolder`)."""
    out = Path(out_dir)
    doc_path = out / RESULTS
    if not doc_path.is_file():
        raise FileNotFoundError(f"{doc_path}: no results.json here (is {out} the --out folder of a run?)")
    read_results(doc_path)  # fail before taking the folder
    with OutputFolder(out) as folder:
        _render_into(out, folder.staging, jobs, progress)
        folder.commit(regenerates=RENDERED)
    return out / "report.html"


def _render_into(source: Path, dest: Path, jobs: int | None, progress: bool) -> None:
    """Table, figures and both reports of the run in `source`, written into `dest`."""
    doc = read_results(source / RESULTS)
    stress = _stress_of(doc)  # a stress run: its dose-response and robustness; the rest is its clean rows'
    if stress is not None:
        from ..sweeps.stress import clean_rows

        doc = {**doc, "results": clean_rows(doc["results"])}
    results = [Result.from_json(r) for r in doc["results"]]
    primary = doc["settings"].get("primary")  # the table's statistics metric, when the run chose one
    table = format_table(results, align=bool(doc["settings"].get("align", False)),
                         primary=primary if primary in KINDS else "total")
    sweep = "\n\n".join(text for text in (_tuning_text(doc), _sweep_text(doc), _stress_text(stress)) if text)
    (dest / "table.txt").write_text(table + (f"\n\n{sweep}" if sweep else "") + "\n")
    fig_dir = dest / "figures"
    fig_dir.mkdir(exist_ok=True)
    series_paths = series_files(source)
    for path in series_paths:
        check_series(path)
    statistics = run_statistics(summary_groups(results))  # from the rows: seeded, the same as results.json's
    tasks: list[tuple[Callable, tuple]] = [(_render_summary, (doc, str(fig_dir))),
                                           (_render_statistics, (statistics.to_json(), doc, str(fig_dir)))]
    truths = truth_names(doc)
    tasks += [(_render_stress, (stress, str(fig_dir)))]
    tasks += [(_render_recording, (str(p), str(fig_dir), truths)) for p in series_paths]
    outputs = _run_tasks(tasks, jobs, progress)
    summary, cd_figures, stress_figures = outputs[0], outputs[1], outputs[2]
    per_recording = [fig for figs, _ in outputs[3:] for fig in figs]
    beliefs = [entry for _, entries in outputs[3:] for entry in entries]
    parts = _stress_parts(stress, stress_figures)
    (dest / "report.md").write_text(_markdown(doc, table, summary, per_recording, beliefs, statistics, cd_figures,
                                              parts))
    (dest / "report.html").write_text(_html(doc, summary, per_recording, fig_dir, beliefs, statistics, cd_figures,
                                            parts))


def _stress_of(doc: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """A stress run's dose-response and robustness (`fusion.evaluation.sweeps.stress`): as its
    results.json holds them (`stress`, `robustness`, computed from its rows), else from the rows;
    None for other runs."""
    if doc["settings"].get("kind") != "stress":
        return None
    from ..sweeps.stress import robustness, stress_summary

    summary = doc.get("stress")
    if not isinstance(summary, dict) or not isinstance(summary.get("datasets"), list):
        primary = doc["settings"].get("primary")
        summary = stress_summary(doc["results"], primary if primary in KINDS else "total")
    robust = doc.get("robustness")
    if not isinstance(robust, dict) or not isinstance(robust.get("entries"), list):
        robust = robustness(summary)
    return summary, robust


def _stress_text(stress: tuple[dict[str, Any], dict[str, Any]] | None) -> str:
    """What `fusion stress` prints under the clean table (`fusion.evaluation.sweeps.stress.format_stress`)."""
    if stress is None:
        return ""
    from ..sweeps.stress import format_stress

    return format_stress(*stress)


def _render_stress(stress: tuple[dict[str, Any], dict[str, Any]] | None, fig_dir: str) -> list[dict[str, Any]]:
    """A stress run's figures: per dataset folder the robustness grid and a dose-response figure per
    fault (`plots.robustness_figure`, `plots.dose_response_figure`); one entry each: {"dataset",
    "fault" (None: the grid), "caption", "file"}."""
    if stress is None:
        return []
    from . import plots

    summary, robust = stress
    several = len(summary["datasets"]) > 1
    out = []
    for d in summary["datasets"]:
        where = f" on {d['dataset']}" if several else ""
        prefix = f"stress-{plots.slug(d['dataset'])}-" if several else "stress-"
        kinds = [f["kind"] for f in d["faults"]]
        fig = plots.robustness_figure(robust, d["dataset"], kinds, {f["kind"]: f["severities"] for f in d["faults"]})
        if fig is not None:
            _save(fig, Path(fig_dir) / f"{prefix}robustness.png")
            out.append({"dataset": d["dataset"], "fault": None, "file": f"{prefix}robustness.png",
                        "caption": f"robustness{where}: the severity at which each estimator's mean "
                                   f"{summary['metric']} RMSE reaches twice its clean error"})
        for f in d["faults"]:
            name = f"{prefix}{plots.slug(f['kind'])}.png"
            _save(plots.dose_response_figure(f, summary["metric"], where), Path(fig_dir) / name)
            out.append({"dataset": d["dataset"], "fault": f["kind"], "file": name,
                        "caption": f"{f['kind']}{where}: mean {summary['metric']} RMSE against the severity "
                                   f"({f['unit']}), 95 % interval over the recordings"})
    return out


STRESS_TEXT = (
    "Every recording was run clean and under each sensor fault at each severity (fusion.faults: each a transform of "
    "the recording's sensor data, the truth untouched, seeded by the recording and the fault). Per fault and "
    "estimator: the mean RMSE over the recordings at each severity with its 95 % bootstrap interval (BCa, the "
    "recordings resampled), over the recordings the estimator was scored on clean (the same at every severity); a "
    "cell that failed (the estimator raised or diverged) is counted and left out of its point's mean. Robustness: "
    "the mildest tested severity at which the mean reaches twice the clean mean, or a cell fails; beyond the range "
    "when none does (tested severities only: no interpolation between them).")


def _stress_parts(stress: tuple[dict[str, Any], dict[str, Any]] | None, figures: list[dict[str, Any]]
                  ) -> list[dict[str, Any]]:
    """Per dataset folder of a stress run, what its report section shows: the robustness table and
    per fault its dose-response table (mean [95 % CI] per severity) and figure."""
    if stress is None:
        return []
    from ..sweeps.stress import BREAKDOWN, robust_rows

    summary, robust = stress
    out = []
    for d in summary["datasets"]:
        kinds = [f["kind"] for f in d["faults"]]
        robust_header, robust_body = robust_rows([x for x in robust["entries"] if x["dataset"] == d["dataset"]], kinds)
        faults = []
        for f in d["faults"]:
            head = ["estimator", "clean", *(f"{v:g} {f['unit']}" for v in f["severities"])]
            rows = []
            for e in f["estimators"]:
                clean = e["clean"]["mean_deg"]
                rows.append([e["estimator"], _point_text(e["clean"], None, BREAKDOWN),
                             *(_point_text(p, clean, BREAKDOWN) for p in e["points"])])
            figure = next((x for x in figures if x["dataset"] == d["dataset"] and x["fault"] == f["kind"]), None)
            faults.append({"kind": f["kind"], "model": f["model"], "header": head, "rows": rows, "figure": figure})
        grid = next((x for x in figures if x["dataset"] == d["dataset"] and x["fault"] is None), None)
        out.append({"dataset": d["dataset"], "recordings": d["recordings"], "metric": summary["metric"],
                    "robust_header": robust_header, "robust_rows": robust_body, "grid": grid,
                    "faults": faults, "criterion": robust["criterion"]})
    return out


def _point_text(p: dict[str, Any], clean: float | None, breakdown: float) -> str:
    text = _fmt(p["mean_deg"])
    if p["ci95_deg"] is not None:
        text += f" [{p['ci95_deg'][0]:.2f}, {p['ci95_deg'][1]:.2f}]"
    if clean and p["mean_deg"] is not None and p["mean_deg"] >= breakdown * clean:
        text += " !"
    if p["failed"]:
        text += f" ({p['failed']} failed)"
    return text


def _tuning_text(doc: dict[str, Any]) -> str:
    """The table of a `fusion tune` run (`fusion.evaluation.sweeps.tune.format_tuning`, as results.json
    holds it), "" for other runs."""
    tune = doc.get("tune")
    return str(tune.get("table") or "") if isinstance(tune, dict) else ""


def _sweep_text(doc: dict[str, Any]) -> str:
    """An ablation's best common and per-recording best settings (`fusion.evaluation.sweeps.ablate.sweep_summary`,
    from the rows, so a re-render agrees with them), '' for a comparison."""
    if doc["settings"].get("kind") != "ablate":
        return ""
    from ..sweeps.ablate import format_sweep, sweep_summary

    summary = sweep_summary(doc["results"], groups=(doc.get("sweep") or {}).get("trial_groups"))
    return format_sweep(summary) if summary else ""


def series_files(out: Path) -> list[Path]:
    """The run's series files: those in the manifest, else (a staging folder, or a folder
    written before manifests) every series/*.npz."""
    files = read_manifest(out)
    if files is not None:
        return [out / f for f in sorted(files) if f.startswith("series/") and f.endswith(".npz") and (out / f).is_file()]
    return sorted((out / "series").glob("*.npz")) if (out / "series").is_dir() else []


def check_series(path: Path) -> None:
    """A series file that `fusion.evaluation.run.series.load` reads and whose arrays agree in shape; else
    one line naming it."""
    try:
        s = series_io.load(path)
    except Exception as exc:  # zipfile/numpy raise many types for a corrupt file; all are one line here
        raise ValueError(f"{path}: not a readable series file ({type(exc).__name__}: {' '.join(str(exc).split())[:150]})") from None
    n, e = len(s.imu_t), len(s.labels)
    expect = {"imu_t": ((n,), s.imu_t.shape), "gyr_valid": ((n,), s.gyr_valid.shape),
              "truth_quat": ((len(s.truth_t), 4), s.truth_quat.shape), "causal": ((e,), (len(s.causal),)),
              "quat": ((e, n, 4), s.quat.shape), "err_deg": ((e, len(KINDS), n), s.err_deg.shape)}
    for e, belief in s.beliefs.items():
        if not 0 <= e < len(s.labels):
            raise ValueError(f"{path}: 'belief_{e}_*' names no estimator of the {len(s.labels)} here; not a series this "
                             "toolkit wrote")
        for attr, shape in (("err_rad", (n, 3)), ("sigma_rad", (n, 3)), ("nees", (n,)), ("nis", (n,)), ("updated", (n,)),
                            ("rest", (n,)), ("guarded", (n,)), ("bias_rad_s", (n, 3))):
            value = getattr(belief, attr)
            required = attr in ("err_rad", "sigma_rad", "nees", "nis", "updated")
            if (value is None and required) or (value is not None and value.shape != shape):
                expect[f"belief_{e} {attr}"] = (shape, None if value is None else value.shape)
    for name, (want, got) in expect.items():
        if got is None:
            raise ValueError(f"{path}: {name!r} is missing; not a series this toolkit wrote")
        if tuple(want) != tuple(got) or (name in ("imu_t", "truth_t") and np.ndim(getattr(s, name)) != 1):
            raise ValueError(f"{path}: {name!r} has shape {tuple(got)}, expected {tuple(want)}; not a series this toolkit wrote")


def read_results(path: Path) -> dict[str, Any]:
    """results.json, checked row by row against what `fusion compare` writes; one line naming
    the file (and the row) otherwise."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a results document ({type(exc).__name__}: {' '.join(str(exc).split())[:120]})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("results"), list):
        raise ValueError(f"{path}: not a results document (no 'results' list)")
    for key in ("settings", "versions"):
        if not isinstance(doc.setdefault(key, {}), dict):
            raise ValueError(f"{path}: {key!r} must be an object")
    details = doc["settings"].get("estimator_details", {})
    if not isinstance(details, dict) or not all(isinstance(d, dict) and isinstance(d.get("params", {}), dict)
                                                for d in details.values()):
        raise ValueError(f"{path}: 'settings.estimator_details' is not what fusion writes")
    for i, row in enumerate(doc["results"]):
        problem = _row_problem(row)
        if problem:
            raise ValueError(f"{path}: results row {i}: {problem}")
    alignments = doc.get("alignments") or []
    if not isinstance(alignments, list) or not all(isinstance(a, dict) and isinstance(a.get("dataset"), str)
                                                   and _alignment_problem(a) is None for a in alignments):
        raise ValueError(f"{path}: 'alignments' is not what fusion writes")
    facts = doc.get("recordings") or []
    if not isinstance(facts, list) or not all(isinstance(f, dict) and isinstance(f.get("dataset"), str)
                                              and f.get("protocol") in ("full", "broad", None)
                                              and isinstance(f.get("truth"), (str, type(None))) for f in facts):
        raise ValueError(f"{path}: 'recordings' is not what fusion writes")
    by_dataset = {f["dataset"]: f for f in facts}
    for row in doc["results"]:  # each row with its recording's protocol and truth (`Result.protocol`, `.truth`)
        if row["dataset"] in by_dataset and row.get("rmse_deg"):
            for key in ("protocol", "truth"):
                if row.get(key) is None:
                    row[key] = by_dataset[row["dataset"]][key]
    return doc


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _alignment_problem(a: Any) -> str | None:
    if a is None:
        return None
    if not isinstance(a, dict) or not all(isinstance(a.get(k), list) and len(a[k]) == 3 and all(map(_number, a[k]))
                                          for k in ("world_deg", "body_deg")):
        return "'alignment' must hold 'world_deg' and 'body_deg' as 3 numbers"
    return None


def _row_problem(r: Any) -> str | None:
    if not isinstance(r, dict):
        return f"not an object ({type(r).__name__})"
    for key in ("dataset", "estimator"):
        if not isinstance(r.get(key), str):
            return f"{key!r} must be a string"
    if not (isinstance(r.get("samples"), int) and not isinstance(r["samples"], bool) and r["samples"] >= 0):
        return "'samples' must be a whole number >= 0"
    if not (_number(r.get("seconds")) and r["seconds"] >= 0):
        return "'seconds' must be a finite number >= 0"
    for key in ("rmse_deg", "max_deg"):
        v = r.get(key)
        if v is not None and not (isinstance(v, dict) and all(_number(v.get(k)) and v[k] >= 0 for k in KINDS)):
            return f"{key!r} must be null or hold {', '.join(KINDS)} as finite numbers >= 0"
    if (r.get("rmse_deg") is None) != (r.get("max_deg") is None):
        return "'rmse_deg' and 'max_deg' must both be null or both be given"
    n = r.get("scored_samples")
    if n is not None and not (isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= r["samples"]):
        return "'scored_samples' must be null or a whole number within 0..samples"
    c = r.get("coverage")
    if c is not None and not (_number(c) and 0 <= c <= 1):
        return "'coverage' must be null or a number in [0, 1]"
    if not isinstance(r.get("magnetometer", False), bool):
        return "'magnetometer' must be true or false"
    if r.get("error") is not None and not (isinstance(r["error"], str) and r.get("rmse_deg") is None):
        return "'error' must be a string, on a row without scores"
    if r.get("not_scored") is not None and not (isinstance(r["not_scored"], str) and r.get("rmse_deg") is None):
        return "'not_scored' must be a string, on a row without scores"
    if r.get("panorama") is not None and not (isinstance(r["panorama"], dict) and all(
            v is None or _number(v) for v in r["panorama"].values())):
        return "'panorama' must be null or an object of numbers"
    return _alignment_problem(r.get("alignment"))


def _run_tasks(tasks: list[tuple[Callable, tuple]], jobs: int | None, progress: bool) -> list[Any]:
    from tqdm import tqdm

    from ..run.pool import WorkerPool, default_jobs

    jobs = min(default_jobs() if not jobs else jobs, len(tasks))
    bar = tqdm(total=len(tasks), disable=not progress, file=sys.stderr, unit="fig", desc="figures", leave=False)
    try:
        if jobs <= 1:
            outputs = []
            for fn, args in tasks:
                outputs.append(fn(*args))
                bar.update()
            return outputs
        from . import plots  # noqa: F401  (imported once here, inherited by forked workers)

        outputs: list[Any] = [None] * len(tasks)
        with WorkerPool(jobs) as pool:
            for n, outcome in pool.imap_unordered(_call, tasks):
                outputs[n] = outcome.result()
                bar.update()
        return outputs
    finally:
        bar.close()


def _call(fn: Callable, args: tuple) -> Any:
    return fn(*args)


# --- the documents ---

def _fmt(v: Any) -> str:
    return "-" if v is None else f"{v:.2f}"


def _tables(doc: dict[str, Any]) -> tuple[list[str], list[list[str]], list[str], list[list[str]]]:
    """(header, rows) of the per-run table and of the per-estimator means, as text cells; rows
    without ground truth come after the scored ones; the rows of recordings that could not be read
    are left out (`_not_scored_rows` lists them)."""
    readable = [r for r in doc["results"] if Result.from_json(r).readable]
    rows = [r for r in readable if r["rmse_deg"]] + [r for r in readable if not r["rmse_deg"]]
    imu = shows_imu([Result.from_json(r) for r in rows])  # rows of both kinds can appear: say which is which
    header = ["dataset", "estimator", "samples", "scored samples", "coverage", *(f"{k} RMSE" for k in KINDS),
              *(f"{k} max" for k in KINDS), "us/sample", *(["imu"] if imu else [])]
    body = []
    for r in rows:
        rmse = [_fmt(r["rmse_deg"][k]) if r["rmse_deg"] else "-" for k in KINDS]
        worst = [_fmt(r["max_deg"][k]) if r["max_deg"] else "-" for k in KINDS]
        scored_samples = r.get("scored_samples")
        body.append([r["dataset"], r["estimator"], str(r["samples"]), "-" if scored_samples is None else str(scored_samples),
                     format_coverage(Result.from_json(r)), *rmse, *worst, f"{1e6 * r['seconds'] / max(r['samples'], 1):.1f}",
                     *([sensors([Result.from_json(r)])] if imu else [])])
    mean_header = ["estimator", "recordings scored", *(f"mean {k} RMSE" for k in KINDS), "mean us/sample",
                   *(["imu"] if imu else [])]
    means = []
    for group, members in summary_groups([Result.from_json(r) for r in rows]):
        for label in dict.fromkeys(r["estimator"] for r in rows):
            mine = [r for r in members if r.estimator == label]
            scored = [r for r in mine if r.in_means]
            if not mine:
                continue
            values = [_fmt(float(np.mean([r.rmse_deg[k] for r in scored]))) if scored else "-" for k in KINDS]
            us = np.mean([r.us_per_sample for r in mine if r.ran] or [np.nan])
            means.append([label, str(len(scored)) if group is None else f"{len(scored)} ({group})", *values, f"{us:.1f}",
                          *([sensors(scored or mine)] if imu else [])])
    means += _across_means(rows, imu)
    return header, body, mean_header, means


def _across_means(rows: list[dict[str, Any]], imu: bool) -> list[list[str]]:
    """The means table's "all datasets" rows (`fusion.evaluation.compare.across_datasets`: each
    estimator's mean of its per-dataset means), laid out as `_tables`' mean rows; none with one folder."""
    results = [Result.from_json(r) for r in rows]
    summary = across_datasets(results, ())
    out = []
    for entry in summary["all"]:
        values = [_fmt(entry["rmse_deg"][k]) if entry["rmse_deg"] else "-" for k in KINDS]
        us = np.mean([r.us_per_sample for r in results if r.estimator == entry["estimator"] and r.ran] or [np.nan])
        out.append([entry["estimator"], f"{entry['recordings']} (all {len(summary['datasets'])} datasets, each once)",
                    *values, f"{us:.1f}", *([entry["imu"]] if imu else [])])
    return out


def _imu_notes(doc: dict[str, Any]) -> list[str]:
    """The notes under the results table that say what 6-D and 9-D mean and which rows had a
    heading offset removed (`fusion.evaluation.compare.heading_offset_note`), where the table has
    an imu column; [] otherwise."""
    results = [Result.from_json(r) for r in doc["results"]]
    return [IMU_NOTE, heading_offset_note(results)] if shows_imu(results) else []


def truth_name(dataset: str) -> str:
    """What a recording's truth is when its row does not say (an older results.json): by its folder,
    VICON for the course sets, BROAD's for `broad`, else "ground truth"."""
    group = dataset_group(dataset)
    kind = ("course" if group in ("ece276a", "ece276a-2018", "ese650") else "broad" if group == "broad"
            else "sim" if dataset == "sim" else None)
    return TRUTH_SYSTEMS.get(kind, GENERIC_TRUTH)


def truth_names(doc: dict[str, Any]) -> dict[str, str]:
    """Recording id -> what its truth is (the rows' `truth`, else `truth_name`), for the scored recordings."""
    out: dict[str, str] = {}
    for r in doc["results"]:
        if r.get("rmse_deg") and r["dataset"] not in out:
            out[r["dataset"]] = r.get("truth") or truth_name(r["dataset"])
    return out


def _truth_text(doc: dict[str, Any]) -> str:
    """"the truth (VICON)", or with recordings of several truth systems "the truth (VICON for
    ece276a; optical motion capture (BROAD) for broad)"."""
    per_group: dict[str, list[str]] = {}
    for dataset, name in truth_names(doc).items():
        per_group.setdefault(name, [])
        if dataset_group(dataset) not in per_group[name]:
            per_group[name].append(dataset_group(dataset))
    if not per_group:
        return "the truth"
    if len(per_group) == 1:
        return f"the truth ({next(iter(per_group))})"
    return "the truth (" + "; ".join(f"{name} for {', '.join(groups)}" for name, groups in per_group.items()) + ")"


NOT_SCORED_HEADER = ["recording", "why it was not scored"]
NOT_SCORED_TEXT = ("Recordings the run could not score, each with its reason (no truth, truth unusable, alignment "
                   "undetermined or poor, files that cannot be read): facts about the data, not failures; the rest "
                   "of the run went on without them. Those that could be read ran every estimator, unscored.")


def _not_scored_rows(doc: dict[str, Any]) -> list[list[str]]:
    """One row per recording that was not scored: its id and reason (results.json's `not_scored`,
    or from the rows of an older document)."""
    entries = doc.get("not_scored") or not_scored_recordings([Result.from_json(r) for r in doc["results"]])
    return [[e["dataset"], e["reason"]] for e in entries]


def _coverage_text(doc: dict[str, Any]) -> str:
    """The note under the results table when a row was scored on too little of its recording."""
    return LOW_COVERAGE_NOTE if any(Result.from_json(r).low_coverage for r in doc["results"]) else ""



def _alignment_text(doc: dict[str, Any]) -> str:
    if doc.get("settings", {}).get("align") or recording_alignments_of(doc):
        return ("Aligned (--align, or a truth in frames of its own): the truth was mapped into our frames as A R_truth B, with A = R_ourworld_truthworld "
                "(a tilt only) and B = R_truthbody_imubody fitted once per recording from its gyro, accelerometer and "
                "truth, the same for every estimator; this hides a constant IMU-to-marker mounting rotation and a "
                "tilted truth world, not an estimator's errors.")
    return "No alignment applied; every estimator starts from the same initial orientation."


def _alignment_rows(doc: dict[str, Any]) -> list[list[str]]:
    return [alignment_cells(a) for a in recording_alignments_of(doc)]


def recording_alignments_of(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """A results document's per-recording alignments (`alignments`, else the rows' first)."""
    if doc.get("alignments"):
        return doc["alignments"]
    out: dict[str, dict[str, Any]] = {}
    for r in doc["results"]:
        if r.get("alignment") and r["dataset"] not in out:
            out[r["dataset"]] = {"dataset": r["dataset"], **r["alignment"]}
    return list(out.values())


def _settings_items(doc: dict[str, Any]) -> list[tuple[str, str]]:
    items = []
    for key, value in doc.get("settings", {}).items():
        if key == "estimator_details":
            continue
        items.append((key, value if isinstance(value, str) else json.dumps(value)))
    return items


def _details_items(doc: dict[str, Any]) -> list[tuple[str, str]]:
    out = []
    for label, d in doc.get("settings", {}).get("estimator_details", {}).items():
        params = ", ".join(f"{k}={v}" for k, v in d.get("params", {}).items()) or "(no parameters)"
        kind = "causal filter" if d.get("causal", True) else "smoother (non-causal: sees the future)"
        origin = d.get("origin")
        source = ""
        if isinstance(origin, dict):  # a user's estimator: where its code comes from
            source = (f"; from {origin.get('kind', '')} {origin.get('where', '')}"
                      + (f", {origin['attribute']}" if origin.get("attribute") else "")
                      + (f" (sha256 {origin['sha256']})" if origin.get("sha256") else ""))
        out.append((label, f"{d.get('class', '')}: {kind}; {params}{source}"))
    return out


CONSISTENCY_HEADER = ["estimator", "samples with truth", "inside +-3 sigma x", "inside +-3 sigma y", "inside +-3 sigma z",
                      "mean NEES", "NIS updates", "NIS in 95 % band", "mean NIS", "95 % band of the mean NIS",
                      "no acc update", "rest updates", "bias guarded"]

CONSISTENCY_TEXT = (
    "What each filter that reports an error covariance believed, against what happened (Bar-Shalom, Li & "
    "Kirubarajan 2001, Estimation with Applications to Tracking and Navigation, Sec. 5.4). Inside +-3 sigma: the "
    "fraction of samples whose attitude error against the truth about a body axis lies within the filter's own "
    "3 sqrt(P_ii) (99.7 % if consistent). NEES: e^T P^-1 e over the attitude block (mean 3 if consistent). NIS: the "
    "normalised innovation squared of the accelerometer updates, chi-square with 3 degrees of freedom if consistent: "
    "95 % of the updates inside the band [0.22, 9.35] and a mean of 3 (the band of the mean assumes white "
    "innovations, which hand motion is not). A mean NIS far below 3: the filter expects larger innovations than it "
    "sees (it trusts the accelerometer less than it could); far above: smaller. Heading (about the vertical) is unobservable from an accelerometer, so its envelope grows "
    "and being inside it says little; the error includes the truth system's own error and any residual time offset "
    "between IMU and truth, the NIS does not.")


def _pct_cell(v: Any) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.1f}%"


def _num_cell(v: Any, fmt: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, fmt)


def _consistency_rows(entries: list[dict[str, Any]]) -> list[list[str]]:
    rows = []
    for entry in entries:
        m = entry["summary"]
        lo, hi = m["nis_mean_band"]
        band = "-" if not np.isfinite(lo) else f"{lo:.2f} - {hi:.2f}"
        rows.append([entry["estimator"], str(m["samples_with_truth"]), *(_pct_cell(v) for v in m["inside_3sigma"]),
                     _num_cell(m["nees_mean"], ".3g"), str(m["updates"]), _pct_cell(m["nis_inside"]),
                     _num_cell(m["nis_mean"], ".3g"), band, str(m["skipped"]),
                     "-" if m["rest"] is None else str(m["rest"]), "-" if m["guarded"] is None else str(m["guarded"])])
    return rows


def _by_recording(entries: list[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    """The consistency entries grouped per recording, in run order."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for entry in entries:
        groups.setdefault(entry["dataset"], []).append(entry)
    return list(groups.items())


STATISTICS_TEXT = (
    "How sure the differences are, over the recordings every row scored (complete cases; a recording where a row "
    "failed or was scored on too little is dropped): each row's mean with its 95 % bootstrap confidence interval "
    "(BCa, the recordings resampled 9999 times with a fixed seed; Efron & Tibshirani 1993, An Introduction to the "
    "Bootstrap, ch. 14.3); against the best row (the lowest mean) its wins, ties and losses per recording and the "
    "two-sided Wilcoxon signed-rank p-value, Holm-corrected over the rows compared (Holm 1979, Scand. J. Statist. "
    "6:65-70); a row whose corrected p is at least 0.05 is not significantly worse than the best. With three rows "
    "or more, the Friedman test over all rows and Nemenyi's post-hoc test on the average ranks (Demsar 2006, JMLR "
    "7:1-30, sec. 3.2.2), drawn as a critical-difference diagram: each row at its average rank (1 = lowest error), "
    "a bar joining the rows Nemenyi's test does not tell apart (p >= 0.05), CD the critical difference of ranks. "
    "The total and heading errors of 6-D and 9-D rows are compared separately (a 6-D row is scored with its "
    "heading offset removed). Fewer than 5 complete recordings give no statistics.")
STATISTICS_HEADER = ["estimator", "mean", "95% CI", "mean rank", "W/T/L vs best", "Wilcoxon p", "Holm p",
                     "not worse than best"]


def _statistics_title(c: Comparison) -> str:
    return f"{c.metric} RMSE" + (f" ({c.name})" if c.name else "")


def _statistics_parts(statistics: RunStatistics, cd_figures: dict[tuple, tuple[str, str]]) -> list[tuple]:
    """Per comparison (`fusion.evaluation.scoring.stats.Comparison`): it, a line saying over what (or why there
    are no statistics), the table rows and its diagram ((caption, file) or None)."""
    out = []
    for c in statistics.comparisons:
        s = c.statistics
        if s is None:
            out.append((c, f"No statistics: {c.reason}.", [], None))
            continue
        text = f"{len(s.recordings)} recordings every row scored"
        text += f" ({dropped_text(s.dropped)})" if s.dropped else ""
        text += (f"; rows scored on at most half of the recordings, not ranked: {', '.join(s.left_out)}"
                 if s.left_out else "")
        text += f"; best (lowest mean): {s.best}"
        if s.friedman_p is not None:
            text += f"; Friedman chi-square {s.friedman_statistic:.2f}, p = {s.friedman_p:.2g}"
        if s.critical_difference is not None:
            text += f"; Nemenyi critical difference {s.critical_difference:.2f} ranks"
        rows = []
        for r in s.rows:
            best = r.label == s.best
            rows.append([r.label, f"{r.mean:.2f}", "-" if r.ci_low is None else f"[{r.ci_low:.2f}, {r.ci_high:.2f}]",
                         f"{r.rank:.2f}", f"{r.wins}/{r.ties}/{r.losses}", "best" if best else f"{r.p_value:.2g}",
                         "best" if best else f"{r.p_holm:.2g}", "best" if best else "yes" if r.not_worse else "no"])
        out.append((c, text + ".", rows, cd_figures.get((c.metric, c.group, c.imu))))
    return out


def _title(doc: dict[str, Any]) -> str:
    settings = doc.get("settings", {})
    if settings.get("kind") == "stress":
        return "fusion stress: estimators under sensor faults"
    if settings.get("kind") == "ablate":
        what = settings.get("preset") or settings.get("estimator", "")
        return f"fusion ablation: {what}"
    return "fusion comparison"


def _markdown(doc: dict[str, Any], table: str, summary: list, per_recording: list,
              beliefs: list[dict[str, Any]] = (), statistics: RunStatistics | None = None,
              cd_figures: dict[tuple, tuple[str, str]] | None = None, stress: list[dict[str, Any]] = ()) -> str:
    header, body, mean_header, means = _tables(doc)

    def md_table(head: list[str], rows: list[list[str]]) -> list[str]:
        esc = [[c.replace("|", "\\|") for c in row] for row in [head, *rows]]
        lines = ["| " + " | ".join(esc[0]) + " |", "|" + "|".join("---" for _ in head) + "|"]
        return lines + ["| " + " | ".join(row) + " |" for row in esc[1:]]

    settings = doc.get("settings", {})
    lines = [f"# {_title(doc)}", "", "Command:", "", "    " + settings.get("command", "(unknown)"), "",
             "Re-render without recomputing: `fusion report <this folder>`.", ""]
    if stress:
        lines += ["## Stress", "", STRESS_TEXT, ""]
        for part in stress:
            title = f" on {part['dataset']}" if len(stress) > 1 else ""
            lines += [f"### Robustness{title} ({part['recordings']} recordings)", "", part["criterion"] + ".", ""]
            lines += md_table(part["robust_header"], part["robust_rows"]) + [""]
            lines += [f"![{part['grid']['caption']}](figures/{part['grid']['file']})", ""] if part["grid"] else []
            for f in part["faults"]:
                lines += [f"### {f['kind']}{title}", "", f"{f['model']}. Mean {part['metric']} RMSE, deg [95 % CI]; "
                          "! twice the clean mean or more.", ""] + md_table(f["header"], f["rows"]) + [""]
                lines += [f"![{f['figure']['caption']}](figures/{f['figure']['file']})", ""] if f["figure"] else []
        lines += ["## The clean run", "", "The rows without a fault, as `fusion compare` gives them.", ""]
    lines += ["## Means per estimator (RMSE, deg)", ""]
    lines += md_table(mean_header, means) + ["", "## Results per recording (RMSE and maximum, deg)", ""]
    lines += md_table(header, body) + (["", _coverage_text(doc)] if _coverage_text(doc) else [])
    lines += ["", *_imu_notes(doc)] if _imu_notes(doc) else []
    lines += ["", f"Errors: total = geodesic angle between estimate and {_truth_text(doc)}; inclination = angle between "
              "the true and estimated gravity direction; heading = twist about world z of the error. "
              + _alignment_text(doc), ""]
    if _not_scored_rows(doc):
        lines += ["## Not scored", "", NOT_SCORED_TEXT, ""] + md_table(NOT_SCORED_HEADER, _not_scored_rows(doc)) + [""]
    if _alignment_rows(doc):
        lines += ["## Alignment (--align)", ""] + md_table(ALIGNMENT_HEADER, _alignment_rows(doc)) + [""]
    if _tuning_text(doc):
        lines += ["## Tuning: library default, best common setting, per-recording best, out of sample", ""] + [
            "    " + line for line in _tuning_text(doc).splitlines()] + [""]
    if _sweep_text(doc):
        lines += ["## Sweep: best common and per-recording best settings", ""] + [
            "    " + line for line in _sweep_text(doc).splitlines()] + [""]
    if statistics is not None and statistics.comparisons:
        lines += ["## Statistics", "", STATISTICS_TEXT, ""]
        for c, text, rows, figure in _statistics_parts(statistics, cd_figures or {}):
            lines += [f"### {_statistics_title(c)}", "", text, ""]
            lines += (md_table(STATISTICS_HEADER, rows) + [""]) if rows else []
            lines += [f"![{figure[0]}](figures/{figure[1]})", ""] if figure else []
    lines += ["## Figures", ""] + [f"![{c}](figures/{n})" for c, n in summary] + [""]
    if per_recording:
        lines += ["## Per recording", ""] + [f"![{c}](figures/{n})" for c, n in per_recording] + [""]
    if beliefs:
        lines += ["## Filter consistency", "", CONSISTENCY_TEXT, ""]
        for dataset, entries in _by_recording(list(beliefs)):
            lines += [f"### {dataset}", ""] + md_table(CONSISTENCY_HEADER, _consistency_rows(entries)) + [""]
            lines += [f"![{e['caption']}](figures/{e['file']})" for e in entries] + [""]
    lines += ["## Settings", ""] + md_table(["setting", "value"], [[k, str(v)] for k, v in _settings_items(doc)])
    if _details_items(doc):
        lines += ["", "## Estimators", ""] + md_table(["estimator", "details"], [[k, v] for k, v in _details_items(doc)])
    lines += ["", "## Versions", ""] + md_table(["package", "version"], [[k, str(v)] for k, v in doc.get("versions", {}).items()])
    return "\n".join(lines) + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;overflow-wrap:anywhere}th{background:#f3f3f3}
td.num{text-align:right;font-variant-numeric:tabular-nums}
pre{background:#f6f6f6;padding:.6em;overflow-x:auto}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#555}
"""


def _html_table(head: list[str], rows: list[list[str]], table_id: str, numeric_from: int) -> str:
    out = [f'<table id="{table_id}"><thead><tr>' + "".join(f"<th>{html.escape(h)}</th>" for h in head)
           + "</tr></thead><tbody>"]
    for row in rows:
        cells = "".join(f'<td class="num">{html.escape(c)}</td>' if i >= numeric_from else f"<td>{html.escape(c)}</td>"
                        for i, c in enumerate(row))
        out.append(f"<tr>{cells}</tr>")
    return "\n".join(out) + "</tbody></table>"


def _html_stress(stress: list[dict[str, Any]], fig_dir: Path) -> list[str]:
    """A stress run's section of report.html (`_stress_parts`): robustness, then per fault its table
    and figure (embedded); [] for other runs."""
    if not stress:
        return []
    out = ['<h2 id="stress">Stress</h2>', f"<p>{html.escape(STRESS_TEXT)}</p>"]
    for n, part in enumerate(stress):
        title = f" on {part['dataset']}" if len(stress) > 1 else ""
        out += [f"<h3>Robustness{html.escape(title)} ({part['recordings']} recordings)</h3>",
                f"<p>{html.escape(part['criterion'])}.</p>",
                _html_table(part["robust_header"], part["robust_rows"], f"robustness-{n:02d}", 1)]
        out += [_img(fig_dir, part["grid"]["caption"], part["grid"]["file"])] if part["grid"] else []
        for k, f in enumerate(part["faults"]):
            out += [f"<h3>{html.escape(f['kind'] + title)}</h3>",
                    f"<p>{html.escape(f['model'])}. Mean {html.escape(part['metric'])} RMSE, deg [95 % CI]; ! twice "
                    "the clean mean or more.</p>", _html_table(f["header"], f["rows"], f"stress-{n:02d}-{k:02d}", 1)]
            out += [_img(fig_dir, f["figure"]["caption"], f["figure"]["file"])] if f["figure"] else []
    out += ["<h2>The clean run</h2><p>The rows without a fault, as <code>fusion compare</code> gives them.</p>"]
    return out


def _img(fig_dir: Path, caption: str, name: str, embed: bool = True) -> str:
    """A figure: embedded (base64 PNG: the page alone shows it) or linked from `figures/` and loaded
    when scrolled to (`loading="lazy"`), so that a report with a hundred figures opens at once."""
    if embed:
        src = "data:image/png;base64," + base64.b64encode((fig_dir / name).read_bytes()).decode("ascii")
    else:
        src = "figures/" + name
    lazy = "" if embed else ' loading="lazy"'
    return (f'<figure><img alt="{html.escape(caption)}" data-file="{html.escape(name)}"{lazy} '
            f'src="{html.escape(src)}"><figcaption>{html.escape(caption)}</figcaption></figure>')


def _html(doc: dict[str, Any], summary: list, per_recording: list, fig_dir: Path,
          beliefs: list[dict[str, Any]] = (), statistics: RunStatistics | None = None,
          cd_figures: dict[tuple, tuple[str, str]] | None = None, stress: list[dict[str, Any]] = ()) -> str:
    header, body, mean_header, means = _tables(doc)
    settings = doc.get("settings", {})
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(_title(doc))}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(_title(doc))}</h1>",
        "<p>Command (re-render this page without recomputing: <code>fusion report &lt;folder&gt;</code>):</p>",
        f"<pre>{html.escape(settings.get('command', '(unknown)'))}</pre>",
        *_html_stress(stress, fig_dir),
        "<h2>Means per estimator</h2><p>RMSE and maximum error in degrees. total = geodesic angle between estimate "
        f"and {html.escape(_truth_text(doc))}; inclination = angle between the true and estimated gravity direction; "
        f"heading = twist about world z of the error. {html.escape(_alignment_text(doc))}</p>",
        _html_table(mean_header, means, "means", 1),
        "<h2>Results per recording</h2><p>Recordings that were not scored come last (their reasons: "
        "<a href=\"#not-scored\">Not scored</a>).</p>",
        _html_table(header, body, "results", 2),
        *([f"<p>{html.escape(_coverage_text(doc))}</p>"] if _coverage_text(doc) else []),
        *([f"<p>{'<br>'.join(html.escape(n) for n in _imu_notes(doc))}</p>"] if _imu_notes(doc) else []),
        *(['<h2 id="not-scored">Not scored</h2>', f"<p>{html.escape(NOT_SCORED_TEXT)}</p>",
           _html_table(NOT_SCORED_HEADER, _not_scored_rows(doc), "not-scored", 9)] if _not_scored_rows(doc) else []),
        *(["<h2>Alignment (--align)</h2>", _html_table(ALIGNMENT_HEADER, _alignment_rows(doc), "alignment", 1)]
          if _alignment_rows(doc) else []),
        *(["<h2>Tuning: library default, best common setting, per-recording best, out of sample</h2>",
           f"<pre>{html.escape(_tuning_text(doc))}</pre>"] if _tuning_text(doc) else []),
        *(["<h2>Sweep: best common and per-recording best settings</h2>", f"<pre>{html.escape(_sweep_text(doc))}</pre>"]
          if _sweep_text(doc) else []),
    ]
    if statistics is not None and statistics.comparisons:
        parts += ['<h2 id="statistics">Statistics</h2>', f"<p>{html.escape(STATISTICS_TEXT)}</p>"]
        for n, (c, text, rows, figure) in enumerate(_statistics_parts(statistics, cd_figures or {})):
            parts += [f"<h3>{html.escape(_statistics_title(c))}</h3>", f"<p>{html.escape(text)}</p>"]
            parts += [_html_table(STATISTICS_HEADER, rows, f"statistics-{n:02d}", 1)] if rows else []
            parts += [_img(fig_dir, *figure)] if figure else []
    parts += ["<h2>Summary figures</h2>", *(_img(fig_dir, c, n) for c, n in summary)]
    if per_recording:
        parts += ["<h2>Per recording</h2><p>Grey: no truth (tracking gaps, outside its span); red: gyro marked invalid. The "
                  "figures are the files in <code>figures/</code> beside this page.</p>",
                  *(_img(fig_dir, c, n, embed=False) for c, n in per_recording)]
    if beliefs:
        parts += ['<h2 id="consistency">Filter consistency</h2>', f"<p>{html.escape(CONSISTENCY_TEXT)}</p>"]
        for n, (dataset, entries) in enumerate(_by_recording(list(beliefs))):
            parts += [f"<h3>{html.escape(dataset)}</h3>",
                      _html_table(CONSISTENCY_HEADER, _consistency_rows(entries), f"consistency-{n:03d}", 1),
                      *(_img(fig_dir, e["caption"], e["file"], embed=False) for e in entries)]
    parts += ["<h2>Settings</h2>", _html_table(["setting", "value"], [[k, str(v)] for k, v in _settings_items(doc)],
                                               "settings", 9)]
    if _details_items(doc):
        parts += ["<h2>Estimators</h2>", _html_table(["estimator", "details"], [list(x) for x in _details_items(doc)],
                                                     "estimators", 9)]
    parts += ["<h2>Versions</h2>", _html_table(["package", "version"],
                                               [[k, str(v)] for k, v in doc.get("versions", {}).items()], "versions", 9),
              "</body></html>"]
    return "\n".join(parts) + "\n"
