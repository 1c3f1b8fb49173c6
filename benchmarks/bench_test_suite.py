"""The test suite's wall time as CI runs it: the README's test command (`pytest`, one worker per core)
with the data, timed, with the machine's load before and after and the slowest tests. A script that
prints figures, never a timed test.

    FUSION_DATA=../shared/data python benchmarks/bench_test_suite.py [--durations 20] [-- extra pytest arguments]

Other work on the machine lengthens the figure: the load averages it prints say how quiet it was
(on 2 cores, a load above 2 while it ran means it shared them).
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--durations", type=int, default=20, help="how many of the slowest tests to print")
    parser.add_argument("extra", nargs="*", help="more arguments for pytest")
    args = parser.parse_args()
    if not os.environ.get("FUSION_DATA"):
        print("FUSION_DATA is not set: the tests that need the data will be skipped (CI sets it)", file=sys.stderr)
    load_before = os.getloadavg()
    start, cpu = time.monotonic(), os.times()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           f"--durations={args.durations}", *args.extra], capture_output=True, text=True)
    wall = time.monotonic() - start
    used = os.times()
    children = (used.children_user - cpu.children_user) + (used.children_system - cpu.children_system)
    lines = proc.stdout.splitlines()
    slowest = [line for line in lines if re.match(r"^\d+\.\d+s (call|setup|teardown)", line)]
    summary = next((line for line in reversed(lines) if re.search(r"\d+ (passed|failed)", line)), "(no summary)")
    print("\n".join(slowest))
    print(summary)
    print(f"wall {wall / 60:.1f} min, CPU {children / 60:.1f} min over {os.cpu_count()} cores; load average "
          f"before {load_before[0]:.1f}, after {os.getloadavg()[0]:.1f} (1 min)")
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
