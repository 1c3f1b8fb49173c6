"""Compiled per-sample loops of `ekf`, `ukf` and `ukf-bias` (numba).

What was chosen and why. A recursive filter cannot be vectorised over time: every sample
needs the state of the one before. Its numpy step works on 3x3 to 9x9 matrices, where each
numpy call costs about a microsecond of overhead and the arithmetic a few nanoseconds, so the
step ran at 40-280 us per sample. Here one `numba.njit` function per filter runs the *whole*
loop of `RecursiveEstimator.estimate` over a recording, in explicit loops over those small
matrices, and writes the same per-sample diagnostics arrays and counts. Numba rather than a C
extension or Cython: no compiler at install time, the kernels stay Python source next to the
reference, and the machine code is cached on disk (`cache=True`), so the compile time
(seconds) is paid once per installation, not per run. A compiled filter loads the kernels
when it is built (`load`; about half a second in a new process), so that its `estimate` is
timed as the filter alone; numba is not imported until then (`impl=numpy`/`lean`/`filterpy`
never import it).

The numpy steps are the reference. `EKF.step`, `UKF.step` and the helpers of `_attitude` are
the definition of the filters (readable, and what a streaming user and the tutorial call);
every line here implements a line there, in the same order where the order matters for
rounding, and `tests/test_compiled.py` checks that both paths give the same quaternions and
diagnostics to 1e-10 on real and simulated recordings with every option. The equations and
their papers are cited in `ekf`, `ukf` and `_attitude`; the kernels cite the step of the
reference they implement. Where the compiled path is organised differently it says so: the
EKF's covariance prediction uses the block structure of F (`predict_covariance`: the reference
multiplies the full matrices; zero blocks contribute exact zeros, identity blocks copies), the
accelerometer's P H^T only H's non-zero columns; the Joseph form is expanded for a symmetric P
as `P - K (P H^T)^T + (K S - P H^T) K^T` (`joseph`, `heading_update`); the covariances are
computed on their upper triangle and mirrored (the reference symmetrises P at the end of each
step); the UKF's sigma points take the attitude exponential only where the Cholesky factor has
an attitude part (step 3). These change the rounding only (1e-14 relative on the recordings).

Constants that decide the maths (the small-angle limits of `fusion.quaternion`, the covariance
floors of `_attitude`, the chi-square bound of `ekf`) are passed in at run time from the
reference modules (`settings`), not frozen into the cached machine code: numba keys its cache on
this file alone and would not see a change elsewhere. The quaternion helpers are
`fusion.quaternion`'s own scalar functions, compiled here; `_kernel_cache.forget_stale_kernels`
drops this module's cache when `fusion/quaternion.py` changes.

Cache location: next to this file (`__pycache__`); if that folder is not writable, numba's
user-wide cache folder; `NUMBA_CACHE_DIR` overrides both. If no folder is writable the kernels
are compiled in every process (a warning says so) and still run.
"""
from __future__ import annotations

import math
import warnings
from collections import namedtuple
from typing import Any

import numba
import numpy as np

from fusion import quaternion as quat
from fusion.types import STANDARD_GRAVITY_M_S2

from ._accel import AccDisturbance, models_lag
from ._linalg import COV_FLOOR, COV_RESET_VAR, SQRT_FLOOR
from ._magnetometer import HARD_IRON_STATE
from ._rest import REST_WINDOW_S, RestDetector
from . import _stuck
from ._kernel_cache import forget_stale_kernels
from .filter_params import BiasFilterParams

forget_stale_kernels(__file__, [quat.__file__, _stuck.__file__])  # the kernels compile functions of both

_GATES = {"off": 0, "skip": 1, "inflate": 2}
_OPTIONS = dict(error_model="numpy", nogil=True)
_cache = True  # False once numba has found no writable cache folder


def _jit(func):
    """`numba.njit` with the on-disk cache, IEEE division (`error_model="numpy"`: x / 0 is inf
    or nan as in numpy, never an exception) and the GIL released. Without a writable cache
    folder (numba raises at decoration), one warning and no cache."""
    global _cache
    if _cache:
        try:
            return numba.njit(cache=True, **_OPTIONS)(func)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            _cache = False
            warnings.warn(f"fusion.estimators: the compiled filters cannot be cached ({exc}); they are "
                          "compiled in every process. Set NUMBA_CACHE_DIR to a writable folder to cache them.",
                          RuntimeWarning, stacklevel=2)
    return numba.njit(**_OPTIONS)(func)


# Options of a kernel run, all scalars (one compiled signature serves every parameter set).
Settings = namedtuple("Settings", [
    "n",  # error-state dimension without the velocity: 3, 6 or 9
    "nv", "vel_bound", "gravity",  # ekf: velocity states (0 or 2), Rv (m^2/s), 1 g in m/s^2
    "use_acc", "gate", "gate_g",  # accelerometer update on, gate (0 off, 1 skip, 2 inflate), gate_g (g)
    "acc_noise", "corr_s", "dist_window",  # R (g^2 s), disturbance correlation time and window (s)
    "lowpass_s", "lowpass_window", "process_noise",  # accelerometer low-pass (s), its variance window (s), Q (rad^2/s)
    "lag",  # the low-pass's lag is modelled (`_attitude.models_lag`)
    "heading_free",
    "rest_on", "rest_gyr", "rest_acc", "rest_time", "rest_window", "rest_noise",  # rest detection + update
    "bias_max", "scale_max",  # clipping of bias (rad/s) and scale
    "chi2",  # ekf: NIS above which bias and scale are not corrected (inf: never)
    "lowpass_calibration",  # ekf: the low-passed sample corrects bias and scale (always without velocity states)
    "scale_test_axes", "scale_test_r", "scale_test_const", "scale_test_bound",  # `_attitude.ScaleTest` (axes bits; 0: off)
    "scale_noise",  # ukf: Qs, s
    "sqrt_c", "mean_tol", "mean_max_iter",  # ukf: sigma-point scale sqrt(c), iterative-mean stopping rule
    "small_angle", "series_rad", "jac_a", "jac_b",  # fusion.quaternion's small-angle rules
    "cov_floor", "cov_reset", "sqrt_floor",  # _attitude's covariance repair
    "mag_noise", "mag_norm_gate", "mag_dip_gate", "mag_min_time", "mag_ref_s",  # ekf: the magnetometer (9-D)
    "mag_rate", "mag_hard_iron", "mag_hi_window", "mag_hi_residual", "mag_hi_coverage",  # ... rate term, hard iron
])


def settings(p: Any, n: int, rest: Any = None, chi2: float = math.inf, scale_noise: float = 0.0,
             sqrt_c: float = 0.0, mean_tol: float = 0.0, mean_max_iter: int = 0, scale_test: Any = None) -> Settings:
    """The kernel options of a filter's parameters `p` (a `FilterParams`), error dimension `n`,
    rest detector `rest` (the `_attitude.RestDetector` its reset built, or None) and scale test
    (its `_attitude.ScaleTest`, or None)."""
    test = scale_test is not None and scale_test.on
    bias = isinstance(p, BiasFilterParams) and n > 3
    rest_on = bias and rest is not None
    nv = int(getattr(p, "velocity_states", 0))
    return Settings(
        int(n), nv, float(p.velocity_bound_m2_s) if nv else 0.0, float(STANDARD_GRAVITY_M_S2), bool(p.use_acc), _GATES[p.gate], float(p.gate_g),
        float(p.acc_noise_g2_s), float(p.disturbance_corr_s), float(p.disturbance_window_s),
        float(p.acc_lowpass_s), float(p.acc_lowpass_window_s), float(p.process_noise_rad2_s),
        bool(models_lag(p, n)), bool(p.heading_free),
        bool(rest_on), float(rest.gyr_th) if rest_on else 0.0, float(rest.acc_th) if rest_on else 0.0,
        float(rest.min_time) if rest_on else math.inf, float(rest.window_s) if rest_on else 1.0,
        float(p.rest_noise_rad2_s) if bias else 0.0,
        float(p.bias_max_rad_s) if bias else math.inf, float(p.scale_max) if bias else math.inf,
        float(chi2), bool(nv == 0 or getattr(p, "lowpass_calibration", True)),
        int(sum(1 << int(a) for a in scale_test.axes)) if test else 0, float(scale_test.r) if test else math.inf,
        float(scale_test.const) if test else 0.0, float(scale_test.bound) if test else math.inf,
        float(scale_noise), float(sqrt_c), float(mean_tol), int(mean_max_iter),
        float(quat.SMALL_ANGLE), float(quat.JACOBIAN_SERIES_RAD),
        tuple(float(c) for c in quat._A[1]), tuple(float(c) for c in quat._B[1]),
        float(COV_FLOOR), float(COV_RESET_VAR), float(SQRT_FLOOR),
        float(getattr(p, "mag_heading_noise_rad2_s", 0.0)), float(getattr(p, "mag_norm_gate_frac", 0.0)),
        float(getattr(p, "mag_dip_gate_rad", 0.0)), float(getattr(p, "mag_min_undisturbed_s", 0.0)),
        float(getattr(p, "mag_ref_s", 1.0)), float(getattr(p, "mag_rate_rad_s", math.inf)),
        bool(getattr(p, "mag_hard_iron", False)), float(getattr(p, "mag_hard_iron_window_s", 1.0)),
        float(getattr(p, "mag_hard_iron_residual_ut", 0.0)), float(getattr(p, "mag_hard_iron_coverage", 0.0)),
    )


def inputs(imu: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`(gyr (N-1, 3), valid (N-1,), dt (N-1,), acc (N, 3))` as the base class's loop reads them
    (`ImuSamples.interval_rates`), as writable C arrays (one compiled signature for all)."""
    gyr, valid = imu.interval_rates()
    return (np.ascontiguousarray(gyr, dtype=float), np.ascontiguousarray(valid, dtype=bool),
            np.ascontiguousarray(imu.dt, dtype=float), np.array(imu.acc_g, dtype=float, order="C"))


def mag_inputs(imu: Any, use: bool) -> tuple[np.ndarray, np.ndarray]:
    """`(mag (N, 3) uT, valid (N,))` for the EKF kernel when `use` (a 9-D filter on a recording with a
    magnetometer), else empty arrays (0, 3), (0,): the 6-D filter."""
    if not (use and imu.has_mag):
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    return np.array(imu.mag_ut, dtype=float, order="C"), np.array(imu.mag_valid, dtype=bool)


def outputs(n_samples: int, n: int, init_quat_wxyz: np.ndarray, current: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per-sample arrays the kernels fill from row 1 on. Row 0 is what `RecursiveEstimator.estimate`
    records after the reset: the initial quaternion as given and the filter's `current()`."""
    out = {
        "quat": np.zeros((n_samples, 4)),
        "cov": np.zeros((n_samples, n, n)),
        "gyr_bias_rad_s": np.zeros((n_samples, 3)),
        "gyr_scale": np.zeros((n_samples, 3)),
        "velocity_m_s": np.zeros((n_samples, 2)),
        "mean_iterations": np.zeros(n_samples, dtype=np.int64),
        "acc_var_g2": np.zeros(n_samples),
        "at_rest": np.zeros(n_samples, dtype=bool),
        "nis": np.zeros(n_samples),
        "bias_guarded": np.zeros(n_samples, dtype=bool),
        "acc_lowpassed": np.zeros(n_samples, dtype=bool),
        "mag_used": np.zeros(n_samples, dtype=bool),
        "mag_hard_iron": np.zeros(n_samples, dtype=bool),
        "scale_llr": np.zeros(n_samples),
    }
    out["quat"][0] = init_quat_wxyz
    for key, value in current.items():
        out[key][0] = value
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
    o = settings(p, n, sqrt_c=math.sqrt(n), mean_tol=1e-9, mean_max_iter=20)
    inputs_ = (np.zeros((1, 3)), np.ones(1, dtype=bool), np.full(1, 0.01), np.tile([0.0, 0.0, 1.0], (2, 1)))
    unit = np.array([1.0, 0.0, 0.0, 0.0])
    dist = AccDisturbance(p.disturbance_window_s, p.acc_lowpass_s, p.acc_lowpass_window_s, lag=True).state()
    rest = RestDetector(p.rest_gyr_rad_s, p.rest_acc_g, p.rest_time_s).state()
    state = (np.eye(n) * 1e-4, np.eye(n) * 1e-4, np.zeros((n, n)), dist, rest)
    out = outputs(2, n, unit, {})
    P, Qrate, Qbad, dist, rest = (a.copy() for a in state)
    ekf_kernel(*inputs_, np.zeros((0, 3)), np.zeros(0, dtype=bool), unit.copy(), np.zeros(3), np.zeros(3),
               np.zeros(2), P, Qrate, Qbad, dist, rest, np.zeros(5), np.zeros(HARD_IRON_STATE), np.zeros(3), o,
               out["quat"], out["cov"], out["gyr_bias_rad_s"], out["gyr_scale"], out["velocity_m_s"], out["acc_var_g2"],
               out["at_rest"], out["nis"], out["bias_guarded"], out["acc_lowpassed"], out["mag_used"],
               out["mag_hard_iron"], out["scale_llr"])
    weights = np.full(2 * n + 1, 0.5 / n)
    weights[0] = 0.0
    P, Qrate, Qbad, dist, rest = (a.copy() for a in state)
    ukf_kernel(*inputs_, np.zeros((0, 3)), np.zeros(0, dtype=bool), np.concatenate([unit, np.zeros(n - 3)]), P, Qrate,
               Qbad, weights, weights, dist, rest, np.zeros(5), np.zeros(HARD_IRON_STATE), np.zeros(3), o,
               out["quat"], out["cov"], out["gyr_bias_rad_s"], out["gyr_scale"], out["mean_iterations"],
               out["acc_var_g2"], out["at_rest"], out["nis"], out["acc_lowpassed"], out["mag_used"],
               out["mag_hard_iron"], out["scale_llr"])
    gyr, valid, dt, acc = inputs_
    stuck_intervals(gyr, dt, acc[1:], valid, _stuck.stuck_gyro_state(), *_stuck.STUCK_THRESHOLDS)
    _loaded = True


# ============================================================================ quaternions
# `fusion.quaternion`'s scalar path, compiled: one definition for numpy, Python and the kernels
# (`_kernel_cache.forget_stale_kernels` drops this module's cache when that module changes).
qmul = _jit(quat.multiply_floats)
qexp = _jit(quat.exp_floats)  # (vx, vy, vz, small): small is `quaternion.SMALL_ANGLE`
qlog = _jit(quat.log_floats)
qnormalize = _jit(quat.normalize_floats)
gravity = _jit(quat.gravity_floats)  # R(q)^T e_z
_rotation = _jit(quat.rotation_floats)


# The online stuck-gyro check of the filters (`_attitude`), compiled over a whole recording.
_stuck_update = _jit(_stuck.stuck_gyro_update)


@_jit
def stuck_intervals(gyr, dt, acc_end, valid, state, window_s, steps, acc_p2p_g):
    """(N - 1,) bool: `_attitude.stuck_gyro_update` over every step (gyro reading, interval,
    accelerometer sample at its end, validity), advancing `state` in place."""
    out = np.zeros(len(dt), dtype=np.bool_)
    for k in range(len(dt)):
        out[k] = _stuck_update(state, gyr[k], acc_end[k], dt[k], valid[k], window_s, steps, acc_p2p_g)
    return out


@_jit
def rotate(q, vx, vy, vz):
    """R(q) v (`quaternion.rotate_floats`)."""
    r = _rotation(q)
    return (r[0] * vx + r[1] * vy + r[2] * vz, r[3] * vx + r[4] * vy + r[5] * vz, r[6] * vx + r[7] * vy + r[8] * vz)


@_jit
def right_jacobian_dt(tx, ty, tz, dt, o, out):
    """out = J_r(t) dt, the SO(3) right Jacobian (`quaternion.right_jacobian_floats`) times dt."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    if t > o.series_rad:
        a = (1.0 - math.cos(t)) / (t * t)
        b = (t - math.sin(t)) / (t * t * t)
    else:
        t2 = t * t
        a = 0.0
        b = 0.0
        for i in range(2, -1, -1):
            a = a * t2 + o.jac_a[i]
            b = b * t2 + o.jac_b[i]
    S = ((0.0, -tz, ty), (tz, 0.0, -tx), (-ty, tx, 0.0))
    for i in range(3):
        for j in range(3):
            ss = S[i][0] * S[0][j] + S[i][1] * S[1][j] + S[i][2] * S[2][j]
            out[i, j] = ((1.0 if i == j else 0.0) - a * S[i][j] + b * ss) * dt


# ============================================================================ small matrices
@_jit
def inv_sym3(S, out):
    """Inverse of a symmetric 3x3 matrix by its adjugate, from its upper triangle (`_attitude.inv_sym3`);
    -> its determinant."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    out[0, 0], out[0, 1], out[0, 2] = A / det, B / det, C / det
    out[1, 0], out[1, 1], out[1, 2] = B / det, D / det, E / det
    out[2, 0], out[2, 1], out[2, 2] = C / det, E / det, F / det
    return det


@_jit
def cholesky(A, L, n):
    """Lower Cholesky factor of A (n x n, lower triangle read) into L, upper part zeroed; False
    (instead of an exception) if A is not positive definite, as LAPACK's dpotrf reports it."""
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:  # also false for nan
            return False
        d = math.sqrt(s)
        L[j, j] = d
        i = j + 1
        while i + 1 < n:  # two rows at a time (each entry sums as alone; the two chains overlap)
            t0 = A[i, j]
            t1 = A[i + 1, j]
            for k in range(j):
                ljk = L[j, k]
                t0 -= L[i, k] * ljk
                t1 -= L[i + 1, k] * ljk
            L[i, j] = t0 / d
            L[i + 1, j] = t1 / d
            i += 2
        if i < n:
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@_jit
def sqrt_psd(A, L, n, floor):
    """L with L L^T = A (`_attitude.sqrt_psd`): Cholesky, else the clipped eigen-decomposition
    of the symmetrised A. Returns True when the fallback was needed."""
    if cholesky(A, L, n):
        return False
    lam, vec = np.linalg.eigh(0.5 * (A + A.T))
    for j in range(n):
        v = lam[j]
        if v < floor:
            v = floor
        r = math.sqrt(v)
        for i in range(n):
            L[i, j] = vec[i, j] * r
    return True


@_jit
def repair_covariance(P, n, o, L):
    """In place, `_attitude.repair_covariance`: symmetrise; a non-finite P becomes cov_reset * I;
    a P that is not positive definite gets its eigenvalues clipped to cov_floor. -> repaired."""
    total = 0.0
    for i in range(n):
        for j in range(i, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
            total += v if i == j else 2.0 * v
    if not math.isfinite(total):
        for i in range(n):
            for j in range(n):
                P[i, j] = o.cov_reset if i == j else 0.0
        return True
    if cholesky(P, L, n):
        return False
    lam, vec = np.linalg.eigh(P.copy())
    for j in range(n):
        if lam[j] < o.cov_floor:
            lam[j] = o.cov_floor
    for a in range(n):
        for b in range(n):
            v = 0.0
            for j in range(n):
                v += vec[a, j] * lam[j] * vec[b, j]
            P[a, b] = v
    return True


@_jit
def joseph(P, K, PHt, S, n, D):
    """P <- (I - K H) P (I - K H)^T + K R K^T for a measurement of up to three rows (the Joseph
    form of `ekf`, `EKF._velocity_step` and `_attitude.bias_rest_update`), any gain K (n x 3),
    from PHt = P H^T (n x 3) and S = H P H^T + R (3 x 3); a measurement of fewer rows has zero
    columns in K and PHt and zero rows and columns in S. For a symmetric P the product expands
    to P - K PHt^T - PHt K^T + K S K^T = P - K PHt^T + D K^T with D = K S - PHt: six products
    per entry instead of the 3 n of (I - K H) P (I - K H)^T, computed on the upper triangle and
    mirrored (D: n x 3 scratch)."""
    for a in range(n):  # D = K S - PHt
        for j in range(3):
            D[a, j] = K[a, 0] * S[0, j] + K[a, 1] * S[1, j] + K[a, 2] * S[2, j] - PHt[a, j]
    for a in range(n):
        k0, k1, k2 = K[a, 0], K[a, 1], K[a, 2]
        d0, d1, d2 = D[a, 0], D[a, 1], D[a, 2]
        for c in range(a, n):
            v = (P[a, c] - (k0 * PHt[c, 0] + k1 * PHt[c, 1] + k2 * PHt[c, 2])
                 + (d0 * K[c, 0] + d1 * K[c, 1] + d2 * K[c, 2]))
            P[a, c] = v
            P[c, a] = v


@_jit
def joseph2(P, K, PHt, S, n, D):
    """`joseph` for a two-row measurement (the velocity pseudo-measurement): K, PHt (n x 2 used),
    S (2 x 2 used); four products per entry instead of six (D: n x 3 scratch, two columns used)."""
    for a in range(n):  # D = K S - PHt
        D[a, 0] = K[a, 0] * S[0, 0] + K[a, 1] * S[1, 0] - PHt[a, 0]
        D[a, 1] = K[a, 0] * S[0, 1] + K[a, 1] * S[1, 1] - PHt[a, 1]
    for a in range(n):
        k0, k1, d0, d1 = K[a, 0], K[a, 1], D[a, 0], D[a, 1]
        for c in range(a, n):
            v = P[a, c] - (k0 * PHt[c, 0] + k1 * PHt[c, 1]) + (d0 * K[c, 0] + d1 * K[c, 1])
            P[a, c] = v
            P[c, a] = v


@_jit
def predict_covariance(P, F, Qrate, Qbad, h, ok, n, N, T):
    """P <- F P F^T + Q (`EKF.step`, Sola 2017, Sec. 5.4) for F = [[A, B, 0], [0, I]]: A (3 x 3) and
    B (3 x (n - 3)) in F's first three rows, the velocity columns zero, the identity below (only
    F[:3, :n] is read), and Q = Qrate dt (+ Qbad dt^2 without a usable gyro) with Qrate, Qbad
    symmetric. With T = F[:3] P (3 x N): the block [:3, :3] is T F[:3]^T, the block [:3, 3:]
    is T[:, 3:] (and its mirror [3:, :3]), the block [3:, 3:] is P's own (T: 3 x N scratch).
    The dense product costs 2 N^3 multiplications, this one 3 n N + 6 n."""
    for c in range(N):  # T = F[:3, :n] P[:n]
        v0, v1, v2 = 0.0, 0.0, 0.0
        for j in range(n):
            pj = P[j, c]
            v0 += F[0, j] * pj
            v1 += F[1, j] * pj
            v2 += F[2, j] * pj
        T[0, c], T[1, c], T[2, c] = v0, v1, v2
    hh = h * h
    for i in range(N):  # the upper triangle, mirrored
        for c in range(i, N):
            if c < 3:
                v = 0.0
                for j in range(n):
                    v += T[i, j] * F[c, j]
            elif i < 3:
                v = T[i, c]
            else:
                v = P[i, c]
            qn = Qrate[i, c] * h
            if not ok:  # no rate integration: the attitude noise is inflated
                qn = qn + Qbad[i, c] * hh
            v = v + qn
            P[i, c] = v
            P[c, i] = v


@_jit
def weighted_outer_sum(E, WE, P, m, n):
    """P = sum_i E[i]^T WE[i] (n x n) over the m rows of E and WE (= Wc E), symmetric: the upper
    triangle, mirrored. Four entries of a row at a time: each sums its terms in the rows' order
    (as one entry at a time would, to the bit), but the four chains of additions overlap."""
    for a in range(n):
        c = a
        while c + 3 < n:
            v0, v1, v2, v3 = 0.0, 0.0, 0.0, 0.0
            for i in range(m):
                ea = E[i, a]
                v0 += ea * WE[i, c]
                v1 += ea * WE[i, c + 1]
                v2 += ea * WE[i, c + 2]
                v3 += ea * WE[i, c + 3]
            P[a, c], P[a, c + 1], P[a, c + 2], P[a, c + 3] = v0, v1, v2, v3
            c += 4
        while c < n:
            v = 0.0
            for i in range(m):
                v += E[i, a] * WE[i, c]
            P[a, c] = v
            c += 1
        for c in range(a + 1, n):
            P[c, a] = P[a, c]


@_jit
def weighted_cross3(E, WZ, out, n, m):
    """out[:n, :3] = sum_i E[i, :n]^T WZ[i, :3] over the m rows (the UKF's P_zz and P_xz, step 8):
    the three entries of a row at a time, each summed in the rows' order."""
    for a in range(n):
        v0, v1, v2 = 0.0, 0.0, 0.0
        for i in range(m):
            ea = E[i, a]
            v0 += ea * WZ[i, 0]
            v1 += ea * WZ[i, 1]
            v2 += ea * WZ[i, 2]
        out[a, 0], out[a, 1], out[a, 2] = v0, v1, v2


# Where the disturbance state array (`AccDisturbance.state`) holds the lag N_b, N_s (row by row).
_LAG = 23


@_jit
def lag_step(st, rate, fresh, h, updated, lowpass_s):
    """`_attitude.LowpassLag.step` on the disturbance state `st`: N_b and N_s advanced with its
    strapdown frame (q_I in st[5:9]); rate (2, 3): the bias-corrected rate u and the gain 1 + s
    (a step that was not integrated restarts the low-pass: fresh)."""
    if fresh:
        for c in range(_LAG, _LAG + 18):
            st[c] = 0.0
        return
    R = _rotation((st[5], st[6], st[7], st[8]))  # R_I, row by row
    for j in range(3):  # column j of R_I, times diag(1 + s) dt and diag(u) dt
        cx, cy, cz = R[j], R[3 + j], R[6 + j]
        gj = rate[1, j] * h
        uj = rate[0, j] * h
        st[_LAG + j] += cx * gj
        st[_LAG + 3 + j] += cy * gj
        st[_LAG + 6 + j] += cz * gj
        st[_LAG + 9 + j] += cx * uj
        st[_LAG + 12 + j] += cy * uj
        st[_LAG + 15 + j] += cz * uj
    if updated:
        decay = math.exp(-h / lowpass_s)
        for c in range(_LAG, _LAG + 18):
            st[c] *= decay


@_jit
def gravity_jacobian(H, hx, hy, hz, n):
    """H (3 x n) <- [[h]x, 0]: the accelerometer's Jacobian `[h]x` for the raw sample."""
    H[0, 0], H[0, 1], H[0, 2] = 0.0, -hz, hy
    H[1, 0], H[1, 1], H[1, 2] = hz, 0.0, -hx
    H[2, 0], H[2, 1], H[2, 2] = -hy, hx, 0.0
    for i in range(3):
        for j in range(3, n):
            H[i, j] = 0.0


@_jit
def lag_jacobian(H, st, n):
    """`AccDisturbance.lag_jacobian` into H (3 x n) holding `[h]x` in its first three columns:
    H[:, 3:6] = A N_b, H[:, 6:9] = -A N_s with A = [h]x R_I^T (N_b, N_s in the state `st`)."""
    qi = (st[5], -st[6], -st[7], -st[8])  # R_I^T
    for m in range(2 if n > 6 else 1):
        sign = 1.0 if m == 0 else -1.0
        for j in range(3):
            c = _LAG + 9 * m + j
            vx, vy, vz = rotate(qi, st[c], st[c + 3], st[c + 6])
            for i in range(3):
                H[i, 3 + 3 * m + j] = sign * (H[i, 0] * vx + H[i, 1] * vy + H[i, 2] * vz)


# ============================================================================ _attitude helpers
@_jit
def acc_variance_scale(ax, ay, az, gate, gate_g):
    """`_attitude.acc_variance_scale` (gate 0 off, 1 skip, 2 inflate)."""
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if not math.isfinite(norm):
        return math.inf
    if gate == 0:
        return 1.0
    dev = abs(norm - 1.0)
    if gate == 1:
        return math.inf if dev > gate_g else 1.0
    r = dev / gate_g
    return 1.0 + r * r


@_jit
def disturbance_lose_frame(st):
    """`AccDisturbance.lose_frame` on the state array of `AccDisturbance.state`."""
    st[0] = 0.0  # no mean
    st[4] = 0.0  # v
    st[9] = 0.0  # age
    st[10] = 0.0  # no low-pass
    st[14], st[15], st[16], st[17] = 0.0, 0.0, 0.0, 0.0  # lp_mean, lp_v
    st[18] = 0.0  # no lowpass_body
    st[22] = math.inf  # lowpass_density


@_jit
def _turn(st, dq):
    qi = qnormalize(qmul((st[5], st[6], st[7], st[8]), dq))
    st[5], st[6], st[7], st[8] = qi
    return qi


@_jit
def disturbance_turn(st, dq, dt, o, lag, rate):
    """`AccDisturbance.turn` on its state array: the frame follows the rate increment dq; with
    lag, N_b and N_s follow it (`lag_step`, rate as there)."""
    fresh = st[10] == 0.0
    _turn(st, dq)
    if lag:
        lag_step(st, rate, fresh, dt, False, o.lowpass_s)


@_jit
def disturbance_update(st, dq, ax, ay, az, dt, o, lag, rate):
    """`AccDisturbance.update` (and `_lowpass` with o.lowpass_s > 0, the lag with `lag`) on its
    state array; -> d, g^2."""
    fresh = st[10] == 0.0  # the low-pass (re)starts with this sample: no lag yet
    qi = _turn(st, dq)
    wx, wy, wz = rotate(qi, ax, ay, az)
    norm_dev = math.sqrt(ax * ax + ay * ay + az * az) - 1.0
    nd2 = norm_dev * norm_dev
    if st[0] == 0.0:
        st[0], st[1], st[2], st[3] = 1.0, wx, wy, wz
    ex, ey, ez = wx - st[1], wy - st[2], wz - st[3]
    inst = ex * ex + ey * ey + ez * ez
    alpha = -math.expm1(-dt / o.dist_window)
    st[1], st[2], st[3] = st[1] + alpha * ex, st[2] + alpha * ey, st[3] + alpha * ez
    st[4] += alpha * (inst - st[4])
    st[9] += dt
    seen = -math.expm1(-st[9] / o.dist_window)
    if o.lowpass_s > 0.0:
        _lowpass(st, qi, wx, wy, wz, dt, o)
    if lag:
        lag_step(st, rate, fresh, dt, True, o.lowpass_s)
    d = st[4] / seen  # max(v / seen, inst, nd2) with Python's max semantics
    if inst > d:
        d = inst
    if nd2 > d:
        d = nd2
    return d


@_jit
def _lowpass(st, qi, wx, wy, wz, dt, o):
    """`AccDisturbance._lowpass`: a_I low-passed, its density, its direction in the body frame."""
    if st[10] == 0.0:
        st[10], st[11], st[12], st[13] = 1.0, wx, wy, wz
        st[14], st[15], st[16] = wx, wy, wz
    beta = -math.expm1(-dt / o.lowpass_s)
    gamma = -math.expm1(-dt / o.lowpass_window)
    lx, ly, lz = st[11] + beta * (wx - st[11]), st[12] + beta * (wy - st[12]), st[13] + beta * (wz - st[13])
    st[11], st[12], st[13] = lx, ly, lz
    ex, ey, ez = lx - st[14], ly - st[15], lz - st[16]
    st[14], st[15], st[16] = st[14] + gamma * ex, st[15] + gamma * ey, st[16] + gamma * ez
    st[17] += gamma * (ex * ex + ey * ey + ez * ez - st[17])
    seen = -math.expm1(-st[9] / o.lowpass_window)
    st[22] = 2.0 * o.lowpass_s * st[17] / seen
    bx, by, bz = rotate((qi[0], -qi[1], -qi[2], -qi[3]), lx, ly, lz)  # back into the body frame
    norm = math.sqrt(bx * bx + by * by + bz * bz)
    if norm > 0.0:
        st[18], st[19], st[20], st[21] = 1.0, bx / norm, by / norm, bz / norm
    else:
        st[18] = 0.0


@_jit
def lowpass_drift_density(lowpass_s, rate_noise):
    """`_attitude.lowpass_drift_density`."""
    return 2.0 * lowpass_s * (lowpass_s * rate_noise)


@_jit
def lowpass_residual_density(density, lowpass_s, rate_noise):
    """`_attitude.lowpass_residual_density`."""
    if rate_noise <= 0.0 or not density > lowpass_s * lowpass_s * rate_noise:
        return density
    return (density * lowpass_s * math.sqrt(rate_noise)) ** (2.0 / 3.0)


@_jit
def acc_measurement(st, ax, ay, az, o, d, drift, rate_noise):
    """`_attitude.acc_measurement`: the raw sample or the low-passed direction, whichever has the
    smaller noise density; -> (z (3 floats), density g^2 s, low-passed)."""
    raw = o.acc_noise + 2.0 * o.corr_s * d
    if st[18] != 0.0:
        lowpassed = o.acc_noise + lowpass_residual_density(st[22], o.lowpass_s, rate_noise) + drift
        if lowpassed < raw:
            return st[19], st[20], st[21], lowpassed, True
    return ax, ay, az, raw, False


@_jit
def measurement(dist, dq, ax, ay, az, dt, scale, rate_noise, o, lag, rate):
    """The measurement and variance of one accelerometer update, as the filters' steps choose
    them: the disturbance estimate (`AccDisturbance.update` with the step's rate increment dq,
    and with `lag` the low-pass's lag, `lag_step` with rate (2, 3) as there),
    the low-pass frame drift (rate_noise: the filter's rate noise density), the raw or the
    low-passed sample (`_attitude.acc_measurement`), its variance times the gate's scale; without
    the disturbance model the raw sample and R / dt. -> (z (3 floats), r g^2, low-passed)."""
    if o.corr_s > 0.0:
        d = disturbance_update(dist, dq, ax, ay, az, dt, o, lag, rate)
        drift = lowpass_drift_density(o.lowpass_s, rate_noise)
        mx, my, mz, density, lowpassed = acc_measurement(dist, ax, ay, az, o, d, drift, rate_noise)
        return mx, my, mz, density / dt * scale, lowpassed
    return ax, ay, az, o.acc_noise / dt * scale, False


@_jit
def rest_update(st, gx, gy, gz, ax, ay, az, dt, o):
    """`RestDetector.update` on its state array `[has_lowpass, lp (3), time_still]`; -> at rest."""
    if not (math.isfinite(ax + ay + az) and math.isfinite(gx + gy + gz)):
        st[4] = 0.0
        return False
    if st[0] == 0.0:
        st[0], st[1], st[2], st[3] = 1.0, ax, ay, az
    alpha = -math.expm1(-dt / o.rest_window)
    dx, dy, dz = ax - st[1], ay - st[2], az - st[3]
    st[1], st[2], st[3] = st[1] + alpha * dx, st[2] + alpha * dy, st[3] + alpha * dz
    g = gx * gx + gy * gy + gz * gz
    a = ax * ax + ay * ay + az * az
    still = (g < o.rest_gyr * o.rest_gyr and dx * dx + dy * dy + dz * dz < o.rest_acc * o.rest_acc
             and abs(math.sqrt(a) - 1.0) < o.rest_acc)
    st[4] = st[4] + dt if still else 0.0
    return st[4] >= o.rest_time


# Options of `rest_kernel`: the `RestDetector` thresholds (the fields `rest_update` reads).
RestSettings = namedtuple("RestSettings", ["rest_gyr", "rest_acc", "rest_time", "rest_window"])


@_jit
def rest_kernel(gyr, valid, dt, acc, o, out):
    """out[k] (N-1,): whether step k ends at rest, as the filters' rest updates see it (the
    detector is fed step k's gyro reading and the accelerometer sample at its end, only on
    steps whose gyro is usable)."""
    st = np.zeros(5)
    for k in range(len(dt)):
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
        out[k] = ok and rest_update(st, gx, gy, gz, ax, ay, az, dt[k], o)


def rest_steps(imu: Any, gyr_th_rad_s: float, acc_th_g: float, min_time_s: float,
               window_s: float = REST_WINDOW_S) -> np.ndarray:
    """(N-1,) bool: the steps of `imu` (`ImuSamples`) that end at rest by `_attitude.RestDetector`
    with these thresholds, run causally over the recording (the samples the `ekf` and `ukf-bias`
    rest updates use). A batch smoother reads its gyro bias there."""
    gyr, valid, dt, acc = inputs(imu)
    out = np.zeros(len(dt), dtype=bool)
    if math.isfinite(min_time_s):
        rest_kernel(gyr, valid, dt, acc, RestSettings(float(gyr_th_rad_s), float(acc_th_g), float(min_time_s),
                                                      float(window_s)), out)
    return out


@_jit
def bias_rest_update(P, n, bx, by, bz, gx, gy, gz, r, K, dx, S, Sinv, PHt, D):
    """`_attitude.bias_rest_update`: the zero-rate update gyr = b + noise, H = [0, I, 0] (3 x n),
    so that P H^T = P[:, 3:6] and H P H^T = P[3:6, 3:6]; P updated in place (Joseph form,
    `joseph`), the correction into dx (n,) (PHt, D: n x 3 scratch)."""
    for i in range(n):
        PHt[i, 0], PHt[i, 1], PHt[i, 2] = P[i, 3], P[i, 4], P[i, 5]
    for i in range(3):
        for j in range(3):
            S[i, j] = P[3 + i, 3 + j] + (r if i == j else 0.0)
    inv_sym3(S, Sinv)
    yx, yy, yz = gx - bx, gy - by, gz - bz
    for i in range(n):
        for j in range(3):
            K[i, j] = P[i, 3] * Sinv[0, j] + P[i, 4] * Sinv[1, j] + P[i, 5] * Sinv[2, j]
        dx[i] = K[i, 0] * yx + K[i, 1] * yy + K[i, 2] * yz
    joseph(P, K, PHt, S, n, D)


@_jit
def _nis(yx, yy, yz, Sinv):
    """y^T S^-1 y, as (y @ Sinv) @ y."""
    t0 = yx * Sinv[0, 0] + yy * Sinv[1, 0] + yz * Sinv[2, 0]
    t1 = yx * Sinv[0, 1] + yy * Sinv[1, 1] + yz * Sinv[2, 1]
    t2 = yx * Sinv[0, 2] + yy * Sinv[1, 2] + yz * Sinv[2, 2]
    return t0 * yx + t1 * yy + t2 * yz


@_jit
def _project_heading(K, row0, hx, hy, hz):
    """K[row0:row0+3] <- (I - h h^T) K[row0:row0+3]: no correction about the vertical h."""
    for j in range(K.shape[1]):
        hk = hx * K[row0, j] + hy * K[row0 + 1, j] + hz * K[row0 + 2, j]
        K[row0, j] -= hx * hk
        K[row0 + 1, j] -= hy * hk
        K[row0 + 2, j] -= hz * hk


@_jit
def _clip(x, lo, hi):
    """np.clip for one float (nan passes through)."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@_jit
def _sample(gyr, valid, acc, k):
    """Step k's gyro reading, the accelerometer sample at its end, and whether the gyro is usable
    (marked valid and finite)."""
    gx, gy, gz = gyr[k, 0], gyr[k, 1], gyr[k, 2]
    ok = valid[k] and math.isfinite(gx) and math.isfinite(gy) and math.isfinite(gz)
    return gx, gy, gz, acc[k + 1, 0], acc[k + 1, 1], acc[k + 1, 2], ok


# ============================================================================ ekf
@_jit
def _inject(q, b, s, v, dx, n, N, small):
    """`EKF._correct`: q exp(dx_e / 2), b + dx_b, s + dx_s, v + dx_v (in place); -> the new q."""
    for i in range(3):
        if n > 3:
            b[i] = b[i] + dx[3 + i]
        if n > 6:
            s[i] = s[i] + dx[6 + i]
    for i in range(N - n):
        v[i] = v[i] + dx[n + i]
    return qmul(q, qexp(dx[0], dx[1], dx[2], small))


@_jit
def mag_reference_update(st, norm, dip, dt, o):
    """`_attitude.MagReference.update` on its state st (5,) `[has_ref, norm, dip, learned, in gates]`;
    -> the sample may correct the heading."""
    if st[0] == 0.0:
        st[0], st[1], st[2], st[3], st[4] = 1.0, norm, dip, dt, 0.0
        return False
    if abs(norm - st[1]) < o.mag_norm_gate * st[1] and abs(dip - st[2]) < o.mag_dip_gate:
        st[3] += dt
        alpha = dt / min(st[3], o.mag_ref_s)
        st[1] += alpha * (norm - st[1])
        st[2] += alpha * (dip - st[2])
        st[4] += dt
    else:
        st[4] = 0.0
    return st[4] >= o.mag_min_time


@_jit
def mag_input(q, mx, my, mz, magst, hist, o, h, hi_fit, hi_work):
    """`_attitude.magnetometer_input`: one finite sample (uT, body) through the sphere fit and the
    gates (magst (5,), hist (22,) advanced in place); -> (usable, east, north, hard iron used)."""
    east, north, up = rotate(q, mx, my, mz)  # `_attitude.field_norm_dip`
    horizontal = math.hypot(east, north)
    norm = math.sqrt(east * east + north * north + up * up)
    dip = math.atan2(-up, horizontal)
    hi_used = False
    if o.mag_hard_iron:
        hard_iron_add(hist, mx, my, mz, min(h / o.mag_hi_window, 1.0))
        if magst[0] != 0.0 and hard_iron_fit(hist, o.mag_hi_residual, o.mag_hi_coverage, hi_fit, hi_work) \
                and abs(hi_fit[3] - magst[1]) < o.mag_norm_gate * magst[1]:
            e2, n2, u2 = rotate(q, mx - hi_fit[0], my - hi_fit[1], mz - hi_fit[2])
            horizontal2 = math.hypot(e2, n2)
            norm2 = math.sqrt(e2 * e2 + n2 * n2 + u2 * u2)
            dip2 = math.atan2(-u2, horizontal2)
            if mag_in_gates(magst, norm2, dip2, o):
                east, north, norm, dip = e2, n2, norm2, dip2
                hi_used = True
    usable = mag_reference_update(magst, norm, dip, h, o) and east * east + north * north > 0.0
    return usable, east, north, hi_used


@_jit
def heading_variance(q, tx, ty, tz, h, o):
    """`_attitude.heading_variance`: Rm / dt (1 + (w / mrate)^2), w the rate about the vertical."""
    vx, vy, vz = gravity(q)
    w_up = (tx * vx + ty * vy + tz * vz) / h
    return o.mag_noise / h * (1.0 + (w_up / o.mag_rate) ** 2)


@_jit
def mag_in_gates(st, norm, dip, o):
    """`_attitude.MagReference.in_gates` on its state st (5,)."""
    return st[0] != 0.0 and abs(norm - st[1]) < o.mag_norm_gate * st[1] and abs(dip - st[2]) < o.mag_dip_gate


@_jit
def hard_iron_add(s, mx, my, mz, alpha):
    """`_attitude.hard_iron_add`: the sphere fit's sums s (22,) <- (1 - alpha) s + alpha (the sample's terms)."""
    y = mx * mx + my * my + mz * mz
    keep = 1.0 - alpha
    for i in range(4):
        xi = mx if i == 0 else my if i == 1 else mz if i == 2 else 1.0
        for j in range(4):
            xj = mx if j == 0 else my if j == 1 else mz if j == 2 else 1.0
            s[4 * i + j] = keep * s[4 * i + j] + alpha * xi * xj
        s[16 + i] = keep * s[16 + i] + alpha * xi * y
    s[20] = keep * s[20] + alpha * y * y
    s[21] = keep * s[21] + alpha


@_jit
def hard_iron_fit(s, residual_ut, coverage, out, a):
    """`_attitude.hard_iron_fit` (with `_attitude.solve4`): True and out (4,) = (ox, oy, oz, r) when
    the sphere fit is trusted (a: 4 x 5 scratch)."""
    w = s[21]
    if not w > 0.0:
        return False
    for i in range(4):
        for j in range(4):
            a[i, j] = s[4 * i + j]
        a[i, 4] = s[16 + i]
    for c in range(4):
        p = c
        for r in range(c + 1, 4):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if not abs(a[p, c]) > 0.0:
            return False
        if p != c:
            for j in range(5):
                a[c, j], a[p, j] = a[p, j], a[c, j]
        for r in range(c + 1, 4):
            f = a[r, c] / a[c, c]
            for j in range(c, 5):
                a[r, j] -= f * a[c, j]
    x0 = x1 = x2 = x3 = 0.0
    for r in range(3, -1, -1):
        v = a[r, 4]
        for j in range(r + 1, 4):
            v -= a[r, j] * (x0 if j == 0 else x1 if j == 1 else x2 if j == 2 else x3)
        if r == 3:
            x3 = v / a[r, r]
        elif r == 2:
            x2 = v / a[r, r]
        elif r == 1:
            x1 = v / a[r, r]
        else:
            x0 = v / a[r, r]
    ox, oy, oz = 0.5 * x0, 0.5 * x1, 0.5 * x2
    r2 = x3 + ox * ox + oy * oy + oz * oz
    if not r2 > 0.0:
        return False
    rad = math.sqrt(r2)
    xAx = 0.0
    xb = 0.0
    for i in range(4):
        xi = x0 if i == 0 else x1 if i == 1 else x2 if i == 2 else x3
        xb += xi * s[16 + i]
        for j in range(4):
            xj = x0 if j == 0 else x1 if j == 1 else x2 if j == 2 else x3
            xAx += xi * s[4 * i + j] * xj
    res = (s[20] - 2.0 * xb + xAx) / w
    if not res < (2.0 * rad * residual_ut) ** 2:
        return False
    mx, my, mz = s[3] / w, s[7] / w, s[11] / w
    cxx, cxy, cxz = s[0] / w - mx * mx, s[1] / w - mx * my, s[2] / w - mx * mz
    cyy, cyz, czz = s[5] / w - my * my, s[6] / w - my * mz, s[10] / w - mz * mz
    det = cxx * (cyy * czz - cyz * cyz) - cxy * (cxy * czz - cyz * cxz) + cxz * (cxy * cyz - cyy * cxz)
    if not det > (coverage * rad) ** 6:
        return False
    if not ox * ox + oy * oy + oz * oz > residual_ut * residual_ut:
        return False
    out[0], out[1], out[2], out[3] = ox, oy, oz, rad
    return True


@_jit
def heading_update(P, n, N, q, east, north, r, K, G, dx):
    """`_attitude.heading_update`: the heading-only update with H = [v^T, 0] (v = R(q)^T e_z), the
    gain restricted to v on the attitude and bias rows and 0 on the velocity rows, Joseph form for a scalar
    measurement, expanded as in `joseph` for a symmetric P: with g = P H^T and s = H P H^T + r,
    P <- P - K g^T - g K^T + s K K^T = P - K g^T + (s K - g) K^T (upper triangle, mirrored); the
    correction into dx (N,) (K, G: (N,) scratch)."""
    vx, vy, vz = gravity(q)
    psi = math.atan2(-east, north)
    for i in range(N):  # g = P H^T
        G[i] = P[i, 0] * vx + P[i, 1] * vy + P[i, 2] * vz
    S = vx * G[0] + vy * G[1] + vz * G[2] + r
    for i in range(N):
        K[i] = G[i] / S
    vk = vx * K[0] + vy * K[1] + vz * K[2]
    K[0], K[1], K[2] = vx * vk, vy * vk, vz * vk
    if n > 3:
        vk = vx * K[3] + vy * K[4] + vz * K[5]
        K[3], K[4], K[5] = vx * vk, vy * vk, vz * vk
    for i in range(n, N):
        K[i] = 0.0
    for i in range(N):
        ka = K[i]
        da = S * ka - G[i]
        for c in range(i, N):
            v = P[i, c] - ka * G[c] + da * K[c]
            P[i, c] = v
            P[c, i] = v
    for i in range(N):
        dx[i] = -psi * K[i]


@_jit
def velocity_step(P, n, N, q, v, ax, ay, az, h, o, K, dx, PHt, S, D):
    """`EKF._velocity_step`: the horizontal world velocity v (2,) integrates the specific force at
    the attitude q, P <- V P V^T with V = I but V[n:, :3] = -(R [a]x)_xy g dt, then the
    pseudo-measurement v = 0 (variance Rv / dt, H = [0, I], so that P H^T = P[:, n:] and
    H P H^T = P[n:, n:]) in Joseph form (`joseph2`); the correction into dx (N,) (K, PHt, D:
    N x 3 scratch, two columns used; S: 3 x 3 scratch, its upper-left 2 x 2 used)."""
    r00, r01, r02, r10, r11, r12, _, _, _ = _rotation(q)  # the first two rows of R(q)
    if math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az):
        g = o.gravity * h
        v[0] += (r00 * ax + r01 * ay + r02 * az) * g
        v[1] += (r10 * ax + r11 * ay + r12 * az) * g
        a00, a01, a02 = -(r01 * az - r02 * ay) * g, -(r02 * ax - r00 * az) * g, -(r00 * ay - r01 * ax) * g
        a10, a11, a12 = -(r11 * az - r12 * ay) * g, -(r12 * ax - r10 * az) * g, -(r10 * ay - r11 * ax) * g
        for c in range(N):  # V P
            P[n, c] += a00 * P[0, c] + a01 * P[1, c] + a02 * P[2, c]
            P[n + 1, c] += a10 * P[0, c] + a11 * P[1, c] + a12 * P[2, c]
        for i in range(N):  # (V P) V^T
            P[i, n] += P[i, 0] * a00 + P[i, 1] * a01 + P[i, 2] * a02
            P[i, n + 1] += P[i, 0] * a10 + P[i, 1] * a11 + P[i, 2] * a12
    r = o.vel_bound / h
    s00, s01, s10, s11 = P[n, n] + r, P[n, n + 1], P[n + 1, n], P[n + 1, n + 1] + r
    det = s00 * s11 - s01 * s10
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    for i in range(N):
        K[i, 0] = P[i, n] * i00 + P[i, n + 1] * i10
        K[i, 1] = P[i, n] * i01 + P[i, n + 1] * i11
        K[i, 2] = 0.0
    if o.heading_free:
        hx, hy, hz = gravity(q)
        _project_heading(K, 0, hx, hy, hz)
        if n > 3:
            _project_heading(K, 3, hx, hy, hz)
    for i in range(N):
        dx[i] = -(K[i, 0] * v[0] + K[i, 1] * v[1])
    for i in range(N):  # P H^T
        PHt[i, 0], PHt[i, 1] = P[i, n], P[i, n + 1]
    S[0, 0], S[0, 1], S[1, 0], S[1, 1] = s00, s01, s10, s11  # H P H^T + r I
    joseph2(P, K, PHt, S, N, D)


@_jit
def scale_test(P, s, st, q, o, N, K, PHt, S, Sinv, D, dx):
    """`_attitude.ScaleTest.step` on its state st (3,) `[on, decision, ln L]` while on and
    undecided, with the attitude q: -> whether it accepted H0 now, with the pseudo-measurement's
    correction in dx (N,) and P updated in place (Joseph form; heading-free as `EKF.step`). The
    axes not tested (`o.scale_test_axes`) take a unit diagonal in S, so that its inverse and
    determinant are those of the tested block, and zero columns in K and PHt (K, PHt, D: N x 3
    scratch)."""
    r = o.scale_test_r
    for i in range(3):
        on_i = (o.scale_test_axes >> i) & 1
        for j in range(3):
            on_j = (o.scale_test_axes >> j) & 1
            S[i, j] = P[6 + i, 6 + j] + (r if i == j else 0.0) if on_i and on_j else (1.0 if i == j else 0.0)
    y0 = -s[0] if o.scale_test_axes & 1 else 0.0
    y1 = -s[1] if o.scale_test_axes & 2 else 0.0
    y2 = -s[2] if o.scale_test_axes & 4 else 0.0
    det = inv_sym3(S, Sinv)
    llr = 0.5 * (_nis(y0, y1, y2, Sinv) + math.log(det)) + o.scale_test_const
    st[2] = llr
    if llr >= o.scale_test_bound:
        st[1] = 1.0
        return False
    if llr > -o.scale_test_bound:
        return False
    st[1] = -1.0
    for i in range(3):  # H selects the tested scale rows: P H^T = P[:, 6 + i]; S's dummy rows to zero
        on_i = (o.scale_test_axes >> i) & 1
        if not on_i:
            S[i, i] = 0.0
        for a in range(N):
            PHt[a, i] = P[a, 6 + i] if on_i else 0.0
    for a in range(N):
        for j in range(3):
            K[a, j] = PHt[a, 0] * Sinv[0, j] + PHt[a, 1] * Sinv[1, j] + PHt[a, 2] * Sinv[2, j]
    if o.heading_free:  # no turn about the vertical h on the attitude and bias rows
        hx, hy, hz = gravity(q)
        _project_heading(K, 0, hx, hy, hz)
        _project_heading(K, 3, hx, hy, hz)
    for a in range(N):
        dx[a] = K[a, 0] * y0 + K[a, 1] * y1 + K[a, 2] * y2
    joseph(P, K, PHt, S, N, D)
    return True


@_jit
def ekf_kernel(gyr, valid, dt, acc, mag, mag_ok, qio, b, s, v, P, Qrate, Qbad, dist, rest, magst, hist, test, o,
               out_q, out_cov, out_b, out_s, out_v, out_var, out_rest, out_nis, out_guard, out_lowpassed, out_mag,
               out_hi, out_llr):
    """`EKF.estimate`: the loop of `EKF.step` over a recording (see `ekf` for the equations).

    gyr (N-1, 3), valid (N-1,), dt (N-1,): the interval rates and steps; acc (N, 3), g;
    mag (N, 3), uT, and mag_ok (N,) its validity, or both empty (no magnetometer: 6-D).
    State in and out: qio (4,), b (3,), s (3,), v (2,), P (N, N) (N = n + nv, the velocity
    last), dist (41,) (`AccDisturbance.state`, with the lag), rest (5,), magst (5,)
    (`MagReference.state`), hist (22,) (`HardIron.state`), test (3,) (`ScaleTest`'s on, decision
    and ln L). Qrate, Qbad (N, N) as built by `EKF.reset`. Fills rows 1.. of the
    (samples, ...) outputs; returns (updates skipped, covariance repairs).
    """
    n = o.n
    N = n + o.nv
    small = o.small_angle
    # Work arrays, allocated once for the whole recording.
    F = np.zeros((3, N))  # the first three rows of F; the others are [0, I]
    T = np.empty((3, N))
    J = np.empty((3, 3))
    H = np.zeros((3, N))
    with_lag = o.lag
    rate = np.zeros((2, 3))  # the lag's inputs: u and 1 + s (`AccDisturbance.update`)
    PHt = np.empty((N, 3))
    S = np.empty((3, 3))
    Sinv = np.empty((3, 3))
    K = np.empty((N, 3))
    D = np.empty((N, 3))
    dx = np.empty(N)
    L = np.empty((N, N))
    q = (qio[0], qio[1], qio[2], qio[3])
    use_mag = mag.shape[0] > 0
    hi_fit = np.empty(4)
    hi_work = np.empty((4, 5))
    Km = np.empty(N)
    Gm = np.empty(N)
    skipped = 0
    repaired = 0
    for k in range(dt.shape[0]):
        h = dt[k]
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
        ux, uy, uz = gx, gy, gz
        sx, sy, sz = 1.0, 1.0, 1.0
        if ok:
            if n > 3:
                ux, uy, uz = gx - b[0], gy - b[1], gz - b[2]
            if n > 6:
                sx, sy, sz = 1.0 + s[0], 1.0 + s[1], 1.0 + s[2]
                tx, ty, tz = ux * sx * h, uy * sy * h, uz * sz * h  # w_true = diag(1 + s) (w_meas - b)
            else:
                tx, ty, tz = ux * h, uy * h, uz * h
        else:  # no rate integration; the attitude noise is inflated below
            tx, ty, tz = 0.0, 0.0, 0.0
            disturbance_lose_frame(dist)
        d = qexp(tx, ty, tz, small)
        q = qmul(q, d)
        # F[:3, :3] = R(theta)^T; F[:3, 3:6] = -J_r diag(1 + s) dt; F[:3, 6:] = J_r diag(w - b) dt
        dw, dxx, dyy, dzz = d
        F[0, 0] = 1 - 2 * (dyy * dyy + dzz * dzz)
        F[1, 0] = 2 * (dxx * dyy - dw * dzz)
        F[2, 0] = 2 * (dxx * dzz + dw * dyy)
        F[0, 1] = 2 * (dxx * dyy + dw * dzz)
        F[1, 1] = 1 - 2 * (dxx * dxx + dzz * dzz)
        F[2, 1] = 2 * (dyy * dzz - dw * dxx)
        F[0, 2] = 2 * (dxx * dzz - dw * dyy)
        F[1, 2] = 2 * (dyy * dzz + dw * dxx)
        F[2, 2] = 1 - 2 * (dxx * dxx + dyy * dyy)
        if n > 3:
            right_jacobian_dt(tx, ty, tz, h, o, J)
            for i in range(3):
                for j in range(3):
                    if not ok:  # the rate was not integrated: no bias or scale enters
                        F[i, 3 + j] = 0.0
                        if n > 6:
                            F[i, 6 + j] = 0.0
                    elif n > 6:
                        F[i, 3 + j] = -J[i, j] * (sx if j == 0 else sy if j == 1 else sz)
                        F[i, 6 + j] = J[i, j] * (ux if j == 0 else uy if j == 1 else uz)
                    else:
                        F[i, 3 + j] = -J[i, j]
        predict_covariance(P, F, Qrate, Qbad, h, ok, n, N, T)  # P <- F P F^T + Q
        if N > n:  # the velocity model (`EKF._velocity_step`)
            velocity_step(P, n, N, q, v, ax, ay, az, h, o, K, dx, PHt, S, D)
            q = _inject(q, b, s, v, dx, n, N, small)
        at_rest = False
        if n > 3 and ok and o.rest_on and rest_update(rest, gx, gy, gz, ax, ay, az, h, o):
            # Zero-rate update at rest (VQF, Sec. 3.4): the gyro reads the bias.
            bias_rest_update(P, N, b[0], b[1], b[2], gx, gy, gz, o.rest_noise / h, K, dx, S, Sinv, PHt, D)
            q = _inject(q, b, s, v, dx, n, N, small)
            at_rest = True
        var = math.nan
        nis = math.nan
        guarded = False
        lowpassed = False
        scale = acc_variance_scale(ax, ay, az, o.gate, o.gate_g) if o.use_acc else math.inf
        if with_lag:
            rate[0, 0], rate[0, 1], rate[0, 2] = ux, uy, uz
            for i in range(3):
                rate[1, i] = 1.0 + s[i] if n > 6 else 1.0
        if scale < math.inf:
            mx, my, mz, r, lowpassed = measurement(dist, d, ax, ay, az, h, scale, o.process_noise, o, with_lag, rate)
            var = r
            hx, hy, hz = gravity(q)
            gravity_jacobian(H, hx, hy, hz, N)  # H = [[h]x, 0, 0]
            if with_lag and lowpassed:  # the low-pass's lag: H = [[h]x, A N_b, -A N_s] (`_attitude.LowpassLag`)
                lag_jacobian(H, dist, n)
            nh = n if with_lag and lowpassed else 3  # H's columns nh.. are zero
            for i in range(N):  # P H^T
                for j in range(3):
                    acc_ = 0.0
                    for c in range(nh):
                        acc_ += P[i, c] * H[j, c]
                    PHt[i, j] = acc_
            for i in range(3):  # H P H^T + R
                for j in range(3):
                    acc_ = 0.0
                    for c in range(nh):
                        acc_ += H[i, c] * PHt[c, j]
                    S[i, j] = acc_
                S[i, i] += r
            inv_sym3(S, Sinv)
            for i in range(N):
                for j in range(3):
                    K[i, j] = PHt[i, 0] * Sinv[0, j] + PHt[i, 1] * Sinv[1, j] + PHt[i, 2] * Sinv[2, j]
            if o.heading_free:  # K <- (I - h h^T) K on the attitude and bias rows
                _project_heading(K, 0, hx, hy, hz)
                if n > 3:
                    _project_heading(K, 3, hx, hy, hz)
            yx, yy, yz = mx - hx, my - hy, mz - hz
            nis = _nis(yx, yy, yz, Sinv)
            guarded = n > 3 and nis > o.chi2  # inconsistent innovation: correct the attitude only
            if guarded or (n > 3 and lowpassed and not o.lowpass_calibration):  # ... or the velocity's to correct
                for i in range(3, n):
                    K[i, 0] = 0.0
                    K[i, 1] = 0.0
                    K[i, 2] = 0.0
            for i in range(N):
                dx[i] = K[i, 0] * yx + K[i, 1] * yy + K[i, 2] * yz
            q = _inject(q, b, s, v, dx, n, N, small)
            joseph(P, K, PHt, S, N, D)  # Joseph form
        else:
            skipped += 1
            if o.corr_s > 0.0:  # the strapdown frame follows the gyro through skipped updates
                disturbance_turn(dist, d, h, o, with_lag, rate)
        mag_used = False
        hi_used = False
        if use_mag and mag_ok[k + 1]:  # 9-D: the gated heading-only update (`EKF.step`)
            mx, my, mz = mag[k + 1, 0], mag[k + 1, 1], mag[k + 1, 2]
            if math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz):
                if test[1] == 0.0:  # 9-D: no scale test (`ScaleTest.stop`)
                    test[0], test[2] = 0.0, math.nan
                usable, east, north, hi_used = mag_input(q, mx, my, mz, magst, hist, o, h, hi_fit, hi_work)
                if usable:
                    r_mag = heading_variance(q, tx, ty, tz, h, o)
                    heading_update(P, n, N, q, east, north, r_mag, Km, Gm, dx)
                    q = _inject(q, b, s, v, dx, n, N, small)
                    mag_used = True
        # Wald's test: a scale error, or a calibrated gyro? (`_attitude.ScaleTest`)
        if o.scale_test_axes and test[0] == 1.0 and test[1] == 0.0:
            if scale_test(P, s, test, q, o, N, K, PHt, S, Sinv, D, dx):
                q = _inject(q, b, s, v, dx, n, N, small)
        if n > 3:
            for i in range(3):
                b[i] = _clip(b[i], -o.bias_max, o.bias_max)
        if n > 6:
            for i in range(3):
                s[i] = _clip(s[i], -o.scale_max, o.scale_max)
        q = qnormalize(q)
        if repair_covariance(P, N, o, L):
            repaired += 1
        out_q[k + 1, 0], out_q[k + 1, 1], out_q[k + 1, 2], out_q[k + 1, 3] = q
        out_cov[k + 1, :, :] = P
        out_b[k + 1, :] = b
        out_s[k + 1, :] = s
        out_v[k + 1, :] = v
        out_var[k + 1] = var
        out_rest[k + 1] = at_rest
        out_nis[k + 1] = nis
        out_guard[k + 1] = guarded
        out_lowpassed[k + 1] = lowpassed
        out_mag[k + 1] = mag_used
        out_hi[k + 1] = hi_used
        out_llr[k + 1] = test[2]
    qio[0], qio[1], qio[2], qio[3] = q
    return skipped, repaired


# ============================================================================ ukf, ukf-bias
@_jit
def ukf_kernel(gyr, valid, dt, acc, mag, mag_ok, x, P, Qrate, Qbad, Wm, Wc, dist, rest, magst, hist, test, o,
               out_q, out_cov, out_b, out_s, out_iter, out_var, out_rest, out_nis, out_lowpassed, out_mag, out_hi,
               out_llr):
    """`UKF.estimate` with impl=numpy: the loop of `UKF.step` (`QuaternionUKF.predict_kraft`,
    `update_kraft`; steps 1-9 of the `ukf` module docstring) over a recording.

    gyr (N-1, 3), valid (N-1,), dt (N-1,): the interval rates and steps; acc (N, 3), g;
    mag (N, 3), uT, and mag_ok (N,), or both empty (6-D; ukf-bias only, as in `ekf_kernel`).
    State in and out: x (n + 1,) `[q, b, s]`, P (n, n), dist (41,) (`AccDisturbance.state`,
    with the lag), rest (5,), magst (5,), hist (22,) (`MagReference`, `HardIron`), test (3,)
    (`ScaleTest`, as in `ekf_kernel`). Qrate, Qbad (n, n) as built by `UKF.reset`; Wm, Wc
    (2n + 1,) the sigma-point weights, centre first. Fills rows 1.. of the (N, ...) outputs; returns (updates
    skipped, square-root recoveries, covariance repairs, mean-iteration cap hits).
    """
    n = o.n
    m = 2 * n + 1
    small = o.small_angle
    A = np.empty((n, n))
    L = np.empty((n, n))
    off = np.zeros((m, n))
    sig = np.empty((m, n + 1))
    Ep = np.empty((2 * n, 4))  # q exp(+-e_i / 2), i < 3 (step 3)
    err = np.empty((m, 3))
    res = np.empty((m, n))
    Wres = np.empty((m, n))
    dZ = np.empty((m, 3))
    WdZ = np.empty((m, 3))
    S = np.empty((3, 3))
    Sinv = np.empty((3, 3))
    Pxz = np.empty((n, 3))
    K = np.empty((n, 3))
    KS = np.empty((n, 3))
    dx = np.empty(n)
    H = np.zeros((3, n))
    with_lag = o.lag
    rate = np.zeros((2, 3))  # the lag's inputs: u and 1 + s (`UKF._lag_rate`)
    use_mag = mag.shape[0] > 0
    hi_fit = np.empty(4)
    hi_work = np.empty((4, 5))
    Km = np.empty(n)
    Gm = np.empty(n)
    skipped = 0
    sqrt_recovered = 0
    repaired = 0
    capped = 0
    iters = 0
    for k in range(dt.shape[0]):
        h = dt[k]
        gx, gy, gz, ax, ay, az, ok = _sample(gyr, valid, acc, k)
        hh = h * h
        scale_noise = ok and o.scale_noise > 0.0  # ukf only: Qs w_i^2 dt added to the attitude noise
        for i in range(n):  # A = P + Q
            for c in range(n):
                qn = Qrate[i, c] * h
                if not ok:  # no rate integration; inflate the attitude noise instead
                    qn = qn + Qbad[i, c] * hh
                elif scale_noise and i == c and i < 3:
                    g = gx if i == 0 else gy if i == 1 else gz
                    qn += o.scale_noise * g * g * h
                A[i, c] = P[i, c] + qn
        if ok:
            # The mean rate increment, for the disturbance estimator's strapdown frame.
            wx, wy, wz = gx, gy, gz
            if n > 3:
                wx, wy, wz = gx - x[4], gy - x[5], gz - x[6]
            if n > 6:
                wx, wy, wz = wx * (1.0 + x[7]), wy * (1.0 + x[8]), wz * (1.0 + x[9])
            dq = qexp(wx * h, wy * h, wz * h, small)
        else:
            wx, wy, wz = 0.0, 0.0, 0.0
            dq = (1.0, 0.0, 0.0, 0.0)
            disturbance_lose_frame(dist)
        # ---- predict (steps 1-5)
        recovered = sqrt_psd(A, L, n, o.sqrt_floor)
        if recovered:  # step 2: +- columns of sqrt(c (P + Q))
            sqrt_recovered += 1
        for i in range(n):
            for j in range(n):
                v = L[j, i] * o.sqrt_c
                off[1 + i, j] = v
                off[1 + n + i, j] = -v
        xq = (x[0], x[1], x[2], x[3])
        # step 3: X_i = q exp(e_i / 2) for the attitude part e_i of offset i. Offset 0 is zero, and
        # a Cholesky factor is lower triangular: the columns 3.. of L have no attitude part, so
        # X_i = q there (exp(0) = 1 exactly); and exp(-e / 2) is the conjugate of exp(e / 2), so
        # only the first three columns need an exponential (all n after the eigen fallback).
        n_att = n if recovered else 3
        for i in range(n_att):
            E = qexp(off[1 + i, 0], off[1 + i, 1], off[1 + i, 2], small)
            Ep[i, 0], Ep[i, 1], Ep[i, 2], Ep[i, 3] = qmul(xq, E)
            Ep[n + i, 0], Ep[n + i, 1], Ep[n + i, 2], Ep[n + i, 3] = qmul(xq, (E[0], -E[1], -E[2], -E[3]))
        for i in range(m):
            if i == 0 or (i - 1) % n >= n_att:
                X = xq
            else:
                X = (Ep[i - 1, 0], Ep[i - 1, 1], Ep[i - 1, 2], Ep[i - 1, 3])
            if not ok:
                sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = X
                for j in range(3, n):
                    sig[i, j + 1] = x[j + 1] + off[i, j]
            elif n > 3:
                bx, by, bz = x[4] + off[i, 3], x[5] + off[i, 4], x[6] + off[i, 5]
                rx, ry, rz = gx - bx, gy - by, gz - bz
                if n > 6:
                    s0, s1, s2 = x[7] + off[i, 6], x[8] + off[i, 7], x[9] + off[i, 8]
                    rx, ry, rz = rx * (1.0 + s0), ry * (1.0 + s1), rz * (1.0 + s2)
                    sig[i, 7], sig[i, 8], sig[i, 9] = s0, s1, s2
                Y = qmul(X, qexp(rx * h, ry * h, rz * h, small))  # steps 1, 4, per point
                sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = Y
                sig[i, 4], sig[i, 5], sig[i, 6] = bx, by, bz
            else:
                sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3] = qmul(X, dq)  # steps 1, 4 (dq: exp(w dt / 2))
        # step 5: iterative quaternion mean (`ukf.quaternion_mean`)
        qt = (sig[0, 0], sig[0, 1], sig[0, 2], sig[0, 3])
        ex, ey, ez = 0.0, 0.0, 0.0
        for it in range(1, o.mean_max_iter + 1):
            iters = it
            ci = (qt[0], -qt[1], -qt[2], -qt[3])
            ex, ey, ez = 0.0, 0.0, 0.0
            for i in range(m):
                e0, e1, e2 = qlog(qmul(ci, (sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3])))
                err[i, 0], err[i, 1], err[i, 2] = e0, e1, e2
                ex += Wm[i] * e0
                ey += Wm[i] * e1
                ez += Wm[i] * e2
            qt = qnormalize(qmul(qt, qexp(ex, ey, ez, small)))
            if math.sqrt(ex * ex + ey * ey + ez * ez) < o.mean_tol:
                break
        if iters >= o.mean_max_iter:
            capped += 1
        x[0], x[1], x[2], x[3] = qt
        for i in range(m):
            res[i, 0], res[i, 1], res[i, 2] = err[i, 0] - ex, err[i, 1] - ey, err[i, 2] - ez
        for j in range(3, n):
            v = 0.0
            for i in range(m):
                v += Wm[i] * sig[i, j + 1]
            x[j + 1] = v
            for i in range(m):
                res[i, j] = sig[i, j + 1] - v
        # P_pred = sum Wc e_i e_i^T, symmetric: the upper triangle, mirrored (Wc e_i once per point)
        for i in range(m):
            for c in range(n):
                Wres[i, c] = Wc[i] * res[i, c]
        weighted_outer_sum(res, Wres, P, m, n)
        # ---- rest update (ukf-bias)
        at_rest = False
        if n > 3 and ok and o.rest_on and rest_update(rest, gx, gy, gz, ax, ay, az, h, o):
            bias_rest_update(P, n, x[4], x[5], x[6], gx, gy, gz, o.rest_noise / h, K, dx, S, Sinv, Pxz, KS)
            qn4 = qnormalize(qmul((x[0], x[1], x[2], x[3]), qexp(dx[0], dx[1], dx[2], small)))
            x[0], x[1], x[2], x[3] = qn4
            for j in range(3, n):
                x[j + 1] = x[j + 1] + dx[j]
            at_rest = True
        # ---- accelerometer update (steps 6-9)
        var = math.nan
        nis = math.nan
        lowpassed = False
        scale = acc_variance_scale(ax, ay, az, o.gate, o.gate_g) if o.use_acc else math.inf
        if with_lag:
            rate[0, 0], rate[0, 1], rate[0, 2] = gx - x[4], gy - x[5], gz - x[6]
            for i in range(3):
                rate[1, i] = 1.0 + x[7 + i] if n > 6 else 1.0
        if scale < math.inf:
            q_rate = o.process_noise  # ukf: plus the scale noise Qs w_i^2, a rate noise density too
            if ok and o.scale_noise > 0.0:
                q_rate += o.scale_noise * max(gx * gx, gy * gy, gz * gz)
            mx, my, mz, r, lowpassed = measurement(dist, dq, ax, ay, az, h, scale, q_rate, o, with_lag, rate)
            var = r
            lagged = with_lag and lowpassed
            if lagged:  # the low-passed sample's lag (`AccDisturbance.lag_jacobian`)
                hx, hy, hz = gravity((x[0], x[1], x[2], x[3]))
                gravity_jacobian(H, hx, hy, hz, n)
                lag_jacobian(H, dist, n)
            zx, zy, zz = 0.0, 0.0, 0.0
            for i in range(m):  # step 6
                g0, g1, g2 = gravity((sig[i, 0], sig[i, 1], sig[i, 2], sig[i, 3]))
                if lagged:
                    for c in range(3, n):
                        g0 += H[0, c] * res[i, c]
                        g1 += H[1, c] * res[i, c]
                        g2 += H[2, c] * res[i, c]
                dZ[i, 0], dZ[i, 1], dZ[i, 2] = g0, g1, g2
                zx += Wm[i] * g0  # step 7
                zy += Wm[i] * g1
                zz += Wm[i] * g2
            for i in range(m):
                dZ[i, 0] -= zx
                dZ[i, 1] -= zy
                dZ[i, 2] -= zz
                for j in range(3):
                    WdZ[i, j] = Wc[i] * dZ[i, j]
            weighted_cross3(dZ, WdZ, S, 3, m)  # step 8: P_zz
            for a in range(3):
                S[a, a] = S[a, a] + r
            weighted_cross3(res, WdZ, Pxz, n, m)  # step 8: P_xz
            inv_sym3(S, Sinv)
            for a in range(n):  # step 9: K = P_xz P_zz^-1
                for c in range(3):
                    K[a, c] = Pxz[a, 0] * Sinv[0, c] + Pxz[a, 1] * Sinv[1, c] + Pxz[a, 2] * Sinv[2, c]
            if o.heading_free:
                nz = math.sqrt(zx * zx + zy * zy + zz * zz)
                hx, hy, hz = zx / nz, zy / nz, zz / nz
                _project_heading(K, 0, hx, hy, hz)
                if n > 3:
                    _project_heading(K, 3, hx, hy, hz)
                # P - K Pxz^T - Pxz K^T + K S K^T (the covariance of a general gain: `joseph`)
                joseph(P, K, Pxz, S, n, KS)
            else:
                for a in range(n):  # step 9: P - K P_zz K^T = P - P_xz K^T (upper triangle, mirrored)
                    for c in range(a, n):
                        v = P[a, c] - (Pxz[a, 0] * K[c, 0] + Pxz[a, 1] * K[c, 1] + Pxz[a, 2] * K[c, 2])
                        P[a, c] = v
                        P[c, a] = v
            yx, yy, yz = mx - zx, my - zy, mz - zz
            for a in range(n):
                dx[a] = K[a, 0] * yx + K[a, 1] * yy + K[a, 2] * yz
            qn4 = qnormalize(qmul((x[0], x[1], x[2], x[3]), qexp(dx[0], dx[1], dx[2], small)))  # step 9
            x[0], x[1], x[2], x[3] = qn4
            for j in range(3, n):
                x[j + 1] = x[j + 1] + dx[j]
            nis = _nis(yx, yy, yz, Sinv)
        else:
            skipped += 1
            if o.corr_s > 0.0:
                disturbance_turn(dist, dq, h, o, with_lag, rate)
        mag_used = False
        hi_used = False
        if use_mag and mag_ok[k + 1]:  # 9-D (ukf-bias): the gated heading-only update (`UKF.step`)
            mx, my, mz = mag[k + 1, 0], mag[k + 1, 1], mag[k + 1, 2]
            if math.isfinite(mx) and math.isfinite(my) and math.isfinite(mz):
                if test[1] == 0.0:  # 9-D: no scale test (`ScaleTest.stop`)
                    test[0], test[2] = 0.0, math.nan
                q4 = (x[0], x[1], x[2], x[3])
                usable, east, north, hi_used = mag_input(q4, mx, my, mz, magst, hist, o, h, hi_fit, hi_work)
                if usable:
                    r_mag = heading_variance(q4, wx * h, wy * h, wz * h, h, o)
                    heading_update(P, n, n, q4, east, north, r_mag, Km, Gm, dx)
                    qn4 = qnormalize(qmul(q4, qexp(dx[0], dx[1], dx[2], small)))
                    x[0], x[1], x[2], x[3] = qn4
                    for j in range(3, n):
                        x[j + 1] = x[j + 1] + dx[j]
                    mag_used = True
        # Wald's test on the scale (`_attitude.ScaleTest`, as in `ekf_kernel`)
        if o.scale_test_axes and test[0] == 1.0 and test[1] == 0.0:
            q4 = (x[0], x[1], x[2], x[3])
            if scale_test(P, x[7:10], test, q4, o, n, K, Pxz, S, Sinv, KS, dx):
                x[0], x[1], x[2], x[3] = qnormalize(qmul(q4, qexp(dx[0], dx[1], dx[2], small)))
                for j in range(3, n):
                    x[j + 1] = x[j + 1] + dx[j]
        if n > 3:
            for i in range(4, 7):
                x[i] = _clip(x[i], -o.bias_max, o.bias_max)
        if n > 6:
            for i in range(7, 10):
                x[i] = _clip(x[i], -o.scale_max, o.scale_max)
        if repair_covariance(P, n, o, L):
            repaired += 1
        out_q[k + 1, :] = x[:4]
        out_cov[k + 1, :, :] = P
        if n > 3:
            out_b[k + 1, :] = x[4:7]
        if n > 6:
            out_s[k + 1, :] = x[7:10]
        out_iter[k + 1] = iters
        out_var[k + 1] = var
        out_rest[k + 1] = at_rest
        out_nis[k + 1] = nis
        out_lowpassed[k + 1] = lowpassed
        out_mag[k + 1] = mag_used
        out_hi[k + 1] = hi_used
        out_llr[k + 1] = test[2]
    return skipped, sqrt_recovered, repaired, capped
