"""The `ahrs` package's filters (Garcia, https://ahrs.readthedocs.io) behind our `Estimator`
interface: Madgwick (Madgwick 2010), Mahony (Mahony et al. 2008) and its EKF, each with a numba
twin of the library's update (`peers._compiled_ahrs`). The conventions, frames and traps every peer
adapter shares are `fusion.estimators.peers.vqf_fusion`' module docstring; its helpers are used here.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, Literal

import numpy as np

from fusion import quaternion as quat
from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples, Trajectory

from ..base import RecursiveEstimator
from ..params import param
from ..search import Tunable
from .vqf_fusion import (
    _RZ90, _TINY_RATE_RAD_S, _acc_m_s2, _check_length, _mag_or_zero, _marg_loop, _non_negative, _positive,
    _require,
)


# --------------------------------------------------------------------------------------
# ahrs (Garcia, https://ahrs.readthedocs.io): Madgwick, Mahony, EKF
#
# Two implementations each (`impl`): "compiled" (the default) runs the whole recording in a numba
# twin of the library's update (`peers._compiled_ahrs`, some hundred times faster; the same numbers to
# 1e-9, `tests/test_compiled_peers.py`), "library" calls the library per sample and is the
# reference. The library is required either way: these estimators are its filters, and the
# reference must be there to check the twin against; `reset`/`step` (streaming) call it always.
_IMPLS = ("compiled", "library")


def _check_impl(owner: str, impl: str) -> None:
    if impl not in _IMPLS:
        raise ValueError(f"{owner}: impl must be compiled or library, got {impl!r}")


def _load_twins(impl: str) -> ModuleType | None:
    """`peers._compiled_ahrs`, compiled or loaded from numba's cache now (not in the first, timed,
    estimate), for impl "compiled"; None for "library"."""
    if impl != "compiled":
        return None
    from . import _compiled_ahrs as _compiled_peers  # numba is imported when a compiled peer is built

    _compiled_peers.load()
    return _compiled_peers


def _twin_inputs(imu: ImuSamples, invalid_rate: np.ndarray) -> tuple[np.ndarray, ...]:
    """What the library path passes per step, as arrays for a twin (`peers._compiled_ahrs`): gyr
    (N-1, 3) the interval rates, rad/s, `invalid_rate` where the gyro sample is invalid; acc
    (N-1, 3) the accelerometer sample at each step's end, m/s^2, zero where not finite (`_acc_m_s2`);
    mag (N-1, 3) uT, zero where invalid (`_mag_or_zero`), or (0, 3) without a magnetometer; dt (N-1,) s."""
    (rates, valid), dt = imu.interval_rates(), imu.dt
    rates[~valid] = invalid_rate
    mag = _mag_or_zero(imu)[1:] if imu.has_mag else np.zeros((0, 3))
    # New, writable, C-ordered float64 arrays: the types the kernels were compiled for (`peers._compiled_ahrs.load`;
    # a read-only array is another type to numba, and would be compiled again).
    return tuple(np.array(a, dtype=np.float64, order="C") for a in (rates, _acc_m_s2(imu.acc_g)[1:], mag, dt))


def _twin_start(imu: ImuSamples, init_quat_wxyz: np.ndarray, nwu: bool) -> tuple[np.ndarray, np.ndarray]:
    """(out, q0) for a twin: out (N, 4) with row 0 set as the library path sets it (the seed as
    given in 6-D, `RecursiveEstimator.estimate`; normalised in 9-D, `_marg_loop`), and q0 (4,) the
    normalised seed in the library's world (turned to NWU when `nwu`)."""
    q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
    out = np.empty((len(imu), 4))
    out[0] = q if imu.has_mag else init_quat_wxyz
    if nwu:
        q = quat.multiply(quat.conjugate(_RZ90), q)
    return out, np.ascontiguousarray(q, dtype=np.float64)


# The references the fields cite (their "reference" metadata, `fusion list NAME`).
_MADGWICK = ('Madgwick 2010, "An efficient orientation filter for inertial and inertial/magnetic sensor '
             'arrays", report, University of Bristol')
_MAHONY = ('Mahony, Hamel & Pflimlin 2008, "Nonlinear complementary filters on the special orthogonal group", '
           "IEEE TAC 53(5)")
_AHRS_EKF = "the ahrs package's documentation of ahrs.filters.EKF (its parameters and defaults)"


@dataclass(frozen=True)
class MadgwickParams:
    """`ahrs.filters.Madgwick` parameters (its IMU default gain), documented at the fields
    (`fusion list madgwick`)."""

    # Range: from nearly pure gyro integration (1e-3) to an accelerometer-dominated filter (1).
    # Grid: BROAD's example code searches beta = 0.01-0.30 in steps of 0.01 and finds 0.12 best
    # over all 39 trials (9-D; Laidig et al., Data 2021); 0.033 is the library's default; 0.06 lies
    # between, 0.01 and 0.3 at the ends of BROAD's search.
    gain: float = param(
        0.033, alias="beta", unit="rad/s", valid=">= 0 (the library takes > 0 only; 0: the gyro alone)",
        reference=_MADGWICK + ", eq. 33", search=Tunable(1e-3, 1.0, log=True, grid=(0.01, 0.033, 0.06, 0.12, 0.3)),
        meaning="The rate beta of the gradient step towards the accelerometer (and magnetometer), in 6-D and 9-D "
                "alike.")
    impl: Literal["compiled", "library"] = param(
        "compiled", unit="", valid="compiled | library",
        meaning="compiled makes `estimate` run the numba twin, library makes it call the library per sample (the "
                "reference); `reset` and `step` are the library's either way.")

    def __post_init__(self) -> None:
        _non_negative("madgwick", gain=self.gain)
        _check_impl("madgwick", self.impl)


class MadgwickPeer(RecursiveEstimator):
    """Madgwick's gradient-descent filter (Madgwick 2010), `ahrs.filters.Madgwick.updateIMU`
    (6-D) and `updateMARG` (9-D, NWU turned to ENU: module docstring).

    Seeded with the initial orientation; real per-sample dt. Invalid gyro samples: a
    1e-150 rad/s rate (the library skips the correction on an exactly zero rate). A missing (or
    zero) magnetometer sample in 9-D: `updateIMU` with the real dt (the library's `updateMARG`
    falls back to `updateIMU` without passing dt on, i.e. over its default 0.01 s). With
    `impl=compiled`, `estimate` runs the numba twin (`peers._compiled_ahrs.madgwick_kernel`); the
    library accepts gain > 0 only, the twin also 0 (the gyro alone).
    """

    Params = MadgwickParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._ahrs = _require("ahrs.filters", "ahrs", "madgwick")
        self._twins = _load_twins(self.params.impl)

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        if self._twins is not None:
            _check_length(imu, "madgwick")
            gyr, acc, mag, dt = _twin_inputs(imu, _TINY_RATE_RAD_S)
            out, q0 = _twin_start(imu, init_quat_wxyz, nwu=imu.has_mag)
            self._twins.madgwick_kernel(gyr, acc, mag, dt, q0, float(self.params.gain), imu.has_mag, out)
            return Trajectory(imu.t, out)
        if not imu.has_mag:
            return super().estimate(imu, init_quat_wxyz)
        filt = self._ahrs.Madgwick(gain=self.params.gain)

        def update(q, rate, acc, mag, dt):  # Madgwick 2010, eqs. 12-13, 31-34, 45-46 (MARG); NWU
            if mag is None or np.linalg.norm(mag) == 0:  # the library's own fallback, with dt
                return filt.updateIMU(q, rate, acc, dt=dt)
            return filt.updateMARG(q, rate, acc, mag, dt=dt)

        return _marg_loop(imu, init_quat_wxyz, update, nwu=True, invalid_rate=_TINY_RATE_RAD_S)

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        self._filter = self._ahrs.Madgwick(gain=self.params.gain)
        self._q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)

    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        rate = gyr_rad_s if gyr_valid else _TINY_RATE_RAD_S
        # Madgwick 2010, eqs. 12-13, 25-26, 33-34
        self._q = self._filter.updateIMU(self._q, rate, _acc_m_s2(acc_g), dt=dt_s)
        return self._q


@dataclass(frozen=True)
class MahonyParams:
    """`ahrs.filters.Mahony` parameters (its defaults), documented at the fields (`fusion list
    mahony`)."""

    # Ranges span two decades either side of the published settings, on a log scale. Grids: BROAD's
    # example code searches Kp = 0.02-2.0 (steps of 0.02) x Ki = 0-0.004 (steps of 0.0001) and finds
    # Kp = 0.74, Ki = 0.0012 best over all 39 trials (9-D; Laidig et al., Data 2021); 1.0 and 0.3 are
    # the library's defaults; the others spread the grid over each range (5 x 4 = 20 settings).
    k_p: float = param(
        1.0, alias="kp", unit="rad/s", valid=">= 0 (the library takes > 0 only)", reference=_MAHONY + ", eq. 32",
        search=Tunable(0.01, 10.0, log=True, grid=(0.1, 0.3, 0.74, 1.0, 3.0)),
        meaning="Proportional gain: the correction rate per unit of the attitude error.")
    k_i: float = param(
        0.3, alias="ki", unit="rad/s^2", valid=">= 0 (the library takes > 0 only; 0: no bias estimate)",
        reference=_MAHONY + ", eq. 32", search=Tunable(1e-4, 1.0, log=True, grid=(0.0003, 0.0012, 0.01, 0.3)),
        meaning="Integral gain of the gyro-bias estimate per unit of the attitude error.")
    impl: Literal["compiled", "library"] = param(
        "compiled", unit="", valid="compiled | library",
        meaning="compiled makes `estimate` run the numba twin, library makes it call the library per sample (the "
                "reference); `reset` and `step` are the library's either way.")

    def __post_init__(self) -> None:
        _non_negative("mahony", k_p=self.k_p, k_i=self.k_i)
        _check_impl("mahony", self.impl)


class MahonyPeer(RecursiveEstimator):
    """Mahony's explicit complementary filter (Mahony 2008), `ahrs.filters.Mahony.updateIMU`
    (6-D) and `updateMARG` (9-D, ENU).

    Seeded with the initial orientation, zero initial bias; real per-sample dt. Invalid
    gyro samples: a 1e-150 rad/s rate (the library skips the correction and the bias
    update on an exactly zero rate). A missing (or zero) magnetometer sample in 9-D: `updateIMU`
    with the real dt (see `MadgwickPeer`). With `impl=compiled`, `estimate` runs the numba twin
    (`peers._compiled_ahrs.mahony_kernel`); the library accepts gains > 0 only, the twin also 0
    (k_i = 0: no bias estimate). Diagnostics: the final bias estimate, rad/s, body frame.
    """

    Params = MahonyParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._ahrs = _require("ahrs.filters", "ahrs", "mahony")
        self._twins = _load_twins(self.params.impl)

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        if self._twins is not None:
            _check_length(imu, "mahony")
            gyr, acc, mag, dt = _twin_inputs(imu, _TINY_RATE_RAD_S)
            out, q0 = _twin_start(imu, init_quat_wxyz, nwu=False)
            bias = np.zeros(3)
            self._twins.mahony_kernel(gyr, acc, mag, dt, q0, bias, float(self.params.k_p), float(self.params.k_i), out)
            return Trajectory(imu.t, out, diagnostics={"gyr_bias_rad_s": bias})
        if not imu.has_mag:
            return super().estimate(imu, init_quat_wxyz)
        self._filter = self._ahrs.Mahony(k_P=self.params.k_p, k_I=self.params.k_i, b0=np.zeros(3))
        filt = self._filter

        def update(q, rate, acc, mag, dt):  # Mahony 2008, eqs. 32, 48 with the magnetometer's error term; ENU
            if mag is None or np.linalg.norm(mag) == 0:  # the library's own fallback, with dt
                return filt.updateIMU(q, rate, acc, dt=dt)
            return filt.updateMARG(q, rate, acc, mag, dt=dt)

        trajectory = _marg_loop(imu, init_quat_wxyz, update, nwu=False, invalid_rate=_TINY_RATE_RAD_S)
        return Trajectory(trajectory.t, trajectory.quat_wxyz, diagnostics=self.diagnostics())

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        self._filter = self._ahrs.Mahony(k_P=self.params.k_p, k_I=self.params.k_i, b0=np.zeros(3))
        self._q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)

    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        rate = gyr_rad_s if gyr_valid else _TINY_RATE_RAD_S
        self._q = self._filter.updateIMU(self._q, rate, _acc_m_s2(acc_g), dt=dt_s)  # Mahony 2008, eqs. 32, 48
        return self._q

    def diagnostics(self) -> dict[str, Any]:
        return {"gyr_bias_rad_s": np.array(self._filter.b)}


@dataclass(frozen=True)
class AhrsEKFParams:
    """`ahrs.filters.EKF` parameters (its defaults), documented at the fields (`fusion list
    ahrs-ekf`)."""

    # The filter's gain depends on the ratios of these variances, so each spans several decades
    # (log scale) from the library's defaults (0.3^2, 0.5^2, 0.8^2, the `ahrs` documentation) down:
    # a MEMS gyro's white noise per sample at 100-300 Hz is some 1e-5 to 1e-3 (rad/s)^2 (noise
    # densities of 0.005-0.015 deg/s/sqrt(Hz) in gyro datasheets), an accelerometer's some 1e-5 g^2,
    # but what the filter must absorb is the motion's acceleration (tenths of a g: variances of
    # 0.01-1) and, in 9-D, magnetic disturbances. Grids: the defaults and one to three values below
    # them (4 x 3 x 2 = 24 settings in 9-D, 12 in 6-D).
    gyr_var_rad2_s2: float = param(
        0.3**2, alias="var_gyr", unit="rad^2/s^2", valid=">= 0", reference=_AHRS_EKF,
        search=Tunable(1e-6, 1.0, log=True, grid=(1e-4, 1e-3, 1e-2, 0.3**2)),
        meaning="The gyro's noise variance (the library's var_gyr, 0.3^2 by default).")
    acc_var: float = param(
        0.5**2, alias="var_acc", unit="1", valid="> 0", reference=_AHRS_EKF,
        search=Tunable(1e-4, 10.0, log=True, grid=(0.01, 0.5**2, 1.0)),
        meaning="The accelerometer's noise variance on the normalised reading (the library's var_acc, 0.5^2).")
    mag_var: float = param(
        0.8**2, alias="var_mag", unit="1", valid="> 0", reference=_AHRS_EKF,
        search=Tunable(1e-3, 10.0, log=True, grid=(0.1, 0.8**2), magnetometer=True),
        meaning="The magnetometer's noise variance on the normalised reading (the library's var_mag, 0.8^2; 9-D "
                "only).")
    init_cov: float = param(
        1.0, alias="P0", unit="1", valid=">= 0", reference=_AHRS_EKF,
        meaning="Initial state covariance, init_cov I_4 on the quaternion's components (the library's default "
                "identity means that the orientation is unknown).")
    impl: Literal["compiled", "library"] = param(
        "compiled", unit="", valid="compiled | library",
        meaning="compiled makes `estimate` run the numba twin, library makes it call the library per sample (the "
                "reference); `reset` and `step` are the library's either way.")

    def __post_init__(self) -> None:
        _non_negative("ahrs-ekf", gyr_var_rad2_s2=self.gyr_var_rad2_s2, init_cov=self.init_cov)
        _positive("ahrs-ekf", acc_var=self.acc_var, mag_var=self.mag_var)
        _check_impl("ahrs-ekf", self.impl)


def _ekf_magnetic_ref(imu: ImuSamples) -> np.ndarray:
    """(3,) the EKF's magnetic reference `[cos d, 0, -sin d]` in its z-up "NED" world (module
    docstring), with the dip d measured on the recording (`fusion.checks.check_magnetometer`)."""
    from fusion.checks import check_magnetometer

    check = check_magnetometer(imu)
    dip = np.radians(check.dip_median_deg if check.dip_median_deg is not None else 0.0)
    return np.array([np.cos(dip), 0.0, -np.sin(dip)])


class AhrsEKFPeer(RecursiveEstimator):
    """The `ahrs` package's quaternion EKF (gyro as control input, accelerometer update).

    Frame "NED" (the library default), which is correct for our z-up world: see the
    module docstring. Seeded with the initial orientation; initial covariance
    `init_cov * I`; real per-sample dt. Invalid gyro samples: zero rate (prediction
    without the rate, the library's usual process noise). With `impl=compiled`, `estimate` runs
    the numba twin (`peers._compiled_ahrs.ekf_kernel`). Diagnostics: the final covariance (4, 4).
    """

    Params = AhrsEKFParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._ahrs = _require("ahrs.filters", "ahrs", "ahrs-ekf")
        self._twins = _load_twins(self.params.impl)

    def _library_filter(self, magnetic_ref: Any) -> Any:
        p = self.params
        return self._ahrs.EKF(frame="NED", magnetic_ref=magnetic_ref, var_gyr=p.gyr_var_rad2_s2, var_acc=p.acc_var,
                              var_mag=p.mag_var, P=p.init_cov * np.identity(4))

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        if self._twins is not None:
            return self._estimate_compiled(imu, init_quat_wxyz)
        if not imu.has_mag:
            return super().estimate(imu, init_quat_wxyz)
        filt = self._library_filter(_ekf_magnetic_ref(imu))
        filt.mag = np.zeros((1, 3))  # the library chooses its 9-D measurement model by this (batch) attribute

        def update(q, rate, acc, mag, dt):  # NWU (module docstring)
            if not np.all(np.isfinite(acc)) or not np.any(acc):
                out = filt.f(q, rate, dt)
                return out / np.linalg.norm(out)
            if mag is None:
                filt.mag = None  # one 6-D update
                out = filt.update(q, rate, acc, dt=dt)
                filt.mag = np.zeros((1, 3))
                return out
            return filt.update(q, rate, acc, mag, dt=dt)

        trajectory = _marg_loop(imu, init_quat_wxyz, update, nwu=True, invalid_rate=np.zeros(3))
        return Trajectory(trajectory.t, trajectory.quat_wxyz, diagnostics={"final_cov": np.array(filt.P)})

    def _estimate_compiled(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """`estimate` through the twin, with the inputs the library path passes: in 6-D the
        accelerometer in m/s^2 with non-finite samples kept (`step` branches on them), in 9-D as
        `_marg_loop` passes it; the library's normalised magnetic reference."""
        _check_length(imu, "ahrs-ekf")
        p = self.params
        gyr, acc, mag, dt = _twin_inputs(imu, np.zeros(3))
        mag_ok = np.array(imu.mag_valid[1:] if imu.has_mag else (), dtype=bool)  # writable (`_twin_inputs`)
        if imu.has_mag:
            zero = mag_ok & ~np.any(mag, axis=1)
            if np.any(zero):  # as `EKF.update` raises on one
                raise ValueError(f"ahrs-ekf: {imu.source or 'input'}: magnetometer sample {int(np.argmax(zero)) + 1} "
                                 "is zero (the EKF needs a field of non-zero magnitude)")
            m_ref = _ekf_magnetic_ref(imu)
            m_ref = m_ref / np.linalg.norm(m_ref)  # as the library normalises it
        else:
            acc = np.array(imu.acc_g[1:], dtype=np.float64, order="C") * STANDARD_GRAVITY_M_S2
            m_ref = np.array([1.0, 0.0, 0.0])  # unused in 6-D
        out, q0 = _twin_start(imu, init_quat_wxyz, nwu=imu.has_mag)
        cov = np.ascontiguousarray(p.init_cov * np.identity(4))
        self._twins.ekf_kernel(gyr, acc, mag, mag_ok, dt, q0, cov, float(p.gyr_var_rad2_s2), float(p.acc_var),
                               float(p.mag_var), m_ref, imu.has_mag, out)
        return Trajectory(imu.t, out, diagnostics={"final_cov": cov})

    def reset(self, init_quat_wxyz: np.ndarray) -> None:
        # magnetic_ref given so the library does not evaluate its geomagnetic model (unused in 6-D).
        self._filter = self._library_filter(0.0)
        self._q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)

    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        rate = gyr_rad_s if gyr_valid else np.zeros(3)
        if np.all(np.isfinite(acc_g)):
            self._q = self._filter.update(self._q, rate, acc_g * STANDARD_GRAVITY_M_S2, dt=dt_s)
        else:  # no accelerometer sample: the EKF's own process model only (its update would return q unrotated)
            q = self._filter.f(self._q, rate, dt_s)
            self._q = q / np.linalg.norm(q)
        return self._q

    def diagnostics(self) -> dict[str, Any]:
        return {"final_cov": np.array(self._filter.P)}
        return {"final_cov": np.array(self._filter.P)}

