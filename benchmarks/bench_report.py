"""Wall time of `fusion compare --estimators all --dataset all --out DIR` and where it goes.

    python benchmarks/bench_report.py [--data-dir ../shared/data/ece276a] [--jobs 2] [--estimators all]

Prints (1) the end-to-end wall time of the CLI in a fresh process (imports included), and
(2) a breakdown from library calls in this process: loading, estimating and scoring (per
estimator, summed over recordings, measured inside the jobs), the pool's wall time,
writing the series, drawing the figures (the filter-consistency figures of one recording
timed again on their own), and writing the pages. Figures only; timings taken while other work
runs on the machine are noisy.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=os.environ.get("FUSION_DATA", str(ROOT.parent / "shared" / "data")))
    parser.add_argument("--dataset", default="all")
    parser.add_argument("--estimators", default="all")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    data_dir = Path(args.data_dir)
    if (data_dir / "ece276a").is_dir():
        data_dir = data_dir / "ece276a"

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "fusion", "compare", "--estimators", args.estimators, "--dataset", args.dataset,
               "--data-dir", str(data_dir), "--out", str(Path(tmp) / "cli"), "--jobs", str(args.jobs), "--no-progress"]
        start = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            sys.exit(proc.stderr)
        print(f"$ fusion compare --estimators {args.estimators} --dataset {args.dataset} --data-dir {data_dir} "
              f"--out DIR --jobs {args.jobs}")
        print(f"end-to-end wall time: {wall:.2f} s (cores available: {os.cpu_count()})\n")
        breakdown(args, data_dir, Path(tmp) / "lib")


def breakdown(args: argparse.Namespace, data_dir: Path, out: Path) -> None:
    t0 = time.perf_counter()
    from fusion.evaluation.report import render as report
    from fusion.evaluation.run import runner, series as series_io
    from fusion.evaluation.compare import results_json
    from fusion.estimators import resolve_all
    from fusion import datasets
    t_import = time.perf_counter() - t0

    sources = datasets.select(args.dataset, data_dir)
    t = time.perf_counter()
    recordings = [datasets.load_source(source) for source in sources]
    t_load = time.perf_counter() - t

    entries = resolve_all(args.estimators)
    t = time.perf_counter()
    results = runner.run(entries, recordings, jobs=args.jobs, keep=True)
    t_pool = time.perf_counter() - t
    estimate = defaultdict(float)
    for r in results:
        estimate[r.estimator] += r.seconds

    # scoring, serially in this process (it also runs inside each job)
    from fusion.evaluation.scoring.metrics import score
    t = time.perf_counter()
    for rec, r in zip((rec for rec in recordings for _ in entries), results):
        if rec.truth is not None:
            score(rec.truth, r.trajectory)
    t_score = time.perf_counter() - t

    doc = results_json(results, {"command": "benchmark", "estimator_details": {e.label: e.describe() for e in entries}})
    out.mkdir(parents=True)
    import json
    (out / "results.json").write_text(json.dumps(doc))
    t = time.perf_counter()
    (out / "series").mkdir()
    causal = {e.label: e.cls.causal for e in entries}
    per = len(entries)
    for n, rec in enumerate(recordings):
        series_io.save(out / "series" / f"{n:03d}.npz", series_io.from_results(rec, results[n * per:(n + 1) * per], causal))
    t_series = time.perf_counter() - t

    t = time.perf_counter()
    report._render_summary(doc, str(out))  # one process: the per-figure cost
    t_summary = time.perf_counter() - t
    t = time.perf_counter()
    report._render_recording(str(out / "series" / "000.npz"), str(out))
    t_one = time.perf_counter() - t
    from fusion.evaluation.report import plots
    first = series_io.load(out / "series" / "000.npz")
    t = time.perf_counter()
    for e in first.beliefs:
        plots.consistency_figure(first, e).savefig(out / "consistency.png")
    t_consistency = time.perf_counter() - t
    t = time.perf_counter()
    report.render(out, jobs=args.jobs)
    t_render = time.perf_counter() - t

    n = len(sources)
    print(f"breakdown ({n} recordings x {len(entries)} estimators = {len(results)} jobs, --jobs {args.jobs}):")
    print(f"  import evaluation/fusion          {t_import:7.2f} s")
    print(f"  load + calibrate all recordings   {t_load:7.2f} s  (serial; in the run each worker loads what it needs)")
    print(f"  job pool wall time                {t_pool:7.2f} s  (estimate + score, {args.jobs} workers)")
    for label, seconds in estimate.items():
        print(f"    estimate {label:24s} {seconds:7.2f} s  (sum over recordings, inside jobs)")
    print(f"  score all results (serial)        {t_score:7.2f} s")
    print(f"  write series .npz                 {t_series:7.2f} s")
    print(f"  summary figures (serial)          {t_summary:7.2f} s")
    print(f"  one recording's figures (serial)  {t_one:7.2f} s")
    print(f"    of which consistency figures    {t_consistency:7.2f} s  ({len(first.beliefs)} filters with a covariance)")
    print(f"  render all figures + pages        {t_render:7.2f} s  ({args.jobs} workers)")


if __name__ == "__main__":
    main()
