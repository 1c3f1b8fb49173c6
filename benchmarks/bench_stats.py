"""Time the statistics a comparison adds (`fusion.evaluation.scoring.stats`): 13 estimators x 14 recordings.

    python benchmarks/bench_stats.py [--estimators 13] [--recordings 14] [--repeat 5]

The rows are made-up but seeded (gamma-distributed RMSEs, one estimator per mean level, as a
BROAD comparison of every estimator has), so every run times the same work. Prints:

1. cold: a fresh process importing the toolkit's comparison layer (what `fusion compare` has
   loaded anyway), then timed: every metric's statistics (`run_statistics`: bootstrap intervals,
   Wilcoxon and Holm, Friedman and Nemenyi, i.e. the critical-difference diagram's data),
   including the first import of SciPy's statistics, statsmodels and scikit-posthocs;
2. what a `compare --out` asks for, in that process afterwards: the table's column
   (`format_table`), results.json (`results_json`) and the report's statistics, the repeated
   requests served from the cache;
3. warm: every metric's statistics once more with the cache cleared (the computation alone);
4. drawing the critical-difference diagrams (the report does it in its figure pool; not part of
   the target).
The target: under 2 s added to a compare for 1 + 2 (figures excluded). Timings taken while other
work runs on the machine are noisy: the median of `--repeat` fresh processes is printed.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import numpy as np
from fusion.evaluation import compare
from fusion.evaluation.run import job  # what a compare has imported before its table
k, n = int(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(2006)
rows = []
for j in range(n):
    for i in range(k):
        total = float(rng.gamma(4.0, 0.5) * (1 + 0.15 * i))
        rmse = {"total": total, "inclination": total / 3, "heading": 0.9 * total}
        rows.append(job.Result(f"broad/{j:02d}", f"est{i:02d}", 50000, 0.5, rmse, dict(rmse), scored_samples=50000,
                               coverage=1.0, magnetometer=True))
t0 = time.perf_counter()
from fusion.evaluation.scoring import stats
run = stats.run_statistics(compare.summary_groups(rows))
t1 = time.perf_counter()
table = compare.format_table(rows)
doc = compare.results_json(rows, {})
again = stats.run_statistics(compare.summary_groups(rows))
t2 = time.perf_counter()
stats._statistics.cache_clear()
stats.run_statistics(compare.summary_groups(rows))
t3 = time.perf_counter()
from fusion.evaluation.report.stats_plots import cd_figure
for c in run.comparisons:
    cd_figure(c.statistics, c.metric).savefig("/dev/null", format="png")
t4 = time.perf_counter()
assert again == run and all(c.statistics is not None for c in run.comparisons)
print(json.dumps({"cold": t1 - t0, "compare": t2 - t1, "warm": t3 - t2, "figures": t4 - t3,
                  "friedman_p": run.of("total")[0].statistics.friedman_p}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimators", type=int, default=13)
    parser.add_argument("--recordings", type=int, default=14)
    parser.add_argument("--repeat", type=int, default=5, help="fresh processes timed (the median is printed)")
    args = parser.parse_args()
    runs = []
    for _ in range(args.repeat):
        proc = subprocess.run([sys.executable, "-c", CHILD, str(args.estimators), str(args.recordings)], cwd=ROOT,
                              capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(proc.stderr)
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))

    def median(key: str) -> float:
        return statistics.median(r[key] for r in runs)

    added = statistics.median(r["cold"] + r["compare"] for r in runs)
    print(f"{args.estimators} estimators x {args.recordings} recordings, 3 metrics, median of {args.repeat} "
          f"fresh processes (Friedman p of total: {runs[0]['friedman_p']:.2g})")
    print(f"  cold (first imports + every metric's statistics): {median('cold'):.2f} s")
    print(f"  then the table, results.json and the report:      {median('compare'):.3f} s")
    print(f"  added to a compare (target < 2 s):                {added:.2f} s")
    print(f"  warm (the computation alone, 3 metrics):          {median('warm'):.3f} s")
    print(f"  drawing the 3 critical-difference diagrams:       {median('figures'):.2f} s (in the report's figure pool)")


if __name__ == "__main__":
    main()
