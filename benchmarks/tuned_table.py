"""The README's tuned tables from a `fusion tune` run's results.json: per estimator, the library
default and the out-of-sample (tuned) mean, the tuned row's 95 % bootstrap interval over the
recordings, its wins / ties / losses against the best tuned row and the Holm-corrected Wilcoxon
p-value (`fusion.evaluation.scoring.stats.paired_statistics` over the tuned rows alone), and the mark
`*` for rows not significantly worse than the best; then the Friedman p-value.

    python benchmarks/tuned_table.py runs/tune-broad9/results.json
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from fusion.evaluation.scoring.stats import no_statistics_reason, paired_statistics


def tuned_table(doc: dict) -> str:
    tune = doc["tune"]
    scores = {t["estimator"]: {k: v for k, v in t["scores_tuned_deg"].items()} for t in tune["estimators"]}
    stats = paired_statistics(scores, metric=doc["settings"].get("metric", "total"))
    width = max(len(t["estimator"]) for t in tune["estimators"]) + 2
    lines = [f"{'estimator':<{width}}{'default':>8}{'tuned':>8}{'95% CI (tuned)':>17}  {'W/T/L':>8}  {'Holm p':>7}  "
             "common setting"]
    for t in tune["estimators"]:
        row = stats.row(t["estimator"]) if stats is not None else None
        ci = f"[{row.ci_low:.2f}, {row.ci_high:.2f}]" if row is not None and row.ci_low is not None else ""
        mark = "*" if row is not None and row.not_worse else " "
        wtl = f"{row.wins}/{row.ties}/{row.losses}" if row is not None else ""
        p = "best" if row is not None and row.p_holm is None else (f"{row.p_holm:.3f}" if row is not None else "")
        setting = ",".join(f"{k}={v:g}" for k, v in t["common_setting"].items()) or "default"
        fmt = lambda x: f"{x:8.2f}" if x is not None and math.isfinite(x) else f"{'-':>8}"  # noqa: E731
        lines.append(f"{t['estimator']:<{width}}{fmt(t['default_deg'])}{fmt(t['out_of_sample_deg'])}"
                     f"{ci:>16}{mark}  {wtl:>8}  {p:>7}  {setting}")
    if stats is None:
        lines.append(no_statistics_reason(scores) or "no statistics")
    else:
        friedman = f"Friedman p = {stats.friedman_p:.2g}" if stats.friedman_p is not None else "no Friedman test"
        lines.append(f"tuned rows over {len(stats.recordings)} recordings; W/T/L and Holm p against the best tuned "
                     f"row; *: not significantly worse than it; {friedman}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="a fusion tune run's results.json")
    print(tuned_table(json.loads(parser.parse_args().results.read_text())))


if __name__ == "__main__":
    main()
