"""Output folders of `fusion compare --out DIR` / `fusion ablate --out DIR`, and their report.

    DIR/results.json     the document `--json` writes (results, settings, versions)
    DIR/table.txt        the table the command printed
    DIR/command.txt      the exact command, and how to re-render
    DIR/series/NNN.npz   per recording, the time series the figures need (`evaluation.series`)
    DIR/figures/*.png    per recording: Euler angles over VICON, errors, smoother cost;
                         summary: RMSE heat maps, accuracy vs speed; ablations: RMSE vs parameter
    DIR/report.html      one self-contained page (images embedded as base64 PNG), readable offline
    DIR/report.md        the same for a repository (links to figures/)

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
from typing import Any, Callable

import numpy as np

from . import series as series_io
from .compare import Result, format_table
from .metrics import KINDS

RESULTS = "results.json"


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


def write_run(out_dir: str | Path, doc: dict[str, Any], results: list[Result], infos: list, jobs: int | None = 1,
              progress: bool = False, per_recording: bool = True) -> Path:
    """Write results.json, the series and the report of a run; returns report.html's path.

    doc: the results.json document (`evaluation.compare.results_json`).
    results: the run's results with trajectories, recording-major.
    infos: one `evaluation.runner.RecordingInfo` per recording (needed when per_recording).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / RESULTS).write_text(json.dumps(doc, indent=2) + "\n")
    command = doc.get("settings", {}).get("command", "")
    (out / "command.txt").write_text(f"{command}\n# re-render the report from this folder without recomputing:\n"
                                     f"fusion report {out}\n")
    series_dir = out / "series"
    if series_dir.is_dir():
        for old in series_dir.glob("*.npz"):
            old.unlink()
    if per_recording:
        series_dir.mkdir(exist_ok=True)
        causal = {label: d.get("causal", True) for label, d in doc["settings"].get("estimator_details", {}).items()}
        if len(results) % max(len(infos), 1):
            raise ValueError(f"{len(results)} results do not split evenly over {len(infos)} recordings")
        per = len(results) // max(len(infos), 1)
        for n, info in enumerate(infos):
            mine = results[n * per:(n + 1) * per]  # recording-major order
            series_io.save(series_dir / f"{n:03d}.npz", series_io.from_results(info, mine, causal))
    return render(out, jobs=jobs, progress=progress)


# --- rendering ---

def _save(fig, path: Path) -> None:
    fig.savefig(path, dpi=fig.dpi)


def _render_recording(series_path: str, fig_dir: str) -> list[tuple[str, str]]:
    """Draw one recording's figures; returns (caption, file name) pairs."""
    from . import plots

    s = series_io.load(Path(series_path))
    stem = f"rec-{Path(series_path).stem}-{plots.slug(s.id)}"
    out = []
    for suffix, make, caption in (
        ("euler", plots.euler_figure, "Euler angles (ZYX) over VICON"),
        ("error", plots.error_figure, "error over time"),
        ("loss", plots.loss_figure, "smoother cost per iteration"),
    ):
        fig = make(s)
        if fig is None:
            continue
        name = f"{stem}-{suffix}.png"
        _save(fig, Path(fig_dir) / name)
        out.append((f"{s.id}: {caption}", name))
    return out


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


def render(out_dir: str | Path, jobs: int | None = 1, progress: bool = False) -> Path:
    """(Re)build table.txt, figures/, report.html and report.md from results.json and series/."""
    out = Path(out_dir)
    doc_path = out / RESULTS
    if not doc_path.is_file():
        raise FileNotFoundError(f"{doc_path}: no results.json here (is {out} the --out folder of a run?)")
    try:
        doc = json.loads(doc_path.read_text())
        rows = doc["results"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{doc_path}: not a results document ({exc})") from None
    doc.setdefault("settings", {})
    results = [Result(r["dataset"], r["estimator"], r["samples"], r["seconds"], r["rmse_deg"], r["max_deg"],
                      alignment=r.get("alignment")) for r in rows]
    table = format_table(results, align=bool(doc["settings"].get("align", False)))
    (out / "table.txt").write_text(table + "\n")
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    for old in fig_dir.glob("*.png"):
        old.unlink()
    series_paths = sorted((out / "series").glob("*.npz")) if (out / "series").is_dir() else []
    tasks: list[tuple[Callable, tuple]] = [(_render_summary, (doc, str(fig_dir)))]
    tasks += [(_render_recording, (str(p), str(fig_dir))) for p in series_paths]
    outputs = _run_tasks(tasks, jobs, progress)
    summary, per_recording = outputs[0], [fig for figs in outputs[1:] for fig in figs]
    (out / "report.md").write_text(_markdown(doc, table, summary, per_recording))
    path = out / "report.html"
    path.write_text(_html(doc, summary, per_recording, fig_dir))
    return path


def _run_tasks(tasks: list[tuple[Callable, tuple]], jobs: int | None, progress: bool) -> list[Any]:
    from tqdm import tqdm

    from .runner import default_jobs, pool_context

    jobs = min(default_jobs() if not jobs else jobs, len(tasks))
    bar = tqdm(total=len(tasks), disable=not progress, file=sys.stderr, unit="fig", desc="figures", leave=False)
    try:
        if jobs <= 1:
            outputs = []
            for fn, args in tasks:
                outputs.append(fn(*args))
                bar.update()
            return outputs
        from concurrent.futures import ProcessPoolExecutor, as_completed

        from . import plots  # noqa: F401  (imported once here, inherited by forked workers)

        outputs: list[Any] = [None] * len(tasks)
        with ProcessPoolExecutor(max_workers=jobs, mp_context=pool_context()) as pool:
            futures = {pool.submit(fn, *args): n for n, (fn, args) in enumerate(tasks)}
            for future in as_completed(futures):
                outputs[futures[future]] = future.result()
                bar.update()
        return outputs
    finally:
        bar.close()


# --- the documents ---

def _fmt(v: Any) -> str:
    return "-" if v is None else f"{v:.2f}"


def _tables(doc: dict[str, Any]) -> tuple[list[str], list[list[str]], list[str], list[list[str]]]:
    """(header, rows) of the per-run table and of the per-estimator means, as text cells."""
    rows = doc["results"]
    header = ["dataset", "estimator", "samples", *(f"{k} RMSE" for k in KINDS), *(f"{k} max" for k in KINDS),
              "us/sample"]
    body = []
    for r in rows:
        rmse = [_fmt(r["rmse_deg"][k]) if r["rmse_deg"] else "-" for k in KINDS]
        worst = [_fmt(r["max_deg"][k]) if r["max_deg"] else "-" for k in KINDS]
        body.append([r["dataset"], r["estimator"], str(r["samples"]), *rmse, *worst,
                     f"{1e6 * r['seconds'] / max(r['samples'], 1):.1f}"])
    mean_header = ["estimator", "recordings scored", *(f"mean {k} RMSE" for k in KINDS), "mean us/sample"]
    means = []
    for label in dict.fromkeys(r["estimator"] for r in rows):
        mine = [r for r in rows if r["estimator"] == label]
        scored = [r for r in mine if r["rmse_deg"]]
        values = [_fmt(float(np.mean([r["rmse_deg"][k] for r in scored]))) if scored else "-" for k in KINDS]
        us = np.mean([1e6 * r["seconds"] / max(r["samples"], 1) for r in mine])
        means.append([label, str(len(scored)), *values, f"{us:.1f}"])
    return header, body, mean_header, means


ALIGNMENT_HEADER = ["dataset", "world A rotation vector, deg", "|A| deg", "body B rotation vector, deg", "|B| deg",
                    "rate pairs", "rate residual deg/s", "|g| g"]


def _alignment_text(doc: dict[str, Any]) -> str:
    if doc.get("settings", {}).get("align"):
        return ("Aligned (--align): the truth was mapped into our frames as A R_truth B, with A = R_ourworld_truthworld "
                "(a tilt only) and B = R_truthbody_imubody fitted once per recording from its gyro, accelerometer and "
                "truth, the same for every estimator; this hides a constant IMU-to-marker mounting rotation and a "
                "tilted truth world, not an estimator's errors.")
    return "No alignment applied; every estimator starts from the same initial orientation."


def _alignment_rows(doc: dict[str, Any]) -> list[list[str]]:
    out = []
    for a in recording_alignments_of(doc):
        out.append([a["dataset"], ", ".join(f"{x:+.2f}" for x in a["world_deg"]), f"{np.linalg.norm(a['world_deg']):.2f}",
                    ", ".join(f"{x:+.2f}" for x in a["body_deg"]), f"{np.linalg.norm(a['body_deg']):.2f}",
                    str(a.get("rate_pairs", "-")), _fmt_opt(a.get("rate_residual_deg_s"), ".2f"),
                    _fmt_opt(a.get("gravity_g"), ".3f")])
    return out


def recording_alignments_of(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """A results document's per-recording alignments (`alignments`, else the rows' first)."""
    if doc.get("alignments"):
        return doc["alignments"]
    out: dict[str, dict[str, Any]] = {}
    for r in doc["results"]:
        if r.get("alignment") and r["dataset"] not in out:
            out[r["dataset"]] = {"dataset": r["dataset"], **r["alignment"]}
    return list(out.values())


def _fmt_opt(value: Any, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


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
        out.append((label, f"{d.get('class', '')}: {kind}; {params}"))
    return out


def _title(doc: dict[str, Any]) -> str:
    settings = doc.get("settings", {})
    if settings.get("kind") == "ablate":
        what = settings.get("preset") or settings.get("estimator", "")
        return f"fusion ablation: {what}"
    return "fusion comparison"


def _markdown(doc: dict[str, Any], table: str, summary: list, per_recording: list) -> str:
    header, body, mean_header, means = _tables(doc)

    def md_table(head: list[str], rows: list[list[str]]) -> list[str]:
        esc = [[c.replace("|", "\\|") for c in row] for row in [head, *rows]]
        lines = ["| " + " | ".join(esc[0]) + " |", "|" + "|".join("---" for _ in head) + "|"]
        return lines + ["| " + " | ".join(row) + " |" for row in esc[1:]]

    settings = doc.get("settings", {})
    lines = [f"# {_title(doc)}", "", "Command:", "", "    " + settings.get("command", "(unknown)"), "",
             "Re-render without recomputing: `fusion report <this folder>`.", "", "## Results (RMSE and maximum, deg)", ""]
    lines += md_table(header, body) + ["", "## Means per estimator", ""] + md_table(mean_header, means)
    lines += ["", "Errors: total = geodesic angle between estimate and VICON; inclination = angle between the true and "
              "estimated gravity direction; heading = twist about world z of the error. " + _alignment_text(doc), ""]
    if _alignment_rows(doc):
        lines += ["## Alignment (--align)", ""] + md_table(ALIGNMENT_HEADER, _alignment_rows(doc)) + [""]
    lines += ["## Figures", ""] + [f"![{c}](figures/{n})" for c, n in summary] + [""]
    if per_recording:
        lines += ["## Per recording", ""] + [f"![{c}](figures/{n})" for c, n in per_recording] + [""]
    lines += ["## Settings", ""] + md_table(["setting", "value"], [[k, str(v)] for k, v in _settings_items(doc)])
    if _details_items(doc):
        lines += ["", "## Estimators", ""] + md_table(["estimator", "details"], [[k, v] for k, v in _details_items(doc)])
    lines += ["", "## Versions", ""] + md_table(["package", "version"], [[k, str(v)] for k, v in doc.get("versions", {}).items()])
    return "\n".join(lines) + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em}th{background:#f3f3f3}
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


def _img(fig_dir: Path, caption: str, name: str) -> str:
    data = base64.b64encode((fig_dir / name).read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(caption)}" data-file="{html.escape(name)}" '
            f'src="data:image/png;base64,{data}"><figcaption>{html.escape(caption)}</figcaption></figure>')


def _html(doc: dict[str, Any], summary: list, per_recording: list, fig_dir: Path) -> str:
    header, body, mean_header, means = _tables(doc)
    settings = doc.get("settings", {})
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(_title(doc))}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(_title(doc))}</h1>",
        "<p>Command (re-render this page without recomputing: <code>fusion report &lt;folder&gt;</code>):</p>",
        f"<pre>{html.escape(settings.get('command', '(unknown)'))}</pre>",
        "<h2>Results</h2><p>RMSE and maximum error in degrees. total = geodesic angle between estimate and VICON; "
        "inclination = angle between the true and estimated gravity direction; heading = twist about world z of "
        f"the error. {html.escape(_alignment_text(doc))}</p>",
        _html_table(header, body, "results", 2),
        "<h2>Means per estimator</h2>", _html_table(mean_header, means, "means", 1),
        *(["<h2>Alignment (--align)</h2>", _html_table(ALIGNMENT_HEADER, _alignment_rows(doc), "alignment", 1)]
          if _alignment_rows(doc) else []),
        "<h2>Summary figures</h2>", *(_img(fig_dir, c, n) for c, n in summary),
    ]
    if per_recording:
        parts += ["<h2>Per recording</h2><p>Grey: no VICON (gaps, outside its span); red: gyro marked invalid.</p>",
                  *(_img(fig_dir, c, n) for c, n in per_recording)]
    parts += ["<h2>Settings</h2>", _html_table(["setting", "value"], [[k, str(v)] for k, v in _settings_items(doc)],
                                               "settings", 9)]
    if _details_items(doc):
        parts += ["<h2>Estimators</h2>", _html_table(["estimator", "details"], [list(x) for x in _details_items(doc)],
                                                     "estimators", 9)]
    parts += ["<h2>Versions</h2>", _html_table(["package", "version"],
                                               [[k, str(v)] for k, v in doc.get("versions", {}).items()], "versions", 9),
              "</body></html>"]
    return "\n".join(parts) + "\n"
