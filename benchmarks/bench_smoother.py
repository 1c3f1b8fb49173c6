"""Benchmark the batch smoothers: time per sample against offlineVQF, iterations, seconds and
final cost against the length, peak memory.

    python benchmarks/bench_smoother.py [--data-dir DIR] [--minutes 6,60] [--no-ablation] [--no-reference]

0. Time per sample of gn and gd (compiled, the default) on ece276a/1 and BROAD trial 15
   (`--vqf-datasets`), with offlineVQF (`vqf-offline`, the `vqf` package) timed in the same
   run on the same recording, and the ratio to it (target: at most 5); best of `--repeat`
   runs of the whole `estimate` (start, solve, significance test), the kernels compiled or
   loaded beforehand; wall and CPU time (the rounds interleave the estimators, so that the
   machine's load falls on all alike). Also their numpy references (`impl=numpy`, one run each; skip with
   --no-reference). The machine's cores and load average are printed: ratios are taken in one
   run because other jobs slow every row down, not all alike.
1. gn and gd, default cost, on ece276a/1 (5,645 samples) and on simulated recordings at 100 Hz
   (default 6 min = 36,000 samples and one hour = 360,000): wall time, time per sample,
   iterations (gd: and preconditioner builds), final cost, and the iteration at which the cost
   first came within 1 % and 0.1 % of the lowest final cost of the row's group. A smoother whose
   iteration count does not grow with the length shows flat "iters" columns. On the long
   recordings gn also runs without the re-levelled start (gn:level=0): from dead reckoning,
   which drifts upside down within the hour, it stays in a far worse local minimum.
   The longest simulated recording is repeated with an exact yaw-gyro scale ("z exact"): the
   default cost estimates x and y scale errors only, and the simulator's 4 % z error lets the
   heading wander over an hour, a slow mode of both solvers (the heading is barely observable).
2. Ablation on ece276a/1: gd without the chain preconditioner (precond=block: each sample's
   own curvature; precond=none: plain projected gradient descent), 200 iterations (tol 0).
3. Peak memory (tracemalloc: the numpy arrays, not numba's few scratch blocks) of gn and gd,
   compiled and numpy, on ece276a/1 and the 6-minute recording, with the bytes per sample (a
   constant figure means linear growth). Peak resident memory on an hour: bench_long.py.
Timings on a shared machine are noisy.
"""
from __future__ import annotations

import argparse
import os
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


VQF_TARGET = 5.0  # gn and gd: at most this many times offlineVQF's time per sample


def _spec(spec: str, extra: str) -> str:
    return spec + ("," if ":" in spec else ":") + extra


def run(spec: str, imu, q0) -> tuple[float, dict]:
    est = build(_spec(spec, "progress=false"))  # built first: the compiled kernels load here, untimed
    start = time.perf_counter()
    traj = est.estimate(imu, q0)
    return time.perf_counter() - start, traj.diagnostics


def best_times(specs: list[str], imu, q0, repeat: int) -> dict[str, tuple[float, float, dict]]:
    """Best wall and CPU time of each spec's `estimate`, s, over `repeat` rounds after an untimed
    one, and its diagnostics. The rounds interleave the specs, so that a change in the machine's
    load falls on all of them; the CPU time (of this process, the kernels are single-threaded)
    is what load changes least."""
    ests = {spec: build(spec if spec.startswith("vqf") else _spec(spec, "progress=false")) for spec in specs}
    diag = {spec: est.estimate(imu, q0).diagnostics or {} for spec, est in ests.items()}
    wall = {spec: float("inf") for spec in specs}
    cpu = dict(wall)
    for _ in range(repeat):
        for spec, est in ests.items():
            w, c = time.perf_counter(), time.process_time()
            est.estimate(imu, q0)
            wall[spec] = min(wall[spec], time.perf_counter() - w)
            cpu[spec] = min(cpu[spec], time.process_time() - c)
    return {spec: (wall[spec], cpu[spec], diag[spec]) for spec in specs}


def against_offline_vqf(datasets_: list[str], data_dir: str, repeat: int, reference: bool) -> None:
    """Section 0: us per sample of gn, gd (and their numpy references) and offlineVQF, one run."""
    print(f"Time per sample against offlineVQF: {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f} at the start (other jobs slow every row; compare ratios from one run)")
    for name in datasets_:
        rec = datasets.load(name, data_dir)
        q0 = datasets.initial_orientation(rec, "truth")
        n = len(rec.imu)
        times = best_times(["vqf-offline", "gn", "gd"], rec.imu, q0, repeat)
        if reference:
            times.update(best_times(["gn:impl=numpy", "gd:impl=numpy"], rec.imu, q0, 1))
        vqf_wall, vqf_cpu, _ = times["vqf-offline"]
        print(f"\n{name}: {n} samples, best of {repeat} interleaved runs (numpy references: 1); "
              f"load average {os.getloadavg()[0]:.1f} at the end")
        print(f"  {'estimator':16s} {'wall us/sample':>14s} {'x offlineVQF':>12s} {'CPU us/sample':>13s} {'x offlineVQF':>12s} "
              f"{'iterations':>10s}")
        for spec, (wall, cpu, d) in times.items():
            verdict = ""
            if spec in ("gn", "gd"):
                verdict = "  target <= 5x (CPU): " + ("met" if cpu <= VQF_TARGET * vqf_cpu else "MISSED")
            print(f"  {spec:16s} {1e6 * wall / n:14.2f} {wall / vqf_wall:12.2f} {1e6 * cpu / n:13.2f} {cpu / vqf_cpu:12.2f} "
                  f"{str(d.get('iterations', '-')):>10s}{verdict}", flush=True)


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
    ap.add_argument("--data-dir", default=os.environ.get("FUSION_DATA", "data"),
                    help="folder holding ece276a/ and broad/ (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--dataset", default="ece276a/1")
    ap.add_argument("--vqf-datasets", default="ece276a/1,broad/15_undisturbed_fast_translation_A",
                    help="recordings of section 0 (empty: skip it)")
    ap.add_argument("--repeat", type=int, default=5, help="section 0: timed runs per estimator (best is kept)")
    ap.add_argument("--no-reference", action="store_true", help="section 0 without the numpy references")
    ap.add_argument("--minutes", default="6,60", help="simulated recordings, minutes at 100 Hz (default: 6,60; empty: none)")
    ap.add_argument("--no-ablation", action="store_true")
    args = ap.parse_args()

    if args.vqf_datasets:
        against_offline_vqf(args.vqf_datasets.split(","), args.data_dir, args.repeat, not args.no_reference)
        print()
    rec = datasets.load(args.dataset, args.data_dir)
    cases = [(args.dataset, rec.imu, datasets.initial_orientation(rec, "truth"))]
    minutes = [float(x) for x in args.minutes.split(",") if x]
    for m in minutes:
        imu, q0 = sim_recording(m)
        cases.append((f"sim {m:g} min", imu, q0))
    if minutes:
        exact_z = SimSettings().gyro_sensitivity_ratio[:2] + (1.0,)
        imu, q0 = sim_recording(minutes[-1], gyro_sensitivity_ratio=exact_z)
        cases.append((f"{minutes[-1]:g} min z exact", imu, q0))

    print(f"{'recording':>16} {'samples':>8} {'spec':>12} {'seconds':>8} {'us/sample':>9} {'iters':>5} {'builds':>6} "
          f"{'final cost':>13} {'vs best':>9} {'iters to 1 %':>12} {'to 0.1 %':>8}")
    for label, imu, q0 in cases:
        specs = ["gn", "gd"] + (["gn:level=0"] if len(imu) > 20000 else [])
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
        for spec in ("gn", "gd", "gn:impl=numpy", "gd:impl=numpy"):
            tracemalloc.start()
            secs, d = run(spec, imu, q0)
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"  {label:14s} {spec:13s} {len(imu):7d} samples  peak {peak / 2**20:7.1f} MiB  {peak / len(imu):7.0f} B/sample"
                  f"  ({secs:.2f} s under tracemalloc, {d['iterations']} iterations)", flush=True)


if __name__ == "__main__":
    main()
