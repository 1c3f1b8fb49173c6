"""Stopping and resuming a sweep on real data, timed: prints how long `fusion ablate --jobs 2`
takes to exit after SIGTERM and whether a process is left, how long the workers of a run killed
outright (SIGKILL), and of a killed Python caller of `run_ablate`, take to die, and checks that
`--resume` runs only the missing jobs and ends with the rows of an uninterrupted run. A script
that prints figures, never a timed test (the behaviour itself is tested in tests/test_stopping.py).

    python benchmarks/bench_stop.py [--data-dir ../shared/data/broad] [--trials 2] [--after 20]

Each stop is sent once `--after` jobs are in the run's journal (the sweep is the
`broad-sweep` preset, 30 `ekf` settings per trial).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def children(pid: int) -> list[int]:
    """The live (non-zombie) children of `pid` (Linux: /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def journal_lines(out: Path) -> int:
    path = out / ".fusion-run" / "journal.jsonl"
    return len(path.read_text().splitlines()) - 1 if path.is_file() else 0


def wait_for(condition, limit_s: float = 600.0) -> float:
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > limit_s:
            raise SystemExit("gave up waiting")
        time.sleep(0.005)
    return time.monotonic() - start


def rows(path: Path) -> list:
    doc = json.loads(path.read_text())
    return [(r["dataset"], r["estimator"], r["rmse_deg"], r["max_deg"], r["coverage"]) for r in doc["results"]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default="../shared/data/broad")
    parser.add_argument("--trials", type=int, default=2)
    parser.add_argument("--after", type=int, default=20, help="send each stop once this many jobs are journalled")
    args = parser.parse_args()
    from fusion import datasets

    ids = ",".join(s.id for s in datasets.select("all", args.data_dir)[:args.trials])
    base = ["ablate", "--preset", "broad-sweep", "--dataset", ids, "--data-dir", args.data_dir, "--jobs", "2",
            "--no-progress"]
    fusion = [sys.executable, "-m", "fusion"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        whole = subprocess.run(fusion + base + ["--json", str(tmp / "whole.json")], capture_output=True, text=True)
        assert whole.returncode == 0, whole.stderr
        total = len(rows(tmp / "whole.json"))
        for sig in (signal.SIGTERM, signal.SIGKILL):
            out = tmp / f"run-{sig.name}"
            proc = subprocess.Popen(fusion + base + ["--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True)
            wait_for(lambda: journal_lines(out) >= args.after)
            workers = children(proc.pid)
            sent = time.monotonic()
            proc.send_signal(sig)
            proc.communicate()
            exited = time.monotonic() - sent
            gone = exited + wait_for(lambda: not [w for w in workers if alive(w)])
            done = journal_lines(out)
            resumed = subprocess.run(fusion + ["ablate", "--resume", str(out), "--no-progress", "--jobs", "2"],
                                     capture_output=True, text=True)
            note = next((line for line in resumed.stderr.splitlines() if "resuming" in line), "")
            same = resumed.returncode == 0 and rows(out / "results.json") == rows(tmp / "whole.json")
            print(f"{sig.name}: main process exited {exited:.2f} s after the signal (status {proc.returncode}), "
                  f"its {len(workers)} workers gone after {gone:.2f} s; {done} of {total} jobs journalled; "
                  f"resume: '{note.removeprefix('fusion: note: ')}', rows equal to an uninterrupted run: {same}")
        for sig in (signal.SIGTERM, signal.SIGKILL):
            out = tmp / f"library-{sig.name}"
            code = ("import sys; from fusion.evaluation.runs import run_ablate; "
                    f"run_ablate(preset='broad-sweep', dataset={ids!r}, data_dir={args.data_dir!r}, jobs=2, out=sys.argv[1])")
            proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            wait_for(lambda: journal_lines(out) >= args.after)
            workers = children(proc.pid)
            sent = time.monotonic()
            os.kill(proc.pid, sig)
            proc.communicate()
            gone = wait_for(lambda: not [w for w in workers if alive(w)])
            print(f"library caller, {sig.name}: its {len(workers)} workers gone {gone:.2f} s after the signal")


if __name__ == "__main__":
    main()
