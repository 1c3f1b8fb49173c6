"""The figure of `fusion inspect --out DIR`: what one recording holds, over time.

Three panels sharing the time axis (s after the first IMU sample): gyro rates (deg/s) with the
nominal +-300 deg/s range, accelerometer (g), and the angular speed from the gyro and from VICON
(on the IMU clock, shifted by the measured offset). Shaded: rests (green), gyro freezes (red),
ADC-saturated samples (purple), VICON gaps (grey).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fusion.checks import NOMINAL_GYRO_RANGE_DEG_S, RecordingCheck, vicon_body_rate
from fusion.types import Recording


def plot_check(recording: Recording, check: RecordingCheck, path: str | Path) -> None:
    from matplotlib.figure import Figure  # no pyplot: the caller's backend is left alone

    imu = recording.imu
    t0 = imu.t[0]
    t = imu.t - t0
    fig = Figure(figsize=(12, 8))
    axes = fig.subplots(3, 1, sharex=True)
    gyr = np.rad2deg(imu.gyr_rad_s)
    for i, name in enumerate("xyz"):
        axes[0].plot(t, gyr[:, i], lw=0.6, label=f"w{name}")
        axes[1].plot(t, imu.acc_g[:, i], lw=0.6, label=f"a{name}")
    for sign in (-1, 1):
        axes[0].axhline(sign * NOMINAL_GYRO_RANGE_DEG_S, color="k", ls=":", lw=0.8)
    axes[2].plot(t, np.linalg.norm(gyr, axis=1), lw=0.6, label="|w| gyro")
    if recording.truth is not None:
        t_mid, omega = vicon_body_rate(recording.truth)
        offset = check.vicon.clock.offset_s if check.vicon is not None and check.vicon.clock else 0.0
        axes[2].plot(t_mid - offset - t0, np.rad2deg(np.linalg.norm(omega, axis=1)), lw=0.6,
                     label=f"|w| VICON (shifted by {-offset * 1e3:+.1f} ms)")
    spans = [(r.interval, "tab:green", "rest") for r in check.rests]
    spans += [(f.interval, "tab:red", "gyro freeze") for f in check.freezes]
    spans += [(iv, "tab:purple", "saturated") for iv in (check.range.saturated if check.range else [])]
    spans += [(iv, "0.5", "VICON gap") for iv in (check.vicon.gaps if check.vicon else [])]
    for ax in axes:
        seen = set()
        for iv, color, label in spans:
            ax.axvspan(iv.start_s, max(iv.stop_s, iv.start_s + 0.02), color=color, alpha=0.2,
                       label=None if label in seen else label)
            seen.add(label)
        ax.legend(loc="upper right", fontsize=7, ncol=4)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("gyro (deg/s)")
    axes[1].set_ylabel("accelerometer (g)")
    axes[2].set_ylabel("angular speed (deg/s)")
    axes[2].set_xlabel("time since first IMU sample (s)")
    axes[0].set_title(f"{check.id}: {len(check.freezes)} gyro freeze(s), "
                      f"{check.range.saturated_samples if check.range else 0} saturated samples, "
                      f"{check.vicon.missing_samples if check.vicon else 0} VICON NaN rows")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
