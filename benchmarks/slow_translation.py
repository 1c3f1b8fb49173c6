"""Slow translation, simulated: how `ekf` (6-D) and VQF tell a sustained linear acceleration from tilt.

    python benchmarks/slow_translation.py [--specs ekf,vqf] [--seeds 3]

A body that holds roughly still in orientation (slow turns of 10-20 deg) while it is carried along
straight lines by minimum-jerk moves (Flash & Hogan 1985, "The coordination of arm movements",
J. Neurosci. 5(7), eq. 2: x(s) = D (10 s^3 - 15 s^4 + 6 s^5)), whose peak accelerations
5.77 D / T^2 span 0.1-1 m/s^2 over moves of 2-8 s, either back to back or with rests between
them, sampled at 100 Hz and at 285.7 Hz with the white noise of the shared recordings' IMUs (std
per sample, measured at rest: course board about 0.01 rad/s and 0.01 g; BROAD 0.002 rad/s and
0.006 g) and a constant gyro bias. Prints each case's inclination RMSE (deg) per estimator, seeded.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from motion_helpers import turning_body  # noqa: E402

from fusion.estimators import build  # noqa: E402
from fusion.evaluation.scoring.metrics import error_angles  # noqa: E402
from fusion.types import STANDARD_GRAVITY_M_S2  # noqa: E402

NOISE = {100.0: (0.01, 0.01), 285.7: (0.002, 0.006)}  # (gyro rad/s, acc g) std per sample


def min_jerk_path(t: np.ndarray, peak_acc_m_s2: float, breaks: bool, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) world acceleration, m/s^2: straight moves one after another in random horizontal (and
    some vertical) directions, each a minimum-jerk profile of peak acceleration about
    `peak_acc_m_s2`, with 1-3 s rests between them when `breaks`."""
    acc = np.zeros((len(t), 3))
    start = 3.0  # an initial rest
    while start < t[-1] - 3.0:
        T = rng.uniform(2.0, 8.0)
        D = peak_acc_m_s2 * T * T / 5.7735 * rng.uniform(0.6, 1.0)
        direction = rng.normal(size=3) * [1.0, 1.0, 0.3]
        direction /= np.linalg.norm(direction)
        inside = (t >= start) & (t < start + T)
        s = (t[inside] - start) / T
        acc[inside] = np.outer(D / (T * T) * (60 * s - 180 * s**2 + 120 * s**3), direction)
        start += T + (rng.uniform(1.0, 3.0) if breaks else 0.0)
    return acc


def case(rate_hz: float, peak_acc: float, breaks: bool, seed: int, seconds: float = 120.0):
    """(ImuSamples, true quaternions) of one simulated slow translation."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    # slow turns: each axis a sum of two sinusoids, 10-20 deg amplitude, periods 10-40 s
    amp = np.radians(rng.uniform(10.0, 20.0, 3))
    freq = rng.uniform(1 / 40, 1 / 10, (2, 3))
    phase = rng.uniform(0, 2 * np.pi, (2, 3))
    w = sum(amp * 2 * np.pi * freq[i] * np.cos(2 * np.pi * freq[i] * t[:, None] + phase[i]) / 2 for i in range(2))
    ext = min_jerk_path(t, peak_acc, breaks, rng) / STANDARD_GRAVITY_M_S2
    q0 = Rotation.from_rotvec(np.radians(rng.uniform(-15, 15, 3))).as_quat(scalar_first=True)
    gyr_std, acc_std = NOISE[rate_hz]
    bias = rng.normal(0.0, np.radians(0.3), 3)
    return turning_body(t, w, q0, ext, gyr_std, acc_std, bias, seed=seed)


def inclination_rmse(truth: np.ndarray, estimate: np.ndarray) -> float:
    e = error_angles(Rotation.from_quat(truth, scalar_first=True), Rotation.from_quat(estimate, scalar_first=True))
    return float(np.degrees(np.sqrt(np.mean(e["inclination"] ** 2))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--specs", default="ekf,vqf")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    specs = args.specs.split(",") if ";" not in args.specs else args.specs.split(";")
    print(f"{'rate':>6} {'peak m/s2':>9} {'breaks':>6}  " + "  ".join(f"{s:>14}" for s in specs))
    means = {s: [] for s in specs}
    for rate in NOISE:
        for peak in (0.1, 0.3, 1.0):
            for breaks in (True, False):
                row = {s: [] for s in specs}
                for seed in range(args.seeds):
                    imu, truth = case(rate, peak, breaks, seed)
                    for s in specs:
                        row[s].append(inclination_rmse(truth, build(s).estimate(imu, truth[0]).quat_wxyz))
                for s in specs:
                    means[s].append(np.mean(row[s]))
                print(f"{rate:6.1f} {peak:9.1f} {str(breaks):>6}  " + "  ".join(f"{np.mean(row[s]):14.3f}" for s in specs))
    print(f"{'mean':>6} {'':>9} {'':>6}  " + "  ".join(f"{np.mean(means[s]):14.3f}" for s in specs))


if __name__ == "__main__":
    main()
