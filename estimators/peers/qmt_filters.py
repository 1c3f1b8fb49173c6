"""The `qmt` toolbox's orientation filters (Laidig, Seel et al., the authors of VQF and BROAD; `qmt`
0.2.4) behind our `Estimator` interface: `oriEstIMU` (Seel & Ruppin 2017), and its C++ versions of
Madgwick's and Mahony's filters (Madgwick's own C code of 2011-2012, which qmt compiles; Madgwick
2010, Mahony et al. 2008).

Installing. `pip install qmt` takes qmt's only published wheel (0.2.4, 2023), compiled against
NumPy 1.x: with NumPy 2 (this project pins none; 2.4 here) its compiled modules (`qmt.cpp.*`) fail
to import ("A module that was compiled using NumPy 1.x cannot be run in NumPy 2.x"). Built from its
source distribution against the installed NumPy it works: `PIP_NO_BINARY=qmt pip install qmt`
(a C++ compiler and some 30 s). A qmt whose compiled modules cannot be imported is, here, a qmt
that is not installed (`PeerUnavailable`, naming that command).

What every adapter gets (the conventions of `peers.vqf_fusion`): one constant sample time, the
rates scaled so that each step rotates by the real interval's reading (`_rate_for_constant_ts`, as
for VQF: qmt's functions take `Ts` only); the accelerometer in m/s^2 with non-finite samples set to
zero (the C code's "no sample": Madgwick's and Mahony's skip the correction; oriEstIMU checks the
norm), the magnetometer in uT with zero rows where it is invalid (the C code's "no sample": the
IMU update for that step), invalid gyro samples as zero rate. The libraries update with gyro k,
then accelerometer k, as VQF's `updateBatch`: row 0 is the seed and rows 1.. are the library's
outputs for samples 1.. (its state seeded with `initQuat` = the initial orientation).

Frames: qmt returns `R_world_body` in ENU (x east, y north, z up), the frame of BROAD's truth:
`oriEstMadgwick` and `oriEstMahony` run Madgwick's code in its x-north world (NWU) and turn the
result by 90 deg about the vertical themselves (`qmt.oriEstMadgwick`: "adjust reference frame to
ENU"), so their `initQuat` is turned back by the adapter (`q_NWU = Rz(-90 deg) q_ENU`); oriEstIMU
works in ENU and takes the seed as it is. In 6-D the frame's heading changes nothing.

Precision: Madgwick's and Mahony's C code computes in single precision (float32), with qmt's
`invSqrt` the exact `1 / sqrt(x)` (qmt disabled the original's fast inverse square root, "as it
seems to lead to noticeable larger deviations in the output quaternion norm"); oriEstIMU in double.
"""
from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from fusion import quaternion as quat
from fusion.types import ImuSamples, Trajectory

from ..base import Estimator
from ..params import param
from ..search import Tunable
from .ahrs_filters import _MADGWICK, _MAHONY
from .vqf_fusion import (
    _RZ90, PeerUnavailable, _acc_m_s2, _check_length, _mag_or_zero, _non_negative, _positive, _rate_for_constant_ts,
)

QMT_INSTALL = "PIP_NO_BINARY=qmt pip install qmt"


def _require_qmt(module: str, estimator: str) -> ModuleType:
    """`qmt.cpp.<module>` (the compiled code), or `PeerUnavailable` saying how to install qmt when
    it is missing or its compiled modules cannot be imported (its wheel, built for NumPy 1.x, under
    NumPy 2: NumPy prints a page about it, which is kept off the user's terminal)."""
    import importlib

    try:
        with contextlib.redirect_stderr(io.StringIO()):
            importlib.import_module("qmt")
            return importlib.import_module(f"qmt.cpp.{module}")
    except ImportError as exc:
        raise PeerUnavailable(
            f"estimator {estimator!r} needs the optional package 'qmt', which is not installed or not built for "
            f"this NumPy ({np.__version__}): {QMT_INSTALL} (qmt's wheel is built for NumPy 1.x; see "
            "fusion.estimators.peers.qmt_filters)") from exc


def _qmt_run(imu: ImuSamples, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """(gyr, acc, mag, ts) for a qmt batch function, samples 1.. (the seed stands for sample 0):
    gyr (N-1, 3) rad/s (`_rate_for_constant_ts`), acc (N-1, 3) m/s^2, mag (N-1, 3) uT or None (6-D)."""
    _check_length(imu, name)
    gyr, ts = _rate_for_constant_ts(imu)
    acc = _acc_m_s2(imu.acc_g)
    mag = _mag_or_zero(imu)[1:] if imu.has_mag else None
    return np.ascontiguousarray(gyr[1:]), np.ascontiguousarray(acc[1:]), mag, ts


def _seeded(imu: ImuSamples, init_quat_wxyz: np.ndarray, quats: np.ndarray) -> Trajectory:
    out = np.empty((len(imu), 4))
    out[0] = init_quat_wxyz
    out[1:] = quats
    return Trajectory(imu.t, out)


def _nwu_seed(init_quat_wxyz: np.ndarray) -> np.ndarray:
    """The seed in Madgwick's x-north world, as qmt's `initQuat` takes it (module docstring)."""
    q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
    return np.ascontiguousarray(quat.multiply(quat.conjugate(_RZ90), q))


# --------------------------------------------------------------------------------------
# oriEstIMU (Seel & Ruppin, "Eliminating the effect of magnetic disturbances on the inclination
# estimates of inertial sensors", IFAC-PapersOnLine 50(1), 2017)


# The references the fields cite (their "reference" metadata, `fusion list NAME`).
_SEEL = "Seel & Ruppin 2017 (oriEstIMU)"


@dataclass(frozen=True)
class OriEstIMUParams:
    """`qmt.oriEstIMU` parameters (its defaults), documented at the fields (`fusion list
    qmt-oriestimu`)."""

    # Ranges: a correction faster than most motions (0.1 s) to one slower than most recordings'
    # disturbances (30 s, 100 s), log scale. Grids around qmt's defaults (1 s and 3 s, the values
    # Seel & Ruppin 2017 use): 4 x 3 = 12 settings in 9-D, 4 in 6-D.
    tau_acc_s: float = param(
        1.0, alias="tauAcc", unit="s", valid="> 0", reference=_SEEL,
        search=Tunable(0.1, 30.0, log=True, grid=(0.5, 1.0, 2.0, 4.0)),
        meaning="Time constant of the inclination correction (its 50 % time).")
    tau_mag_s: float = param(
        3.0, alias="tauMag", unit="s", valid="> 0", reference=_SEEL,
        search=Tunable(0.3, 100.0, log=True, grid=(1.0, 3.0, 9.0), magnetometer=True),
        meaning="Time constant of the heading correction (9-D only).")
    zeta: float = param(0.0, unit="1", valid=">= 0; 0: off", reference=_SEEL,
                        meaning="Strength of the gyro-bias estimation.")
    acc_rating: float = param(1.0, alias="accRating", unit="1", valid=">= 0; 0: off", reference=_SEEL,
                              meaning="The down-rating of the accelerometer in fast motion.")

    def __post_init__(self) -> None:
        _positive("qmt-oriestimu", tau_acc_s=self.tau_acc_s, tau_mag_s=self.tau_mag_s)
        _non_negative("qmt-oriestimu", zeta=self.zeta, acc_rating=self.acc_rating)


class OriEstIMUPeer(Estimator):
    """oriEstIMU (Seel & Ruppin 2017), from the `qmt` package.

    6-D, or 9-D with its magnetic-disturbance-robust heading correction (C++, double precision)."""

    Params = OriEstIMUParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        _require_qmt("oriestimu", "qmt-oriestimu")
        import qmt

        self._qmt = qmt

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        gyr, acc, mag, ts = _qmt_run(imu, "qmt-oriestimu")
        p = self.params
        seed = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
        quats = self._qmt.oriEstIMU(gyr, acc, mag, params=dict(
            Ts=ts, tauAcc=p.tau_acc_s, tauMag=p.tau_mag_s, zeta=p.zeta, accRating=p.acc_rating, initQuat=seed))
        return _seeded(imu, init_quat_wxyz, quats)


# --------------------------------------------------------------------------------------
# Madgwick and Mahony in Madgwick's C code, as qmt compiles it


@dataclass(frozen=True)
class QmtMadgwickParams:
    """`qmt.oriEstMadgwick` parameters (its default), documented at the field."""

    # Grid: qmt's default 0.1 (the C code's `betaDef`), the `ahrs` package's 0.033, and BROAD's
    # search (0.01-0.30; 0.12 best over its 39 trials, 9-D; Laidig et al., Data 2021): 6 settings.
    gain: float = param(
        0.1, alias="beta", unit="rad/s", valid=">= 0", reference=_MADGWICK + ", eq. 33",
        search=Tunable(1e-3, 1.0, log=True, grid=(0.01, 0.033, 0.06, 0.1, 0.12, 0.3)),
        meaning="The rate beta of the gradient step towards the accelerometer (and magnetometer), in 6-D and 9-D "
                "alike.")

    def __post_init__(self) -> None:
        _non_negative("qmt-madgwick", gain=self.gain)


class QmtMadgwickPeer(Estimator):
    """Madgwick's filter in Madgwick's C code (single precision), from the `qmt` package.

    `qmt.oriEstMadgwick` (Madgwick 2010; 6-D, or 9-D in ENU)."""

    Params = QmtMadgwickParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        _require_qmt("madgwick", "qmt-madgwick")
        import qmt

        self._qmt = qmt

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """The library on samples 1..; where its state turns NaN (a zero gradient, `s / |s|` =
        0 * 1/sqrt(0) in the C code, which exact readings can reach in single precision: the
        estimate agrees with the accelerometer to the last bit), that one step is the library's
        without the accelerometer sample (its "no sample" branch: no correction, which is what a zero
        gradient means; beta = 0 would not do: 0 * NaN) and the library continues from it."""
        gyr, acc, mag, ts = _qmt_run(imu, "qmt-madgwick")
        quats = np.empty((len(gyr), 4))
        start, q = 0, _nwu_seed(init_quat_wxyz)
        while start < len(gyr):
            part = slice(start, None)
            out = self._qmt.oriEstMadgwick(gyr[part], acc[part], None if mag is None else mag[part],
                                           params=dict(Ts=ts, beta=self.params.gain, initQuat=q))
            bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
            stop = len(out) if len(bad) == 0 else int(bad[0])
            quats[start:start + stop] = out[:stop]
            if len(bad) == 0:
                break
            k = start + stop  # the step that divided 0 by 0, again without the accelerometer
            q = _nwu_seed(quats[k - 1]) if k > 0 else q
            one = slice(k, k + 1)
            quats[k] = self._qmt.oriEstMadgwick(gyr[one], np.zeros((1, 3)), None if mag is None else mag[one],
                                                params=dict(Ts=ts, beta=self.params.gain, initQuat=q))[0]
            q, start = _nwu_seed(quats[k]), k + 1
        return _seeded(imu, init_quat_wxyz, quats)


@dataclass(frozen=True)
class QmtMahonyParams:
    """`qmt.oriEstMahony` parameters (its defaults), documented at the fields."""

    # Grids: qmt's defaults (Kp = 0.5, Ki = 0), BROAD's best over its 39 trials with this very code
    # (Kp = 0.74, Ki = 0.0012, 9-D; Laidig et al., Data 2021), and values spreading each range
    # (5 x 4 = 20 settings). Ki is searched on a linear scale: its default is 0.
    k_p: float = param(
        0.5, alias="Kp", unit="rad/s", valid=">= 0", reference=_MAHONY + ", eq. 32",
        search=Tunable(0.01, 10.0, log=True, grid=(0.1, 0.3, 0.5, 0.74, 2.0)),
        meaning="Proportional gain: the correction rate per unit of the attitude error (the C code's twoKp is "
                "2 k_p).")
    k_i: float = param(
        0.0, alias="Ki", unit="rad/s^2", valid=">= 0; 0: no bias estimate", reference=_MAHONY + ", eq. 32",
        search=Tunable(0.0, 0.1, log=False, grid=(0.0, 0.0003, 0.0012, 0.01)),
        meaning="Integral gain of the gyro-bias estimate per unit of the attitude error (the C code's twoKi is "
                "2 k_i).")

    def __post_init__(self) -> None:
        _non_negative("qmt-mahony", k_p=self.k_p, k_i=self.k_i)


class QmtMahonyPeer(Estimator):
    """Mahony's filter in Madgwick's C code (single precision), from the `qmt` package.

    `qmt.oriEstMahony` (Mahony et al. 2008; 6-D, or 9-D in ENU); zero initial bias."""

    Params = QmtMahonyParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        _require_qmt("madgwick", "qmt-mahony")
        import qmt

        self._qmt = qmt

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        gyr, acc, mag, ts = _qmt_run(imu, "qmt-mahony")
        quats = self._qmt.oriEstMahony(gyr, acc, mag, params=dict(
            Ts=ts, Kp=self.params.k_p, Ki=self.params.k_i, initQuat=_nwu_seed(init_quat_wxyz), initBias=np.zeros(3)))
        return _seeded(imu, init_quat_wxyz, quats)
