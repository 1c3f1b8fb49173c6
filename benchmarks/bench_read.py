"""Seconds to load a large camera file: `fusion.camera.load_camera` against SciPy in-process.

    python benchmarks/bench_read.py [--frames 1700] [--repeat 5]

Writes a synthetic camera file of the course's layout (`cam`: 240 x 320 x 3 x frames, uint8;
`ts`: 1 x frames) as a MATLAB file and as a pickle into a temporary folder, then times
`load_camera` on each in `--repeat` fresh processes (so no run reuses another's memory), and
`scipy.io.loadmat` / `pickle.load` in-process for reference. `load_camera` reads a MATLAB file
in a forked child (`fusion.format_checks.read_isolated`: a corrupt file cannot crash the caller) and
a pickle with the restricted unpickler; the difference to the plain readers is what that
safety costs. Prints the best and the median of the runs.
"""
from __future__ import annotations

import argparse
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.io

ROOT = Path(__file__).resolve().parents[1]
TIMED = """
import sys, time
sys.path.insert(0, {root!r})
from fusion.camera import load_camera
t0 = time.perf_counter()
camera = load_camera({path!r})
print(time.perf_counter() - t0)
"""


def fresh_process_seconds(path: Path) -> float:
    code = TIMED.format(root=str(ROOT), path=str(path))
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return float(out.split()[-1])


def in_process_seconds(read, path: Path) -> float:
    t0 = time.perf_counter()
    read(path)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1700)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    cam = rng.integers(0, 256, (240, 320, 3, args.frames), dtype=np.uint8)
    ts = np.arange(args.frames, dtype=float)[None] / 10.0
    print(f"camera: {cam.shape} uint8, {cam.nbytes / 1e6:.0f} MB; best / median of {args.repeat} runs, s")
    with tempfile.TemporaryDirectory() as folder:
        mat, pkl = Path(folder) / "cam1.mat", Path(folder) / "cam1.p"
        scipy.io.savemat(mat, {"cam": cam, "ts": ts})
        with open(pkl, "wb") as f:
            pickle.dump({"cam": cam, "ts": ts}, f, protocol=pickle.HIGHEST_PROTOCOL)
        del cam
        rows = [
            ("load_camera, MATLAB file", [fresh_process_seconds(mat) for _ in range(args.repeat)]),
            ("scipy.io.loadmat in-process", [in_process_seconds(scipy.io.loadmat, mat) for _ in range(args.repeat)]),
            ("load_camera, pickle", [fresh_process_seconds(pkl) for _ in range(args.repeat)]),
            ("pickle.load in-process", [in_process_seconds(lambda p: pickle.loads(p.read_bytes()), pkl)
                                        for _ in range(args.repeat)]),
        ]
    for name, seconds in rows:
        print(f"{name:30s} {min(seconds):6.2f} {statistics.median(seconds):6.2f}")


if __name__ == "__main__":
    main()
