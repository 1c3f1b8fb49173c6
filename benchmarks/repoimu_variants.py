"""RepoIMU as published against two alternatives, measured: its held samples, and its clipped gyro.

    FUSION_DATA=../shared/data python benchmarks/repoimu_variants.py [--estimators ekf,gn,vqf,vqf-offline,madgwick]

Held samples: the pendulum's rows come at about 163 Hz while its IMU's values change at about 50 Hz
(gyro) and 25 Hz (accelerometer); each row repeats a sensor's last value until the next arrives.
Each pendulum recording is run as published (every row) and with only the rows where the gyro
changed (the held rows dropped, so each gyro sample stands for the interval since the last new
one). Clipped gyro: the T-stick's gyro sits flat at about +-7.3 rad/s in Test05 and Test10; those
recordings are run as published (the clipped reading integrated: the sensor's range, a lower bound
of the true rate) and with the flat tops marked invalid (`fusion.checks.FlatTopDetector`: the
estimators then hold the orientation across them, as they do across a dropout). 6-D (`--mag off`),
every recording scored through its own alignment (`--align`), inclination RMSE in degrees; a
recording whose alignment is poor is left out of both columns. Prints each variant's mean per
estimator over the same recordings.
"""
from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np

from fusion.checks import FlatTopDetector
from fusion.evaluation.run.job import run_one
from fusion.selection import load_selected


def held_dropped(recording):
    """Only the rows where some gyro axis changed from the row before (the first row kept)."""
    imu = recording.imu
    fresh = np.r_[True, np.any(np.diff(imu.gyr_rad_s, axis=0) != 0, axis=1)]
    kept = imu.replace(t=imu.t[fresh], gyr_rad_s=imu.gyr_rad_s[fresh], acc_g=imu.acc_g[fresh],
                       gyr_valid=imu.gyr_valid[fresh], mag_ut=None if imu.mag_ut is None else imu.mag_ut[fresh],
                       mag_valid=None if imu.mag_valid is None else imu.mag_valid[fresh])
    return dataclasses.replace(recording, imu=kept), float(fresh.mean())


def clipped_invalid(recording):
    """The gyro's flat tops marked invalid."""
    flat = FlatTopDetector().mask(recording.imu.gyr_rad_s).any(axis=1)
    valid = np.array(recording.imu.gyr_valid) & ~flat
    return dataclasses.replace(recording, imu=recording.imu.replace(gyr_valid=valid)), int(flat.sum())


def inclination(recording, spec: str) -> float | None:
    result = run_one(recording, spec, align=True)
    return None if result.rmse_deg is None else result.rmse_deg["inclination"]


def compare(recordings, variant, label: str, estimators: list[str]) -> None:
    rows = {e: ([], []) for e in estimators}
    for rec in recordings:
        other, amount = variant(rec)
        scores = [(inclination(rec, e), inclination(other, e)) for e in estimators]
        if any(a is None or b is None for a, b in scores):
            print(f"  {rec.id}: not scored (alignment), left out")
            continue
        print(f"  {rec.id} ({label}: {amount:.3g}): " + ", ".join(f"{e} {a:.2f} / {b:.2f}"
                                                            for e, (a, b) in zip(estimators, scores)))
        for e, (a, b) in zip(estimators, scores):
            rows[e][0].append(a)
            rows[e][1].append(b)
    n = len(next(iter(rows.values()))[0])
    print(f"  mean over {n} recordings, inclination RMSE deg: as published / {label}")
    for e, (a, b) in rows.items():
        print(f"    {e:12s} {np.mean(a):6.2f} / {np.mean(b):6.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimators", default="ekf,gn,vqf,vqf-offline,madgwick")
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args()
    estimators = args.estimators.split(",")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the loaders' notes on held values and truth rows: known here
        pendulum = [r for r in load_selected("repoimu/pendulum/*", args.data_dir, mag=False) if r.truth is not None]
        clipped = load_selected("repoimu/tstick/TStick_Test05*,repoimu/tstick/TStick_Test10*", args.data_dir,
                                mag=False)
        print("held samples (pendulum, 6-D): every row as published / the held rows dropped "
              "(share of rows kept in brackets)")
        compare(pendulum, held_dropped, "rows kept", estimators)
        print("clipped gyro (T-stick Test05, Test10, 6-D): integrated as published / flat tops invalid "
              "(samples on a flat top in brackets)")
        compare(clipped, clipped_invalid, "flat-top samples", estimators)


if __name__ == "__main__":
    main()
