"""The rest of the `ahrs` package's recursive filters (Garcia, https://ahrs.readthedocs.io, version
0.4) behind our `Estimator` interface: AQUA (Valenti et al. 2015), the complementary filter, FKF
(Guo et al. 2017), Fourati's filter (Fourati et al. 2011), ROLEQ (Zhou et al. 2018), the UKF, and
the gyro's integration alone (`AngularRate`). Madgwick, Mahony and the EKF are
`peers.ahrs_filters`; the conventions every peer shares, `peers.vqf_fusion`' module docstring.

Every adapter starts the filter at the initial orientation, steps it with the real per-sample dt
(the complementary filter, which has no per-sample update, with one constant sample time:
`_rate_for_constant_ts`), and calls the library's own update per sample: step k with the gyro
reading of the interval [t[k], t[k+1]] and the accelerometer (and magnetometer) sample k + 1, the
library's own pairing (its batch loops pair gyro t with accelerometer t). Inputs in the units the
library documents: gyro rad/s, accelerometer m/s^2, magnetometer mT (each filter normalises them).

Frames, found by running each on simulated motion in an ENU world and checked by
`tests/test_more_peers.py`: AQUA's quaternion is the *inverse* of `R_world_body` (Valenti et al.'s
L_G q, the global frame in the local one), its 9-D world x north (NWU); FKF's world is NWU
(its start, `ecompass(frame="NED")`, is `R_world_body` in NWU, whatever the name); the
complementary filter's angles are roll, pitch, yaw (ZYX) of `R_world_body` in NWU; Fourati's filter,
ROLEQ and the UKF take their magnetic reference from the adapter, which gives it in ENU, so they
work in ENU. The adapter turns every estimate into ENU (x east, y north, z up), the frame of BROAD's
truth; in 6-D the turn changes nothing measurable.

The magnetic reference (Fourati, ROLEQ, UKF): north and the dip d measured on the recording
(`peers.ahrs_single.measured_dip_deg`), as the vector `[0, cos d, -sin d]` of a z-up ENU world
(Fourati's `magnetic_dip=[0, 0, cos d, -sin d]`, ROLEQ's `magnetic_ref=d` with `frame="ENU"`, the
UKF's `m_ref` attribute, which it has no keyword for). The libraries' defaults are Munich's field
in NED, whose z points down, against gravity references of a z-up world in Fourati's filter and the
UKF: a northern field there would point up.

9-D only methods in 6-D. FKF, Fourati's filter and ROLEQ correct with both vectors at once and have
no accelerometer-only update. In 6-D (and for a missing magnetometer sample in 9-D) the adapter
gives them a *virtual field*: the reading of a horizontal northern field at the filter's own
current orientation (ROLEQ: after its gyro step; FKF: at its prediction), which disagrees with
nothing, so the magnetometer's term corrects nothing and the accelerometer corrects the inclination
while the gyro carries the heading, as in any 6-D filter. Likewise a missing accelerometer sample
(non-finite or zero) is, for FKF, Fourati and the UKF, the reading their current orientation
predicts (no correction; the UKF still shrinks its covariance as after a measurement); AQUA and
ROLEQ have their own "no sample" branch (a zero vector), the complementary filter none: there the
last usable sample stands in (and, in 9-D, the last usable magnetometer sample).

Invalid gyro samples: zero rate, except for AQUA and Fourati, which skip the whole update, the
accelerometer's correction included, on an exactly zero rate: there a rate of 1e-150 rad/s stands
for zero (as for Madgwick and Mahony).

Library traps: the complementary filter's 6-D heading is held at 0 by the library (it updates roll
and pitch only): the adapter starts it at the initial orientation's roll and pitch and turns the result by
its yaw, so its heading stays the initial one; its angles are filtered as numbers (a yaw wrapping
past +-180 deg is averaged with one near the other end), as published. AQUA's `adaptive=True`
replaces `alpha` after the first step by the library's `adaptive_gain(acc)`, whose own default
alpha_bar is 0.1 (not `alpha`). The UKF's `Omega`-based prediction and its sigma-point weights are
the library's (alpha 1e-3: a centre weight near -1e6).
"""
from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any, Callable, ClassVar, Literal

import numpy as np

from fusion import quaternion as quat
from fusion.types import ImuSamples, Trajectory

from ..base import Estimator
from ..params import param
from ..search import Tunable
from .ahrs_filters import _check_impl
from .ahrs_single import MT_PER_UT, measured_dip_deg
from .vqf_fusion import (
    _RZ90, _TINY_RATE_RAD_S, _acc_m_s2, _check_length, _non_negative, _positive, _rate_for_constant_ts, _require,
)

_ZERO = np.zeros(3)
_UP = np.array([0.0, 0.0, 1.0])


def _enu_field(dip_deg: float) -> np.ndarray:
    """(3,) the unit reference field of a z-up ENU world, dipping `dip_deg` (positive down)."""
    d = np.radians(dip_deg)
    return np.array([0.0, np.cos(d), -np.sin(d)])


def _in_body(q_world_body: np.ndarray, v_world: np.ndarray) -> np.ndarray:
    """(3,) `R(q)^T v`: the body-frame reading of the world vector v at `R_world_body` = q."""
    return quat.rotation_matrix(q_world_body / np.linalg.norm(q_world_body)).T @ v_world


def _inputs(imu: ImuSamples, invalid_rate: np.ndarray) -> tuple[np.ndarray, ...]:
    """(rates, dt, acc, acc_ok, mag, mag_ok): the interval rates (N-1, 3) rad/s with `invalid_rate`
    where the gyro sample is invalid, dt (N-1,) s, and each step's end samples: acc (N-1, 3) m/s^2,
    acc_ok where finite and non-zero; mag (N-1, 3) mT, mag_ok where valid and non-zero (all False
    in 6-D)."""
    (rates, valid), dt = imu.interval_rates(), imu.dt
    rates[~valid] = invalid_rate
    acc = _acc_m_s2(imu.acc_g)[1:]
    acc_ok = np.any(acc != 0.0, axis=1)
    if imu.has_mag:
        mag = np.where(imu.mag_valid[:, None], imu.mag_ut, 0.0)[1:] * MT_PER_UT
        mag_ok = np.any(mag != 0.0, axis=1)
    else:
        mag, mag_ok = np.zeros_like(acc), np.zeros(len(acc), dtype=bool)
    return rates, dt, acc, acc_ok, mag, mag_ok


def _loop(imu: ImuSamples, init_quat_wxyz: np.ndarray, step: Callable | None, lib_from_enu: Callable,
          enu_from_lib: Callable, invalid_rate: np.ndarray = _ZERO, kernel: Callable | None = None) -> Trajectory:
    """The library's update over the recording: `step(q, rate, acc, acc_ok, mag, mag_ok, dt)` in the
    library's own convention, started at `lib_from_enu(q0)`; rows 1.. are `enu_from_lib` of its
    outputs (vectorised over the rows), row 0 the initial orientation as given. With `kernel` (a compiled twin's
    loop, `peers._compiled_ahrs_recursive`), `kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out)`
    writes the outputs (N-1, 4) instead, from the same inputs."""
    _check_length(imu, "ahrs")
    rates, dt, acc, acc_ok, mag, mag_ok = _inputs(imu, invalid_rate)
    q = lib_from_enu(np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz))
    lib = np.empty((len(imu) - 1, 4))
    if kernel is not None:
        # writable C-ordered float64 (and bool) arrays: the types the kernels were compiled for (`load`)
        args = [np.array(a, dtype=bool if a.dtype == bool else np.float64, order="C")
                for a in (rates, dt, acc, acc_ok, mag, mag_ok, q)]
        kernel(*args, lib)
    else:
        for k in range(len(imu) - 1):
            q = np.asarray(step(q, rates[k], acc[k], acc_ok[k], mag[k], mag_ok[k], dt[k]), dtype=float)
            lib[k] = q
    out = np.empty((len(imu), 4))
    out[0] = init_quat_wxyz
    out[1:] = enu_from_lib(lib)
    return Trajectory(imu.t, out)


def _from_nwu(q: np.ndarray) -> np.ndarray:
    return quat.multiply(_RZ90, q)


def _to_nwu(q: np.ndarray) -> np.ndarray:
    return quat.multiply(quat.conjugate(_RZ90), q)


def _same(q: np.ndarray) -> np.ndarray:
    return q


class _AhrsRecursive(Estimator):
    """A recursive `ahrs` filter (module docstring); subclasses write `estimate`. With
    `impl=compiled` (the default) `_twins` is `peers._compiled_ahrs_recursive` (compiled, or loaded
    from numba's cache, now), with `impl=library` None."""

    magnetometer = True
    _name: ClassVar[str] = ""

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._filters = _require("ahrs.filters", "ahrs", self._name)
        impl = getattr(self.params, "impl", "library")  # (the complementary filter has no twin)
        _check_impl(self._name, impl)
        self._twins: ModuleType | None = None
        if impl == "compiled":
            from . import _compiled_ahrs_recursive  # numba is imported when a compiled peer is built

            _compiled_ahrs_recursive.load()
            self._twins = _compiled_ahrs_recursive


# Two implementations each (`impl`), as for Madgwick, Mahony and the EKF (`peers.ahrs_filters`), but for
# the complementary filter (the library's batch call is vectorised already): "compiled" (the default)
# runs the adapter's loop in a numba twin of the library's update (`peers._compiled_ahrs_recursive`;
# the same numbers to 1e-9, `tests/test_compiled_peers.py`), "library" calls the library per sample
# and is the reference.

# ------------------------------------------------------------------------------ AQUA


# The references the fields cite (their "reference" metadata, `fusion list NAME`).
_AHRS_DOCS = "the ahrs package's documentation of the filter (its parameters and defaults)"
_VALENTI = 'Valenti, Dryanovski & Xiao 2015, "Keeping a good attitude", Sensors 15(8)'
_GUO = "Guo et al. 2017 (the fast Kalman filter, FKF)"
_FOURATI = "Fourati et al. 2011 (the nonlinear complementary filter)"
_ZHOU = "Zhou et al. 2018 (OLEQ and its recursive form, ROLEQ)"
_WAN = 'Wan & van der Merwe 2000, "The unscented Kalman filter for nonlinear estimation"'


def _impl() -> Any:
    """The `impl` field of the recursive ahrs peers."""
    return param("compiled", unit="", valid="compiled | library",
                 meaning="compiled runs the numba twin of the library's update (`peers._compiled_ahrs_recursive`), "
                         "library the library per sample (the reference).")


@dataclass(frozen=True)
class AQUAParams:
    """`ahrs.filters.AQUA` parameters (its defaults), documented at the fields (`fusion list aqua`)."""

    # Range: a correction from 1e-4 to 1 per sample (log scale). Grids: the library's 0.01, and a
    # decade of gains around it (at 100-300 Hz a gain of 0.01 per sample is a time constant of
    # 0.3-1 s): 3 x 2 = 6 settings in 9-D, 3 in 6-D.
    alpha: float = param(
        0.01, unit="1", valid="(0, 1]", reference=_VALENTI + ", eqs. 50-52",
        search=Tunable(1e-4, 1.0, log=True, grid=(0.003, 0.01, 0.03)),
        meaning="The accelerometer correction's interpolation gain per sample (LERP or SLERP of the correction "
                "quaternion towards identity).")
    beta: float = param(
        0.01, unit="1", valid="(0, 1]", reference=_VALENTI + ", eq. 59",
        search=Tunable(1e-4, 1.0, log=True, grid=(0.001, 0.01), magnetometer=True),
        meaning="The magnetometer correction's interpolation gain per sample (9-D only).")
    threshold: float = param(
        0.9, unit="1", valid="> 0", reference=_VALENTI + ", eq. 50",
        meaning="The correction quaternion's scalar part above which LERP replaces SLERP.")
    adaptive: bool = param(
        False, unit="", valid="true | false", reference=_VALENTI + ", eqs. 60-61",
        meaning="Adapt the accelerometer gain to the acceleration's magnitude error (the library's adaptive_gain, "
                "with its own alpha_bar of 0.1).")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _positive("aqua", alpha=self.alpha, beta=self.beta, threshold=self.threshold)
        if self.alpha > 1 or self.beta > 1:
            raise ValueError(f"aqua: alpha and beta must be at most 1, got {self.alpha}, {self.beta}")


class AQUAPeer(_AhrsRecursive):
    """AQUA, the algebraic quaternion filter (Valenti et al. 2015), from the `ahrs` package.

    `ahrs.filters.AQUA.updateIMU` (6-D) and `updateMARG` (9-D, NWU turned to ENU)."""

    Params = AQUAParams
    _name = "aqua"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        filt = self._filters.AQUA(alpha=p.alpha, beta=p.beta, threshold=p.threshold, adaptive=p.adaptive)
        to_lib, from_lib = (lambda q: quat.conjugate(_to_nwu(q))), (lambda q: _from_nwu(quat.conjugate(q)))
        if self._twins is not None:
            gravity = float(self._filters.aqua.GRAVITY)  # `adaptive_gain`'s g
            twin = self._twins.aqua_kernel

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                twin(rates, acc, mag, dt, q0, float(p.alpha), float(p.beta), float(p.threshold), bool(p.adaptive),
                     gravity, imu.has_mag, out)

            return _loop(imu, init_quat_wxyz, None, to_lib, from_lib, invalid_rate=_TINY_RATE_RAD_S, kernel=kernel)

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):  # Valenti et al. 2015, eqs. 42-59; zeros: its "no sample"
            if imu.has_mag:
                return filt.updateMARG(q, rate, acc, mag, dt=dt)
            return filt.updateIMU(q, rate, acc, dt=dt)

        # the library's q is the inverse of R_world_body (module docstring), in NWU
        return _loop(imu, init_quat_wxyz, step, to_lib, from_lib, invalid_rate=_TINY_RATE_RAD_S)


# ------------------------------------------------------------------------------ complementary filter


@dataclass(frozen=True)
class ComplementaryParams:
    """`ahrs.filters.Complementary` parameters (its default), documented at the field."""

    # Grid: the library's 0.9 (a time constant of some 10 samples) and gains up to a time constant
    # of 1000 samples (4-10 s at 100-286 Hz): 4 settings.
    gain: float = param(
        0.9, unit="1", valid="[0, 1]", reference=_AHRS_DOCS,
        search=Tunable(0.5, 0.9999, log=False, grid=(0.9, 0.98, 0.995, 0.999)),
        meaning="The weight of the gyro-propagated angles per sample, 1 - gain being that of the accelerometer's "
                "(and magnetometer's) angles.")

    def __post_init__(self) -> None:
        if not 0.0 <= self.gain <= 1.0:
            raise ValueError(f"complementary: gain must be in [0, 1], got {self.gain}")


def _fill_forward(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Rows where `ok` is False replaced by the last row where it is True (the first such row for
    the leading ones)."""
    rows = np.where(ok, np.arange(len(ok)), -1)
    rows = np.maximum.accumulate(rows)
    rows[rows < 0] = int(np.argmax(ok))
    return values[rows]


class ComplementaryPeer(_AhrsRecursive):
    """A complementary filter of roll, pitch and yaw angles, from the `ahrs` package.

    `ahrs.filters.Complementary` (batch only; one constant sample time; 6-D: roll and pitch)."""

    Params = ComplementaryParams
    _name = "complementary"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        from scipy.spatial.transform import Rotation

        _check_length(imu, self._name)
        gyr, ts = _rate_for_constant_ts(imu)  # the library pairs gyro t with accelerometer t
        acc = _acc_m_s2(imu.acc_g)
        acc_ok = np.any(acc != 0.0, axis=1)
        if not np.any(acc_ok):
            raise ValueError(f"complementary: {imu.source or 'input'} has no usable accelerometer sample")
        acc = _fill_forward(acc, acc_ok)
        q0 = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
        kw: dict[str, Any] = {}
        if imu.has_mag:
            mag = _fill_forward(np.where(imu.mag_valid[:, None], imu.mag_ut, 0.0) * MT_PER_UT, imu.mag_valid)
            kw["mag"] = mag
            q0 = _to_nwu(q0)
        yaw, pitch, roll = Rotation.from_quat(q0, scalar_first=True).as_euler("ZYX")
        w0 = np.array([roll, pitch, yaw if imu.has_mag else 0.0])
        filt = self._filters.Complementary(gyr=gyr, acc=acc, frequency=1.0 / ts, gain=self.params.gain, w0=w0, **kw)
        q = np.asarray(filt.Q, dtype=float)
        if imu.has_mag:
            q = _from_nwu(q)
        else:  # the library holds the 6-D yaw at 0: turned by the initial one's (module docstring)
            q = quat.multiply(np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), q)
        q[0] = init_quat_wxyz
        return Trajectory(imu.t, q)


# ------------------------------------------------------------------------------ FKF


@dataclass(frozen=True)
class FKFParams:
    """`ahrs.filters.FKF` parameters (its defaults; Guo et al. 2017), documented at the fields."""

    # Ranges: several decades around the library's 0.01, log scale. Grid: 3 x 2 = 6 settings.
    gyr_var: float = param(
        0.01, alias="sigma_g", unit="rad^2/s^2", valid="> 0", reference=_GUO,
        search=Tunable(1e-6, 1.0, log=True, grid=(1e-4, 1e-3, 0.01)),
        meaning="The gyro's noise variance (the library's sigma_g).")
    acc_var: float = param(
        0.01, alias="sigma_a", unit="1", valid="> 0", reference=_GUO,
        search=Tunable(1e-4, 10.0, log=True, grid=(0.01, 0.1)),
        meaning="The normalised accelerometer's noise variance (the library's sigma_a).")
    mag_var: float = param(0.01, alias="sigma_m", unit="1", valid="> 0", reference=_GUO,
                           meaning="The normalised magnetometer's noise variance (the library's sigma_m).")
    init_cov: float = param(0.01, alias="Pk", unit="1", valid=">= 0", reference=_GUO,
                            meaning="The initial covariance, init_cov I_4 (the library's Pk).")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _positive("fkf", gyr_var=self.gyr_var, acc_var=self.acc_var, mag_var=self.mag_var)
        _non_negative("fkf", init_cov=self.init_cov)


class FKFPeer(_AhrsRecursive):
    """FKF, the fast linear Kalman filter (Guo et al. 2017), from the `ahrs` package.

    The quaternion from accelerometer and magnetometer in closed form as the measurement of a
    linear Kalman filter, `ahrs.filters.FKF` (9-D; 6-D with a virtual field: module docstring).
    NWU, turned to ENU."""

    Params = FKFParams
    _name = "fkf"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        filt = self._filters.FKF(sigma_g=p.gyr_var, sigma_a=p.acc_var, sigma_m=p.mag_var, Pk=p.init_cov)
        from_lib = lambda q: _from_nwu(quat.normalize(q))  # noqa: E731
        if self._twins is not None:
            twin = self._twins.fkf_kernel

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                twin(rates, acc, acc_ok, mag, mag_ok, dt, q0, np.array(filt.Pk, dtype=float), float(p.gyr_var),
                     float(p.acc_var), float(p.mag_var), out)

            return _loop(imu, init_quat_wxyz, None, _to_nwu, from_lib, kernel=kernel)
        sigma_g = p.gyr_var * np.identity(3)  # the lines of `FKF._compute_all`, with the step's dt
        sigma_am = np.diag([p.acc_var] * 3 + [p.mag_var] * 3)
        north = np.array([1.0, 0.0, 0.0])

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):  # Guo et al. 2017; NWU
            phi = np.identity(4) + 0.5 * dt * filt.Omega4(rate)
            xi = np.array([[q[1], q[2], q[3]], [-q[0], -q[3], -q[2]], [q[2], -q[0], -q[1]], [-q[2], q[1], -q[0]]])
            sigma_eps = (dt / 2.0) ** 2 * xi @ sigma_g @ xi.transpose()
            predicted = phi @ q
            if not acc_ok:  # the reading the prediction expects (module docstring)
                acc = _in_body(predicted, _UP)
            if not mag_ok:  # the virtual field at the prediction
                mag = _in_body(predicted, north)
            q_am, jac = filt.measurement_quaternion_acc_mag(q, acc, mag)
            sigma_v = jac @ sigma_am @ jac.transpose()
            q_new, filt.Pk = filt.kalman_update(q, q_am, filt.Pk, phi, sigma_eps, sigma_v)
            return q_new

        return _loop(imu, init_quat_wxyz, step, _to_nwu, from_lib)


# ------------------------------------------------------------------------------ Fourati


@dataclass(frozen=True)
class FouratiParams:
    """`ahrs.filters.Fourati` parameters (its default), documented at the fields."""

    # Range: from nearly the gyro alone to a correction dominating it, log scale. Grid: the
    # library's 0.1 and a factor 3 either side: 3 settings.
    gain: float = param(
        0.1, unit="1", valid="> 0", reference=_FOURATI + ", eq. 31",
        search=Tunable(1e-3, 10.0, log=True, grid=(0.03, 0.1, 0.3)),
        meaning="The gain k of the Levenberg-Marquardt correction.")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _positive("fourati", gain=self.gain)


class FouratiPeer(_AhrsRecursive):
    """Fourati's nonlinear complementary filter (Fourati et al. 2011), from the `ahrs` package.

    `ahrs.filters.Fourati.update` (9-D; 6-D with a virtual field: module docstring). ENU."""

    Params = FouratiParams
    _name = "fourati"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        m_ref = _enu_field(measured_dip_deg(imu)) if imu.has_mag else np.array([0.0, 1.0, 0.0])
        filt = self._filters.Fourati(gain=self.params.gain, magnetic_dip=np.array([0.0, *m_ref]))
        if self._twins is not None:
            twin = self._twins.fourati_kernel
            g_q, m_q = np.array(filt.g_q, dtype=float), np.array(filt.m_q, dtype=float)  # the library's references

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                twin(rates, acc, acc_ok, mag, mag_ok, dt, q0, float(self.params.gain), g_q, m_q, m_ref, out)

            return _loop(imu, init_quat_wxyz, None, _same, _same, invalid_rate=_TINY_RATE_RAD_S, kernel=kernel)

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):  # Fourati et al. 2011, eqs. 25-31
            if not acc_ok:
                acc = _in_body(q, _UP)
            if not mag_ok:
                mag = _in_body(q, m_ref)
            return filt.update(q, rate, acc, mag, dt=dt)

        return _loop(imu, init_quat_wxyz, step, _same, _same, invalid_rate=_TINY_RATE_RAD_S)


# ------------------------------------------------------------------------------ ROLEQ


@dataclass(frozen=True)
class ROLEQParams:
    """`ahrs.filters.ROLEQ` parameters (its defaults), documented at the fields."""

    acc_weight: float = param(1.0, unit="1", valid="> 0", reference=_ZHOU,
                              meaning="The weight of the normalised accelerometer in OLEQ's matrix (the library's "
                                      "weights).")
    mag_weight: float = param(
        1.0, unit="1", valid=">= 0", reference=_ZHOU,
        search=Tunable(1e-3, 1e3, log=True, grid=(0.1, 1.0, 10.0), magnetometer=True),
        meaning="The weight of the normalised magnetometer in OLEQ's matrix (the library's weights).")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _non_negative("roleq", acc_weight=self.acc_weight, mag_weight=self.mag_weight)
        if not self.acc_weight > 0:
            raise ValueError(f"roleq: acc_weight must be positive, got {self.acc_weight}")


class ROLEQPeer(_AhrsRecursive):
    """ROLEQ, the recursive OLEQ (Zhou et al. 2018), from the `ahrs` package.

    The gyro step, then one step of OLEQ's power iteration, `ahrs.filters.ROLEQ` (9-D; 6-D with a
    virtual field: module docstring). ENU."""

    Params = ROLEQParams
    _name = "roleq"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        dip = measured_dip_deg(imu) if imu.has_mag else 0.0
        filt = self._filters.ROLEQ(weights=np.array([p.acc_weight, p.mag_weight]), magnetic_ref=float(dip),
                                   frame="ENU")
        m_ref = _enu_field(dip)
        if self._twins is not None:
            twin = self._twins.roleq_kernel
            a_ref, lib_m_ref = np.array(filt.a_ref, dtype=float), np.array(filt.m_ref, dtype=float)

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                twin(rates, acc, acc_ok, mag, mag_ok, dt, q0, float(filt.a[0]), float(filt.a[1]), a_ref, lib_m_ref,
                     m_ref, out)

            return _loop(imu, init_quat_wxyz, None, _same, _same, kernel=kernel)

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):  # `ROLEQ.update`: Zhou et al. 2018
            q_g = filt.attitude_propagation(q, rate, dt)
            if acc_ok and not mag_ok:  # the virtual field after the gyro step (a zero acc: the library's branch)
                mag = _in_body(q_g, m_ref)
            return filt.oleq(acc, mag, q_g)

        return _loop(imu, init_quat_wxyz, step, _same, _same)


# ------------------------------------------------------------------------------ UKF


@dataclass(frozen=True)
class AhrsUKFParams:
    """`ahrs.filters.UKF` parameters (its defaults), documented at the fields."""

    # Grids: the library's defaults and a decade below (the UKF costs some 0.5 ms a sample in the
    # library: 2 x 2 = 4 settings).
    process_var: float = param(
        1e-4, alias="Q", unit="1", valid="> 0", reference=_AHRS_DOCS,
        search=Tunable(1e-8, 1e-1, log=True, grid=(1e-5, 1e-4)),
        meaning="The process noise, process_var I_4 on the quaternion (the library's process_noise_covariance).")
    meas_var: float = param(
        1e-2, alias="R", unit="1", valid="> 0", reference=_AHRS_DOCS,
        search=Tunable(1e-5, 10.0, log=True, grid=(1e-3, 1e-2)),
        meaning="The measurement noise of each normalised vector, meas_var I_3 (the library's "
                "measurement_noise_covariance).")
    init_cov: float = param(1e-2, alias="P", unit="1", valid=">= 0", reference=_AHRS_DOCS,
                            meaning="The initial covariance, init_cov I_4 (the library's P).")
    alpha: float = param(1e-3, unit="1", valid="> 0", reference=_WAN,
                         meaning="The unscented transform's spread of the sigma points.")
    beta: float = param(2.0, unit="1", valid="a number", reference=_WAN,
                        meaning="The unscented transform's prior knowledge of the distribution (2: Gaussian).")
    kappa: float = param(0.0, unit="1", valid="a number", reference=_WAN,
                         meaning="The unscented transform's secondary scaling.")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        _positive("ahrs-ukf", process_var=self.process_var, meas_var=self.meas_var, alpha=self.alpha)
        _non_negative("ahrs-ukf", init_cov=self.init_cov)


class AhrsUKFPeer(_AhrsRecursive):
    """A quaternion UKF, from the `ahrs` package.

    `ahrs.filters.UKF.update` (6-D, or 9-D with its magnetic reference set to the recording's field
    in ENU). ENU."""

    Params = AhrsUKFParams
    _name = "ahrs-ukf"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        p = self.params
        filt = self._filters.UKF(alpha=p.alpha, beta=p.beta, kappa=p.kappa, P=p.init_cov * np.identity(4),
                                 process_noise_covariance=p.process_var * np.identity(4),
                                 measurement_noise_covariance=p.meas_var * np.identity(3))
        if imu.has_mag:
            filt.m_ref = _enu_field(measured_dip_deg(imu))  # (no keyword for it: module docstring)
        if self._twins is not None:
            twin = self._twins.ukf_kernel
            wm, wc = np.array(filt.weight_mean, dtype=float), np.array(filt.weight_covariance, dtype=float)
            refs = np.array(filt.a_ref, dtype=float), np.array(filt.m_ref, dtype=float)

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                k = twin(rates, acc, acc_ok, mag, mag_ok, dt, q0, np.array(filt.P, dtype=float), wm, wc,
                         float(filt.state_dimension + filt.lambda_param), float(p.process_var), float(p.meas_var),
                         *refs, imu.has_mag, out)
                if k >= 0:  # where the library's `np.linalg.cholesky` raises
                    raise np.linalg.LinAlgError(
                        f"ahrs-ukf: {imu.source or 'input'}: the library's UKF fails at sample {k + 1}: its "
                        "covariance is not positive definite (Matrix is not positive definite), even regularised")

            return _loop(imu, init_quat_wxyz, None, _same, _same, kernel=kernel)

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):
            acc = acc / np.linalg.norm(acc) if acc_ok else _in_body(q, filt.a_ref)  # normalised, as its batch does
            if not imu.has_mag:
                return filt.update(q, rate, acc, dt=dt)
            mag = mag / np.linalg.norm(mag) if mag_ok else _in_body(q, filt.m_ref)
            return filt.update(q, rate, acc, mag, dt=dt)

        return _loop(imu, init_quat_wxyz, step, _same, _same)


# ------------------------------------------------------------------------------ AngularRate


@dataclass(frozen=True)
class AngularRateParams:
    """`ahrs.filters.AngularRate.update` parameters (its defaults), documented at the fields."""

    method: str = param("closed", unit="", valid="closed | series", reference=_AHRS_DOCS,
                        meaning="closed integrates by the exponential of the rate over dt, series by its truncated "
                                "series.")
    order: int = param(1, unit="", valid="a whole number >= 0; applies only with method=series",
                       reference=_AHRS_DOCS, meaning="The series' order.")
    impl: Literal["compiled", "library"] = _impl()

    def __post_init__(self) -> None:
        if self.method not in ("closed", "series"):
            raise ValueError(f"ahrs-angular: method must be closed or series, got {self.method!r}")
        if self.order < 0:
            raise ValueError(f"ahrs-angular: order must be >= 0, got {self.order}")


class AngularRatePeer(_AhrsRecursive):
    """The gyro's integration alone (no correction), from the `ahrs` package.

    `ahrs.filters.AngularRate.update`."""

    Params = AngularRateParams
    magnetometer = False
    _name = "ahrs-angular"

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        filt = self._filters.AngularRate()
        p = self.params
        if self._twins is not None:
            twin = self._twins.angular_kernel

            def kernel(rates, dt, acc, acc_ok, mag, mag_ok, q0, out):
                twin(rates, dt, q0, p.method == "closed", int(p.order), out)

            return _loop(imu, init_quat_wxyz, None, _same, _same, kernel=kernel)

        def step(q, rate, acc, acc_ok, mag, mag_ok, dt):
            return filt.update(q, rate, method=p.method, order=p.order, dt=dt)

        return _loop(imu, init_quat_wxyz, step, _same, _same)
