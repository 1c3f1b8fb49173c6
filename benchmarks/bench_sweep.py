"""The BROAD sweep (`fusion ablate --preset broad-sweep`: 30 settings of `ekf`) over the BROAD
trials of the data directory, on the local process pool: prints the wall time, the filter time,
the peak resident memory of the main process and of the largest worker, the best common
setting (TAGP) and each trial's own best. A script that prints figures, never a timed test.

    python benchmarks/bench_sweep.py [--data-dir ../shared/data/broad] [--jobs 2] [--out DIR]
    python benchmarks/bench_sweep.py --scaling 2,14     # memory against the number of jobs
    python benchmarks/bench_sweep.py --local-cluster 2  # the same sweep on a two-worker Dask LocalCluster
    python benchmarks/bench_sweep.py --local-cluster 2 --dask-default-environ   # with dask's worker environment

The cluster's workers get the environment docs/dask.md recommends (dask's `MALLOC_TRIM_THRESHOLD_`
and one-thread BLAS variables unset); with dask's own, the filters run about a fifth slower per sample.

With `--scaling N1,N2,...` it runs the sweep on the first N1, N2, ... trials, each in a fresh
process (so each peak is its own), and prints one line per size: memory must not grow with
the number of jobs. Peaks are `getrusage`'s `ru_maxrss`: of the main process (RUSAGE_SELF) and
of the largest worker it reaped (RUSAGE_CHILDREN).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from fusion.evaluation.sweeps.ablate import PRESETS, format_sweep, sweep_summary
from fusion.evaluation.runs import run_ablate


def measure(data_dir: str, dataset: str, jobs: int, scheduler: str | None, out: str | None, progress: bool) -> dict:
    """One sweep in this process: its run and figures."""
    start = time.perf_counter()
    run = run_ablate(preset="broad-sweep", dataset=dataset, data_dir=data_dir, jobs=jobs, scheduler=scheduler,
                     out=out, progress=progress)
    wall = time.perf_counter() - start
    return {"run": run, "wall_s": wall, "trials": len({r.dataset for r in run.results}), "jobs": len(run.results),
            "samples": sum(r.samples for r in run.results), "filter_s": sum(r.seconds for r in run.results),
            "main_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "worker_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}


def trial_ids(data_dir: str, count: int) -> str:
    from fusion import datasets

    ids = [s.id for s in datasets.select("all", data_dir)]
    if count > len(ids):
        raise SystemExit(f"--scaling {count}: {data_dir} holds {len(ids)} trials")
    return ",".join(ids[:count])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default="../shared/data/broad")
    parser.add_argument("--dataset", default="all")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--scheduler", default=None, help="a dask.distributed scheduler instead of the pool")
    parser.add_argument("--local-cluster", type=int, default=None, metavar="N",
                        help="run on a dask.distributed LocalCluster of N single-threaded worker processes")
    parser.add_argument("--dask-default-environ", action="store_true",
                        help="with --local-cluster: dask's default worker environment instead of docs/dask.md's")
    parser.add_argument("--out", default=None, help="also write the report folder (and its journal)")
    parser.add_argument("--scaling", default=None, metavar="N1,N2", help="memory for the first N1, N2, ... trials")
    parser.add_argument("--json-line", action="store_true", help=argparse.SUPPRESS)  # one size, for --scaling
    args = parser.parse_args()
    if args.scaling:
        print(f"{'trials':>6} {'jobs':>5} {'wall s':>7} {'main MB':>8} {'worker MB':>9}")
        for count in (int(n) for n in args.scaling.split(",")):
            line = subprocess.run([sys.executable, __file__, "--data-dir", args.data_dir, "--jobs", str(args.jobs),
                                   "--dataset", trial_ids(args.data_dir, count), "--json-line"],
                                  capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
            m = json.loads(line)
            print(f"{m['trials']:6d} {m['jobs']:5d} {m['wall_s']:7.1f} {m['main_mb']:8.0f} {m['worker_mb']:9.0f}")
        return
    cluster = None
    if args.local_cluster:
        import dask
        from distributed import LocalCluster

        from fusion.evaluation.run.runner import WORKER_ENVIRON

        # docs/dask.md's worker environment, unless --dask-default-environ asks for dask's own
        with dask.config.set({} if args.dask_default_environ else WORKER_ENVIRON):
            cluster = LocalCluster(n_workers=args.local_cluster, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        args.scheduler, args.jobs = cluster.scheduler_address, args.local_cluster
    try:
        m = measure(args.data_dir, args.dataset, args.jobs, args.scheduler, args.out, progress=not args.json_line)
    finally:
        if cluster is not None:
            cluster.close()
    if args.json_line:
        print(json.dumps({k: v for k, v in m.items() if k != "run"}))
        return
    print(f"broad-sweep: {len(PRESETS['broad-sweep'])} settings x {m['trials']} trials = {m['jobs']} jobs, "
          f"{m['samples'] / 1e6:.1f} M filter-samples, jobs={args.jobs if not args.scheduler else args.scheduler}")
    print(f"wall time {m['wall_s']:.1f} s ({m['wall_s'] / 60:.1f} min); filter time summed over jobs "
          f"{m['filter_s']:.1f} s ({1e6 * m['filter_s'] / m['samples']:.1f} us/sample)")
    print(f"filter share of the workers' time: {m['filter_s'] / (m['wall_s'] * args.jobs):.0%} "
          f"(filter time / (wall time x {args.jobs} workers))")
    print(f"peak resident memory: main process {m['main_mb']:.0f} MB, largest worker {m['worker_mb']:.0f} MB")
    print(format_sweep(sweep_summary([r.to_json() for r in m["run"].results])))


if __name__ == "__main__":
    main()
