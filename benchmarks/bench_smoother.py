"""Benchmark the batch smoothers: iterations, seconds and final cost against the length.

    python benchmarks/bench_smoother.py --data-dir /work/shared/data/ece276a [--minutes 6,60] [--no-ablation]

1. gn and gd, default cost, on ece276a/1 (5,645 samples) and on simulated recordings at 100 Hz
   (default 6 min = 36,000 samples and one hour = 360,000): wall time, time per sample,
   iterations (gd: and preconditioner builds), final cost, and the iteration at which the cost
   first came within 1 % and 0.1 % of the lowest final cost of the row's group. A smoother whose
   iteration count does not grow with the length shows flat "iters" columns. On the long
   recordings gn also runs with gd's re-levelled start (gn:level=10): from dead reckoning,
   which drifts upside down within the hour, both stay in a far worse local minimum.
   The longest simulated recording is repeated with an exact yaw-gyro scale ("z exact"): the
   default cost estimates x and y scale errors only, and the simulator's 4 % z error lets the
   heading wander over an hour, a slow mode of both solvers (the heading is barely observable).
2. Ablation on ece276a/1: gd without the chain preconditioner (precond=block: each sample's
   own curvature; precond=none: plain projected gradient descent), 200 iterations (tol 0).
3. Peak memory (tracemalloc) of gn and gd on ece276a/1 and the 6-minute recording, with the
   bytes per sample (a constant figure means linear growth).
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

from fusion import datasets
from fusion.calibration import calibrate
from fusion.estimators import build
from fusion.sim import SimSettings, simulate


def run(spec: str, imu, q0) -> tuple[float, dict]:
    start = time.perf_counter()
    est = build(spec + ",progress=false").estimate(imu, q0)
    return time.perf_counter() - start, est.diagnostics


def sim_recording(minutes: float, **settings):
    raw, truth = simulate(SimSettings(duration_s=60.0 * minutes, **settings))
    imu = calibrate(raw).apply(raw)
    q0 = truth.interpolate(imu.t[:1])[0].as_quat(scalar_first=True)[0]
    return imu, q0


def first_within(loss: np.ndarray, target: float, fraction: float) -> str:
    hit = np.flatnonzero(loss <= target * (1.0 + fraction))
    return str(hit[0]) if len(hit) else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default="/work/shared/data/ece276a")
    ap.add_argument("--dataset", default="ece276a/1")
    ap.add_argument("--minutes", default="6,60", help="simulated recordings, minutes at 100 Hz (default: 6,60)")
    ap.add_argument("--no-ablation", action="store_true")
    args = ap.parse_args()

    rec = datasets.load(args.dataset, args.data_dir)
    cases = [(args.dataset, rec.imu, datasets.initial_orientation(rec, "truth"))]
    minutes = [float(x) for x in args.minutes.split(",")]
    for m in minutes:
        imu, q0 = sim_recording(m)
        cases.append((f"sim {m:g} min", imu, q0))
    exact_z = SimSettings().gyro_sensitivity_ratio[:2] + (1.0,)
    imu, q0 = sim_recording(minutes[-1], gyro_sensitivity_ratio=exact_z)
    cases.append((f"{minutes[-1]:g} min z exact", imu, q0))

    print(f"{'recording':>16} {'samples':>8} {'spec':>12} {'seconds':>8} {'us/sample':>9} {'iters':>5} {'builds':>6} "
          f"{'final cost':>13} {'vs best':>9} {'iters to 1 %':>12} {'to 0.1 %':>8}")
    for label, imu, q0 in cases:
        specs = ["gn", "gd"] + (["gn:level=10"] if len(imu) > 20000 else [])
        rows = [(spec, *run(spec, imu, q0)) for spec in specs]
        best = min(d["loss"][-1] for _, _, d in rows)
        for spec, secs, d in rows:
            loss = d["loss"]
            print(f"{label:>16} {len(imu):>8} {spec:>12} {secs:8.2f} {1e6 * secs / len(imu):9.1f} {d['iterations']:5d} "
                  f"{d.get('preconditioner_builds', '-'):>6} {loss[-1]:13.6g} {100 * (loss[-1] / best - 1):8.4f}% "
                  f"{first_within(loss, best, 0.01):>12} {first_within(loss, best, 0.001):>8}", flush=True)

    if not args.no_ablation:
        label, imu, q0 = cases[0]
        print(f"\nAblation on {label} ({len(imu)} samples): gd without the chain preconditioner, 200 iterations")
        _, gn = run("gn", imu, q0)
        best = gn["loss"][-1]
        for spec in ("gd", "gd:precond=block,iters=200,tol=0", "gd:precond=none,iters=200,tol=0"):
            secs, d = run(spec, imu, q0)
            print(f"  {spec:34s} {secs:7.2f} s  {d['iterations']:4d} iterations  final cost {d['loss'][-1]:12.6g} "
                  f"= {d['loss'][-1] / best:9.4f} x gn's  (to 1 %: {first_within(d['loss'], best, 0.01)})", flush=True)

    print("\nPeak memory (tracemalloc):")
    for label, imu, q0 in cases[:2]:  # (tracemalloc slows numpy down: the short ones only)
        for spec in ("gn", "gd"):
            tracemalloc.start()
            secs, d = run(spec, imu, q0)
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"  {label:14s} {spec:3s} {len(imu):7d} samples  peak {peak / 2**20:7.1f} MiB  {peak / len(imu):7.0f} B/sample"
                  f"  ({secs:.2f} s under tracemalloc, {d['iterations']} iterations)", flush=True)


if __name__ == "__main__":
    main()
