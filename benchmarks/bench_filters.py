"""Microseconds per sample of each recursive filter on recording ece276a/1.

    python benchmarks/bench_filters.py [--data-dir DIR] [--repeat 3] [--profile ukf]

Prints the best of `--repeat` runs for each filter (the whole-recording `estimate`, so the
base-class loop is included), the lean and the FilterPy-reference implementations of the
UKFs, and with `--profile SPEC` a cProfile of one run sorted by internal time. Figures
taken while other jobs share the machine are noisy; compare them on a quiet machine.
Without data the built-in `sim` recording is used (and said so).
"""
from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fusion.estimators import build  # noqa: E402
from fusion import datasets  # noqa: E402

SPECS = ("dr", "ukf", "ukf-bias", "ekf", "ukf:sigma=julier", "ukf:impl=filterpy", "ukf-bias:impl=filterpy,hf=false")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="folder holding ece276a/ (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--dataset", default="ece276a/1")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", default=None, metavar="SPEC", help="cProfile one run of this estimator")
    args = ap.parse_args(argv)
    try:
        rec = datasets.load(args.dataset, args.data_dir)
    except (FileNotFoundError, ValueError) as err:
        print(f"{args.dataset} not available ({err}); using the simulated recording 'sim'")
        rec = datasets.load("sim")
    q0 = datasets.initial_orientation(rec, "truth" if rec.truth is not None else None)
    n = len(rec.imu)
    print(f"{rec.id}: {n} samples")
    print(f"{'estimator':36s} {'us/sample':>10s}")
    for spec in SPECS:
        best = float("inf")
        for _ in range(args.repeat):
            est = build(spec)
            start = time.perf_counter()
            est.estimate(rec.imu, q0)
            best = min(best, time.perf_counter() - start)
        print(f"{spec:36s} {best / n * 1e6:10.1f}")
    if args.profile:
        prof = cProfile.Profile()
        est = build(args.profile)
        prof.runcall(est.estimate, rec.imu, q0)
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
