"""Microseconds per sample of each recursive filter on recording ece276a/1, and the compile times.

    python benchmarks/bench_filters.py [--data-dir DIR] [--dataset ID] [--mag off] [--repeat 5] [--cpu]
                                       [--specs SPEC;SPEC...] [--profile SPEC] [--no-compile-times]

Prints, per estimator, the best of at least `--repeat` runs (more for the fast ones, up to
about a second each) of the whole-recording `estimate` (the loop and the per-sample
diagnostics recording included): the compiled filters (`impl=compiled`, the default), their
numpy references (`ekf:impl=numpy`, the UKFs' `impl=numpy` and `impl=filterpy`) and VQF (the
`vqf` package: `VQF.updateBatch` and `offlineVQF`, through this toolkit's adapters) on the
same recording, with the ratio to VQF (`--specs`: these estimators instead, separated by `;`;
`--mag off`: without the magnetometer, 6-D; `--cpu`: the process's CPU time instead of the wall
clock, less disturbed by other work on a shared machine; each estimator is run in turn, round after
round, so that a change in the machine's load reaches them all). Then the compile time of the two numba kernels
(`_compiled_ekf.estimate`, `_compiled_ukf.estimate`, which serves `ukf` and `ukf-bias`; a
compiled filter compiles or loads them when it is built, `_compiled.load`), measured in a
fresh process with an empty cache (`NUMBA_CACHE_DIR` pointed at a new temporary folder: numba
compiles), and again in another with that cache filled (numba loads the machine code). With
`--profile SPEC` a cProfile of one run sorted by internal time. Figures taken while other
jobs share the machine are noisy; compare them on a quiet machine. Without data the built-in
`sim` recording is used (and said so).
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fusion.estimators import build  # noqa: E402
from fusion import datasets  # noqa: E402

SPECS = (
    "ekf", "ukf", "ukf-bias",  # compiled (the defaults)
    "ekf:Rv=inf",  # ekf without its velocity states (9 states, the model of ukf-bias)
    "ukf:sigma=julier,kappa=2", "ukf-bias:sigma=merwe,alpha=1,kappa=0.5",
    "ekf:impl=numpy", "ukf:impl=numpy", "ukf-bias:impl=numpy",  # the numpy references
    "ukf:impl=filterpy", "ukf-bias:impl=filterpy,hf=false",  # FilterPy's update
    "dr", "vqf", "vqf-offline",  # peers: dead reckoning, VQF (updateBatch), offlineVQF
)
MIN_SECONDS = 1.0  # fast estimators are repeated until they have run this long

# Run in a fresh process: the time to import the kernel module (numba included) and of
# `_compiled.load()`, which compiles both kernels (empty cache) or loads them from the cache; the
# filters call it when they are built.
_FIRST_CALL = r"""
import json, time
t0 = time.perf_counter()
from fusion.estimators.filters import _compiled
t1 = time.perf_counter()
_compiled.load()
print(json.dumps({"import": t1 - t0, "kernels": time.perf_counter() - t1}))
"""


def time_estimate(spec: str, imu, q0, repeat: int, clock=time.perf_counter) -> float:
    """Best time of `build(spec).estimate(imu, q0)` by `clock`, s (one untimed warm-up run first)."""
    return time_estimates([spec], imu, q0, repeat, clock)[spec]


def time_estimates(specs, imu, q0, repeat: int, clock=time.perf_counter) -> dict[str, float]:
    """{spec: best time of `build(spec).estimate(imu, q0)` by `clock`, s}: one untimed warm-up run
    each, then rounds of one run of each spec in turn, at least `repeat` rounds and until every
    spec has run for `MIN_SECONDS` (at most 50 rounds)."""
    for spec in specs:
        build(spec).estimate(imu, q0)
    best = {spec: float("inf") for spec in specs}
    total = {spec: 0.0 for spec in specs}
    runs = 0
    while runs < repeat or (min(total.values()) < MIN_SECONDS and runs < 50):
        for spec in specs:
            est = build(spec)
            start = clock()
            est.estimate(imu, q0)
            elapsed = clock() - start
            best[spec], total[spec] = min(best[spec], elapsed), total[spec] + elapsed
        runs += 1
    return best


def compile_times(first_call: str = _FIRST_CALL) -> tuple[dict, dict]:
    """(empty cache, cached): {"import": s, "kernels": s}, each from a fresh process running
    `first_call` (a script printing those two times as JSON on its last line)."""
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
        runs = [subprocess.run([sys.executable, "-c", first_call], env=env, capture_output=True, text=True,
                               check=True, cwd=ROOT) for _ in range(2)]
    cold, cached = (json.loads(run.stdout.strip().splitlines()[-1]) for run in runs)
    return cold, cached


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="folder holding ece276a/ (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--dataset", default="ece276a/1")
    ap.add_argument("--mag", choices=("on", "off"), default="on", help="off: drop the magnetometer (6-D)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cpu", action="store_true", help="time with the process's CPU time, not the wall clock")
    ap.add_argument("--specs", default=None, help="the estimators to time, separated by ';' (default: all; vqf is "
                    "always added for the ratio)")
    ap.add_argument("--profile", default=None, metavar="SPEC", help="cProfile one run of this estimator")
    ap.add_argument("--no-compile-times", action="store_true", help="skip the compile-time measurement")
    args = ap.parse_args(argv)
    try:
        rec = datasets.load(args.dataset, args.data_dir)
    except (FileNotFoundError, ValueError) as err:
        print(f"{args.dataset} not available ({err}); using the simulated recording 'sim'")
        rec = datasets.load("sim")
    q0 = datasets.initial_orientation(rec, "truth" if rec.truth is not None else None)
    imu = rec.imu if args.mag == "on" else rec.imu.replace(mag_ut=None)
    n = len(imu)
    specs = list(SPECS) if args.specs is None else [spec for spec in args.specs.split(";") if spec]
    if "vqf" not in specs:
        specs.append("vqf")
    clock = time.process_time if args.cpu else time.perf_counter
    print(f"{rec.id}{' (6-D)' if args.mag == 'off' else ''}: {n} samples; best of >= {args.repeat} runs of the "
          f"whole estimate, {'CPU time' if args.cpu else 'wall clock'}")
    print(f"{'estimator':40s} {'us/sample':>10s} {'x vqf':>8s}")
    times = {spec: best / n * 1e6 for spec, best in time_estimates(specs, imu, q0, args.repeat, clock).items()}
    for spec, us in times.items():
        print(f"{spec:40s} {us:10.2f} {us / times['vqf']:8.2f}")
    if not args.no_compile_times:
        cold, cached = compile_times()
        print("numba kernels in a fresh process (s):")
        print(f"{'':40s} {'empty cache':>12s} {'cached':>8s}")
        print(f"{'import fusion.estimators.filters._compiled':40s} {cold['import']:12.2f} {cached['import']:8.2f}")
        print(f"{'compile / load the filters kernels':40s} {cold['kernels']:12.2f} {cached['kernels']:8.2f}")
    if args.profile:
        prof = cProfile.Profile()
        est = build(args.profile)
        prof.runcall(est.estimate, imu, q0)
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
