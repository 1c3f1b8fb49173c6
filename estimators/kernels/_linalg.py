"""Small dense linear algebra of one filter step (`ekf`, `ukf`, `ukf-bias`): the inverse of a
symmetric 3x3 matrix, a square root of a positive semi-definite matrix, and the repair that keeps
a covariance symmetric positive definite.

Contract: every function takes and returns numpy arrays of at most 11 x 11 float64 and never
modifies its input. `sqrt_psd` and `repair_covariance` say whether they had to recover (the
filters count it in their diagnostics). The constants here decide the recoveries and are read by
the compiled mirror, `_compiled_linalg`, at run time (`_compiled.settings`).

Everything here works on one filter step's tiny arrays, so it is written for low per-call
overhead: LAPACK's `dpotrf` directly (Golub & Van Loan, "Matrix Computations", 4th ed. 2013,
Alg. 4.2.1, the Cholesky factorisation) instead of `numpy.linalg`, and the adjugate for 3 x 3.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf

SQRT_FLOOR = 0.0  # eigenvalues of a failed square root are clipped to this (sqrt_psd)


COV_FLOOR = 1e-15  # eigenvalues of a repaired covariance are clipped to this (repair_covariance)


COV_RESET_VAR = 1e-2  # a non-finite covariance is replaced by this times I (repair_covariance)


def inv_sym3(s: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric 3x3 matrix by its adjugate (numpy.linalg.inv costs more here).

    The caller guarantees positive definiteness (a covariance plus R > 0).
    """
    (a, b, c), (_, d, e), (_, _, f) = s.tolist()
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    return np.array(((A, B, C), (B, D, E), (C, E, F))) / det


def sqrt_psd(a: np.ndarray) -> tuple[np.ndarray, bool]:
    """A square root `L` with `L @ L.T = a` for a symmetric positive semi-definite matrix.

    Cholesky first (fast). If it fails (a singular matrix, e.g. P = Q = 0 in the
    dead-reckoning test, or round-off pushed an eigenvalue below zero), the documented
    recovery: symmetrise, clip negative eigenvalues to zero and return `V sqrt(lambda)`,
    a square root of the nearest PSD matrix. Returns `(L, recovered)`.
    """
    c, info = dpotrf(a, lower=1, clean=1)  # LAPACK Cholesky, without numpy.linalg's overhead
    if info == 0:
        return c, False
    lam, vec = np.linalg.eigh(0.5 * (a + a.T))
    return vec * np.sqrt(np.maximum(lam, SQRT_FLOOR)), True


def repair_covariance(p: np.ndarray, floor: float = COV_FLOOR) -> tuple[np.ndarray, bool]:
    """Symmetrise `p`; if an eigenvalue is below `floor` (or not finite), clip it there.

    Returns `(p, repaired)`. Called after every update so that the covariance handed to
    the next step is symmetric positive definite (the SPD test checks it).
    """
    p = 0.5 * (p + p.T)
    if not math.isfinite(p.sum()):  # one reduction instead of an elementwise test
        return np.eye(len(p)) * COV_RESET_VAR, True
    # Cheap test first: a Cholesky succeeds exactly for SPD matrices.
    if dpotrf(p, lower=1)[1] == 0:
        return p, False
    lam, vec = np.linalg.eigh(p)
    return (vec * np.maximum(lam, floor)) @ vec.T, True
