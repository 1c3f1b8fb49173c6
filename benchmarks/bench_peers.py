"""Microseconds per sample of the `ahrs` peers: the library per sample against its compiled twin.

    python benchmarks/bench_peers.py [--data-dir DIR] [--broad ID] [--course ID] [--repeat 5]
                                     [--library-samples N] [--no-compile-times]
    python benchmarks/bench_peers.py --more [--data-dir DIR] [--broad ID] [--library-samples 3000]

`--more`: the rest of `ahrs` and `qmt` on the BROAD trial instead (6-D and 9-D): every peer with a
twin (`peers._compiled_ahrs_recursive`, `peers._compiled_ahrs_single`) with `impl=library` on the
first `--library-samples` samples (one run) and with its twin on the whole trial (best of `--repeat`),
and the peers without one (the complementary filter, SAAM and Tilt, whose library calls are
vectorised, and qmt's three, C++) on the whole trial.

For `madgwick`, `mahony` and `ahrs-ekf`, on a BROAD trial (286 Hz; 6-D with the magnetometer
dropped, and 9-D) and a course recording (100 Hz, 6-D): the whole-recording `estimate` with
`impl=library` (the `ahrs` package's update called per sample, the reference; one run, on the
first `--library-samples` samples if given) and with `impl=compiled` (the numba twin of
`peers._compiled_ahrs`, best of at least `--repeat` runs), their ratio, and VQF's adapter
(`vqf`, the `vqf` package's C++ `updateBatch`) on the same samples for scale. Then the time to
compile the twins (`peers._compiled_ahrs.load`) in a fresh process with an empty numba cache, and to
load them from the cache in another. Figures taken while other jobs share the machine are noisy;
compare them on a quiet machine. Without data the built-in `sim` recording is used (and said so).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fusion import datasets  # noqa: E402
from fusion.estimators import build  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_filters import compile_times, time_estimate  # noqa: E402

PEERS = ("madgwick", "mahony", "ahrs-ekf")
MORE_TWINS = ("aqua", "fkf", "fourati", "roleq", "ahrs-ukf", "ahrs-angular", "davenport", "quest", "oleq", "flae", "fqa",
              "triad", "famc")
MORE_WITHOUT = ("complementary", "saam", "tilt", "qmt-oriestimu", "qmt-madgwick", "qmt-mahony")

_FIRST_CALL = r"""
import json, time
t0 = time.perf_counter()
from fusion.estimators.peers import _compiled_ahrs as _compiled_peers
t1 = time.perf_counter()
_compiled_peers.load()
print(json.dumps({"import": t1 - t0, "kernels": time.perf_counter() - t1}))
"""


def time_once(spec: str, imu, q0) -> float:
    """Wall time of one `estimate`, s (the library's runs take seconds to minutes)."""
    est = build(spec)
    start = time.perf_counter()
    est.estimate(imu, q0)
    return time.perf_counter() - start


def load(dataset: str, data_dir: str | None):
    try:
        return datasets.load(dataset, data_dir)
    except (FileNotFoundError, ValueError) as err:
        print(f"{dataset} not available ({err}); using the simulated recording 'sim'")
        return datasets.load("sim")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="the recordings (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--broad", default="broad/01_undisturbed_slow_rotation_A")
    ap.add_argument("--course", default="ece276a/1")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--library-samples", type=int, default=None, metavar="N",
                    help="time the library on the first N samples only (default: the whole recording)")
    ap.add_argument("--no-compile-times", action="store_true", help="skip the compile-time measurement")
    ap.add_argument("--more", action="store_true", help="the rest of ahrs and qmt (module docstring)")
    args = ap.parse_args(argv)
    if args.more:
        more(args)
        return
    runs = []
    for dataset in (args.broad, args.course):
        rec = load(dataset, args.data_dir)
        q0 = datasets.initial_orientation(rec)
        runs.append((rec.id, "6-D", rec.imu.replace(mag_ut=None), q0))
        if rec.imu.has_mag:
            runs.append((rec.id, "9-D", rec.imu, q0))
    print("us/sample: library (one run), compiled twin and vqf (best of several runs)")
    print(f"{'recording':38s} {'':4s} {'samples':>8s} {'estimator':10s} {'library':>9s} {'twin':>7s} "
          f"{'speed-up':>9s} {'vqf':>6s}")
    for rid, label, imu, q0 in runs:
        n = len(imu)
        lib_imu = imu.window(0, args.library_samples) if args.library_samples else imu
        vqf = time_estimate("vqf", imu, q0, args.repeat) / n * 1e6
        for peer in PEERS:
            library = time_once(f"{peer}:impl=library", lib_imu, q0) / len(lib_imu) * 1e6
            twin = time_estimate(peer, imu, q0, args.repeat) / n * 1e6
            print(f"{rid:38s} {label:4s} {n:8d} {peer:10s} {library:9.1f} {twin:7.2f} {library / twin:9.0f} {vqf:6.2f}")
    if not args.no_compile_times:
        cold, cached = compile_times(_FIRST_CALL)
        print("numba twins in a fresh process (s):")
        print(f"{'':40s} {'empty cache':>12s} {'cached':>8s}")
        print(f"{'import fusion.estimators.peers._compiled_ahrs':40s} {cold['import']:12.2f} {cached['import']:8.2f}")
        print(f"{'compile / load the three kernels':40s} {cold['kernels']:12.2f} {cached['kernels']:8.2f}")


def more(args: argparse.Namespace) -> None:
    """`--more`: us/sample of the rest of ahrs (library and twin) and of the peers without a twin."""
    import warnings

    warnings.simplefilter("ignore")
    rec = load(args.broad, args.data_dir)
    q0 = datasets.initial_orientation(rec)
    n_lib = args.library_samples or 3000
    print(f"us/sample on {rec.id} ({len(rec.imu)} samples): the library on its first {n_lib} samples (one run), "
          "the twin on all (best of several runs)")
    print(f"{'estimator':14s} {'':4s} {'library':>9s} {'twin':>7s} {'speed-up':>9s}")
    for label, imu in (("6-D", rec.imu.replace(mag_ut=None)), ("9-D", rec.imu)):
        for peer in MORE_TWINS:
            library = time_once(f"{peer}:impl=library", imu.window(0, n_lib), q0) / n_lib * 1e6
            twin = time_estimate(peer, imu, q0, args.repeat) / len(imu) * 1e6
            print(f"{peer:14s} {label:4s} {library:9.1f} {twin:7.2f} {library / twin:9.0f}", flush=True)
        for peer in MORE_WITHOUT:
            try:
                alone = time_estimate(peer, imu, q0, args.repeat) / len(imu) * 1e6
            except ImportError as exc:  # qmt not installed (PeerUnavailable)
                print(f"{peer:14s} {label:4s} not installed: {exc}")
                continue
            print(f"{peer:14s} {label:4s} {alone:9.2f} {'-':>7s} {'-':>9s}", flush=True)


if __name__ == "__main__":
    main()
