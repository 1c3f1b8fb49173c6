"""Where in frequency the BROAD inclination errors lie, with the IMU-truth lag removed.

    python benchmarks/broad_error_bands.py [--data-dir DIR] [--dataset 'broad/*'] [--estimators gd,vqf,vqf-offline]

For each trial and estimator: the inclination RMSE under BROAD's protocol (movement phases,
mean heading offset removed) against the truth with the trial's measured clock offset taken
out (`fusion.checks.clock_offset`, what `fusion calibrate --clock-offset` stores), then the
horizontal tilt error split into three bands (below 0.5 Hz, 0.5-4 Hz, above 4 Hz; zero-phase
Butterworth filters), and how much of the 0.5-4 Hz part a least-squares fit on the world-frame
horizontal specific force (m/s^2 per g; from the truth's orientation) and its integral
explains: a tilt about the horizontal axis perpendicular to the acceleration, k (e_z x f) plus
the same for f's integral ("explained": the RMS the fit removes, deg; "deg per g": k).

The tilt error is the small-angle rotation vector, world frame, between the truth's and the
estimate's gravity direction: `R_true (h_true x h_est)`, `h = R^T e_z`. Its x and y components
are the inclination error; the RMS of its norm over the movement phases is the inclination
RMSE the tables print (to the small-angle approximation), before the heading offset, which
does not change inclination.

"mean x" and "mean y" are the error's mean over the movement phases (world frame, deg).

What it shows on BROAD's fast-translation trial (15): the two smoothers (`gd`, offlineVQF)
follow the gyro above 0.5 Hz, and there the gyro-integrated tilt differs from the truth by an
amount that moves with the translation (0.33 deg per g of horizontal acceleration, which
explains 0.40 of the band's 0.42 deg). No weighting of the accelerometer or of the velocity
model changes that band (`gd:R=...`, `gd:Rv=inf`: the same 0.42 deg). VQF's causal filter
shows less of it (0.12 deg per g): its correction, the low-passed inertial-frame
acceleration, still carries a small part of the translation's acceleration, and on this trial
that part leans against the error.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fusion import datasets  # noqa: E402
from fusion.checks import clock_offset  # noqa: E402
from fusion.estimators import build  # noqa: E402
from fusion.evaluation.scoring.metrics import score  # noqa: E402
from fusion.types import Trajectory  # noqa: E402

BANDS_HZ = ((None, 0.5), (0.5, 4.0), (4.0, None))


def band_pass(x: np.ndarray, fs: float, lo: float | None, hi: float | None) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth filter along axis 0 (low-, band- or high-pass)."""
    if lo is None:
        sos = butter(2, hi, "lowpass", fs=fs, output="sos")
    elif hi is None:
        sos = butter(2, lo, "highpass", fs=fs, output="sos")
    else:
        sos = butter(2, [lo, hi], "bandpass", fs=fs, output="sos")
    return sosfiltfilt(sos, x, axis=0)


def tilt_error_world(r_true: Rotation, r_est: Rotation) -> np.ndarray:
    """(N, 2) horizontal small-angle tilt error, world frame, rad."""
    up_true = r_true.apply([0.0, 0.0, 1.0], inverse=True)
    up_est = r_est.apply([0.0, 0.0, 1.0], inverse=True)
    return r_true.apply(np.cross(up_true, up_est))[:, :2]


def rms_deg(x: np.ndarray) -> float:
    return float(np.degrees(np.sqrt(np.mean(np.sum(x**2, axis=1)))))


def analyse(recording, estimate, fs: float) -> dict[str, float]:
    """The inclination RMSE, its band split and the 0.5-4 Hz part the specific force explains."""
    s = score(recording.truth, estimate, "broad", recording.movement)
    r_true, inside = recording.truth.interpolate(estimate.t)
    # the whole span with truth (filters need contiguous samples); scored on the movement phases
    est = Rotation.from_quat(estimate.quat_wxyz[inside], scalar_first=True)
    err = tilt_error_world(r_true, est)
    f_world = r_true.apply(recording.imu.acc_g[inside])[:, :2]
    moving = recording.movement[inside] if recording.movement is not None else np.ones(len(err), bool)
    out = {"inclination": s.rmse_deg["inclination"]}
    mean_tilt = np.degrees(err[moving].mean(axis=0))
    out["mean x"], out["mean y"] = float(mean_tilt[0]), float(mean_tilt[1])
    for lo, hi in BANDS_HZ:
        label = f"<{hi:g} Hz" if lo is None else f">{lo:g} Hz" if hi is None else f"{lo:g}-{hi:g} Hz"
        out[label] = rms_deg(band_pass(err, fs, lo, hi)[moving])
    mid_err = band_pass(err, fs, 0.5, 4.0)[moving]
    f_mid = band_pass(f_world, fs, 0.5, 4.0)
    v_mid = band_pass(np.cumsum(f_mid, axis=0) / fs, fs, 0.5, 4.0)[moving]
    f_mid = f_mid[moving]
    # a tilt about the horizontal axis perpendicular to the acceleration: e_z x f = (-f_y, f_x)
    regressors = np.concatenate([np.column_stack([-f_mid[:, 1], -v_mid[:, 1]]), np.column_stack([f_mid[:, 0], v_mid[:, 0]])])
    coef, *_ = np.linalg.lstsq(regressors, np.concatenate([mid_err[:, 0], mid_err[:, 1]]), rcond=None)
    left = mid_err - np.column_stack(np.split(regressors @ coef, 2))
    out["explained"] = float(np.sqrt(max(rms_deg(mid_err) ** 2 - rms_deg(left) ** 2, 0.0)))
    out["deg per g"] = float(np.degrees(coef[0]))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="folder holding broad/ (default: $FUSION_DATA, else ./data)")
    ap.add_argument("--dataset", default="broad/*")
    ap.add_argument("--estimators", default="gd,vqf,vqf-offline")
    args = ap.parse_args(argv)
    try:
        sources = datasets.select(args.dataset, args.data_dir)
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"broad_error_bands: {err}")
    specs = args.estimators.split(",")
    rows = []
    for source in sources:
        recording = datasets.load_source(source)
        if recording.truth is None:
            print(f"{source.id}: no ground truth, skipped", file=sys.stderr)
            continue
        offset = clock_offset(recording.imu, recording.truth)
        lag_s = offset.offset_s if offset is not None else 0.0
        truth = recording.truth
        recording = dataclasses.replace(recording, truth=Trajectory(truth.t - lag_s, truth.quat_wxyz, truth.diagnostics))
        fs = 1.0 / float(np.median(np.diff(recording.imu.t)))
        q0 = datasets.initial_orientation(recording)
        for spec in specs:
            estimate = build(spec).estimate(recording.imu, q0)
            rows.append((source.id.split("/")[-1][:30], spec, lag_s, analyse(recording, estimate, fs)))
            print(f"{rows[-1][0]:30s} {spec:12s} done", file=sys.stderr, flush=True)
    if not rows:
        sys.exit("broad_error_bands: no recording with ground truth")
    keys = list(rows[0][3])
    print("inclination error with the truth lag removed, deg (movement phases)")
    print(f"{'trial':30s} {'estimator':12s} {'lag ms':>6s} " + " ".join(f"{k:>12s}" for k in keys))
    for trial, spec, lag_s, values in rows:
        print(f"{trial:30s} {spec:12s} {lag_s * 1e3:6.2f} " + " ".join(f"{values[k]:12.3f}" for k in keys))


if __name__ == "__main__":
    main()
