"""Seconds and peak memory to load a one-hour 200 Hz ROS 2 bag (720,000 `sensor_msgs/msg/Imu`
messages, and a 100 Hz PoseStamped truth) through `fusion.datasets.load`.

    python benchmarks/bench_bag.py [--minutes 60] [--storage sqlite3 mcap] [--ros1] [--repeat 3]

Writes the bag with rosbags' own writer (each message serialised by rosbags) into a temporary
folder, then loads it in `--repeat` fresh processes (each starts with numpy, SciPy and fusion
imported, so a run pays only for the bag). Load time is wall time of `fusion.datasets.load` in the
child; peak memory is the child's peak resident set size (`resource.getrusage(RUSAGE_SELF)
.ru_maxrss`, at the end of the child), of which the baseline before loading (the imports) is
printed too. Linux keeps ru_maxrss across exec, so a child starts from its parent's peak: the
bag is written by another child, and this script's own process stays small (no numpy).
Also times rosbags' own per-message deserialiser on the IMU topic, for reference.
Target: under 20 s and under 1 GB for 60 minutes.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TIMED = """
import resource, sys, time
sys.path.insert(0, {root!r})
import numpy, scipy.spatial.transform
from fusion import datasets
import rosbags.highlevel
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
rec = datasets.load({path!r})
seconds = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(seconds, before * 1024, peak * 1024, len(rec.imu), len(rec.truth))
"""
DESERIALISE = """
import sys, time
from pathlib import Path
from rosbags.highlevel import AnyReader
with AnyReader([Path({path!r})]) as reader:
    conns = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/Imu"]
    t0 = time.perf_counter()
    n = sum(1 for c, _, raw in reader.messages(connections=conns) if reader.deserialize(raw, c.msgtype))
    print(time.perf_counter() - t0, n)
"""


WRITE = """
import sys, time
sys.path.insert(0, {tests!r})
import numpy as np
from scipy.spatial.transform import Rotation
from robotics_writers import write_bag

n = int(round({minutes!r} * 60 * 200))
rng = np.random.default_rng(0)
t = np.arange(n) / 200.0
rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.003, (n, 3)), axis=0))
t0 = time.perf_counter()
write_bag(__import__("pathlib").Path({path!r}), {version!r}, t, rng.normal(0, 0.3, (n, 3)), rot.inv().apply([0, 0, 1.0]),
          t[::2], rot[::2].as_quat(scalar_first=True), storage={storage!r})
print(n, time.perf_counter() - t0)
"""


def write(path: Path, minutes: float, version: int, storage: str) -> tuple[int, float]:
    """The bag (IMU at 200 Hz, PoseStamped truth at 100 Hz), written with rosbags in a child
    process; returns (IMU messages, seconds to write)."""
    n, seconds = child(WRITE.format(tests=str(ROOT / "tests"), minutes=minutes, path=str(path), version=version,
                                    storage=storage))
    return int(n), seconds


def child(code: str) -> list[float]:
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return [float(x) for x in out.split()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--storage", nargs="+", default=["sqlite3", "mcap"], choices=["sqlite3", "mcap"])
    ap.add_argument("--ros1", action="store_true", help="also a ROS 1 bag")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    kinds = [(2, s) for s in args.storage] + ([(1, "")] if args.ros1 else [])
    with tempfile.TemporaryDirectory() as folder:
        for version, storage in kinds:
            path = Path(folder) / (f"run_{storage}" if version == 2 else "run.bag")
            n, write_s = write(path, args.minutes, version, storage or "sqlite3")
            size = sum(p.stat().st_size for p in ([path] if path.is_file() else path.iterdir()))
            runs = [child(TIMED.format(root=str(ROOT), path=str(path))) for _ in range(args.repeat)]
            seconds = [r[0] for r in runs]
            peak = max(r[2] for r in runs)
            base = min(r[1] for r in runs)
            assert all(int(r[3]) == n for r in runs), runs
            label = f"ROS {version}" + (f" {storage}" if storage else "")
            print(f"{label}: {n} Imu messages ({args.minutes:g} min at 200 Hz) + {int(runs[0][4])} PoseStamped, "
                  f"{size / 1e6:.0f} MB, written in {write_s:.0f} s")
            grown = max(r[2] - r[1] for r in runs)
            print(f"  fusion.datasets.load: best {min(seconds):.2f} s, median {statistics.median(seconds):.2f} s "
                  f"of {args.repeat}; peak RSS {peak / 1e6:.0f} MB ({base / 1e6:.0f} MB before loading, "
                  f"so loading added at most {grown / 1e6:.0f} MB)")
            deser_s, count = child(DESERIALISE.format(path=str(path)))
            print(f"  rosbags read + deserialise, IMU topic only: {deser_s:.2f} s ({1e6 * deser_s / count:.1f} us per message)")


if __name__ == "__main__":
    main()
