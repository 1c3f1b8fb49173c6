"""One error per recording and estimator, as a grid: the per-trial tables of `docs/results.md`,
from the `results.json` of a `fusion compare --out` (or `--json`) run. Prints, never computes.

    python benchmarks/results_pivot.py runs/broad/results.json --metric inclination
    python benchmarks/results_pivot.py runs/broad/results.json --metric total --estimators ekf,gd,vqf,vqf-offline
"""
from __future__ import annotations

import argparse
import json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", help="results.json of a compare run")
    parser.add_argument("--metric", default="inclination", choices=("total", "inclination", "heading"))
    parser.add_argument("--estimators", default=None, help="comma-separated rows to show (default: all, in run order)")
    args = parser.parse_args()
    rows = json.load(open(args.results))["results"]
    names = args.estimators.split(",") if args.estimators else list(dict.fromkeys(r["estimator"] for r in rows))
    trials = list(dict.fromkeys(r["dataset"] for r in rows))
    value = {(r["dataset"], r["estimator"]): (r.get("rmse_deg") or {}).get(args.metric) for r in rows}
    width = max(len(t.split("/")[-1]) for t in trials)
    print(f"{args.metric} RMSE, deg")
    print(f"{'recording':<{width}} " + " ".join(f"{n:>{max(6, len(n))}}" for n in names))
    for t in trials:
        cells = [value.get((t, n)) for n in names]
        print(f"{t.split('/')[-1]:<{width}} " + " ".join(
            f"{c:>{max(6, len(n))}.2f}" if c is not None else f"{'-':>{max(6, len(n))}}" for c, n in zip(cells, names)))


if __name__ == "__main__":
    main()
