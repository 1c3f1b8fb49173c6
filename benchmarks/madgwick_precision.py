"""Where Madgwick's 0.12 deg between our table and BROAD's goes: ahrs' double-precision Madgwick,
qmt's compiled C code (single precision, exact inverse square root) and the original C code's
arithmetic (single precision with its fast inverse square root), all at BROAD's beta = 0.12, on the
shared BROAD trials, scored with BROAD's protocol (9-D: total error, movement phases) as the table is.

    python benchmarks/madgwick_precision.py [--data-dir DIR] [--beta 0.12]

Rows (each the mean over the trials of the total RMSE, deg, and the step from the row above):

- `madgwick:beta=0.12`: the `ahrs` package's update in double precision (through our adapter, as the
  README's table; real per-sample dt; its gradient is J^T f, Madgwick 2010, eqs. 25-26, 31-34).
- `C, double, eq. 31's 2b`: Madgwick's C update in double precision with the field reference's
  factor 2 of the report's eq. 31 restored (`make_filter`'s b_scale): the published algorithm.
- `C, double`: Madgwick's C update (the 2012 release's `MadgwickAHRSupdate`/`updateIMU`, its
  gradient multiplied out) in double precision, one constant sample time (1 / sampleFreq).
- `C, float32, exact 1/sqrt`: the same in single precision with an exact inverse square root,
  qmt's build of that code (qmt disabled the fast inverse square root); checked against
  `qmt-madgwick` where qmt can be imported.
- `C, float32, fast 1/sqrt`: the original C code's arithmetic: single precision and its fast
  inverse square root (the bit trick `0x5f3759df - (i >> 1)` and one Newton step).

Every variant gets the same inputs as the `qmt-madgwick` adapter (`peers.qmt_filters`): rows 1.. of
`_rate_for_constant_ts`, the accelerometer in m/s^2, the magnetometer in uT (zero rows where
invalid), seeded with the recording's initial orientation turned into the C code's x-north world,
and its output turned to ENU. Written from the published algorithm and the C code's update
equations (Madgwick 2010, "An efficient orientation filter for inertial and inertial/magnetic
sensor arrays", report, x-io and University of Bristol, sec. 3-4), not copied.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fusion import datasets  # noqa: E402
from fusion import quaternion as quat  # noqa: E402
from fusion.types import Trajectory  # noqa: E402


def make_filter(dtype, fast: bool, b_scale: float = 1.0):
    """A numba function running Madgwick's C update over a recording in `dtype` arithmetic (float32
    or float64), with the fast inverse square root when `fast` (float32 only). b_scale: the factor on
    the C code's `_2bx`, `_2bz`: 1 as in the C code, whose `_2bx = sqrt(hx^2 + hy^2)` is b_x itself
    (eq. 46), not 2 b_x as its name and its use in the objective (eq. 31's 2 b_x terms) say, so that
    its predicted field has half the measured one's length; 2 restores eq. 31."""
    F = dtype
    scale = F(b_scale)
    half, one, two, four, eight, onehalf = F(0.5), F(1.0), F(2.0), F(4.0), F(8.0), F(1.5)
    magic = np.int32(0x5F3759DF)

    @njit(cache=False)
    def inv_sqrt(x):
        if fast:  # Madgwick's C code: the fast inverse square root and one Newton step
            halfx = half * x
            bits = np.empty(1, dtype=np.float32)
            bits[0] = x
            i = bits.view(np.int32)
            i[0] = magic - (i[0] >> 1)
            y = bits[0]
            return y * (onehalf - (halfx * y * y))
        return one / np.sqrt(x)

    @njit(cache=False)
    def update_imu(q, gx, gy, gz, ax, ay, az, beta, ts):
        q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
        # rate of change of quaternion from gyroscope (Madgwick 2010, eq. 12)
        d1 = half * (-q1 * gx - q2 * gy - q3 * gz)
        d2 = half * (q0 * gx + q2 * gz - q3 * gy)
        d3 = half * (q0 * gy - q1 * gz + q3 * gx)
        d4 = half * (q0 * gz + q1 * gy - q2 * gx)
        if not (ax == 0 and ay == 0 and az == 0):
            r = inv_sqrt(ax * ax + ay * ay + az * az)
            ax, ay, az = ax * r, ay * r, az * r
            _2q0, _2q1, _2q2, _2q3 = two * q0, two * q1, two * q2, two * q3
            _4q0, _4q1, _4q2 = four * q0, four * q1, four * q2
            _8q1, _8q2 = eight * q1, eight * q2
            q0q0, q1q1, q2q2, q3q3 = q0 * q0, q1 * q1, q2 * q2, q3 * q3
            # gradient J_g^T f_g (eqs. 25-26, 34), multiplied out as in the C code
            s0 = _4q0 * q2q2 + _2q2 * ax + _4q0 * q1q1 - _2q1 * ay
            s1 = _4q1 * q3q3 - _2q3 * ax + four * q0q0 * q1 - _2q0 * ay - _4q1 + _8q1 * q1q1 + _8q1 * q2q2 + _4q1 * az
            s2 = four * q0q0 * q2 + _2q0 * ax + _4q2 * q3q3 - _2q3 * ay - _4q2 + _8q2 * q1q1 + _8q2 * q2q2 + _4q2 * az
            s3 = four * q1q1 * q3 - _2q1 * ax + four * q2q2 * q3 - _2q2 * ay
            r = inv_sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
            s0, s1, s2, s3 = s0 * r, s1 * r, s2 * r, s3 * r  # the step normalised (eq. 33), then applied
            d1, d2, d3, d4 = d1 - beta * s0, d2 - beta * s1, d3 - beta * s2, d4 - beta * s3
        q0, q1, q2, q3 = q0 + d1 * ts, q1 + d2 * ts, q2 + d3 * ts, q3 + d4 * ts  # eq. 13
        r = inv_sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q[0], q[1], q[2], q[3] = q0 * r, q1 * r, q2 * r, q3 * r

    @njit(cache=False)
    def update_marg(q, gx, gy, gz, ax, ay, az, mx, my, mz, beta, ts):
        q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
        d1 = half * (-q1 * gx - q2 * gy - q3 * gz)
        d2 = half * (q0 * gx + q2 * gz - q3 * gy)
        d3 = half * (q0 * gy - q1 * gz + q3 * gx)
        d4 = half * (q0 * gz + q1 * gy - q2 * gx)
        if not (ax == 0 and ay == 0 and az == 0):
            r = inv_sqrt(ax * ax + ay * ay + az * az)
            ax, ay, az = ax * r, ay * r, az * r
            r = inv_sqrt(mx * mx + my * my + mz * mz)
            mx, my, mz = mx * r, my * r, mz * r
            _2q0mx, _2q0my, _2q0mz, _2q1mx = two * q0 * mx, two * q0 * my, two * q0 * mz, two * q1 * mx
            _2q0, _2q1, _2q2, _2q3 = two * q0, two * q1, two * q2, two * q3
            _2q0q2, _2q2q3 = two * q0 * q2, two * q2 * q3
            q0q0, q0q1, q0q2, q0q3 = q0 * q0, q0 * q1, q0 * q2, q0 * q3
            q1q1, q1q2, q1q3 = q1 * q1, q1 * q2, q1 * q3
            q2q2, q2q3, q3q3 = q2 * q2, q2 * q3, q3 * q3
            # the earth's field in the world frame, its reference b (eqs. 45-46)
            hx = mx * q0q0 - _2q0my * q3 + _2q0mz * q2 + mx * q1q1 + _2q1 * my * q2 + _2q1 * mz * q3 - mx * q2q2 - mx * q3q3
            hy = _2q0mx * q3 + my * q0q0 - _2q0mz * q1 + _2q1mx * q2 - my * q1q1 + my * q2q2 + _2q2 * mz * q3 - my * q3q3
            _2bx = scale * np.sqrt(hx * hx + hy * hy)
            _2bz = scale * (-_2q0mx * q2 + _2q0my * q1 + mz * q0q0 + _2q1mx * q3 - mz * q1q1 + _2q2 * my * q3 - mz * q2q2
                            + mz * q3q3)
            _4bx, _4bz = two * _2bx, two * _2bz
            # gradient J^T f (eqs. 31-32, 34), multiplied out as in the C code
            fa1 = two * q1q3 - _2q0q2 - ax
            fa2 = two * q0q1 + _2q2q3 - ay
            fa3 = one - two * q1q1 - two * q2q2 - az
            fm1 = _2bx * (half - q2q2 - q3q3) + _2bz * (q1q3 - q0q2) - mx
            fm2 = _2bx * (q1q2 - q0q3) + _2bz * (q0q1 + q2q3) - my
            fm3 = _2bx * (q0q2 + q1q3) + _2bz * (half - q1q1 - q2q2) - mz
            s0 = -_2q2 * fa1 + _2q1 * fa2 - _2bz * q2 * fm1 + (-_2bx * q3 + _2bz * q1) * fm2 + _2bx * q2 * fm3
            s1 = (_2q3 * fa1 + _2q0 * fa2 - four * q1 * fa3 + _2bz * q3 * fm1 + (_2bx * q2 + _2bz * q0) * fm2
                  + (_2bx * q3 - _4bz * q1) * fm3)
            s2 = (-_2q0 * fa1 + _2q3 * fa2 - four * q2 * fa3 + (-_4bx * q2 - _2bz * q0) * fm1
                  + (_2bx * q1 + _2bz * q3) * fm2 + (_2bx * q0 - _4bz * q2) * fm3)
            s3 = _2q1 * fa1 + _2q2 * fa2 + (-_4bx * q3 + _2bz * q1) * fm1 + (-_2bx * q0 + _2bz * q2) * fm2 + _2bx * q1 * fm3
            r = inv_sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
            s0, s1, s2, s3 = s0 * r, s1 * r, s2 * r, s3 * r
            d1, d2, d3, d4 = d1 - beta * s0, d2 - beta * s1, d3 - beta * s2, d4 - beta * s3
        q0, q1, q2, q3 = q0 + d1 * ts, q1 + d2 * ts, q2 + d3 * ts, q3 + d4 * ts
        r = inv_sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q[0], q[1], q[2], q[3] = q0 * r, q1 * r, q2 * r, q3 * r

    @njit(cache=False)
    def run(gyr, acc, mag, q0, beta, freq):
        """The C code's loop: `update` (or `updateIMU` on a zero magnetometer sample) per row."""
        q = q0.astype(F)
        b = F(beta)
        ts = one / F(freq)
        out = np.empty((gyr.shape[0], 4))
        for k in range(gyr.shape[0]):
            g, a, m = gyr[k].astype(F), acc[k].astype(F), mag[k].astype(F)
            if m[0] == 0 and m[1] == 0 and m[2] == 0:
                update_imu(q, g[0], g[1], g[2], a[0], a[1], a[2], b, ts)
            else:
                update_marg(q, g[0], g[1], g[2], a[0], a[1], a[2], m[0], m[1], m[2], b, ts)
            out[k] = q
        return out

    return run


VARIANTS = {"C, double, eq. 31's 2b": make_filter(np.float64, False, 2.0), "C, double": make_filter(np.float64, False), "C, float32, exact 1/sqrt": make_filter(np.float32, False),
            "C, float32, fast 1/sqrt": make_filter(np.float32, True)}


def c_estimate(run, imu, seed, beta: float) -> Trajectory:
    """A C variant with the inputs of the `qmt-madgwick` adapter (module docstring)."""
    from fusion.estimators.peers.qmt_filters import _nwu_seed, _qmt_run
    from fusion.estimators.peers.vqf_fusion import _RZ90

    gyr, acc, mag, ts = _qmt_run(imu, "madgwick-c")
    mag = np.zeros_like(acc) if mag is None else mag
    q = run(gyr, acc, mag, _nwu_seed(seed), beta, 1.0 / ts)
    out = np.empty((len(imu), 4))
    out[0] = seed
    out[1:] = quat.multiply(_RZ90, q)
    return Trajectory(imu.t, out)


def main(argv: list[str] | None = None) -> None:
    from fusion.estimators import build
    from fusion.estimators.peers.vqf_fusion import PeerUnavailable
    from fusion.evaluation.run.job import run_one
    from fusion.evaluation.scoring.metrics import score

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=None, help="the recordings (default: $FUSION_DATA)")
    ap.add_argument("--beta", type=float, default=0.12, help="BROAD's published beta")
    args = ap.parse_args(argv)
    try:
        build("qmt-madgwick")
        have_qmt = True
    except PeerUnavailable:
        have_qmt = False
    rows: dict[str, list[float]] = {"madgwick (ahrs, double)": [], **{k: [] for k in VARIANTS}}
    if have_qmt:
        rows["qmt-madgwick"] = []
    worst_qmt = 0.0
    start = time.perf_counter()
    for source in datasets.select("broad/*", args.data_dir):
        rec = datasets.LoadOptions().load(source)
        seed = datasets.initial_orientation(rec)
        rows["madgwick (ahrs, double)"].append(run_one(rec, f"madgwick:beta={args.beta}").rmse_deg["total"])
        for name, run in VARIANTS.items():
            traj = c_estimate(run, rec.imu, seed, args.beta)
            rows[name].append(score(rec.truth, traj, "broad", rec.movement, nine_d=True).rmse_deg["total"])
            if name == "C, float32, exact 1/sqrt" and have_qmt:
                qmt_traj = build(f"qmt-madgwick:beta={args.beta}").estimate(rec.imu, seed)
                dots = np.abs(np.sum(qmt_traj.quat_wxyz * traj.quat_wxyz, axis=1)).clip(max=1.0)
                worst_qmt = max(worst_qmt, float(np.degrees(2 * np.arccos(dots)).max()))
        if have_qmt:
            rows["qmt-madgwick"].append(run_one(rec, f"qmt-madgwick:beta={args.beta}").rmse_deg["total"])
    print(f"Madgwick at beta = {args.beta} on {len(rows['C, double'])} BROAD trials, 9-D, BROAD's protocol "
          f"(total RMSE, deg; mean over the trials); BROAD reports 5.54 for its single-precision C run")
    print(f"{'variant':28s} {'mean':>7s} {'step':>7s}")
    previous = None
    for name, values in rows.items():
        mean = float(np.mean(values))
        step = "" if previous is None else f"{mean - previous:+7.3f}"
        print(f"{name:28s} {mean:7.3f} {step:>7s}")
        previous = mean if name != "qmt-madgwick" else previous
    if have_qmt:
        print(f"largest angle between qmt-madgwick and 'C, float32, exact 1/sqrt' on any sample: {worst_qmt:.3g} deg")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
