"""`_linalg` compiled, and the small matrix products the kernels share.

`inv_sym3`, `sqrt_psd` and `repair_covariance` are the kernels of `_linalg`'s functions of the same
names, on preallocated arrays (the result into an output argument). The others have no numpy
reference of their own: `cholesky` is LAPACK's dpotrf (Golub & Van Loan 2013, Alg. 4.2.1), which
`_linalg` calls; `joseph` and `joseph2` are the Joseph-form covariance update
`(I - K H) P (I - K H)^T + K R K^T` (Sola 2017, "Quaternion kinematics for the error-state Kalman
filter", Sec. 6.1-6.3) expanded for a symmetric P, which the numpy steps write as matrix
products; `_nis` and `_project_heading` are one line each in the numpy steps.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ._linalg import COV_FLOOR, COV_RESET_VAR, SQRT_FLOOR
from ._numba import _jit, _jit_leaf, forget_stale, mirrors

forget_stale(__file__)

HELPERS = ("cholesky", "joseph", "joseph2", "_nis", "_project_heading")


class KalmanUpdateWork(NamedTuple):
    """The work arrays of a Kalman update in the kernels (the rest update, the scale test, `ekf`'s
    velocity model), allocated once per run by the filter's loop: N rows of the error state."""

    K: np.ndarray  # (N, 3) the gain
    dx: np.ndarray  # (N,) the correction
    S: np.ndarray  # (3, 3) the innovation covariance
    Sinv: np.ndarray  # (3, 3) its inverse
    PHt: np.ndarray  # (N, 3) P H^T
    D: np.ndarray  # (N, 3) the Joseph form's scratch


class CovSettings(NamedTuple):
    """`_linalg`'s recovery constants, read at run time."""

    floor: float  # COV_FLOOR
    reset: float  # COV_RESET_VAR
    sqrt_floor: float  # SQRT_FLOOR


def cov_settings() -> CovSettings:
    return CovSettings(floor=float(COV_FLOOR), reset=float(COV_RESET_VAR), sqrt_floor=float(SQRT_FLOOR))


@mirrors("fusion.estimators.kernels._linalg.inv_sym3", leaf=True)
def inv_sym3(S, out):
    """Inverse of a symmetric 3x3 matrix by its adjugate, from its upper triangle (`_linalg.inv_sym3`);
    -> its determinant."""
    a, b, c, d, e, f = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * A + b * B + c * C
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    out[0, 0], out[0, 1], out[0, 2] = A / det, B / det, C / det
    out[1, 0], out[1, 1], out[1, 2] = B / det, D / det, E / det
    out[2, 0], out[2, 1], out[2, 2] = C / det, E / det, F / det
    return det


@_jit_leaf
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


@mirrors("fusion.estimators.kernels._linalg.sqrt_psd")
def sqrt_psd(A, L, n, floor):
    """L with L L^T = A (`_linalg.sqrt_psd`): Cholesky, else the clipped eigen-decomposition
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


@mirrors("fusion.estimators.kernels._linalg.repair_covariance")
def repair_covariance(P, n, o, L):
    """In place, `_linalg.repair_covariance`: symmetrise; a non-finite P becomes o.reset * I;
    a P that is not positive definite gets its eigenvalues clipped to o.floor. -> repaired."""
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
                P[i, j] = o.reset if i == j else 0.0
        return True
    if cholesky(P, L, n):
        return False
    lam, vec = np.linalg.eigh(P.copy())
    for j in range(n):
        if lam[j] < o.floor:
            lam[j] = o.floor
    for a in range(n):
        for b in range(n):
            v = 0.0
            for j in range(n):
                v += vec[a, j] * lam[j] * vec[b, j]
            P[a, b] = v
    return True


@_jit_leaf
def joseph(P, K, PHt, S, n, D):
    """P <- (I - K H) P (I - K H)^T + K R K^T for a measurement of up to three rows (the Joseph
    form of `ekf`, `EKF._velocity_step` and `_rest.bias_rest_update`), any gain K (n x 3),
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


@_jit_leaf
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


@_jit_leaf
def _nis(yx, yy, yz, Sinv):
    """y^T S^-1 y, as (y @ Sinv) @ y."""
    t0 = yx * Sinv[0, 0] + yy * Sinv[1, 0] + yz * Sinv[2, 0]
    t1 = yx * Sinv[0, 1] + yy * Sinv[1, 1] + yz * Sinv[2, 1]
    t2 = yx * Sinv[0, 2] + yy * Sinv[1, 2] + yz * Sinv[2, 2]
    return t0 * yx + t1 * yy + t2 * yz


@_jit_leaf
def _project_heading(K, row0, hx, hy, hz):
    """K[row0:row0+3] <- (I - h h^T) K[row0:row0+3]: no correction about the vertical h."""
    for j in range(K.shape[1]):
        hk = hx * K[row0, j] + hy * K[row0 + 1, j] + hz * K[row0 + 2, j]
        K[row0, j] -= hx * hk
        K[row0 + 1, j] -= hy * hk
        K[row0 + 2, j] -= hz * hk
