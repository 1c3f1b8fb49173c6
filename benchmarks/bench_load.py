"""Seconds to load a selection of recordings as `fusion compare` does (read, check, calibrate), in
one process, with no estimator: what a run pays before its first job.

    FUSION_DATA=../shared/data python benchmarks/bench_load.py ['repoimu/*'] [--repeat 3]

Prints the number of recordings loaded (and of those that could not be read), the best and the
median wall time of the runs, and the seconds per recording. The loaders' warnings (held values,
non-unit truth rows, ...) are counted, not printed.
"""
from __future__ import annotations

import argparse
import statistics
import time
import warnings

from fusion.selection import load_selected


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?", default="repoimu/*")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    times = []
    for _ in range(args.repeat):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            start = time.perf_counter()
            recordings = load_selected(args.dataset, args.data_dir)
            times.append(time.perf_counter() - start)
    unreadable = sum("skipped (the other recordings go on)" in str(w.message) for w in caught)
    print(f"{args.dataset}: {len(recordings)} recordings loaded, {unreadable} could not be read, "
          f"{len(caught)} warnings")
    print(f"best {min(times):.2f} s, median {statistics.median(times):.2f} s over {args.repeat} runs; "
          f"{1e3 * min(times) / max(len(recordings), 1):.0f} ms a recording")


if __name__ == "__main__":
    main()
