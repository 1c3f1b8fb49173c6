"""`fusion compare --estimators all --dataset all` over the course recordings, timed on the local
process pool (`--jobs 2`) and on a two-worker Dask cluster started here on this machine
(127.0.0.1); prints both wall times and their ratio (target: Dask within 1.3x of local) and
checks that the rows agree. A script that prints figures, never a timed test.

The cluster is timed twice: with dask's default worker environment
(`distributed.nanny.pre-spawn-environ`: `MALLOC_TRIM_THRESHOLD_=65536`, which makes glibc return
freed memory at once, so the smoothers' large temporary arrays are paged in again on every
iteration, and one BLAS/OpenMP thread per worker), and with those variables unset (the
README's recommended worker configuration; the local pool's processes have neither).

    python benchmarks/bench_compare.py [--data-dir ../shared/data/ece276a]
"""
from __future__ import annotations

import argparse
import time

import dask
from distributed import LocalCluster

from fusion.evaluation.run.runner import WORKER_ENVIRON
from fusion.evaluation.runs import run_compare


def rows(run):
    return [{k: v for k, v in r.to_json().items() if k != "seconds"} for r in run.results]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default="../shared/data/ece276a")
    parser.add_argument("--estimators", default="all")
    args = parser.parse_args()

    start = time.perf_counter()
    local = run_compare(args.estimators, "all", args.data_dir, jobs=2)
    t_local = time.perf_counter() - start

    print(f"{len(local.results)} jobs ({len(set(r.dataset for r in local.results))} recordings x "
          f"{len(set(r.estimator for r in local.results))} estimators)")
    print(f"local pool, --jobs 2:        {t_local:6.1f} s")
    for label, trim in (("default worker environment", {}), ("pre-spawn environment unset", WORKER_ENVIRON)):
        with dask.config.set(trim):
            start = time.perf_counter()
            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                              dashboard_address=None) as cluster:
                t_up = time.perf_counter() - start
                start = time.perf_counter()
                run = run_compare(args.estimators, "all", args.data_dir, scheduler=cluster.scheduler_address)
                t_dask = time.perf_counter() - start
        print(f"Dask, 2 workers (localhost), {label}: {t_dask:6.1f} s  (+ {t_up:.1f} s to start the cluster, "
              f"not counted); ratio Dask / local {t_dask / t_local:.2f} (target <= 1.3); "
              f"rows equal (all but seconds): {rows(local) == rows(run)}")


if __name__ == "__main__":
    main()
