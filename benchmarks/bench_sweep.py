"""The BROAD sweep (`fusion ablate --preset broad-sweep`: 30 settings of `ekf`) over the BROAD
trials of the data directory, on the local process pool: prints the wall time, the best common
setting (TAGP) and each trial's own best. A script that prints figures, never a timed test.

    python benchmarks/bench_sweep.py [--data-dir ../shared/data/broad] [--jobs 2] [--out DIR]
"""
from __future__ import annotations

import argparse
import time

from fusion.evaluation.ablate import PRESETS, format_sweep
from fusion.evaluation.runs import run_ablate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default="../shared/data/broad")
    parser.add_argument("--dataset", default="all")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--scheduler", default=None, help="a dask.distributed scheduler instead of the pool")
    parser.add_argument("--out", default=None, help="also write the report folder")
    args = parser.parse_args()
    start = time.perf_counter()
    run = run_ablate(preset="broad-sweep", dataset=args.dataset, data_dir=args.data_dir, jobs=args.jobs,
                     scheduler=args.scheduler, out=args.out, progress=True)
    wall = time.perf_counter() - start
    trials = list(dict.fromkeys(r.dataset for r in run.results))
    samples = sum(r.samples for r in run.results)
    cpu = sum(r.seconds for r in run.results)
    from fusion.evaluation.ablate import sweep_summary

    summary = sweep_summary([r.to_json() for r in run.results])
    print(f"broad-sweep: {len(PRESETS['broad-sweep'])} settings x {len(trials)} trials = {len(run.results)} jobs, "
          f"{samples / 1e6:.1f} M filter-samples, jobs={args.jobs if not args.scheduler else args.scheduler}")
    print(f"wall time {wall:.1f} s ({wall / 60:.1f} min); filter time summed over jobs {cpu:.1f} s "
          f"({1e6 * cpu / samples:.1f} us/sample)")
    print(format_sweep(summary))


if __name__ == "__main__":
    main()
