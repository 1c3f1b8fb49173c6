"""Are the filters' defaults chosen on the data they are scored on? Leave-one-recording-out over
every shared recording (the nine course recordings at 100 Hz, BROAD's fourteen trials at 286 Hz,
and RepoIMU's TStick at 100 Hz and pendulum at about 167 Hz, each scored through its own alignment,
`--align`: the 78 of its 89 files that score): a script that prints figures, never a test.

For each tuned parameter of the estimator, one at a time (the others at their defaults), a grid
of values a factor of about 3 apart around the default is run on every recording (6-D,
inclination RMSE: what a gyro and an accelerometer observe; BROAD's protocol on BROAD, the
whole recording elsewhere). Every mean is the toolkit's one mean across datasets
(`scoring.stats.mean_across_datasets`: per dataset folder, broad, ece276a, repoimu/Pendulum and
repoimu/TStick, the mean over its recordings, then the mean of those), so that RepoIMU's 78 files
do not outweigh BROAD's fourteen. Then:

- in-sample: the value with the lowest mean over all recordings, and that mean;
- out-of-sample: for each recording, the value with the lowest mean over the *other* recordings,
  scored on the held-out one; the mean across datasets of those scores (no recording is scored
  with a value chosen on itself);
- the default's own mean, and how often the held-out choice equals the default.

A default that holds on data nobody tuned to has an out-of-sample mean within a few per cent of
its in-sample one, and is the value chosen in most folds.

    python benchmarks/cross_validate.py [--data-dir ../shared/data] [--estimator ekf] [--jobs 2] [--no-repoimu]
    python benchmarks/cross_validate.py --params Q,R --metric inclination --detail
    python benchmarks/cross_validate.py --estimator ukf-bias:taulp=2
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from fusion.evaluation.runs import run_compare
from fusion.evaluation.scoring.stats import mean_across_datasets

# parameter alias -> the grid (the default among the values); ekf's and ukf-bias's tuned defaults
GRIDS = {
    "Q": ["1e-4", "3e-4", "1e-3"],  # gyro noise density, rad^2/s
    "R": ["1e-5", "3e-5", "1e-4"],  # accelerometer noise density, g^2 s
    "tauc": ["0.03", "0.1", "0.3"],  # disturbance correlation time, s
    "taulp": ["0.3", "1.0", "1.5", "2.0", "3.0", "10.0"],  # accelerometer low-pass time constant, s
    "Qb": ["1e-9", "1e-8", "1e-7"],  # gyro bias random walk, rad^2/s^3
    "Ps0": ["1e-3", "1e-2", "3e-2"],  # gyro scale prior variance (3 %, 10 %, 17 %)
    "Rv": ["0.25", "1.0", "4.0"],  # velocity bound density, m^2/s (ekf only)
    "Qv": ["9e-6", "1e-4", "9e-4"],  # velocity states' acceleration noise density, g^2 s (ekf only)
    "lpcal": ["false", "true"],  # the low-passed sample corrects the calibration beside the velocity (ekf only)
    "sprt": ["0", "0.05", "0.1", "0.2"],  # the scale test's error probabilities (0: no test)
    "Psc": ["3e-5", "1e-4", "3e-4"],  # the scale test's calibrated prior variance (0.5 %, 1 %, 1.7 %)
    "tauslow": ["0", "1.0", "2.0", "5.0"],  # the slow external acceleration's correlation time, s (0: none; ekf only)
    "rtilt": ["0.0017", "0.0052", "0.0087", "inf"],  # the rest detector's tilt test, rad (0.1, 0.3, 0.5 deg; inf: none)
}
EKF_ONLY = {"Rv", "Qv", "lpcal", "tauslow"}


def default_values(estimator: str) -> dict[str, float | bool]:
    """alias -> the estimator's default value (from its Params dataclass)."""
    from dataclasses import fields

    from fusion.estimators import resolve

    params = resolve(estimator).params
    return {f.metadata["alias"]: getattr(params, f.name) for f in fields(params) if "alias" in f.metadata}


def is_value(text: str, value: float | bool) -> bool:
    """Whether a grid entry (`"1e-4"`, `"true"`) is the parameter value `value` (a float grid entry
    within 2 % of it: the grid prints rounded radians)."""
    if isinstance(value, bool):
        return text == str(value).lower()
    return float(text) == value or abs(float(text) - value) <= 0.02 * abs(value)


def across(recordings, scores) -> float:
    """The mean across datasets (`mean_across_datasets`) of scores, one per recording id."""
    return mean_across_datasets(dict(zip(recordings, scores)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default="../shared/data")
    parser.add_argument("--dataset", default="broad/*,ece276a/*",
                        help="recordings scored as they are (default: BROAD's and the course's, copies merged)")
    parser.add_argument("--aligned", default="repoimu/*",
                        help="recordings scored through a per-recording alignment (--align; default: RepoIMU's)")
    parser.add_argument("--no-repoimu", dest="aligned", action="store_const", const="", help="no aligned recordings")
    parser.add_argument("--estimator", default="ekf", help="the estimator, with parameters fixed for the sweep: ekf:taulp=2")
    parser.add_argument("--params", default=None, help=f"comma-separated aliases (default: {','.join(GRIDS)})")
    parser.add_argument("--metric", default="inclination", choices=("inclination", "total"))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--detail", action="store_true", help="also each value's mean per data set")
    args = parser.parse_args()
    names = args.params.split(",") if args.params else [n for n in GRIDS
                                                          if args.estimator.startswith("ekf") or n not in EKF_ONLY]
    unknown = [n for n in names if n not in GRIDS]
    if unknown:
        raise SystemExit(f"--params: no grid for {', '.join(unknown)} (known: {', '.join(GRIDS)})")
    name_only, _, fixed = args.estimator.partition(":")
    fixed_names = {item.split("=")[0] for item in fixed.split(",") if item}
    names = [n for n in names if n not in fixed_names]  # a parameter fixed in --estimator is not swept
    join = "," if fixed else ":"
    specs = [f"{args.estimator}{join}{n}={v}" for n in names for v in GRIDS[n]]
    start = time.perf_counter()
    results = list(run_compare(",".join(specs), args.dataset, args.data_dir, jobs=args.jobs, progress=True,
                               mag=False).results) if args.dataset else []
    if args.aligned:  # scored through the alignment; a file without truth (or that does not align) is left out
        aligned = run_compare(",".join(specs), args.aligned, args.data_dir, jobs=args.jobs, progress=True, mag=False,
                              align=True).results
        results += [r for r in aligned if r.error is None and r.rmse_deg is not None]
    wall = time.perf_counter() - start
    table: dict[tuple[str, str], float] = {}
    for r in results:
        if r.error is not None or r.rmse_deg is None:
            raise SystemExit(f"{r.dataset} {r.estimator}: {r.error or 'not scored'}")
        table[(r.estimator, r.dataset)] = r.rmse_deg[args.metric]
    # a recording counts where every setting scored it
    recordings = sorted(d for d in {d for _, d in table} if all((spec, d) in table for spec in specs))
    print(f"{args.estimator}: {len(specs)} settings x {len(recordings)} recordings, 6-D, {args.metric} RMSE (deg), "
          f"mean across datasets; "
          f"wall {wall:.0f} s")
    defaults = default_values(args.estimator)
    print(f"{'param':<6} {'values':<22} {'default':>8} {'in-sample':>18} {'out-of-sample':>14} {'gap':>6} "
          f"{'folds on default':>16}")
    for name in names:
        grid = {v: np.array([table[(f"{args.estimator}{join}{name}={v}", d)] for d in recordings]) for v in GRIDS[name]}
        default_value = next((v for v in grid if is_value(v, defaults[name])), None)
        values = list(grid)
        means = np.array([across(recordings, grid[v]) for v in values])
        best = int(np.argmin(means))
        out, on_default = [], 0
        for k in range(len(recordings)):
            others = np.array([across(np.delete(recordings, k), np.delete(grid[v], k)) for v in values])
            choice = int(np.argmin(others))
            out.append(grid[values[choice]][k])
            on_default += values[choice] == default_value
        out_mean = across(recordings, out)
        default_mean = across(recordings, grid[default_value]) if default_value else float("nan")
        print(f"{name:<6} {'/'.join(values):<22} {default_mean:8.3f} {means[best]:9.3f} ({name}={values[best]:<5}) "
              f"{out_mean:14.3f} {100 * (out_mean / means[best] - 1):5.1f}% {on_default:>9d} of {len(recordings)}")
        if args.detail:  # the mean per data set (the part before the '/' of a recording id) for each value
            groups = sorted({d.rsplit("/", 1)[0] for d in recordings})
            for v in values:
                parts = ", ".join(f"{g} {np.mean([x for x, d in zip(grid[v], recordings) if d.rsplit('/', 1)[0] == g]):.3f}"
                                  for g in groups)
                print(f"       {name}={v:<8} {parts}")
    print("default: the mean with the shipped value; gap: out-of-sample over in-sample")


if __name__ == "__main__":
    main()
