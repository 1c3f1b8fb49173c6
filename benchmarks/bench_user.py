"""What the harness adds to a user's estimator: prints, on a real recording, the time of the
user's code called directly and through the toolkit, and their ratio. A script that prints
figures, never a timed test.

    python benchmarks/bench_user.py [--data-dir ../shared/data] [--dataset ece276a/1] [--repeat 5]

Two estimators of the kind the README's "Your estimator in the table" shows (tests/test_user_estimators.py
and tests/user_fixtures/my_ukf.py hold them):

- a complementary filter, a plain function `f(t, gyro, acc, q0)`: called directly on the contract's
  arrays, against `fusion compare`'s job (the arrays built from the recording, the output checked:
  shape, finiteness, norms, the convention-slip test) timed as the table times it;
- a FilterPy UKF through `fusion.estimators.adapters.filterpy`: the filter's own predict/update loop
  written by hand, against the adapter's `estimate`.

The job's time is what the table reports (`seconds`: the estimator's `estimate`, the checks of
its output included); scoring, which every estimator's row needs, is timed apart. Best of
`--repeat` runs each.
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def best_pair(a, b, repeat: int) -> tuple[float, float]:
    """Best times of `a` and `b`, run alternately (so that a change in the machine's load falls on both)."""
    ta, tb = [], []
    for _ in range(repeat):
        ta.append(best(a, 1))
        tb.append(best(b, 1))
    return min(ta), min(tb)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=os.environ.get("FUSION_DATA", str(ROOT.parent / "shared" / "data")))
    parser.add_argument("--dataset", default="ece276a/1")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    from fusion import datasets
    from fusion.estimators import resolve
    from fusion.estimators.adapters import user
    from fusion.evaluation.run.job import run_one
    from fusion.evaluation.scoring.metrics import score

    rec = datasets.load(args.dataset, args.data_dir)
    q0 = datasets.initial_orientation(rec)
    n = len(rec.imu)
    tests = (ROOT / "tests" / "test_user_estimators.py").read_text()
    student = re.search(r"STUDENT = '''(.*?)'''", tests, re.S).group(1)
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "student.py").write_text(student)
        (Path(tmp) / "my_ukf.py").write_text((ROOT / "tests" / "user_fixtures" / "my_ukf.py").read_text())
        os.chdir(tmp)
        sys.path.insert(0, tmp)
        print(f"{args.dataset}: {n} samples; best of {args.repeat}")

        entry = resolve("./student.py:complementary")
        fn = entry.cls.function
        inputs = user.function_inputs(rec.imu, q0)
        seconds = []
        direct, _ = best_pair(lambda: fn(*[np.array(a) for a in inputs]),
                              lambda: seconds.append(run_one(rec, entry).seconds), args.repeat)
        job = min(seconds)
        trajectory = run_one(rec, entry).trajectory
        scoring = best(lambda: score(rec.truth, trajectory), args.repeat)
        print(f"complementary filter (function): direct {1e6 * direct / n:.2f} us/sample, as a job "
              f"{1e6 * job / n:.2f} us/sample: harness {100 * (job / direct - 1):+.1f} % of the estimator's own time "
              f"(scoring, apart: {1e3 * scoring:.1f} ms for every estimator)")

        entry = resolve("./my_ukf.py:MyUKF")
        module = user.load_source(Path(tmp) / "my_ukf.py", (Path(tmp) / "my_ukf.py").read_bytes())
        t, gyro, acc, q = user.function_inputs(rec.imu, q0)
        valid = np.all(np.isfinite(gyro), axis=1)

        def by_hand() -> None:
            ukf = module.make_ukf(q, float(np.median(np.diff(t))))
            out = np.empty((n, 4))
            out[0] = q
            for k in range(1, n):
                if valid[k]:
                    ukf.predict(dt=t[k] - t[k - 1], gyro=gyro[k])
                    ukf.update(acc[k])
                out[k] = ukf.x / np.linalg.norm(ukf.x)

        own, adapted = best_pair(by_hand, lambda: entry.build().estimate(rec.imu, q0), args.repeat)
        print(f"FilterPy UKF: its own loop {1e6 * own / n:.1f} us/sample, through the adapter {1e6 * adapted / n:.1f} "
              f"us/sample: adapter {100 * (adapted / own - 1):+.1f} %")


if __name__ == "__main__":
    main()
