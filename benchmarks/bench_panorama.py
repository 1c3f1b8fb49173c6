"""Stitching speed and memory: frames of 320 x 240 per second into a 1920 x 960 panorama.

    python benchmarks/bench_panorama.py [--frames 600] [--step 8]

Frames are rendered beforehand from the procedural scene (a pool of 60, reused), so only
`Stitcher.add` is timed: the orientation's footprint, the remap coordinates, cv2.remap and
the blend. Orientations: a hand-held style sweep (yaw all round, pitch and roll wobble, a
few frames near the zenith). Peak memory: tracemalloc peak of NumPy allocations during
stitching, for two frame counts (it must not grow with the number of frames), plus the
process's peak RSS. Timings are noisy on a shared machine: rerun when it is quiet.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation import camsim  # noqa: E402
from evaluation.panorama import BLENDS, PanoramaGrid, Stitcher  # noqa: E402


def orientations(n: int) -> np.ndarray:
    t = np.arange(n) / 10.0
    eul = np.stack([np.linspace(-180.0, 540.0, n), 25.0 * np.sin(0.9 * t), 15.0 * np.cos(0.6 * t)], axis=1)
    eul[::50, 1] = -80.0  # now and then look (nearly) straight up: a whole-width footprint
    return Rotation.from_euler("ZYX", eul, degrees=True).as_matrix()


def run(blend: str, frames: list[np.ndarray], rots: np.ndarray, step: int) -> float:
    stitcher = Stitcher(grid=PanoramaGrid(), blend=blend, map_step_px=step)
    stitcher.add(frames[0], rots[0])  # warm-up (buffers)
    start = time.perf_counter()
    for k, R in enumerate(rots):
        stitcher.add(frames[k % len(frames)], R)
    seconds = time.perf_counter() - start
    stitcher.result()
    return len(rots) / seconds


def peak_mib(blend: str, frames: list[np.ndarray], rots: np.ndarray, step: int) -> float:
    tracemalloc.start()
    stitcher = Stitcher(grid=PanoramaGrid(), blend=blend, map_step_px=step)
    for k, R in enumerate(rots):
        stitcher.add(frames[k % len(frames)], R)
    stitcher.result()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--step", type=int, default=8, help="map_step_px (1 = exact map at every pixel)")
    args = parser.parse_args()
    rots = orientations(args.frames)
    renderer = camsim.SceneRenderer(camsim.procedural_scene())
    frames = [renderer.render(R) for R in rots[:60]]
    import cv2

    print(f"{args.frames} frames of 320 x 240 into 1920 x 960, map_step_px={args.step}, "
          f"OpenCV {cv2.__version__} with {cv2.getNumThreads()} threads")
    for blend in BLENDS:
        fps = run(blend, frames, rots, args.step)
        small = peak_mib(blend, frames, rots[:100], args.step)
        large = peak_mib(blend, frames, rots, args.step)
        print(f"  {blend:8s} {fps:7.0f} frames/s  ({1e3 / fps:.2f} ms/frame)   "
              f"peak NumPy memory {small:5.1f} MiB for 100 frames, {large:5.1f} MiB for {args.frames}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"process peak RSS {rss:.0f} MiB (includes the interpreter, OpenCV, the scene and 60 pre-rendered frames)")
    start = time.perf_counter()
    for R in rots[:200]:
        renderer.render(R)
    print(f"rendering frames from the scene (camsim): {200 / (time.perf_counter() - start):.0f} frames/s")


if __name__ == "__main__":
    main()
