"""The compiled filters (`ekf`, `ukf`, `ukf-bias`, numba): what a kernel run takes and gives, and
where each kernel is.

What was chosen and why. A recursive filter cannot be vectorised over time: every sample
needs the state of the one before. Its numpy step works on 3x3 to 11x11 matrices, where each
numpy call costs about a microsecond of overhead and the arithmetic a few nanoseconds. Here one
`numba.njit` function per filter runs the *whole* loop of `RecursiveEstimator.estimate` over a
recording, in explicit loops over those small matrices, and writes the same per-sample
diagnostics. Numba rather than a C extension or Cython: no compiler at install time, the kernels
stay Python source next to the reference, and the machine code is cached on disk, so the compile
time is paid once per installation, not per run. A compiled filter loads the kernels when it is
built (`load`), so that its `estimate` is timed as the filter alone; numba is not imported until
then (`impl=numpy`/`lean`/`filterpy` never import it). Timings: `benchmarks/bench_filters.py`,
`docs/results.md`.

The numpy steps are the reference: `EKF.step`, `UKF.step` and the helpers of `_linalg`, `_accel`,
`_rest`, `_stuck`, `_scale_test` and `_magnetometer` define the filters (readable, and what a
streaming user and the tutorial call). Each has a compiled mirror that carries its name:

    numpy reference                        kernel
    fusion.quaternion (scalar path)        _compiled_quaternion
    _linalg                                _compiled_linalg
    _accel (AccDisturbance, LowpassLag)    _compiled_accel (update, turn, step, ...)
    _rest (RestDetector)                   _compiled_rest (update, bias_rest_update)
    _stuck                                 _compiled_stuck (stuck_gyro_update itself, compiled)
    _scale_test (ScaleTest)                _compiled_scale_test (step)
    _magnetometer                          _compiled_magnetometer (update, magnetometer_input, ...)
    ekf.EKF (KalmanFilter.step with EKF's parts)   _compiled_ekf (estimate, _correct, _velocity_step)
    ukf.UKF, quaternion_ukf (the same, UKF's)      _compiled_ukf (estimate)

Each loop is the sequence of `KalmanFilter.step`, section by section (predict, before updates,
rest, accelerometer, magnetometer, scale test, finish), with its filter's parts written in place:
one loop per filter, not one loop calling each filter's parts, which ran at half the speed (the
work arrays of a loop allocated in it are what numba's compiler optimises best).

Every kernel line implements a line of its reference, in the same order where the order matters
for rounding, and `tests/test_compiled.py` checks that both paths give the same quaternions and
diagnostics to 1e-10 on real and simulated recordings with every option, and that every
kernel's declared reference (`_numba.REFERENCES`) exists under the kernel's name. The packed
states that the kernels carry are laid out once, by the offsets of the numpy modules
(`_accel.DIST_*`, `_rest.REST_*`, `_magnetometer.MAG_*` and `HARD_IRON_*`, `_scale_test.TEST_*`,
`_stuck.STUCK_*`), which both sides import.

A kernel run takes the recording (`_numba.Inputs`), the filter's state, the packed states
(`SensorStates`) and its options (`Settings`, all scalars and small tuples, built by keyword from
the filter's parameters and the constants of the reference modules at run time, not frozen into
the cached machine code), and fills one `Outputs`.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from fusion.types import STANDARD_GRAVITY_M_S2

from ..kernels._compiled_linalg import CovSettings, cov_settings
from ..kernels._compiled_quaternion import QuatSettings, multiply_floats, quat_settings
from ..kernels._numba import _jit, inputs
from . import _compiled_ekf, _compiled_ukf
from .filter_params import BiasFilterParams
from .steps._accel import AccDisturbance, models_lag
from .steps._compiled_accel import AccSettings, acc_settings
from .steps._compiled_magnetometer import MagSettings, mag_settings
from .steps._compiled_rest import RestSettings, rest_settings, rest_steps
from .steps._compiled_scale_test import ScaleTestSettings, scale_test_settings
from .steps._compiled_stuck import stuck_intervals
from .steps._error_state import ErrorLayout
from .steps._magnetometer import HARD_IRON_STATE, MAG_STATE
from .steps._rest import RestDetector
from .steps._scale_test import TEST_STATE
from .steps._stuck import STUCK_THRESHOLDS, stuck_gyro_state

# `fusion.quaternion.multiply_floats` compiled, under the name the peers' and the smoothers' kernels import.
qmul = multiply_floats

__all__ = ["Outputs", "SensorStates", "Settings", "UnscentedSettings", "inputs", "load", "outputs", "rest_steps",
           "settings", "stuck_intervals", "_jit", "qmul"]


class Settings(NamedTuple):
    """A kernel run's options, one object (one compiled signature serves every parameter set)."""

    unscented: bool  # the UKFs' step (sigma points), else ekf's (Jacobians)
    n: int  # error-state dimension without the velocity: 3, 6 or 9
    nv: int  # ekf: velocity states, 0 or 2
    bias: bool  # the bias block (`ErrorLayout.bias`)
    scale: bool  # the scale block (`ErrorLayout.scale`)
    vel_bound: float  # ekf: Rv, m^2/s
    gravity: float  # 1 g in m/s^2
    use_acc: bool  # the accelerometer update is on
    process_noise: float  # Q, rad^2/s
    heading_free: bool  # no correction about the vertical
    rest_on: bool  # the rest update is on (a bias filter with a rest detector)
    rest_noise: float  # its variance density, rad^2/s
    bias_max: float  # clipping of the bias, rad/s
    scale_max: float  # clipping of the scale
    chi2: float  # ekf: NIS above which bias and scale are not corrected (inf: never)
    lowpass_calibration: bool  # ekf: the low-passed sample corrects bias and scale
    slow_corr: float  # ekf: the slow disturbance's correlation time, s (0: none; `_accel.AccDisturbance.slow_power`)
    slow_scale_var: float  # ekf: ... and its unmodelled rate error's variance (init_scale_var; 0 without scale)
    scale_noise: float  # ukf: Qs, s
    sqrt_c: float  # ukf: the sigma points' scale sqrt(c)
    mean_tol: float  # ukf: the iterative mean's stopping rule, rad
    mean_max_iter: int  # ... and its iteration cap
    quat: QuatSettings  # fusion.quaternion's small-angle rules
    cov: CovSettings  # _linalg's covariance recovery
    acc: AccSettings  # the accelerometer: gate, noise, disturbance model, low-pass
    rest: RestSettings  # the rest detector's thresholds
    mag: MagSettings  # the magnetometer (9-D)
    test: ScaleTestSettings  # the scale test


class UnscentedSettings(NamedTuple):
    """The UKFs' own options (`settings`); `ekf` has none."""

    scale_noise: float = 0.0  # ukf: Qs, s
    sqrt_c: float = 0.0  # the sigma points' scale sqrt(c)
    mean_tol: float = 0.0  # the iterative mean's stopping rule, rad
    mean_max_iter: int = 0  # ... and its iteration cap


def settings(p: Any, layout: Any, rest: Any = None, scale_test: Any = None, chi2: float = math.inf,
             unscented: UnscentedSettings | None = None) -> Settings:
    """The kernel options of a filter's parameters `p` (a `FilterParams`), its error state's
    `ErrorLayout`, rest detector `rest` (the `RestDetector` its reset built, or None), scale test
    (its `ScaleTest`, or None), `ekf`'s chi-square guard `chi2` and the UKFs' `UnscentedSettings`
    (None: `ekf`)."""
    bias = isinstance(p, BiasFilterParams) and layout.bias
    rest_on = bias and rest is not None
    nv = int(layout.velocity_states)
    ut = unscented if unscented is not None else UnscentedSettings()
    return Settings(
        unscented=unscented is not None, n=int(layout.n), nv=nv, bias=bool(layout.bias), scale=bool(layout.scale),
        vel_bound=float(p.velocity_bound_m2_s) if nv else 0.0, gravity=float(STANDARD_GRAVITY_M_S2),
        use_acc=bool(p.use_acc), process_noise=float(p.process_noise_rad2_s),
        heading_free=bool(p.heading_free), rest_on=bool(rest_on),
        rest_noise=float(p.rest_noise_rad2_s) if bias else 0.0,
        bias_max=float(p.bias_max_rad_s) if bias else math.inf, scale_max=float(p.scale_max) if bias else math.inf,
        chi2=float(chi2), lowpass_calibration=bool(nv == 0 or getattr(p, "lowpass_calibration", True)),
        slow_corr=float(getattr(p, "slow_disturbance_corr_s", 0.0)) if models_lag(p, layout.bias) else 0.0,
        slow_scale_var=float(p.init_scale_var) if bias and layout.scale else 0.0,
        scale_noise=float(ut.scale_noise), sqrt_c=float(ut.sqrt_c), mean_tol=float(ut.mean_tol),
        mean_max_iter=int(ut.mean_max_iter), quat=quat_settings(), cov=cov_settings(),
        acc=acc_settings(p, layout.bias), rest=rest_settings(rest if rest_on else None), mag=mag_settings(p),
        test=scale_test_settings(scale_test))


class SensorStates(NamedTuple):
    """The packed states a kernel advances in place (each laid out by its numpy module's offsets)."""

    dist: np.ndarray  # `AccDisturbance.state()`
    rest: np.ndarray  # `RestDetector.state()` (zeros without a detector)
    mag: np.ndarray  # `MagReference.state()` (zeros without a magnetometer)
    hard_iron: np.ndarray  # `HardIron.state()`
    test: np.ndarray  # `ScaleTest.state()`


class Outputs(NamedTuple):
    """The per-sample arrays a kernel fills from row 1 on (N samples, n the covariance's size); the
    names are the diagnostics' keys."""

    quat: np.ndarray  # (N, 4)
    cov: np.ndarray  # (N, n, n)
    gyr_bias_rad_s: np.ndarray  # (N, 3)
    gyr_scale: np.ndarray  # (N, 3)
    velocity_m_s: np.ndarray  # (N, 2)
    mean_iterations: np.ndarray  # (N,) int64
    acc_var_g2: np.ndarray  # (N,)
    at_rest: np.ndarray  # (N,) bool
    nis: np.ndarray  # (N,)
    bias_guarded: np.ndarray  # (N,) bool
    acc_lowpassed: np.ndarray  # (N,) bool
    mag_used: np.ndarray  # (N,) bool
    mag_hard_iron: np.ndarray  # (N,) bool
    scale_llr: np.ndarray  # (N,)


def outputs(n_samples: int, n: int, init_quat_wxyz: np.ndarray, current: dict[str, Any]) -> Outputs:
    """The `Outputs` of a run over `n_samples`. Row 0 is what `RecursiveEstimator.estimate` records
    after the reset: the initial quaternion as given and the filter's `current()`."""
    out = Outputs(
        quat=np.zeros((n_samples, 4)), cov=np.zeros((n_samples, n, n)), gyr_bias_rad_s=np.zeros((n_samples, 3)),
        gyr_scale=np.zeros((n_samples, 3)), velocity_m_s=np.zeros((n_samples, 2)),
        mean_iterations=np.zeros(n_samples, dtype=np.int64), acc_var_g2=np.zeros(n_samples),
        at_rest=np.zeros(n_samples, dtype=bool), nis=np.zeros(n_samples), bias_guarded=np.zeros(n_samples, dtype=bool),
        acc_lowpassed=np.zeros(n_samples, dtype=bool), mag_used=np.zeros(n_samples, dtype=bool),
        mag_hard_iron=np.zeros(n_samples, dtype=bool), scale_llr=np.zeros(n_samples))
    out.quat[0] = init_quat_wxyz
    for key, value in current.items():
        getattr(out, key)[0] = value
    return out


_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache: run each once on a one-step
    recording. The first call in a process costs the compilation (seconds, once per
    installation and numba version) or the cache load (about half a second); the filters call
    this when they are built, so that `estimate` is timed as the filter alone."""
    global _loaded
    if _loaded:
        return
    n = 9
    p = BiasFilterParams()
    layout = ErrorLayout.of(n)
    inp = inputs(_OneStep())
    unit = np.array([1.0, 0.0, 0.0, 0.0])

    def states() -> SensorStates:
        return SensorStates(
            dist=AccDisturbance(p.disturbance_window_s, p.acc_lowpass_s, p.acc_lowpass_window_s, lag=True).state(),
            rest=RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s, tilt_rad=p.rest_tilt_rad).state(), mag=np.zeros(MAG_STATE),
            hard_iron=np.zeros(HARD_IRON_STATE), test=np.zeros(TEST_STATE))

    out = outputs(2, n, unit, {})
    o = settings(p, layout)
    _compiled_ekf.estimate(inp, unit.copy(), np.zeros(3), np.zeros(3), np.zeros(2), np.eye(n) * 1e-4,
                           np.eye(n) * 1e-4, np.zeros((n, n)), states(), o, out)
    weights = np.full(2 * n + 1, 0.5 / n)
    weights[0] = 0.0
    o = settings(p, layout, unscented=UnscentedSettings(sqrt_c=math.sqrt(n), mean_tol=1e-9, mean_max_iter=20))
    _compiled_ukf.estimate(inp, np.concatenate([unit, np.zeros(n - 3)]), np.eye(n) * 1e-4, np.eye(n) * 1e-4,
                           np.zeros((n, n)), weights, weights, states(), o, out)
    stuck_intervals(inp.gyr, inp.dt, inp.acc[1:], inp.valid, stuck_gyro_state(), *STUCK_THRESHOLDS)
    _loaded = True


class _OneStep:
    """A one-step recording at rest, without a magnetometer, for `load`."""

    dt = np.full(1, 0.01)
    acc_g = np.tile([0.0, 0.0, 1.0], (2, 1))
    has_mag = False

    def interval_rates(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((1, 3)), np.ones(1, dtype=bool)
