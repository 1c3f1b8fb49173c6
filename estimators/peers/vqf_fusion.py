"""The community's orientation filters behind our `Estimator` interface.

Adapters for VQF (`vqf`: `VQF`, `BasicVQF`, `offlineVQF`; Laidig & Seel 2023), the `ahrs`
package's Madgwick, Mahony and EKF (in `peers.ahrs_filters`), and x-io's Fusion (`imufusion`). They are an optional
extra: `pip install -e '.[peers]'`. Each library is imported when its estimator is built,
so the toolkit runs without them and asking for a missing one says what to install.

Every adapter gets what our own estimators get: the calibrated samples (gyro rad/s, body
frame; accelerometer in g, converted to whatever unit the library wants), the real
per-sample time steps where the library accepts them, and the initial orientation
`R_world_body` at `t[0]`. The libraries' own published defaults are the defaults here;
each parameter dataclass names the library's keyword as the field's alias, so
`vqf:tauAcc=1` and `vqf:tau_acc_s=1` are the same. The traps, checked by
`tests/test_peers.py` (a wrong frame or quaternion order fails those tests):

- Quaternions: every library here returns scalar-first `[w, x, y, z]` orientations of the
  sensor in a z-up world (`R_world_body`), once given the inputs below; no reordering.
- `vqf`: gyro rad/s, accelerometer m/s^2, C-contiguous float64 arrays; one constant sample
  time (see `_rate_for_constant_ts` for how the real time steps are honoured). `VQF` and
  `BasicVQF` are seeded through their state (`gyrQuat` = initial orientation, `accQuat` =
  identity; the 6-D output is `accQuat * gyrQuat`). `offlineVQF` takes no initial
  orientation: its output is turned about the vertical once so that its heading at `t[0]`
  matches the initial orientation (inclination is its own).
- `ahrs` Madgwick/Mahony: body rates, z-up gravity reference, any accelerometer unit (they
  normalise). They skip the whole update, accelerometer correction included, when the
  gyro sample is exactly zero.
- `ahrs` EKF: its default frame `"NED"` is the right one for us. With `frame="NED"` it
  predicts the accelerometer as `R^T [0, 0, 1]`, which is what a specific-force
  accelerometer reads in a z-up world; `frame="ENU"` predicts `R^T [0, 0, -1]` and would
  turn every estimate upside down. Its default initial covariance is the identity on the
  four quaternion components (`P0 = 1`), i.e. "orientation unknown", even when seeded: the
  first accelerometer samples then pull the inclination hard. Kept as published (`P0`
  changes it).
- `imufusion` 1.3.3: gyro in deg/s, accelerometer in g; the sample period is set before
  every update (`set_sample_period`); the `AhrsSettings(convention=...)` keyword is ignored
  (the attribute has to be set afterwards); its default NWU convention is z-up, which is
  ours. Its start-up phase ignores the gyro for 3 s (while a gain ramp aligns the
  inclination): as we seed it with the initial orientation, the adapter skips it unless
  `startup=true`.

9-D (a recording with a magnetometer, `ImuSamples.mag_ut`; `magnetometer = True` on every
adapter): each library gets the magnetometer through its own API (VQF's and BasicVQF's
`updateBatch(gyr, acc, mag)` and `offlineVQF(gyr, acc, mag, ...)` with their `quat9D`; ahrs'
`Madgwick.updateMARG`, `Mahony.updateMARG` and `EKF.update(..., mag)`; Fusion's `Ahrs.update`),
in uT (every one of them normalises it), and the estimate is returned in our 9-D world: ENU (x
east, y north, z up), the frame of BROAD's truth, whose heading agrees with magnetic north. The
frames, found by starting each from a heading 30 deg off and watching it converge to the truth's
(`tests/test_peers.py`): VQF and Mahony are ENU already; Fusion is set to its ENU convention;
Madgwick and the EKF work in a z-up world with x north (NWU): their estimate is turned by 90 deg
about the vertical, `q_ENU = Rz(90 deg) q_NWU`, and seeded with the inverse. Traps: the EKF
compares the accelerometer with `R^T [0, 0, 1]` in its "NED" frame, i.e. its world is z up, so
its magnetic reference must point down for a northern field: it is given as `[cos d, 0, -sin
d]` with the dip d measured on the recording (`fusion.checks.check_magnetometer`; the library's
default is Munich's field from its WMM, signed for a true NED world); and it switches its
measurement model to 9-D on the attribute `mag` (the batch input), which the adapter sets.
offlineVQF's 9-D estimate is not turned to the initial heading (the magnetometer sets it).
Magnetometer samples marked invalid (NaN) are passed as the libraries' "no sample" (a zero
vector for VQF; `None` for the EKF; `update_no_magnetometer` for Fusion); Madgwick and Mahony get
`updateIMU` with the real dt for them (and for a zero sample), which is what their `updateMARG`
does on a zero vector, except that it does not pass dt on and would integrate that step over its
default 0.01 s.

The `ahrs` filters run, by default, as compiled twins (`peers._compiled_ahrs`, `impl=compiled`): the
same arithmetic as the library's per-sample Python, a few hundred times faster; `impl=library`
calls the library, the reference the twins are tested against (`tests/test_compiled_peers.py`).

Flags: where a library reports per-sample states, the trajectory's diagnostics carry them as
(N,) bool arrays (row 0, the seed, False), which the report and `--rerun` show against the error:
VQF's rest and magnetic-disturbance detection (`VQF_FLAGS`: the `restDetected` and
`magDistDetected` outputs of its batch functions; BasicVQF has neither) and Fusion's rejections
and recoveries (`FUSION_FLAGS`: `Ahrs.get_flags()` and `Ahrs.get_internal_states()` after each
update). Reading them costs nothing measurable (VQF returns them anyway; Fusion's are two calls
per sample).

Invalid gyro samples (`imu.gyr_valid` False) are handled as well as each library allows:
zero rate for VQF, offlineVQF, the EKF and Fusion (propagation without the rate, the
accelerometer still corrects; the EKF still adds its usual, not an inflated, process
noise; VQF integrates minus its bias estimate there); for Madgwick and Mahony, which skip
the accelerometer correction on an exactly zero rate, a rate of 1e-150 rad/s stands for
zero so that the correction still runs.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Any, ClassVar

import numpy as np

from fusion import quaternion as quat
from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples, Trajectory

from ..base import Estimator, RecursiveEstimator
from ..params import param, param_as
from ..search import Tunable

INSTALL_HINT = "pip install -e '.[peers]'"
# Stands for a zero rate where a library skips its update on an exactly zero gyro sample.
_TINY_RATE_RAD_S = np.full(3, 1e-150)


class PeerUnavailable(ImportError):
    """A peer estimator's library is not installed."""


def _require(module: str, package: str, estimator: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise PeerUnavailable(
            f"estimator {estimator!r} needs the optional package {package!r}, which is not installed: "
            f"{INSTALL_HINT} (or pip install {package})"
        ) from exc


def _acc_m_s2(acc_g: np.ndarray) -> np.ndarray:
    """Accelerometer in m/s^2, C-contiguous float64, with non-finite samples set to zero:
    VQF, Madgwick, Mahony and Fusion all skip the accelerometer correction on an all-zero
    sample (their convention for "no measurement"), so a NaN never enters their state."""
    acc = np.asarray(acc_g, dtype=np.float64) * STANDARD_GRAVITY_M_S2
    finite = np.all(np.isfinite(acc), axis=-1)
    return np.ascontiguousarray(np.where(finite[..., None], acc, 0.0))


def _positive(owner: str, **values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{owner}: {name} must be positive, got {value}")


def _non_negative(owner: str, **values: float) -> None:
    for name, value in values.items():
        if not value >= 0:
            raise ValueError(f"{owner}: {name} must be >= 0, got {value}")


def align_heading(quat_wxyz: np.ndarray, ref_wxyz: np.ndarray, k: int = 0) -> np.ndarray:
    """Turn a trajectory about the world vertical so its heading at row `k` is `ref_wxyz`'s.

    quat_wxyz: (N, 4) `R_world_body`; ref_wxyz: (4,). Returns a new (N, 4) array
    `Rz(psi) * q`, where `Rz(psi)` is the twist about world z of `ref * q[k]^-1` (the
    swing-twist decomposition). Inclination is unchanged.
    """
    delta = quat.multiply(np.asarray(ref_wxyz, dtype=float), quat.conjugate(quat_wxyz[k]))
    twist = np.array([delta[0], 0.0, 0.0, delta[3]])
    norm = np.linalg.norm(twist)
    if norm < 1e-9:  # the two differ by a half turn about a horizontal axis: no heading defined
        return np.array(quat_wxyz, dtype=float)
    return quat.multiply(twist / norm, quat_wxyz)


def _rate_for_constant_ts(imu: ImuSamples) -> tuple[np.ndarray, float]:
    """Gyro input for a library that integrates with one constant sample time.

    Returns `(gyr, ts)`: `ts` is the mean step `(t[-1] - t[0]) / (N - 1)`, and row `j >= 1`
    of `gyr` (N, 3) is the gyro reading for [t[j-1], t[j]] (`ImuSamples.interval_rates`, which
    honours the recording's `gyr_timing`) scaled by `dt[j - 1] / ts`, so that the library's
    step `j` (gyro `j`, then accelerometer `j`) rotates by exactly that reading times
    `dt[j-1]` and then corrects with accelerometer sample `j`, as `RecursiveEstimator.step`
    does. Row 0 is zero. Invalid gyro samples give zero rows.
    """
    n = len(imu)
    dt = imu.dt
    ts = float((imu.t[-1] - imu.t[0]) / (n - 1))
    rate, valid = imu.interval_rates()
    rate[~valid] = 0.0
    gyr = np.zeros((n, 3))
    gyr[1:] = rate * (dt / ts)[:, None]
    return np.ascontiguousarray(gyr, dtype=np.float64), ts


def _mag_or_zero(imu: ImuSamples) -> np.ndarray:
    """(N, 3) uT, C-contiguous float64, zero rows where there is no valid sample (the VQF, Madgwick
    and Mahony convention for "no magnetometer sample")."""
    return np.ascontiguousarray(np.where(imu.mag_valid[:, None], imu.mag_ut, 0.0), dtype=np.float64)


_RZ90 = np.array([np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])  # 90 deg about z: NWU -> ENU (x north -> y north)


def _marg_loop(imu: ImuSamples, init_quat_wxyz: np.ndarray, update: Any, nwu: bool, invalid_rate: np.ndarray) -> Trajectory:
    """A library's 9-D step over the recording: `update(q, rate, acc_m_s2, mag_ut_or_None, dt)` in
    the library's world (NWU when `nwu`, else ENU), returned in ENU (module docstring).
    `invalid_rate` stands for an invalid gyro sample."""
    (rates, valid), dt = imu.interval_rates(), imu.dt
    acc = _acc_m_s2(imu.acc_g)
    mag, mag_ok = imu.mag_ut, imu.mag_valid
    q = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
    out = np.empty((len(imu), 4))
    out[0] = q
    if nwu:
        q = quat.multiply(quat.conjugate(_RZ90), q)
    for k in range(len(imu) - 1):
        q = np.asarray(update(q, rates[k] if valid[k] else invalid_rate, acc[k + 1],
                              mag[k + 1] if mag_ok[k + 1] else None, dt[k]), dtype=float)
        out[k + 1] = quat.multiply(_RZ90, q) if nwu else q
    return Trajectory(imu.t, out)


def _check_length(imu: ImuSamples, name: str) -> None:
    if len(imu) < 2:
        raise ValueError(f"{name}: needs at least 2 samples, {imu.source or 'input'} has {len(imu)}")


# --------------------------------------------------------------------------------------
# VQF (Laidig & Seel, "VQF: Highly accurate IMU orientation estimation with bias
# estimation and magnetic disturbance rejection", Information Fusion 2023)


# The references the fields cite (their "reference" metadata, `fusion list NAME`).
_VQF = ('Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation with bias estimation and magnetic '
        'disturbance rejection", Information Fusion 91')
_FUSION = "x-io Technologies, Fusion's README (the AHRS algorithm and its settings)"

# Search ranges of VQF's and BasicVQF's time constants (log scale): from a correction faster than
# most motions (0.3 s: corner 0.5 Hz) to one slower than most recordings' disturbances (30 s and
# 100 s). Grids around VQF's documented defaults, 3 s and 9 s (Laidig & Seel 2023; the `vqf`
# documentation): tauAcc 1-10 s, tauMag 3-20 s (5 x 3 = 15 settings in 9-D, 5 in 6-D).
_TAU_ACC_SEARCH = Tunable(0.3, 30.0, log=True, grid=(1.0, 2.0, 3.0, 5.0, 10.0))
_TAU_MAG_SEARCH = Tunable(1.0, 100.0, log=True, grid=(3.0, 9.0, 20.0), magnetometer=True)


@dataclass(frozen=True)
class VQFParams:
    """`vqf.VQF` parameters (its defaults; units in the names, VQF's keyword as alias), each
    documented at its field after VQF's own `VQFParams` documentation (`fusion list vqf`)."""

    tau_acc_s: float = param(
        3.0, alias="tauAcc", unit="s", valid="> 0", reference=_VQF + ", Sec. 3.2", search=_TAU_ACC_SEARCH,
        meaning="Time constant of the inclination correction: the accelerometer is low-passed in the almost "
                "inertial frame with this time constant (a first-order low-pass, its corner at 1 / (2 pi tau)), so "
                "a larger value trusts the gyro longer.")
    tau_mag_s: float = param(
        9.0, alias="tauMag", unit="s", valid="> 0", reference=_VQF + ", Sec. 3.3", search=_TAU_MAG_SEARCH,
        meaning="Time constant of the heading correction by the magnetometer (9-D only).")
    mag_dist_rejection: bool = param(
        True, alias="magDistRejectionEnabled", unit="", valid="true | false", reference=_VQF + ", Sec. 3.3",
        meaning="Detect magnetic disturbances and reject the magnetometer while they last (9-D only).")
    motion_bias_est: bool = param(
        True, alias="motionBiasEstEnabled", unit="", valid="true | false", reference=_VQF + ", Sec. 3.4",
        meaning="Estimate the gyro bias during motion, from the inclination correction only.")
    rest_bias_est: bool = param(
        True, alias="restBiasEstEnabled", unit="", valid="true | false", reference=_VQF + ", Sec. 3.4",
        meaning="Detect rest and estimate the gyro bias during it.")
    bias_sigma_init_deg_s: float = param(
        0.5, alias="biasSigmaInit", unit="deg/s", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Standard deviation of the initial bias estimate's uncertainty.")
    bias_forgetting_time_s: float = param(
        100.0, alias="biasForgettingTime", unit="s", valid="> 0", reference=_VQF + ", Sec. 3.4",
        meaning="Time in which the bias estimate's uncertainty grows from 0 to 0.1 deg/s.")
    bias_clip_deg_s: float = param(
        2.0, alias="biasClip", unit="deg/s", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="The largest gyro bias expected: the bias estimate and the bias update's measurement error are "
                "clipped to it, and rest detection does not take a larger constant rate for rest.")
    bias_sigma_motion_deg_s: float = param(
        0.1, alias="biasSigmaMotion", unit="deg/s", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Standard deviation of the converted bias update during motion.")
    bias_vertical_forgetting_factor: float = param(
        0.0001, alias="biasVerticalForgettingFactor", unit="1", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Relative weight of an artificial zero measurement that lets the bias about the vertical, which "
                "the motion bias estimation cannot observe, decay to zero.")
    bias_sigma_rest_deg_s: float = param(
        0.03, alias="biasSigmaRest", unit="deg/s", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Standard deviation of the converted bias update during rest.")
    rest_min_t_s: float = param(
        1.5, alias="restMinT", unit="s", valid="> 0", reference=_VQF + ", Sec. 3.4",
        meaning="Rest is detected once the measurements have stayed close to their low-passed reference this long.")
    rest_filter_tau_s: float = param(
        0.5, alias="restFilterTau", unit="s", valid="> 0", reference=_VQF + ", Sec. 3.4",
        meaning="Time constant of the low-pass that gives rest detection its reference.")
    rest_th_gyr_deg_s: float = param(
        2.0, alias="restThGyr", unit="deg/s", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Rest detection's threshold on the gyro's deviation from its low-passed reference.")
    rest_th_acc_m_s2: float = param(
        0.5, alias="restThAcc", unit="m/s^2", valid=">= 0", reference=_VQF + ", Sec. 3.4",
        meaning="Rest detection's threshold on the accelerometer's deviation from its low-passed reference.")

    def __post_init__(self) -> None:
        _positive("vqf", tau_acc_s=self.tau_acc_s, tau_mag_s=self.tau_mag_s,
                  bias_forgetting_time_s=self.bias_forgetting_time_s,
                  rest_min_t_s=self.rest_min_t_s, rest_filter_tau_s=self.rest_filter_tau_s)
        _non_negative("vqf", bias_sigma_init_deg_s=self.bias_sigma_init_deg_s, bias_clip_deg_s=self.bias_clip_deg_s,
                      bias_sigma_motion_deg_s=self.bias_sigma_motion_deg_s,
                      bias_vertical_forgetting_factor=self.bias_vertical_forgetting_factor,
                      bias_sigma_rest_deg_s=self.bias_sigma_rest_deg_s, rest_th_gyr_deg_s=self.rest_th_gyr_deg_s,
                      rest_th_acc_m_s2=self.rest_th_acc_m_s2)

    def library_kwargs(self) -> dict[str, Any]:
        """The parameters under VQF's own keyword names."""
        return {f.metadata["alias"]: getattr(self, f.name) for f in self.__dataclass_fields__.values()}


@dataclass(frozen=True)
class BasicVQFParams:
    """`vqf.BasicVQF` parameters (its defaults), documented at the fields as `VQFParams`'."""

    tau_acc_s: float = param_as(VQFParams, "tau_acc_s", 3.0)
    tau_mag_s: float = param_as(VQFParams, "tau_mag_s", 9.0)

    def __post_init__(self) -> None:
        _positive("vqf-basic", tau_acc_s=self.tau_acc_s, tau_mag_s=self.tau_mag_s)

    def library_kwargs(self) -> dict[str, Any]:
        return {"tauAcc": self.tau_acc_s, "tauMag": self.tau_mag_s}


# VQF's per-sample states (the `restDetected` and `magDistDetected` outputs of `updateBatch` and
# `offlineVQF`) under our diagnostics' names: per-sample flags, (N,) bool (`Trajectory`).
VQF_FLAGS = {"restDetected": "rest_detected", "magDistDetected": "mag_disturbance_detected"}


def _vqf_flags(result: dict[str, np.ndarray], first: int = 0) -> dict[str, np.ndarray]:
    """VQF's flags from a batch result (`VQF_FLAGS`), as (first + K,) bool arrays: False for the
    `first` rows the library did not produce (the seed)."""
    out = {}
    for key, name in VQF_FLAGS.items():
        if key in result:
            out[name] = np.concatenate([np.zeros(first, dtype=bool), np.asarray(result[key], dtype=bool)])
    return out


class _SeededVQF(Estimator):
    """`VQF`/`BasicVQF`, 6-D, seeded with the initial orientation through the filter state.

    The state's `gyrQuat` (strapdown integration) is set to the initial orientation and
    `accQuat` (inclination correction) to identity, so `quat6D = accQuat * gyrQuat` starts
    at the initial orientation. VQF then corrects towards its low-passed accelerometer,
    which it initialises with the mean of the first samples, so the inclination settles
    on the accelerometer's within a few samples (VQF's design); the heading is the initial orientation's.
    Constant sample time: see `_rate_for_constant_ts`. Invalid gyro samples: zero rate.

    9-D (`quat9D`): started as the library starts (identity), not seeded: its accelerometer and
    magnetometer corrections (with their fast initial convergence) set inclination and heading
    within the first second, and seeding it changed its score on BROAD's trial 09 by 0.034 deg
    (through its magnetic disturbance detection), more than running the library directly should.
    """

    _class_name: ClassVar[str] = "VQF"
    _name: ClassVar[str] = "vqf"
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._vqf = _require("vqf", "vqf", self._name)

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        _check_length(imu, self._name)
        gyr, ts = _rate_for_constant_ts(imu)
        acc = _acc_m_s2(imu.acc_g)
        filt = getattr(self._vqf, self._class_name)(ts, **self.params.library_kwargs())
        if imu.has_mag:  # 9-D: started as published (identity), see the class docstring
            result = filt.updateBatch(gyr, np.ascontiguousarray(acc), _mag_or_zero(imu))
            return Trajectory(imu.t, result["quat9D"], diagnostics=_vqf_flags(result))
        state = filt.state
        state["gyrQuat"] = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz)
        state["accQuat"] = np.array([1.0, 0.0, 0.0, 0.0])
        filt.state = state
        out = np.empty((len(imu), 4))
        out[0] = state["gyrQuat"]
        result = filt.updateBatch(gyr[1:], np.ascontiguousarray(acc[1:]))
        out[1:] = result["quat6D"]
        return Trajectory(imu.t, out, diagnostics=_vqf_flags(result, first=1))


class VQFPeer(_SeededVQF):
    """VQF (6-D or 9-D, with rest and motion gyro-bias estimation), from the `vqf` package."""

    Params = VQFParams
    _class_name = "VQF"
    _name = "vqf"


class BasicVQFPeer(_SeededVQF):
    """BasicVQF (6-D or 9-D, no bias estimation), from the `vqf` package."""

    Params = BasicVQFParams
    _class_name = "BasicVQF"
    _name = "vqf-basic"


class OfflineVQFPeer(Estimator):
    """`vqf.offlineVQF`: VQF run forwards and backwards over the whole recording (6-D or 9-D).

    offlineVQF takes no initial orientation: its output is turned once about the world
    vertical so that its heading at `t[0]` equals the initial orientation's (inclination
    is its own throughout). Sees the future: `causal = False`. Constant sample time: see
    `_rate_for_constant_ts`. Invalid gyro samples: zero rate.
    """

    Params = VQFParams
    causal = False
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._vqf = _require("vqf", "vqf", "vqf-offline")

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        _check_length(imu, "vqf-offline")
        gyr, ts = _rate_for_constant_ts(imu)
        acc = _acc_m_s2(imu.acc_g)
        if imu.has_mag:  # 9-D: the magnetometer sets the heading
            result = self._vqf.offlineVQF(gyr, acc, _mag_or_zero(imu), ts, self.params.library_kwargs())
            return Trajectory(imu.t, result["quat9D"], diagnostics=_vqf_flags(result))
        result = self._vqf.offlineVQF(gyr, acc, None, ts, self.params.library_kwargs())
        return Trajectory(imu.t, align_heading(result["quat6D"], init_quat_wxyz), diagnostics=_vqf_flags(result))


# --------------------------------------------------------------------------------------
# Fusion (x-io Technologies, `imufusion`)


@dataclass(frozen=True)
class FusionParams:
    """`imufusion.Ahrs` settings (the defaults of `imufusion.AhrsSettings()` in 1.3.3), each
    documented at its field after Fusion's README (`fusion list fusion-ahrs`)."""

    # Ranges and grids from Fusion's README (x-io Technologies), which calls a gain of 0.5 and
    # thresholds of 10 deg "appropriate for most applications" and a recovery trigger period of 5 s:
    # gain from nearly the gyro alone (0.01) to 10 (the start-up ramp's initial gain), log scale;
    # thresholds 0 (off, the library's default) to 90 deg, linear; the trigger period 0 (the
    # library's default: no rejection) to 50 s at 100 Hz, linear. Grid: 4 gains x rejections off
    # or 10 deg x one trigger period, 5 s at 100 Hz (1.75 s at BROAD's 286 Hz; with both thresholds
    # 0 the period changes nothing, so the grid's settings include the library's defaults): 16
    # settings in 9-D, 8 in 6-D.
    gain: float = param(
        0.5, unit="1", valid=">= 0", reference=_FUSION, search=Tunable(0.01, 10.0, log=True, grid=(0.1, 0.25, 0.5, 1.0)),
        meaning="The complementary filter's gain, which weighs the accelerometer and magnetometer against the gyro.")
    gyroscope_range_deg_s: float = param(
        0.0, alias="gyroscope_range", unit="deg/s", valid=">= 0; 0: off", reference=_FUSION,
        meaning="The gyro's range: a reading beyond 98 % of it starts the angular-rate recovery (over-range "
                "detection).")
    acceleration_rejection_deg: float = param(
        0.0, alias="acceleration_rejection", unit="deg", valid=">= 0; 0: off", reference=_FUSION,
        search=Tunable(0.0, 90.0, log=False, grid=(0.0, 10.0)),
        meaning="The angle between the estimate's inclination and the accelerometer's above which the "
                "accelerometer is ignored for the update.")
    magnetic_rejection_deg: float = param(
        0.0, alias="magnetic_rejection", unit="deg", valid=">= 0; 0: off", reference=_FUSION,
        search=Tunable(0.0, 90.0, log=False, grid=(0.0, 10.0), magnetometer=True),
        meaning="The angle between the estimate's heading and the magnetometer's above which the magnetometer is "
                "ignored for the update (9-D only).")
    rejection_timeout: int = param(
        0, unit="samples", valid="a whole number >= 0; 0 turns both rejections off, whatever the thresholds",
        reference=_FUSION, search=Tunable(0, 5000, log=False, integer=True, grid=(500,)),
        meaning="Fusion's recovery trigger period: how long a sensor may be rejected before it is trusted again.")
    startup: bool = param(
        False, unit="", valid="true | false",
        meaning="Run Fusion's start-up phase (3 s with the gyro ignored and a gain ramp), meant for an unknown "
                "initial orientation; off because the adapter seeds the estimate.")

    def __post_init__(self) -> None:
        _non_negative("fusion-ahrs", gain=self.gain, gyroscope_range_deg_s=self.gyroscope_range_deg_s,
                      acceleration_rejection_deg=self.acceleration_rejection_deg,
                      magnetic_rejection_deg=self.magnetic_rejection_deg, rejection_timeout=self.rejection_timeout)


# Fusion's flags (`Ahrs.get_flags()`) and the flags among its internal states
# (`Ahrs.get_internal_states()`) after each update, under our diagnostics' names: per-sample flags,
# (N,) bool (`Trajectory`). Library name -> (our name, 9-D only). x-io's README, "AHRS flags" and
# "AHRS internal states": the accelerometer (magnetometer) is ignored while its error exceeds the
# rejection threshold; a recovery runs when it has been ignored for the trigger period (the
# `rejection_timeout`) and the sensor is then trusted again; an over-range recovery follows a gyro
# sample beyond `gyroscope_range`; start-up is the 3 s gain ramp (off unless `startup=true`).
FUSION_FLAGS = {"accelerometer_ignored": ("accelerometer_ignored", False),
                "acceleration_recovery": ("acceleration_recovery", False),
                "overrange_recovery": ("overrange_recovery", False), "startup": ("startup", False),
                "magnetometer_ignored": ("magnetometer_ignored", True),
                "magnetic_recovery": ("magnetic_recovery", True)}
_FUSION_STATES = {"accelerometer_ignored", "magnetometer_ignored"}  # read from `get_internal_states()`


class FusionPeer(RecursiveEstimator):
    """x-io Fusion's AHRS (`imufusion.Ahrs.update_no_magnetometer`, 6-D, NWU; `update`, 9-D, ENU).

    Inputs in deg/s and g; the sample period is set before every update (real dt).
    Seeded with `set_quaternion`; its start-up phase is skipped unless `startup=true`
    (during it, the gyro is ignored: from a seed, that only loses the first 3 s of
    rotation). Fusion computes in single precision. Invalid gyro samples: zero rate.
    """

    Params = FusionParams
    magnetometer = True

    def __init__(self, params: Any = None) -> None:
        super().__init__(params)
        self._fusion = _require("imufusion", "imufusion", "fusion-ahrs")

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        """The library's update at every step, as `step` makes it (6-D, NWU; 9-D: `Ahrs.update`, the
        magnetometer in uT, normalised inside, ENU), with the inputs converted once for the whole
        recording, and Fusion's flags and states after each update as per-sample flags
        (`FUSION_FLAGS`; row 0, the seed: False)."""
        mag = imu.has_mag
        self.reset_for(imu, init_quat_wxyz, convention="ENU" if mag else "NWU")
        ahrs = self._ahrs
        n = len(imu)
        (rates, valid), dt = imu.interval_rates(), imu.dt
        rate_deg_s = np.degrees(np.where(valid[:, None], rates, 0.0))  # Fusion wants deg/s; invalid: zero rate
        acc_g = _acc_m_s2(imu.acc_g) / STANDARD_GRAVITY_M_S2
        mag_ut, mag_ok = (imu.mag_ut, imu.mag_valid) if mag else (None, np.zeros(n, dtype=bool))
        out = np.empty((n, 4))
        out[0] = np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz) if mag else init_quat_wxyz
        read = [(key, key in _FUSION_STATES) for key, (_, magnetic) in FUSION_FLAGS.items() if mag or not magnetic]
        names = [FUSION_FLAGS[key][0] for key, _ in read]
        rows = []
        for k in range(n - 1):
            ahrs.set_sample_period(dt[k])
            if mag_ok[k + 1]:
                ahrs.update(rate_deg_s[k], acc_g[k + 1], mag_ut[k + 1])
            else:
                ahrs.update_no_magnetometer(rate_deg_s[k], acc_g[k + 1])
            out[k + 1] = ahrs.get_quaternion()
            f, st = ahrs.get_flags(), ahrs.get_internal_states()
            rows.append(tuple(getattr(st if state else f, key) for key, state in read))
        flags = np.zeros((n, len(names)), dtype=bool)
        if rows:
            flags[1:] = rows
        return Trajectory(imu.t, out, diagnostics={name: flags[:, j].copy() for j, name in enumerate(names)})

    def reset_for(self, imu: ImuSamples, init_quat_wxyz: np.ndarray, convention: str = "NWU") -> None:
        rate_hz = float((len(imu) - 1) / (imu.t[-1] - imu.t[0])) if len(imu) > 1 else None
        self.reset(init_quat_wxyz, sample_rate_hz=rate_hz, convention=convention)

    def reset(self, init_quat_wxyz: np.ndarray, sample_rate_hz: float | None = None, convention: str = "NWU") -> None:
        """sample_rate_hz: the nominal rate Fusion's settings take (None: the library's default);
        convention: "NWU" (6-D: any z-up world) or "ENU" (9-D: the magnetometer's north along y)."""
        f, p = self._fusion, self.params
        ahrs = f.Ahrs()
        settings = f.AhrsSettings()
        # Attributes, not keywords: AhrsSettings(convention=...) is ignored in imufusion 1.3.3.
        settings.convention = getattr(f, f"CONVENTION_{convention}")
        settings.gain = p.gain
        settings.gyroscope_range = p.gyroscope_range_deg_s
        settings.acceleration_rejection = p.acceleration_rejection_deg
        settings.magnetic_rejection = p.magnetic_rejection_deg
        settings.rejection_timeout = p.rejection_timeout
        if sample_rate_hz is not None:
            settings.sample_rate = sample_rate_hz
        ahrs.set_settings(settings)
        ahrs.set_quaternion(np.asarray(init_quat_wxyz, dtype=float) / np.linalg.norm(init_quat_wxyz))
        if not p.startup:
            ahrs.skip_startup()
        self._ahrs = ahrs

    def step(self, gyr_rad_s: np.ndarray, dt_s: float, acc_g: np.ndarray, gyr_valid: bool) -> np.ndarray:
        self._ahrs.set_sample_period(dt_s)
        rate_deg_s = np.degrees(gyr_rad_s) if gyr_valid else np.zeros(3)  # Fusion wants deg/s
        self._ahrs.update_no_magnetometer(rate_deg_s, _acc_m_s2(acc_g) / STANDARD_GRAVITY_M_S2)
        return self._ahrs.get_quaternion()

