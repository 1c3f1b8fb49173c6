"""The first minute of a new user: `fusion compare` (the main job, every estimator) as on a fresh
installation, with an empty numba cache, timed line by line. Prints the wall time, the time to
the first output, and the longest stretch with nothing new on the terminal (stdout, stderr and
the progress bar's redraws alike). A script that prints figures, never a timed test.

    python benchmarks/bench_first_run.py [--data-dir DIR] [-- extra fusion arguments]

Without `--data-dir` it runs on the built-in simulated recording, as a new user without data does.
"""
from __future__ import annotations

import argparse
import os
import selectors
import subprocess
import sys
import tempfile
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("extra", nargs="*", help="more arguments for `fusion compare`")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as cwd:
        env = {k: v for k, v in os.environ.items() if k != "FUSION_DATA"}
        env["NUMBA_CACHE_DIR"] = cache  # nothing compiled yet, as on a fresh installation
        cmd = [sys.executable, "-m", "fusion", "compare", *(["--data-dir", args.data_dir] if args.data_dir else []),
               *args.extra]
        start = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        sel = selectors.DefaultSelector()
        sel.register(proc.stdout, selectors.EVENT_READ)
        sel.register(proc.stderr, selectors.EVENT_READ)
        last = start
        first = None
        longest = (0.0, 0.0)  # (length, where it started)
        open_streams = 2
        while open_streams:
            for key, _ in sel.select():
                chunk = os.read(key.fileobj.fileno(), 65536)
                if not chunk:
                    sel.unregister(key.fileobj)
                    open_streams -= 1
                    continue
                now = time.monotonic()
                first = first if first is not None else now - start
                if now - last > longest[0]:
                    longest = (now - last, last - start)
                last = now
        proc.wait()
        wall = time.monotonic() - start
    print(f"$ {' '.join(cmd[2:])}   (fresh numba cache; exit {proc.returncode})")
    print(f"wall {wall:.1f} s; first output after {first:.1f} s; longest silence {longest[0]:.1f} s "
          f"(from {longest[1]:.1f} s)")


if __name__ == "__main__":
    main()
