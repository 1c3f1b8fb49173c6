"""numba for the compiled filters (`ekf`, `ukf`, `ukf-bias`): how a kernel is compiled and cached,
and which numpy reference it mirrors.

`_jit` is `numba.njit` with the on-disk cache, IEEE division and the GIL released. `mirrors`
is `_jit` for a kernel that implements a numpy function or method: it records the reference's
dotted name in `REFERENCES`, and `tests/test_compiled.py` imports every reference and checks
that the kernel carries its name (a reader finds the kernel of `EKF._correct` as `_correct` in
`_compiled_ekf`, of `RestDetector.update` as `update` in `_compiled_rest`). A compiled module
lists the kernels without a reference of their own (explicit loops that the numpy side writes as
one matrix product, batch loops) in `HELPERS`; the test checks that the two lists cover every
kernel.

Cache: numba keys a cached function on its own source file alone. A kernel is compiled together
with the functions it calls and the module constants it reads (the packed states' offsets of
`_accel`, `_rest`, ...), which live in other files; `forget_stale` drops a module's cache when any
file of the family (`KERNEL_SOURCES`) changes (`_kernel_cache.forget_stale_kernels`). The cache
lies next to the module (`__pycache__`); if that folder is not writable, numba's user-wide cache
folder; `NUMBA_CACHE_DIR` overrides both. If no folder is writable the kernels are compiled in
every process (a warning says so) and still run.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numba
import numpy as np

from fusion import quaternion as quat

from ._kernel_cache import forget_stale_kernels

# The files whose contents the filters' kernels are compiled from: the compiled modules, the numpy
# modules whose functions or constants they compile in, and `fusion.quaternion`.
_HERE = Path(__file__).parent  # estimators/kernels/
_FILTERS, _STEPS = _HERE.parent / "filters", _HERE.parent / "filters" / "steps"
KERNEL_SOURCES = [str(folder / f"{name}.py") for folder, names in (
    (_HERE, ("_numba", "_compiled_quaternion", "_compiled_linalg", "_linalg")),
    (_STEPS, ("_compiled_accel", "_compiled_rest", "_compiled_stuck", "_compiled_magnetometer", "_compiled_scale_test",
              "_accel", "_rest", "_stuck", "_magnetometer", "_scale_test", "_error_state")),
    (_FILTERS, ("_compiled_ekf", "_compiled_ukf"))) for name in names] + [quat.__file__]

# The kernels' numpy references: (compiled module, kernel name) -> the reference's dotted name.
REFERENCES: dict[tuple[str, str], str] = {}

# No numpy reference of their own: the per-step reading of `RecursiveEstimator.estimate`'s loop,
# and `np.clip` for one float.
HELPERS = ("_sample", "_clip")


def forget_stale(module_file: str) -> None:
    """Drop the in-tree cache of the compiled module at `module_file` when a file of
    `KERNEL_SOURCES` changed since it was written."""
    forget_stale_kernels(module_file, KERNEL_SOURCES)


forget_stale(__file__)

_OPTIONS = dict(error_model="numpy", nogil=True)
_cache = True  # False once numba has found no writable cache folder


def _jit(func, leaf: bool = False):
    """`numba.njit` with the on-disk cache, IEEE division (`error_model="numpy"`: x / 0 is inf
    or nan as in numpy, never an exception) and the GIL released. Without a writable cache
    folder (numba raises at decoration), one warning and no cache.

    `leaf`: a kernel that allocates no array (the small kernels a filter's loop calls every step),
    compiled without numba's reference counting (`_nrt=False`): numba otherwise counts every array
    argument on entry and exit, an atomic increment and decrement each, a tenth of a filter's time.
    The arithmetic is the same; a leaf that tried to allocate would not compile."""
    global _cache
    options = dict(_OPTIONS, _nrt=False) if leaf else _OPTIONS
    if _cache:
        try:
            return numba.njit(cache=True, **options)(func)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            _cache = False
            warnings.warn(f"fusion.estimators: the compiled filters cannot be cached ({exc}); they are "
                          "compiled in every process. Set NUMBA_CACHE_DIR to a writable folder to cache them.",
                          RuntimeWarning, stacklevel=2)
    return numba.njit(**options)(func)


def _jit_leaf(func):
    """`_jit` for a kernel that allocates nothing (`leaf`)."""
    return _jit(func, leaf=True)


def mirrors(reference: str, leaf: bool = False) -> Callable:
    """Decorator: `_jit` for a kernel that implements `reference` (a dotted name, e.g.
    "fusion.estimators.filters.ekf.EKF._correct"), recorded in `REFERENCES` (leaf: see `_jit`)."""
    def decorate(func):
        REFERENCES[(func.__module__, func.__name__)] = reference
        return _jit(func, leaf)
    return decorate


def compiled(func: Callable, module: str):
    """A numpy reference function compiled as it is (one definition for both sides), recorded in
    `REFERENCES` as the kernel of that name in `module`."""
    REFERENCES[(module, func.__name__)] = f"{func.__module__}.{func.__qualname__}"
    return _jit(func)


@_jit
def _clip(x, lo, hi):
    """np.clip for one float (nan passes through)."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@_jit_leaf
def _sample(gyr, valid, acc, k):
    """Step k's gyro reading, the accelerometer sample at its end, and whether the gyro is usable
    (marked valid and finite)."""
    gx, gy, gz = gyr[k, 0], gyr[k, 1], gyr[k, 2]
    ok = valid[k] and math.isfinite(gx) and math.isfinite(gy) and math.isfinite(gz)
    return gx, gy, gz, acc[k + 1, 0], acc[k + 1, 1], acc[k + 1, 2], ok


class Inputs(NamedTuple):
    """A recording as the kernels read it (writable C arrays: one compiled signature for all)."""

    gyr: np.ndarray  # (N-1, 3) the interval rates, rad/s, body (`ImuSamples.interval_rates`)
    valid: np.ndarray  # (N-1,) bool: the interval's gyro reading may be integrated
    dt: np.ndarray  # (N-1,) the steps, s
    acc: np.ndarray  # (N, 3) g, body
    mag: np.ndarray  # (N, 3) uT, body, or (0, 3): no magnetometer (6-D)
    mag_ok: np.ndarray  # (N,) bool, or (0,)


def inputs(imu: Any, use_mag: bool = False) -> Inputs:
    """The `Inputs` of `imu` (`ImuSamples`) as the base class's loop reads them; the magnetometer
    when `use_mag` (a 9-D filter) and the recording has one, else none."""
    gyr, valid = imu.interval_rates()
    if use_mag and imu.has_mag:
        mag, mag_ok = np.array(imu.mag_ut, dtype=float, order="C"), np.array(imu.mag_valid, dtype=bool)
    else:
        mag, mag_ok = np.zeros((0, 3)), np.zeros(0, dtype=bool)
    return Inputs(gyr=np.ascontiguousarray(gyr, dtype=float), valid=np.ascontiguousarray(valid, dtype=bool),
                  dt=np.ascontiguousarray(imu.dt, dtype=float), acc=np.array(imu.acc_g, dtype=float, order="C"),
                  mag=mag, mag_ok=mag_ok)
