"""Rest detection and the gyro-bias update at rest (`ekf`, `ukf-bias`; the smoothers read the
same detector through `_compiled_rest.rest_steps`).

Contract: `RestDetector.update` takes one step's gyro (rad/s) and accelerometer (g) reading, body
frame, and says whether the recording is at rest now; `bias_rest_update` is then the Kalman update
with the pseudo-measurement `gyr = b + noise` (the true rate is zero), exact because it is linear.

Paper: Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation with bias estimation
and magnetic disturbance rejection", Information Fusion 91, Sec. 3.4 (rest detection from the
gyro norm and the accelerometer's deviation from its low-pass; the bias read at rest). The
update's covariance is in Joseph form (Sola 2017, "Quaternion kinematics for the error-state
Kalman filter", Sec. 6.1-6.3).

`RestDetector.state()` packs the detector into `REST_STATE` float64 numbers, the state the
compiled filters carry (`_compiled_rest`); its layout is the `REST_*` offsets below.
"""
from __future__ import annotations

import math

import numpy as np

from ...kernels._linalg import inv_sym3
from ._error_state import BIAS

# The layout of `RestDetector.state()`: offsets into the (REST_STATE,) float64 array.
REST_HAS_LOWPASS = 0  # flag: the accelerometer low-pass has started
REST_LOWPASS = 1  # lp (3), g, body
REST_TIME_STILL = 4  # s still without interruption
REST_START = 5  # the low-pass where the still stretch began (3), g, body (the tilt test)
REST_STATE = 8


REST_WINDOW_S = 0.5  # time constant of the rest detector's accelerometer low-pass, s


# Default rest detection (`RestDetector`) of the filters and the smoothers: gyro norm, rad/s;
# accelerometer deviation, g; minimum duration, s.
REST_GYR_RAD_S, REST_ACC_G, REST_TIME_S = 0.035, 0.05, 1.5
# The filters' tilt test (`RestDetector`, tilt_rad): the low-passed accelerometer may turn by at most
# this within a still stretch, rad (inf: no test, the detector of the smoothers). Off by default: at
# 0.3 deg it keeps a slow turn out of the bias on the slow-translation simulation (ekf 0.85 -> 0.75
# deg) and changes nothing on BROAD, but an accelerometer quantised coarser than the angle (the
# built-in simulation's, 0.55 deg a count) ends every still stretch before it counts, the bias goes
# unread and the heading drifts (ekf 6.9 -> 10.3 deg total there); docs/results.md.
REST_TILT_RAD = math.inf


class RestDetector:
    """Rest detection for gyro-bias estimation (after Laidig & Seel 2023, VQF, Sec. 3.4).

    At rest the gyro reads its bias. A sample counts as still when the gyro reading is below
    `gyr_th_rad_s` in norm and the accelerometer is within `acc_th_g` of its low-pass value
    (time constant `window_s`) and within `acc_th_g` of 1 g; the recording is at rest once
    that has held for `min_time_s` without interruption.

    Tilt test (`tilt_rad`; inf: none): a body that turns more slowly than `gyr_th_rad_s` passes
    the tests above, and the bias update would take its rate for bias. Unless the turn is about
    the vertical, it turns gravity in the body frame: a still stretch also ends when the
    accelerometer's low-pass has turned by more than `tilt_rad` from where it was when the
    stretch began (whose direction the stretch keeps), so that a turn faster than
    `tilt_rad / min_time_s` never reaches a rest update and a slower one feeds it for at most
    the time it takes to turn by `tilt_rad`. At true rest the low-pass's direction moves only by
    its noise (0.02-0.06 deg for the shared recordings' IMUs at a 0.5 s window).
    """

    __slots__ = ("gyr_th", "acc_th", "min_time", "window_s", "tilt", "lp", "lp0", "time_still")

    def __init__(self, gyr_th_rad_s: float, acc_th_g: float, min_time_s: float, window_s: float = REST_WINDOW_S,
                 tilt_rad: float = math.inf) -> None:
        self.gyr_th, self.acc_th, self.min_time, self.window_s = gyr_th_rad_s, acc_th_g, min_time_s, window_s
        self.tilt = tilt_rad
        self.lp: np.ndarray | None = None
        self.lp0 = np.zeros(3)
        self.time_still = 0.0

    def state(self) -> np.ndarray:
        """(REST_STATE,) float64, laid out by the `REST_*` offsets: the state as the compiled
        filters (`_compiled_rest`) carry it; `set_state` takes it back."""
        st = np.zeros(REST_STATE)
        if self.lp is not None:
            st[REST_HAS_LOWPASS] = 1.0
            st[REST_LOWPASS:REST_LOWPASS + 3] = self.lp
        st[REST_TIME_STILL] = self.time_still
        st[REST_START:REST_START + 3] = self.lp0
        return st

    def set_state(self, state: np.ndarray) -> None:
        self.lp = np.array(state[REST_LOWPASS:REST_LOWPASS + 3], dtype=float) if state[REST_HAS_LOWPASS] else None
        self.time_still = float(state[REST_TIME_STILL])
        self.lp0 = np.array(state[REST_START:REST_START + 3], dtype=float)

    def update(self, gyr_rad_s: np.ndarray, acc_g: np.ndarray, dt_s: float) -> bool:
        """Feed one step (gyro (3,) rad/s, accelerometer (3,) g, body); -> at rest now."""
        if not (math.isfinite(float(acc_g.sum())) and math.isfinite(float(gyr_rad_s.sum()))):
            self.time_still = 0.0
            return False
        if self.lp is None:
            self.lp = np.array(acc_g, dtype=float)
        alpha = -math.expm1(-dt_s / self.window_s)
        dev = acc_g - self.lp
        self.lp = self.lp + alpha * dev
        g = float(gyr_rad_s @ gyr_rad_s)
        a = float(acc_g @ acc_g)
        still = (
            g < self.gyr_th * self.gyr_th
            and float(dev @ dev) < self.acc_th * self.acc_th
            and abs(math.sqrt(a) - 1.0) < self.acc_th
        )
        if still and self.tilt < math.inf:  # the tilt test: has the low-pass turned within the stretch?
            if self.time_still == 0.0:
                self.lp0 = self.lp.copy()
            elif _turned(self.lp0, self.lp, self.tilt):  # a turn, not a rest: a new stretch begins next
                self.time_still = 0.0
                return False
        self.time_still = self.time_still + dt_s if still else 0.0
        return self.time_still >= self.min_time


def _turned(a: np.ndarray, b: np.ndarray, angle_rad: float) -> bool:
    """Whether the directions of a and b (3,) are more than angle_rad (< pi / 2) apart:
    |a x b|^2 > sin^2(angle) |a|^2 |b|^2 with a . b > 0."""
    c = np.cross(a, b)
    s = math.sin(angle_rad)
    return float(a @ b) <= 0.0 or float(c @ c) > s * s * float(a @ a) * float(b @ b)


def bias_rest_update(x_bias: np.ndarray, P: np.ndarray, gyr_rad_s: np.ndarray, r_rad2_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the rest pseudo-measurement `gyr = b + noise` (true rate zero).

    x_bias: (3,) bias estimate, rad/s; P: (n, n) error covariance `[attitude, bias, ...]`
    (the bias in the rows `BIAS`); gyr_rad_s: (3,) the reading at rest; r_rad2_s2: its variance per
    axis, (rad/s)^2. At zero rate the scale factor does not enter the model, so
    H = [0, I, 0] is linear and the standard update is exact for the EKF and the UKF alike
    (the attitude and scale rows move through the cross-covariances). Returns
    `(dx (n,), P)`, with P in Joseph form.
    """
    n = len(P)
    S = P[BIAS, BIAS] + np.eye(3) * r_rad2_s2
    K = P[:, BIAS] @ inv_sym3(S)
    dx = K @ (gyr_rad_s - x_bias)
    IKH = np.eye(n)
    IKH[:, BIAS] -= K
    return dx, IKH @ P @ IKH.T + (K * r_rad2_s2) @ K.T
