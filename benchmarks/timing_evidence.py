"""Which interval does a course-board gyro sample cover? Evidence on ece276a 1-9.

    python benchmarks/timing_evidence.py [--data-dir DIR] [--estimators dr,ekf,gn,vqf]

`ImuSamples.gyr_timing` says which interval gyro sample k stands for: "start" = [t[k], t[k+1])
(gyro k, then accelerometer k + 1) or "end" = (t[k-1], t[k]] (gyro k, then accelerometer k).
The choice cannot be read off the VICON comparison alone: moving the gyro by one sample is,
against VICON, the same as moving VICON's clock, whose offset is unknown (VICON lags the IMU by
3-24 ms). So three measurements are printed:

1. Gyro against accelerometer, on the IMU's own clock (no VICON): while the board turns,
   gravity in the body frame changes as `d a / dt = -w x a` (plus linear acceleration).
   The lag minimising the residual of `(a[k+1] - a[k]) / dt[k]` against
   `-w(t_mid - lag) x a_mid` (gyro interpolated between its stamps, both sides smoothed
   alike) says where gyro sample k belongs on the accelerometer's time line: at
   `t[k] + lag`. A mean rate over [t[k], t[k+1]] ("start") gives +dt/2 (about +5 ms), over
   (t[k-1], t[k]] ("end") -dt/2, an instantaneous sample 0. Checked on the simulator
   (`fusion.sim`, `SimSettings(gyr_timing=...)`): +5.6 ms for "start", -4.4 ms for "end".
2. The IMU-VICON clock offset with each pairing: the cross-correlation of angular speeds
   (`fusion.checks.clock_offset`, what `fusion calibrate --clock-offset` stores), each
   interval's gyro reading stamped at the interval's midpoint.
3. Estimator errors (mean over the recordings of the RMSE, deg; --init truth, default
   board, detected dropouts) for each pairing, with no clock shift and with that pairing's
   measured offset applied to VICON. Against VICON, dead reckoning cannot tell the pairings
   apart once the offset is measured with the same pairing (both are one consistent time
   shift); the filters can, through the gyro-accelerometer pairing, but only weakly.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fusion.estimators import build  # noqa: E402
from fusion.evaluation.scoring.metrics import score  # noqa: E402
from fusion import datasets  # noqa: E402
from fusion.checks import clock_offset  # noqa: E402
from fusion.types import ImuSamples, Recording, Trajectory  # noqa: E402

PAIRINGS = ("start", "end")
CLOCKS = ("none", "measured")


def _moving_average(x: np.ndarray, k: int) -> np.ndarray:
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    return (c[k:] - c[:-k]) / k


LAGS_S = np.arange(-0.03, 0.03 + 1e-9, 0.001)  # candidate gyro-accelerometer lags


def lag_cost(imu: ImuSamples, smooth: int = 11) -> np.ndarray:
    """Residual of the gravity kinematics for each lag in `LAGS_S`, normalised to its minimum.

    The residual is `(a[k+1] - a[k]) / dt[k] + w(t_mid - lag) x a_mid` (`d a/dt = -w x a`, a in
    g, w the gyro interpolated between its stamps), both sides smoothed alike over `smooth`
    samples, over the steps whose gyro samples are valid.
    """
    t, a, w = imu.t, imu.acc_g, imu.gyr_rad_s
    dt = np.diff(t)
    t_mid, a_mid = 0.5 * (t[1:] + t[:-1]), 0.5 * (a[1:] + a[:-1])
    da = np.diff(a, axis=0) / dt[:, None]
    ok = _moving_average((imu.gyr_valid[1:] & imu.gyr_valid[:-1]).astype(float)[:, None], smooth)[:, 0] > 0.999
    cost = np.empty(len(LAGS_S))
    for j, lag in enumerate(LAGS_S):
        w_at = np.column_stack([np.interp(t_mid - lag, t, w[:, i]) for i in range(3)])
        r = _moving_average(da + np.cross(w_at, a_mid), smooth)
        cost[j] = np.mean(np.sum(r[ok] ** 2, axis=1))
    return cost / cost.min()


def best_lag(cost: np.ndarray) -> float:
    """The lag (s) at the minimum of `cost`, refined by a parabola through its neighbours.

    Positive: the gyro sample stamped t is the accelerometer's turn rate at t + lag. For a
    gyro reading that is the mean rate over its interval, "start" gives +dt/2, "end" -dt/2.
    """
    j = int(np.clip(np.argmin(cost), 1, len(cost) - 2))
    c0, c1, c2 = cost[j - 1:j + 2]
    curv = c0 - 2 * c1 + c2
    delta = 0.5 * (c0 - c2) / curv if curv > 0 else 0.0
    return float(LAGS_S[j] + delta * (LAGS_S[1] - LAGS_S[0]))


def run(data_dir: str | None, names: list[str], numbers: range) -> None:
    errors = {(e, p, c): [] for e in names for p in PAIRINGS for c in CLOCKS}
    pooled = np.zeros(len(LAGS_S))
    print("recording   gyro-acc lag   VICON lag (ms), pairing start   end")
    for n in numbers:
        rec = datasets.load(f"ece276a/{n}", data_dir)
        cost = lag_cost(rec.imu)
        pooled = pooled + cost
        offsets = {p: clock_offset(rec.imu.replace(gyr_timing=p), rec.truth).offset_s for p in PAIRINGS}
        print(f"ece276a/{n}  {best_lag(cost) * 1e3:+8.1f} ms  {offsets['start'] * 1e3:+27.1f}  {offsets['end'] * 1e3:+5.1f}")
        for pairing in PAIRINGS:
            imu = rec.imu.replace(gyr_timing=pairing)
            for clock, off in (("none", 0.0), ("measured", offsets[pairing])):
                truth = Trajectory(rec.truth.t - off, rec.truth.quat_wxyz)
                shifted = Recording(rec.id, imu, truth, rec.raw, rec.calibration)
                q0 = datasets.initial_orientation(shifted, "truth")
                for name in names:
                    rmse = score(truth, build(name).estimate(imu, q0)).rmse_deg
                    errors[name, pairing, clock].append((rmse["inclination"], rmse["total"]))
    print(f"all (pooled)  {best_lag(pooled) * 1e3:+5.1f} ms")
    print("\nmean RMSE over the recordings, deg (inclination / total)")
    print(f"{'estimator':10s} {'pairing':8s}" + "".join(f"{'clock ' + c:>20s}" for c in CLOCKS))
    for name in names:
        for pairing in PAIRINGS:
            cells = [np.mean(errors[name, pairing, c], axis=0) for c in CLOCKS]
            print(f"{name:10s} {pairing:8s}" + "".join(f"{inc:11.2f} / {tot:6.2f}" for inc, tot in cells))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="folder holding ece276a/ (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--estimators", default="dr,ekf,gn,vqf")
    ap.add_argument("--recordings", default="1-9", help="ece276a recording numbers, a range like 1-9")
    args = ap.parse_args(argv)
    first, _, last = args.recordings.partition("-")
    run(args.data_dir, args.estimators.split(","), range(int(first), int(last or first) + 1))


if __name__ == "__main__":
    main()
