"""Run estimators over recordings and score them: the library behind `fusion compare`.

    from fusion import datasets
    from fusion.evaluation.compare import compare
    results = compare(["dr", "ukf:R=1e-3"], [datasets.load("sim")])

Every (recording, estimator) pair is one job (`fusion.evaluation.run.job.run_one`: build the
estimator from its spec, time `estimate` on the recording's calibrated samples from the shared
initial orientation, score it against the truth when there is one), scheduled by
`fusion.evaluation.run.runner`. Results come back in a stable order: recordings as given,
estimators as given within each recording. This module also formats them (the table,
the `--json` document).
"""
from __future__ import annotations

import platform
from typing import Any, Iterable

import numpy as np

from fusion.estimators.params import EstimatorSpec
from fusion.types import Recording

from .run.job import (  # noqa: F401  (the job layer, re-exported: `from fusion.evaluation.compare import run_one`)
    Result, aligned, default_protocol, recording_alignment, run_one,
)
from .run.runner import run
from .scoring.metrics import KINDS, MIN_COVERAGE
from .scoring.stats import dataset_group, run_statistics, table_column  # noqa: F401  (dataset_group re-exported)


def compare(specs: Iterable[EstimatorSpec | str] | str, recordings: Iterable[Recording], init: str | None = None,
            progress: bool = False, protocol: str | None = None, jobs: int | None = 1,
            align: bool = False) -> list[Result]:
    """Every estimator on every recording, in a stable order (recording-major), with whole results
    (trajectories and per-sample errors: for a few recordings; `fusion.evaluation.runs.run_compare`
    keeps rows only).

    specs: estimator specs or spec texts (`"ukf:R=1e-3"`, `"all"`).
    recordings: loaded `Recording`s, or dataset `Source`s (loaded once per worker).
    init: `truth`, `accel`, `identity`, or None for each recording's default.
    progress: show a progress bar on stderr.
    protocol: scoring protocol, "full" or "broad" (`fusion.evaluation.scoring.metrics`), or None for each
        recording's default (`default_protocol`).
    jobs: worker processes (None or 0: all cores); the results do not depend on it
        (see `fusion.evaluation.run.runner`).
    align: score against the truth mapped into our frames by constant world and body rotations
        fitted once per recording from its IMU and truth (`fusion.evaluation.scoring.align`), the same for
        every estimator; each result's `alignment` holds them.
    """
    return run(specs, list(recordings), init=init, jobs=jobs, progress=progress, protocol=protocol, align=align,
               keep=True)


def versions() -> dict[str, str]:
    """Versions of Python and the packages that shape the numbers."""
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for package in ("fusion", "numpy", "scipy", "filterpy", "numba", "vqf", "ahrs", "imufusion"):
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


def not_scored_recordings(results: list[Result]) -> list[dict[str, str]]:
    """One entry per recording that was not scored, in run order: `{"dataset", "reason"}`, the reason
    its rows carry (`Result.not_scored`: no truth, truth unusable, alignment undetermined or poor, or
    files that cannot be read)."""
    out: dict[str, dict[str, str]] = {}
    for r in results:
        if r.not_scored and r.dataset not in out:
            out[r.dataset] = {"dataset": r.dataset, "reason": r.not_scored}
    return list(out.values())


def recording_facts(results: list[Result]) -> list[dict[str, Any]]:
    """One entry per scored recording whose rows know them, in run order: `{"dataset", "protocol",
    "truth"}`, how its rows were scored ("full" or "broad": `Result.protocol`) and what its truth is
    (`fusion.evaluation.run.job.truth_system`); null where no row knows (rows read back from an older
    journal or results.json)."""
    out: dict[str, dict[str, Any]] = {}
    for r in results:
        if not r.rmse_deg:
            continue
        entry = out.setdefault(r.dataset, {"dataset": r.dataset, "protocol": None, "truth": None})
        entry["protocol"] = entry["protocol"] or r.protocol
        entry["truth"] = entry["truth"] or r.truth
    return [entry for entry in out.values() if entry["protocol"] or entry["truth"]]


def results_json(results: list[Result], settings: dict[str, Any]) -> dict[str, Any]:
    """The document `--json` writes: `results`, `alignments` (one per recording, empty without
    `--align`), `recordings` (one per recording with truth: `recording_facts`), `not_scored` (one per
    recording that was not scored, with its reason: `not_scored_recordings`), `statistics` (every
    metric's, `fusion.evaluation.scoring.stats.run_statistics`), `datasets` (each dataset's means apart and
    together: `across_datasets`), `settings`, `versions`."""
    return {"results": [r.to_json() for r in results], "alignments": recording_alignments(results),
            "recordings": recording_facts(results), "not_scored": not_scored_recordings(results),
            "statistics": run_statistics(summary_groups(results)).to_json(),
            "datasets": across_datasets(results), "settings": settings,
            "versions": versions()}


ALIGN_NOTE = ("aligned (--align, or a truth in frames of its own): truth mapped into our frames as A R_truth B, "
              "A = R_ourworld_truthworld and B = R_truthbody_imubody fitted once per recording from its gyro, "
              "accelerometer and truth, the same for every estimator")


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


ACROSS = "all datasets"  # the key of the "all datasets" rows among the table's (group, estimator) keys


def across_datasets(results: list[Result], intervals: Iterable[str] = KINDS) -> dict[str, Any]:
    """Each dataset apart and together: results.json's `datasets` (docs/json-format.md).

    `per_dataset`: per folder (`dataset_group`, in run order) and estimator, the recordings scored
    (as in the means: a row below `MIN_COVERAGE` or failed is left out), the mean RMSE of each
    metric and its 95 % BCa interval (`fusion.evaluation.scoring.stats.mean_of_means_interval` with one
    sample: over this estimator's own recordings) and the sensors ("6-D", "9-D", "mixed").
    `all` (with two folders or more, else empty): per estimator the mean of its per-dataset means,
    each dataset counted once whatever its number of recordings, and its interval by the
    stratified bootstrap (recordings resampled within each dataset); the mean is null unless the
    estimator was scored on every dataset. An interval needs `MIN_RECORDINGS` scored recordings in
    every dataset it covers (null otherwise), and is computed for the metrics in `intervals` only.
    Datasets scored by different protocols (`recording_facts`) are averaged as their means stand.
    """
    from .scoring.stats import MIN_RECORDINGS, mean_of_means_interval

    intervals = [k for k in intervals]
    folders = list(dict.fromkeys(dataset_group(r.dataset) for r in results if r.rmse_deg))
    labels = list(dict.fromkeys(r.estimator for r in results))

    def interval(samples: list[list[float]]) -> list[float | None] | None:
        if not samples or any(len(s) < MIN_RECORDINGS for s in samples):
            return None
        low, high = mean_of_means_interval(samples)
        return None if low is None or high is None else [low, high]

    per_dataset, scored_in = [], {}
    for folder in folders:
        for label in labels:
            mine = [r for r in results if r.estimator == label and dataset_group(r.dataset) == folder]
            scored = [r for r in mine if r.in_means]
            if not mine:
                continue
            scored_in[(folder, label)] = scored
            per_dataset.append({
                "dataset": folder, "estimator": label, "recordings": len(scored),
                "rmse_deg": {k: float(np.mean([r.rmse_deg[k] for r in scored])) for k in KINDS} if scored else None,
                "ci95_deg": {k: interval([[r.rmse_deg[k] for r in scored]]) if scored else None for k in intervals},
                "imu": sensors(scored or mine)})
    across = []
    if len(folders) >= 2:
        for label in labels:
            parts = [scored_in[(f, label)] for f in folders if scored_in.get((f, label))]
            complete = len(parts) == len(folders)
            across.append({
                "estimator": label, "datasets": len(parts), "recordings": sum(map(len, parts)),
                "rmse_deg": {k: float(np.mean([np.mean([r.rmse_deg[k] for r in p]) for p in parts])) for k in KINDS}
                if complete else None,
                "ci95_deg": {k: interval([[r.rmse_deg[k] for r in p] for p in parts]) if complete else None
                             for k in intervals},
                "imu": sensors([r for p in parts for r in p] or [r for r in results if r.estimator == label])})
    return {"datasets": folders, "per_dataset": per_dataset, "all": across}


ACROSS_NOTE = ("all datasets: each row the mean of the estimator's per-dataset means (each dataset counts once, whatever "
               "its number of recordings; '-' for an estimator not scored on every dataset)")


def across_rows(results: list[Result], primary: str) -> tuple[list[list[str]], list[tuple[str, str]],
                                                              dict[tuple[str, str], str], list[str]]:
    """The table's "all datasets" rows (`across_datasets`), one per estimator, laid out as
    `format_table`'s mean rows (name, estimator, total, inclination, heading, "", us/sample, imu);
    their keys, their cells of the `primary` interval column, and the notes. Nothing with one
    folder."""
    if len({dataset_group(r.dataset) for r in results if r.rmse_deg}) < 2:
        return [], [], {}, []
    summary = across_datasets(results, [primary])
    rows, keys, cells = [], [], {}
    n = len(summary["datasets"])
    for entry in summary["all"]:
        label = entry["estimator"]
        values = [f"{entry['rmse_deg'][k]:.2f}" for k in KINDS] if entry["rmse_deg"] else ["-"] * 3
        us = np.mean([r.us_per_sample for r in results if r.estimator == label and r.ran] or [np.nan])
        rows.append([f"mean {ACROSS} ({n})", label, *values, "", f"{us:.1f}", entry["imu"]])
        keys.append((ACROSS, label))
        ci = entry["ci95_deg"][primary]
        if ci is not None:
            cells[(ACROSS, label)] = f"[{ci[0]:.2f}, {ci[1]:.2f}]  "
    note = ACROSS_NOTE
    if cells:
        note += (f"; its {primary} 95% CI: BCa bootstrap resampling the recordings within each dataset (needs 5 "
                 "scored recordings in each)")
    return rows, keys, cells, [note]


def format_table(results: list[Result], align: bool | None = None, primary: str = "total") -> str:
    """A readable table: first a mean row per estimator over the recordings that have ground
    truth (per folder when they come from several, see `summary_groups`), then one row per recording x estimator (RMSE in degrees), recordings without ground
    truth last; with alignment, the fitted rotations after it.

    align: whether the run used `--align` (None: whether any result carries an alignment).
    primary: the metric whose statistics the table shows (`fusion.evaluation.scoring.stats`): with five
        recordings or more that every row scored, a column of 95 % intervals of the mean on the mean
        rows, marked for the rows not significantly worse than the best, and a note saying so; with
        fewer, a note saying why there are none (the columns as they are).
    """
    if primary not in KINDS:
        raise ValueError(f"unknown metric {primary!r}; use one of {', '.join(KINDS)}")
    if align is None:
        align = any(r.alignment for r in results)
    header = ["dataset", "estimator", "total", "inclination", "heading", "coverage", "us/sample"]
    not_scored = not_scored_recordings(results)
    results = [r for r in results if r.readable]  # the rows of recordings that could be read: the others are listed
    rows = []
    for r in results:
        rmse = [f"{r.rmse_deg[k]:.2f}" for k in KINDS] if r.rmse_deg else ["failed" if r.error else "-"] * 3
        rows.append([r.dataset, r.estimator, *rmse, format_coverage(r), "-" if r.error else f"{r.us_per_sample:.1f}"])
    labels = list(dict.fromkeys(r.estimator for r in results))
    means, keys = [], []  # keys: (group, estimator) of each mean row
    across_cells, across_notes = {}, []
    if len({r.dataset for r in results}) >= 2:
        for group, members in summary_groups(results):
            for label in labels:
                mine = [r for r in members if r.estimator == label]
                scored = [r for r in mine if r.in_means]
                if not mine:
                    continue
                mean = [f"{np.mean([r.rmse_deg[k] for r in scored]):.2f}" for k in KINDS] if scored else ["-"] * 3
                us = np.mean([r.us_per_sample for r in mine if r.ran] or [np.nan])
                name = f"mean ({len(scored)})" if group is None else f"mean {group} ({len(scored)})"
                means.append([name, label, *mean, "", f"{us:.1f}", sensors(scored or mine)])
                keys.append((group, label))
        more, more_keys, across_cells, across_notes = across_rows(results, primary)  # each dataset apart, then together
        means, keys = means + more, keys + more_keys
    for row, r in zip(rows, results):
        row.append(sensors([r]))
    if shows_imu(results):  # rows of both kinds can appear: a column says which rows used the magnetometer
        header.append("imu")
    else:
        rows, means = [row[:-1] for row in rows], [row[:-1] for row in means]
    if any(r.panorama for r in results):
        header += ["pano PSNR dB", "SSIM"]
        for row, r in zip(rows, results):
            p = r.panorama or {}
            row += [f"{p.get('psnr_db', float('nan')):.2f}", f"{p.get('ssim', float('nan')):.3f}"]
        means = [row + ["", ""] for row in means]
    interval, cells, notes = table_column(run_statistics(summary_groups(results), [primary]), primary) if means else (
        "", {}, [])
    cells, notes = {**cells, **across_cells}, notes + across_notes
    if cells:  # the interval column after heading, filled on the mean rows
        header.insert(5, interval)
        rows = [row[:5] + [""] + row[5:] for row in rows]
        means = [row[:5] + [cells.get(key, "")] + row[5:] for row, key in zip(means, keys)]
    widths = [max(len(str(row[i])) for row in [header, *rows, *means]) for i in range(len(header))]

    def line(row: list[str]) -> str:
        return "  ".join(str(c).ljust(w) if i < 2 else str(c).rjust(w) for i, (c, w) in enumerate(zip(row, widths)))

    out = ["RMSE in degrees (total = geodesic angle; inclination = gravity direction; heading = twist about world z); "
           + (ALIGN_NOTE if align else "no alignment"),
           line(header), line(["-" * w for w in widths])]
    scored_rows = [row for row, r in zip(rows, results) if r.rmse_deg]
    unscored_rows = [row for row, r in zip(rows, results) if not r.rmse_deg and not r.error]
    failed_rows = [row for row, r in zip(rows, results) if r.error]
    if means:
        out += [line(r) for r in means]
        out.append(line(["-" * w for w in widths]))
    out += [line(r) for r in scored_rows]
    if unscored_rows:
        if scored_rows or means:
            out += [f"not scored (the reasons below): {len({r.dataset for r in results if r.not_scored})} recordings"]
        out += [line(r) for r in unscored_rows]
    if failed_rows:
        out += [f"failed (no result; the errors say why): {len(failed_rows)} rows"] + [line(r) for r in failed_rows]
    if any(r.low_coverage for r in results):
        out += [LOW_COVERAGE_NOTE]
    if shows_imu(results):
        out += [IMU_NOTE, heading_offset_note(results)]
    out += notes
    if any(r.alignment for r in results):
        out += ["", format_alignments(results)]
    if not_scored:
        out += ["", format_not_scored(not_scored, len({r.dataset for r in results} | {e["dataset"] for e in not_scored}))]
    return "\n".join(out)


def format_not_scored(entries: list[dict[str, str]], recordings: int) -> str:
    """The table's footer: how many of the run's recordings were not scored, and each one's reason
    (`not_scored_recordings`), one line each."""
    return "\n".join([f"not scored: {len(entries)} of {recordings} recordings (facts about the data: the run went on "
                      "without them)"] + [f"  {e['dataset']}: {e['reason']}" for e in entries])


def sensors(results: list[Result]) -> str:
    """"9-D" when the rows used a magnetometer, "6-D" when none did, "mixed" otherwise."""
    used = {r.magnetometer for r in results}
    return "9-D" if used == {True} else "6-D" if used == {False} else "mixed"


def shows_imu(results: list[Result]) -> bool:
    """Whether a table of these rows says which are 6-D and which 9-D: where rows of both kinds can
    appear, i.e. a row used a magnetometer or was scored with BROAD's protocol (whose recordings
    have one, and which scores 6-D and 9-D rows differently; rows that do not say how they were
    scored, from an older results.json, count only if one is 9-D)."""
    return any(r.magnetometer or (r.protocol == "broad" and r.rmse_deg) for r in results)


IMU_NOTE = "imu: 9-D = the row used the magnetometer (heading observable); 6-D = gyro and accelerometer only"


def heading_offset_note(results: list[Result]) -> str:
    """Which rows had a heading offset removed before they were scored, and which did not (from
    each row's protocol and sensors: `Result.heading_offset_removed`), naming the recordings'
    folders."""
    def where(rows: list[Result]) -> str:
        return ", ".join(dict.fromkeys(dataset_group(r.dataset) for r in rows))

    scored = [r for r in results if r.rmse_deg]
    removed = [r for r in scored if r.heading_offset_removed]
    nine_d = [r for r in scored if not r.heading_offset_removed and r.magnetometer]
    full = [r for r in scored if not r.heading_offset_removed and not r.magnetometer]
    parts = []
    if removed:
        parts.append(f"removed from the 6-D rows on {where(removed)} (BROAD's protocol: the estimate turned about world "
                     "z by its mean heading error over the movement phases before scoring)")
    kept = []
    if nine_d:
        kept.append(f"the 9-D rows on {where(nine_d)} (scored with their own heading)")
    if full:
        kept.append(f"the rows on {where(full)} (the full protocol: every sample, as estimated)")
    if kept:
        parts.append("not removed from " + " nor from ".join(kept))
    return "heading offset: " + ("; ".join(parts) if parts else "none removed")
LOW_COVERAGE_NOTE = (f"LOW: scored on less than {MIN_COVERAGE:.0%} of the recording (the truth covers too little of it); "
                     "left out of the means")


def format_coverage(r: Result) -> str:
    """`98.5%` (scored samples / samples the protocol scores), `0.0% LOW` below `MIN_COVERAGE`, `-` without."""
    if r.coverage is None:
        return "-"
    return f"{100 * r.coverage:.1f}%" + (" LOW" if r.low_coverage else "")


ALIGNMENT_HEADER = ["dataset", "world A (x, y, z)", "|A|", "north", "body B (x, y, z)", "|B|", "rate pairs",
                    "residual deg/s", "of rate", "|g| g", "halves", "quality"]
ALIGNMENT_NOTE = ("Alignment per recording, deg (rotation vectors: A = R_ourworld_truthworld, a tilt and, with a "
                  "magnetometer, the turn to magnetic north; B = R_truthbody_imubody; truth in our frames = A R_truth B; "
                  "residual: the median rate residual, and its share of the median rate; halves: how far B fitted on "
                  "each half of the recording differ; quality: 'poor' leaves the recording unscored)")


def alignment_cells(a: dict[str, Any]) -> list[str]:
    """One alignment (`Alignment.to_json`, with its `dataset`) as the cells of `ALIGNMENT_HEADER`."""
    w, b = a["world_deg"], a["body_deg"]
    rate = a.get("truth_rate_deg_s")
    share = (f"{100 * a['rate_residual_deg_s'] / rate:.0f} %" if rate and a.get("rate_residual_deg_s") is not None
             else "-")
    return [a["dataset"], " ".join(f"{x:+7.2f}" for x in w), f"{np.linalg.norm(w):.2f}", _maybe(a.get("north_deg"), "+.1f"),
            " ".join(f"{x:+7.2f}" for x in b), f"{np.linalg.norm(b):.2f}", str(a.get("rate_pairs", "-")),
            _maybe(a.get("rate_residual_deg_s"), ".2f"), share, _maybe(a.get("gravity_g"), ".3f"),
            _maybe(a.get("halves_deg"), ".1f"), "poor" if a.get("problem") else "ok"]


def format_alignments(results: list[Result]) -> str:
    """The fitted rotations of an aligned run, one row per recording (`alignment_cells`): rotation
    vectors (axis * angle) and angles, deg, and the fit's quality."""
    rows = [alignment_cells(a) for a in recording_alignments(results)]
    widths = [max(len(row[i]) for row in [ALIGNMENT_HEADER, *rows]) for i in range(len(ALIGNMENT_HEADER))]
    lines = [ALIGNMENT_NOTE]
    lines += ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
              for row in [ALIGNMENT_HEADER, ["-" * w for w in widths], *rows]]
    return "\n".join(lines)


def _maybe(value: Any, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)
