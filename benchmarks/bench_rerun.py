"""What `--rerun FILE.rrd` adds to a compare run (targets: under 5 s and under 100 MB).

    FUSION_DATA=../shared/data python benchmarks/bench_rerun.py [--dataset ece276a/1]
        [--estimators ekf,gn,vqf] [--repeat 3]

Runs `fusion compare --estimators ... --dataset ... --jobs 1` in a fresh process each time, without
and with `--rerun`, alternating, `--repeat` times each (a first, untimed run warms the kernel
cache and the file cache), and prints the median wall time of each, their difference, the .rrd
file's size and each run's peak resident memory (ru_maxrss of its process).
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# one compare run in this process, then its peak resident memory (KiB on Linux) on stderr's last line
CHILD = ("import resource, sys\nfrom fusion.cli import main\ncode = main(sys.argv[1:])\n"
         "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\nsys.exit(code)\n")


def run(args: list[str]) -> tuple[float, float]:
    """(wall seconds, peak resident MiB) of one compare run in a new process."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"fusion {' '.join(args)} failed:\n{done.stderr}")
    return seconds, int(done.stderr.strip().splitlines()[-1]) / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="ece276a/1")
    parser.add_argument("--estimators", default="ekf,gn,vqf")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    base = ["compare", "--estimators", args.estimators, "--dataset", args.dataset, "--jobs", "1", "--no-progress"]
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "run.rrd"
        run(base + ["--rerun", str(rrd)])  # warm-up: compiled kernels, files in the page cache
        plain, viz = [], []
        for _ in range(args.repeat):
            plain.append(run(base))
            viz.append(run(base + ["--rerun", str(rrd)]))
        size_mb = rrd.stat().st_size / 1e6
    t0, t1 = statistics.median(s for s, _ in plain), statistics.median(s for s, _ in viz)
    m0, m1 = statistics.median(m for _, m in plain), statistics.median(m for _, m in viz)
    print(f"fusion {' '.join(base)}  (median of {args.repeat} runs each)")
    print(f"without --rerun  {t0:6.2f} s   peak memory {m0:6.0f} MiB")
    print(f"with --rerun     {t1:6.2f} s   peak memory {m1:6.0f} MiB")
    print(f"added            {t1 - t0:6.2f} s   peak memory {m1 - m0:+6.0f} MiB   .rrd file {size_mb:.1f} MB")


if __name__ == "__main__":
    main()
