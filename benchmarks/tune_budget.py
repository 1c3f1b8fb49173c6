"""What `fusion tune --estimators all --dataset 'broad/*'` costs, estimator by estimator, before it is run.

    python benchmarks/tune_budget.py [--data-dir DIR] [--trial ID] [--repeat 3] [--library]
                                     [--library-samples 3000] [--estimators all]

For every estimator of `--estimators` (default all registered), 6-D (`--mag off`) and 9-D (`--mag on`):
its grid's size (`fusion.evaluation.sweeps.tune.grid_settings`, the default included), its cost per
sample with its default setting on one BROAD trial (`--trial`, best of `--repeat` runs), and the
product with the number of samples of BROAD's trials (all of them, as the tune runs each setting on
each): the CPU time of the tune's runs, and that time over 2 cores. Scoring, loading and the pool's
overhead are not counted (the tune's wall time is measured by running it: docs/results.md). With
`--library` the peers that have a compiled twin are timed with `impl=library` instead (on the first
`--library-samples` samples): the cost the twins remove. Figures taken while other work shares the
machine are high; re-measure on a quiet machine.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from fusion import datasets  # noqa: E402
from fusion.estimators import ESTIMATORS, build, resolve  # noqa: E402
from fusion.evaluation.sweeps.tune import grid_settings  # noqa: E402

from bench_filters import time_estimate  # noqa: E402


def has_twin(name: str) -> bool:
    return "impl" in getattr(ESTIMATORS[name].Params, "__dataclass_fields__", {})


def per_sample_us(spec: str, imu, q0, repeat: int, first: int | None = None) -> float:
    if first is not None:  # one run on the first samples (the library path takes seconds to minutes)
        part = imu.window(0, first)
        est = build(spec)
        start = time.perf_counter()
        est.estimate(part, q0)
        return (time.perf_counter() - start) / len(part) * 1e6
    return time_estimate(spec, imu, q0, repeat) / len(imu) * 1e6


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="the recordings (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--trial", default="broad/06_undisturbed_fast_rotation_A")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--library", action="store_true", help="time the peers with a twin through their library")
    ap.add_argument("--library-samples", type=int, default=3000)
    ap.add_argument("--estimators", default="all")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    sources = datasets.select("broad/*", args.data_dir)
    total = sum(len(datasets.LoadOptions().load(s).imu) for s in sources)
    rec = datasets.load(args.trial, args.data_dir)
    q0 = datasets.initial_orientation(rec)
    names = list(ESTIMATORS) if args.estimators == "all" else args.estimators.split(",")
    print(f"{len(sources)} BROAD trials, {total} samples; cost per sample on {rec.id}"
          f"{' (peers with a twin: their library)' if args.library else ''}")
    print(f"{'estimator':15s} {'grid 6-D':>8s} {'us 6-D':>8s} {'grid 9-D':>8s} {'us 9-D':>8s} {'CPU min':>8s}")
    cpu_s = 0.0
    for name in names:
        entry = resolve(name)
        row, cost = [], 0.0
        for mag, imu in ((False, rec.imu.replace(mag_ut=None)), (True, rec.imu)):
            grid = len(grid_settings(entry, mag))
            library = args.library and has_twin(name)
            spec = f"{name}:impl=library" if library else name
            try:
                us = per_sample_us(spec, imu, q0, args.repeat, args.library_samples if library else None)
            except ImportError as exc:  # a peer whose library is not installed
                print(f"{name:15s} not installed: {exc}")
                break
            row += [grid, us]
            cost += grid * total * us * 1e-6
        else:
            cpu_s += cost
            print(f"{name:15s} {row[0]:8d} {row[1]:8.2f} {row[2]:8d} {row[3]:8.2f} {cost / 60:8.1f}", flush=True)
    print(f"total: {cpu_s / 60:.1f} CPU-minutes for the runs of both tunes (6-D and 9-D), "
          f"{cpu_s / 120:.1f} min on 2 cores; one of them about half")


if __name__ == "__main__":
    main()
