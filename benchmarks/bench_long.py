"""Long recordings: time and peak memory of every registered estimator on a simulated recording
of one hour at 100 Hz (360,000 samples), and whether memory grows linearly (10, 30, 60 min).

    python benchmarks/bench_long.py                      # every estimator, 10/30/60 min
    python benchmarks/bench_long.py --estimators dr --minutes 60
    python benchmarks/bench_long.py --check              # exit 1 if a target is missed
    python benchmarks/bench_long.py --estimators gn,gd --minutes 60 --one-thread   # the smoothers on one thread

Each (estimator, duration) runs in a fresh subprocess, so estimators do not share a peak:
the worker simulates the recording (`fusion.sim`), calibrates it, runs the estimator, scores
it (`fusion.evaluation.scoring.metrics.score`) and reports the wall time of each phase (and the CPU time of the
estimate: the smoothers run on two threads, `smoothers._compiled_cost.range_cost` and `_eliminate_in_ranges`), its peak resident
memory (`VmHWM` from /proc/self/status, or `ru_maxrss`) and, for the smoothers, the number of
iterations. The row `(none)` is the same pipeline
without an estimator: the simulator, calibration and scoring themselves.

Targets: peak < 2 GB for every estimator; a smoother (`causal = False`: gn, gd) under 5 s
and under 500 MB peak on the one-hour recording (the peak is the whole worker's: the simulator
and the scoring too; the `(none)` row shows theirs). "linear" compares the memory slope
30 -> 60 min with 10 -> 30 min (MB per 100k samples); a ratio near 1 is linear, well above 1
superlinear. Timing on a shared machine is noisy: the load average is printed at the start and
for each run; rerun on a quiet one before quoting.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PEAK_LIMIT_MB = 2048.0
SMOOTHER_LIMIT_S = 5.0  # on the longest recording
SMOOTHER_PEAK_MB = 500.0
BASELINE = "(none)"


def peak_rss_mb() -> float:
    """Peak resident set size of this process, MB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def worker(name: str, duration_s: float, one_thread: bool = False) -> dict:
    """One pipeline run in this (fresh) process; returns the figures as a dict. one_thread: the
    smoothers on one thread (`smoothers._compiled_ranges.SPLIT_MIN_SAMPLES` and `RANGE_SAMPLES` out of reach)."""
    import numpy as np

    from fusion import estimators
    from fusion.evaluation.scoring.metrics import score
    from fusion.calibration import calibrate
    from fusion.sim import SimSettings, simulate

    out: dict = {"estimator": name, "duration_s": duration_s, "rss_start_mb": peak_rss_mb()}
    t0 = time.perf_counter()
    raw, truth = simulate(SimSettings(duration_s=duration_s))
    t1 = time.perf_counter()
    imu = calibrate(raw).apply(raw)
    t2 = time.perf_counter()
    out.update(samples=len(imu), sim_s=t1 - t0, calib_s=t2 - t1)
    if name == BASELINE:
        traj = estimators.build("dr").estimate(imu, truth.quat_wxyz[0])  # something to score (lean, vectorised)
        out["estimate_s"] = None
    else:
        try:
            estimator = estimators.build(name)
        except ImportError as exc:
            return {**out, "skipped": str(exc)}
        if one_thread:
            from fusion.estimators.smoothers import _compiled_ranges as _compiled_smoother_ranges

            _compiled_smoother_ranges.SPLIT_MIN_SAMPLES = sys.maxsize
            _compiled_smoother_ranges.RANGE_SAMPLES = (sys.maxsize, sys.maxsize)
        rot, _ = truth.interpolate(imu.t[:1])
        t3, c3 = time.perf_counter(), time.process_time()
        traj = estimator.estimate(imu, rot[0].as_quat(scalar_first=True))
        out["estimate_s"], out["estimate_cpu_s"] = time.perf_counter() - t3, time.process_time() - c3
        out["causal"] = type(estimator).causal
        iterations = traj.diagnostics.get("iterations") if traj.diagnostics else None
        out["iterations"] = None if iterations is None else int(iterations)
    t4 = time.perf_counter()
    result = score(truth, traj)
    out.update(score_s=time.perf_counter() - t4, rmse_total_deg=result.rmse_deg["total"],
               finite=bool(np.all(np.isfinite(traj.quat_wxyz))), peak_mb=peak_rss_mb())
    return out


def run_worker(name: str, duration_s: float, timeout_s: float, one_thread: bool = False) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", name, "--duration-s", str(duration_s)]
    cmd += ["--one-thread"] if one_thread else []
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"estimator": name, "duration_s": duration_s, "error": f"timeout after {timeout_s:.0f} s"}
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return {"estimator": name, "duration_s": duration_s, "error": f"exit {proc.returncode}: {last}"}
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - start
    out["load"] = os.getloadavg()[0]
    return out


def fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--estimators", default="all", help="comma-separated registry names (default: all)")
    parser.add_argument("--minutes", default="10,30,60", help="recording lengths, minutes (default: 10,30,60)")
    parser.add_argument("--timeout-s", type=float, default=1800.0, help="per run")
    parser.add_argument("--check", action="store_true", help="exit 1 if a target is missed")
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    parser.add_argument("--one-thread", action="store_true",
                        help="the smoothers on one thread, as before their passes were split in two (for comparison)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--duration-s", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        print(json.dumps(worker(args.worker, args.duration_s, args.one_thread)))
        return 0

    from fusion import estimators
    names = list(estimators.ESTIMATORS) if args.estimators == "all" else args.estimators.split(",")
    minutes = [float(m) for m in args.minutes.split(",")]
    print(f"one-hour benchmark: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} (noisy if high)")
    rows = []
    for name in [BASELINE, *names]:
        for m in minutes:
            row = run_worker(name, 60.0 * m, args.timeout_s, args.one_thread)
            rows.append(row)
            print(f"  {name:>10} {m:>4g} min: " + (row.get("error") or row.get("skipped") or
                  f"estimate {fmt(row.get('estimate_s'), '.2f')} s, peak {row['peak_mb']:.0f} MB, "
                  f"load average {row['load']:.1f}"), flush=True)

    print()
    header = f"{'estimator':>10} {'min':>4} {'samples':>8} {'sim s':>6} {'calib s':>7} {'estimate s':>10} " \
             f"{'cpu s':>6} {'us/sample':>9} {'iters':>5} {'score s':>7} {'peak MB':>8} {'RMSE deg':>8}"
    print(header)
    print("-" * len(header))
    for r in rows:
        if "peak_mb" not in r:
            print(f"{r['estimator']:>10} {r['duration_s'] / 60:>4g}  {r.get('error') or 'skipped: ' + r.get('skipped', '')}")
            continue
        us = None if r["estimate_s"] is None else 1e6 * r["estimate_s"] / r["samples"]
        print(f"{r['estimator']:>10} {r['duration_s'] / 60:>4g} {r['samples']:>8} {r['sim_s']:>6.2f} {r['calib_s']:>7.2f} "
              f"{fmt(r['estimate_s'], '.2f'):>10} {fmt(r.get('estimate_cpu_s'), '.2f'):>6} {fmt(us, '.2f'):>9} {fmt(r.get('iterations'), 'd'):>5} {r['score_s']:>7.2f} {r['peak_mb']:>8.0f} "
              f"{r['rmse_total_deg']:>8.2f}")

    print()
    print(f"{'estimator':>10} {'MB/100k 10->30':>14} {'MB/100k 30->60':>14} {'ratio':>6} {'linear':>6} "
          f"{'peak<2GB':>8} {'smoother<5s':>12} {'smoother<500MB':>14}")
    failed = False
    for name in [BASELINE, *names]:
        mine = sorted((r for r in rows if r["estimator"] == name and "peak_mb" in r), key=lambda r: r["samples"])
        if not mine:
            continue
        slopes = [1e5 * (b["peak_mb"] - a["peak_mb"]) / (b["samples"] - a["samples"]) for a, b in zip(mine, mine[1:])]
        ratio = slopes[-1] / slopes[0] if len(slopes) >= 2 and slopes[0] > 1.0 else None
        linear = "-" if ratio is None else ("yes" if ratio < 1.5 else "NO")
        peak_ok = all(r["peak_mb"] < PEAK_LIMIT_MB and r["finite"] for r in mine)
        longest = mine[-1]
        smoother = "-" if longest.get("causal", True) else (
            "yes" if longest["estimate_s"] < SMOOTHER_LIMIT_S else f"NO ({longest['estimate_s']:.1f} s)")
        smoother_mb = "-" if longest.get("causal", True) else (
            "yes" if longest["peak_mb"] < SMOOTHER_PEAK_MB else f"NO ({longest['peak_mb']:.0f} MB)")
        failed |= (not peak_ok) or smoother.startswith("NO") or smoother_mb.startswith("NO") or linear == "NO"
        s1 = fmt(slopes[0] if slopes else None, ".1f")
        s2 = fmt(slopes[-1] if len(slopes) >= 2 else None, ".1f")
        print(f"{name:>10} {s1:>14} {s2:>14} {fmt(ratio, '.2f'):>6} {linear:>6} {'yes' if peak_ok else 'NO':>8} {smoother:>12} "
              f"{smoother_mb:>14}")
    failed |= any("error" in r for r in rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 1 if (args.check and failed) else 0


if __name__ == "__main__":
    sys.exit(main())
