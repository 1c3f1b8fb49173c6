"""`fusion stress` on BROAD's trials with every fault kind at its five documented severities (and the
clean run): prints the wall time, the jobs, and the peak memory of the whole run (the main process
and its worker processes together), against the targets (15 minutes, 1 GB on 2 cores). A script
that prints figures, never a timed test; other work on the machine slows it: say so beside a figure.

    FUSION_DATA=../shared/data python benchmarks/bench_stress.py [--estimators ekf,vqf,madgwick,mahony,gn]
        [--dataset 'broad/*'] [--jobs 2] [--out DIR] [--fault KIND=LEVELS ...]

The run is `fusion stress` in a child process (its command line is printed); a sampler here reads,
every `--every` seconds, the memory of that process and of every process below it from /proc:
the sum of their resident set sizes (RSS: pages shared between the forked workers and the main
process counted once per process, an upper bound) and of their proportional set sizes (PSS,
/proc/PID/smaps_rollup: each shared page split between the processes sharing it, what the run
really occupies); the peaks of both sums are printed. The CPU time of the run (user + system, the
main process and the workers it reaped: `getrusage(RUSAGE_CHILDREN)`) divided by the cores used is
what the run would take on an idle machine with that many cores (a lower bound: it assumes both
workers busy throughout); the load average before and after says how busy the machine was.
"""
from __future__ import annotations

import argparse
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def _tree(pid: int) -> list[int]:
    """`pid` and every process below it (from /proc/*/stat's parent field)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            parents.setdefault(int(fields[1]), []).append(int(entry))
        except (OSError, IndexError, ValueError):
            continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += parents.get(p, [])
    return out


def _memory_kib(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of one process, KiB (0, 0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            values = {line.split(":")[0]: int(line.split()[1]) for line in f if line.split(":")[0] in ("Rss", "Pss")}
        return values.get("Rss", 0), values.get("Pss", 0)
    except (OSError, ValueError, IndexError):
        return 0, 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimators", default="ekf,vqf,madgwick,mahony,gn")
    parser.add_argument("--dataset", default="broad/*")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", default=None, help="the run's folder (default: a temporary one, removed)")
    parser.add_argument("--fault", action="append", default=[], help="as fusion stress --fault (default: every kind)")
    parser.add_argument("--every", type=float, default=0.5, help="seconds between memory samples")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or str(Path(tmp) / "stress")
        argv = ["stress", "--estimators", args.estimators, "--dataset", args.dataset, "--jobs", str(args.jobs),
                "--out", out, "--no-progress", *(w for f in args.fault for w in ("--fault", f))]
        print("fusion " + shlex.join(argv))
        print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} cores")
        start = time.perf_counter()
        cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
        child = subprocess.Popen([sys.executable, "-m", "fusion", *argv], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        peak = {"rss": 0, "pss": 0, "processes": 0}
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                pids = _tree(child.pid)
                rss, pss = map(sum, zip(*(_memory_kib(p) for p in pids))) if pids else (0, 0)
                peak["rss"], peak["pss"] = max(peak["rss"], rss), max(peak["pss"], pss)
                peak["processes"] = max(peak["processes"], len(pids))
                done.wait(args.every)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        stdout, stderr = child.communicate()
        wall = time.perf_counter() - start
        cpu_after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (cpu_after.ru_utime - cpu_before.ru_utime) + (cpu_after.ru_stime - cpu_before.ru_stime)
        done.set()
        sampler.join()
        if child.returncode not in (0, 1):
            raise SystemExit(f"the run failed ({child.returncode}):\n{stderr}")
        import json

        doc = json.loads((Path(out) / "results.json").read_text())
        rows = doc["results"]
        failed = sum(1 for r in rows if r.get("error"))
        print(stdout.rstrip("\n"))
        print(f"\n{len(rows)} jobs ({len({r['dataset'] for r in rows})} recordings x "
              f"{len({(r['fault']['kind'], r['fault']['severity']) for r in rows})} fault levels incl. clean x "
              f"{len({r['estimator'] for r in rows})} estimators), {failed} failed cells; "
              f"estimators' own time {sum(r['seconds'] for r in rows):.0f} s")
        print(f"wall time {wall:.0f} s ({wall / 60:.1f} min; target 15 min) with --jobs {args.jobs}")
        print(f"CPU time {cpu:.0f} s (user + system, main and workers): on an idle machine with {args.jobs} cores at "
              f"least {cpu / args.jobs:.0f} s ({cpu / args.jobs / 60:.1f} min)")
        print(f"peak memory of the run (main + workers, sampled every {args.every:g} s): PSS {peak['pss'] / 1024:.0f} "
              f"MiB, RSS {peak['rss'] / 1024:.0f} MiB (shared pages counted per process); target 1 GB; "
              f"up to {peak['processes']} processes")
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())} (other work on the machine slows "
              "the run: re-measure on a quiet machine with the command above)")


if __name__ == "__main__":
    main()
