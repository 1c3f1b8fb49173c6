"""The smoothers `gd` and `gn` in 9-D on BROAD's fourteen trials, beside offlineVQF.

    python benchmarks/broad_9d_smoothers.py [--data-dir DIR] [--estimators gd,gn,vqf-offline] [--jobs 1]
                                            [--leave-one-out] [--grid 0.03,0.1,0.3]

Runs each estimator through the harness twice (`fusion.evaluation.runs.run_compare`, the same
runs as `fusion compare --estimators gd,gn,vqf-offline --dataset 'broad/*'` with and without
`--mag off`) under BROAD's protocol (the movement phases; a 9-D row is scored on its total error
with no heading offset removed, a 6-D row on its inclination) and prints:
- the per-trial total RMSE (deg) of the 9-D rows, each row's 6-D/9-D mark, the mean over the
  fourteen trials and over the five magnet trials (28-36), beside VQF's 9-D figures run directly
  on the trials (the data README);
- the inclination RMSE (deg) of the 9-D rows beside that of the 6-D rows (`--mag off`): the
  6-D rows are the smoothers without a magnetometer, unchanged; with the heading term in the
  cost (the default) the 9-D inclination may differ a little (the heading moves the velocity
  model's and the x/y gyro biases' fit), with `gn:mterm=stage` not at all.

The smoothers' magnetometer defaults (`SmootherParams`, mag_*) were chosen on the simulator
(`tests/test_mag_smoothers.py`) and the filters' gates, once for every recording; they were not
fitted to BROAD. `--leave-one-out` checks what a choice on BROAD would give: for each trial, the
heading measurement density Rm among `--grid` (`SmootherParams.mag_heading_noise_rad2_s`, rad^2
s) with the best `gn` mean on the other thirteen trials is run on the held-out one; the
held-out mean is printed beside the default's.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fusion import datasets

sys.path.insert(0, str(Path(__file__).resolve().parent))
from broad_9d import VQF_DIRECT_DEG, VQF_DIRECT_MEAN_DEG, leave_one_out, rows  # noqa: E402

MAGNET_TRIALS = ("28", "30", "32", "34", "36")
OFFLINE_VQF_DIRECT_MEAN_DEG = 2.68


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--estimators", default="gd,gn,vqf-offline")
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--leave-one-out", action="store_true")
    parser.add_argument("--grid", default="0.03,0.1,0.3", help="heading noise densities Rm for --leave-one-out, rad^2 s")
    args = parser.parse_args(argv)
    sources = datasets.select("broad/*", args.data_dir)
    if len(sources) != 14:
        print(f"expected BROAD's fourteen trials, found {len(sources)}", file=sys.stderr)
        return 1
    specs = args.estimators.split(",")
    nine = rows(specs, args.data_dir, args.jobs, mag=True)
    six = rows(specs, args.data_dir, args.jobs, mag=False)
    trials = sorted(nine[specs[0]])
    total = {s: {t: nine[s][t][0]["total"] for t in trials} for s in specs}
    print("total RMSE, deg (BROAD protocol, movement phases; 9-D rows: no heading offset removed)")
    print(f"{'trial':6s}" + "".join(f"{s:>16s}" for s in specs) + f"{'VQF direct':>12s}")
    for t in trials:
        cells = "".join(f"{total[s][t]:11.2f} {'9-D' if nine[s][t][1] else '6-D':4s}" for s in specs)
        direct = VQF_DIRECT_DEG.get(t)
        print(f"{t:6s}{cells}{'' if direct is None else f'{direct:12.2f}'}")
    print(f"{'mean':6s}" + "".join(f"{np.mean(list(total[s].values())):11.2f}     " for s in specs)
          + f"{VQF_DIRECT_MEAN_DEG:12.2f}   (offlineVQF direct {OFFLINE_VQF_DIRECT_MEAN_DEG:.2f})")
    magnets = [t for t in trials if t in MAGNET_TRIALS]
    print(f"{'magnet':6s}" + "".join(f"{np.mean([total[s][t] for t in magnets]):11.2f}     " for s in specs)
          + f"{np.mean([VQF_DIRECT_DEG[t] for t in magnets]):12.2f}   (trials {', '.join(magnets)})")
    print()
    print("inclination RMSE, deg: 9-D rows beside the 6-D rows (--mag off)")
    print(f"{'trial':6s}" + "".join(f"{s + ' 9-D':>16s}{s + ' 6-D':>16s}" for s in specs))
    for t in trials:
        print(f"{t:6s}" + "".join(f"{nine[s][t][0]['inclination']:16.3f}{six[s][t][0]['inclination']:16.3f}"
                                  for s in specs))
    print(f"{'mean':6s}" + "".join(f"{np.mean([nine[s][t][0]['inclination'] for t in trials]):16.3f}"
                                   f"{np.mean([six[s][t][0]['inclination'] for t in trials]):16.3f}" for s in specs))
    for s in specs:
        diff = max(abs(nine[s][t][0]["inclination"] - six[s][t][0]["inclination"]) for t in trials)
        print(f"{s}: largest |9-D - 6-D| inclination difference {diff:.2e} deg")
    if args.leave_one_out:
        default = np.mean(list(total["gn"].values())) if "gn" in total else float("nan")
        leave_one_out([f"gn:Rm={rm}" for rm in args.grid.split(",")], args.data_dir, args.jobs, default, "gn")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
