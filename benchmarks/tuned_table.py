"""The README's tuned tables, compact, from a `fusion tune` run's results.json: per estimator, the
library default and the out-of-sample (tuned) mean, and the tuned row's statistics as `fusion tune`'s
own table prints them (`fusion.evaluation.sweeps.tune.tuned_statistics`: its 95 % bootstrap interval
over the recordings, wins / ties / losses against the best tuned row, the Holm-corrected Wilcoxon
p-value, `*` for rows not significantly worse than the best, the Friedman p-value).

    python benchmarks/tuned_table.py runs/tune-broad9/results.json
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from fusion.evaluation.sweeps.tune import tuned_statistics


def tuned_table(doc: dict) -> str:
    tune = doc["tune"]
    _, cells, note = tuned_statistics(tune["estimators"], doc["settings"].get("metric", "total"))
    width = max(len(t["estimator"]) for t in tune["estimators"]) + 2
    lines = [f"{'estimator':<{width}}{'default':>8}{'tuned':>8}  {'95% CI (tuned)':>17}  {'W/T/L':>8}  {'Holm p':>7}  "
             "common setting"]
    for t in tune["estimators"]:
        setting = ",".join(f"{k}={v:g}" for k, v in t["common_setting"].items()) or "default"
        fmt = lambda x: f"{x:8.2f}" if x is not None and math.isfinite(x) else f"{'-':>8}"  # noqa: E731
        lines.append(f"{t['estimator']:<{width}}{fmt(t['default_deg'])}{fmt(t['out_of_sample_deg'])}  "
                     f"{cells[t['estimator']]}  {setting}")
    return "\n".join(lines + [note])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="a fusion tune run's results.json")
    print(tuned_table(json.loads(parser.parse_args().results.read_text())))


if __name__ == "__main__":
    main()
