"""Frames per second into the panorama (target: >= 200 frames of 320 x 240 per second).

    python benchmarks/bench_panorama.py [--frames 400] [--blend feather]

Frames are rendered first (not timed) from the generated scene with the simulated recording's
true orientations, then stitched with `Stitcher.add`, which is what is timed. Also prints the
peak memory of the stitching phase (tracemalloc: numpy buffers), which does not grow with the
number of frames.
"""
from __future__ import annotations

import argparse
import time
import tracemalloc


from fusion.evaluation.panorama import camsim
from fusion.evaluation.panorama.recording import Stitcher
from fusion import datasets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--blend", default="feather", choices=("last", "average", "feather"))
    args = parser.parse_args()
    rec = datasets.load("sim")
    camera = camsim.simulate_camera(rec.truth, camsim.procedural_scene(), rate_hz=10.0)
    n = min(args.frames, len(camera.t))
    frames = [camera.frame(k) for k in range(n)]
    rotations = camera.rotations[:n]
    for blend in (args.blend,) if args.blend != "feather" else ("last", "average", "feather"):
        stitcher = Stitcher(blend=blend)
        stitcher.add(frames[0], rotations[0])  # warm-up (first-touch allocations)
        tracemalloc.start()
        start = time.perf_counter()
        for frame, rot in zip(frames, rotations):
            stitcher.add(frame, rot)
        seconds = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        print(f"{blend:8s} {n} frames of {frames[0].shape[1]}x{frames[0].shape[0]} into "
              f"{stitcher.grid.width_px}x{stitcher.grid.height_px}: {n / seconds:6.0f} frames/s "
              f"({1e3 * seconds / n:.2f} ms/frame), peak extra memory {peak / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
