"""Benchmark the batch smoothers: seconds, iterations, final cost, memory.

    python benchmarks/bench_smoother.py --data-dir /work/shared/data/ece276a [--gd-seconds 30]

1. gn and gd on ece276a/1 (init truth), both weightings: wall time, iterations, final cost,
   and for gd the time and iteration at which its cost first came within 1 % of gn's.
2. Peak memory (tracemalloc) of gn on ece276a/1 and on a simulated recording 10x longer,
   with the bytes per sample (linear growth means a constant per-sample figure).
Timings on a shared machine are noisy.
"""
from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout, not an installed copy

from fusion.estimators import build
from fusion import datasets
from fusion.calibration import calibrate
from fusion.sim import SimSettings, simulate


def run(spec: str, imu, q0):
    start = time.perf_counter()
    est = build(spec).estimate(imu, q0)
    return time.perf_counter() - start, est.diagnostics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default="/work/shared/data/ece276a")
    ap.add_argument("--dataset", default="ece276a/1")
    ap.add_argument("--gd-iters", type=int, default=3000)
    args = ap.parse_args()

    rec = datasets.load(args.dataset, args.data_dir)
    q0 = datasets.initial_orientation(rec, "truth")
    print(f"{args.dataset}: {len(rec.imu)} samples")
    print(f"{'spec':42s} {'seconds':>8s} {'iters':>6s} {'final cost':>14s} {'gd: s / iters to 1 % of gn':>28s}")
    for weighting in ("noise", "scalar"):
        secs, gn = run(f"gn:weighting={weighting},progress=false", rec.imu, q0)
        target = gn["loss"][-1] * 1.01
        print(f"{'gn:weighting=' + weighting:42s} {secs:8.3f} {gn['iterations']:6d} {gn['loss'][-1]:14.6g}")
        spec = f"gd:weighting={weighting},progress=false,iters={args.gd_iters}"
        secs, gd = run(spec, rec.imu, q0)
        hit = np.flatnonzero(gd["loss"] <= target)
        reach = f"{gd['elapsed_s'][hit[0]]:.2f} s / {hit[0]}" if len(hit) else "not reached"
        gap = gd["loss"][-1] / gn["loss"][-1] - 1
        print(f"{spec:42s} {secs:8.3f} {gd['iterations']:6d} {gd['loss'][-1]:14.6g} {reach:>28s}  (final gap {100 * gap:.2f} %)")

    print("\nPeak memory of gn (tracemalloc):")
    raw, truth = simulate(SimSettings(duration_s=10 * len(rec.imu) / 100.0))
    sim_imu = calibrate(raw).apply(raw)
    sim_q0 = truth.interpolate(sim_imu.t[:1])[0].as_quat(scalar_first=True)[0]
    for label, imu, q in ((args.dataset, rec.imu, q0), ("sim (10x longer)", sim_imu, sim_q0)):
        tracemalloc.start()
        secs, diag = run("gn:progress=false", imu, q)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"  {label:18s} {len(imu):7d} samples  peak {peak / 2**20:7.1f} MiB  {peak / len(imu):7.0f} B/sample"
              f"  ({secs:.2f} s under tracemalloc, {diag['iterations']} iterations)")


if __name__ == "__main__":
    main()
