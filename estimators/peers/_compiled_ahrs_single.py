"""Twins of the `ahrs` package's single-sample attitude determinations, run on all samples at once:
OLEQ, FQA, TRIAD and FAMC compiled (numba), Davenport's q method, QUEST and FLAE batched in numpy.

What was chosen and why. Each of these methods of `ahrs` 0.4 loops its `estimate` over the samples in
Python: 80-300 us a sample through the library (`python benchmarks/bench_peers.py --more`). The
samples are independent, so a twin need only compute each sample's `estimate` as the library does,
over all samples in one call. Where the library's `estimate` is scalar arithmetic and small vector
products (OLEQ, FQA, TRIAD, FAMC), it is written out in scalars, one numba loop over the samples,
with `peers._compiled_ahrs`' helpers for numpy's rounding (`_norm3`, `_norm4`: `np.linalg.norm` as
BLAS `ddot`'s fused multiply-adds; `_square`: `x ** 2` of a float64 scalar; `_versor`, `_product`:
`ahrs.Quaternion`). Where it calls LAPACK (Davenport's `np.linalg.eig`, QUEST's `det` and `inv`,
FLAE's `det`, `inv`, `solve` and `eig`), numpy's own batched calls on the stack of all samples' matrices
run the same LAPACK routine on each matrix as the library's call on one: those three are written
in numpy over the stack, line by line, with each line's batched equivalent. Every function names the
library method it mirrors in its docstring's first line.

How close. The methods are not recursive, so a rounding difference would stay a rounding
difference; but the twins round as numpy does on the library's scalars and small arrays, and agree
with the library bit for bit on the shared recordings (for the OpenBLAS build they were read from, as
`peers._compiled_ahrs`): their products with a matrix as OpenBLAS's `dgemv` and `dgemm` order their
fused multiply-adds for these shapes (read off by comparing bit for bit), a norm as BLAS `ddot`, a
power `x ** p` of a float64 as the C library's `pow` (`_powers`: numpy's array power rounds
otherwise in the last bit), and the batched twins keep each matrix's memory layout where it decides
which BLAS call numpy makes (FLAE's `H`). `tests/test_compiled_peers.py` checks every twin against
the library to 1e-9.

Inputs, as `peers.ahrs_single.SingleSampleEstimator.solve` passes them to its `_solve`: acc (M, 3)
m/s^2 and mag (M, 3) mT, both non-zero and finite (the adapter's usable samples); each twin
returns (M, 4), the library's quaternion of each sample in its own convention (the adapter turns it
into ENU), NaN rows where the library itself would fail.
"""
from __future__ import annotations

import math

import numpy as np

from fusion import quaternion as quat

from ..kernels._kernel_cache import forget_stale_kernels
from ..kernels._numba import _clip, _jit
from . import _compiled_ahrs, _compiled_ahrs_recursive
from ._compiled_ahrs import _fma, _norm3, _norm4, _product, _square, _versor
from ._compiled_ahrs_recursive import WW, _mat_vec4, _pow

# the kernels compile in `_compiled_ahrs`' helpers and ROLEQ's `WW`
forget_stale_kernels(__file__, [quat.__file__, _compiled_ahrs.__file__, _compiled_ahrs_recursive.__file__])


@_jit
def _sign(x):
    """`np.sign` of a float64: -1, 0 or 1 (NaN stays NaN)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0 if x == 0.0 else x


# ================================================================= ahrs.filters.OLEQ
@_jit
def oleq_estimate(ax, ay, az, mx, my, mz, a0, a1, a_ref, m_ref, start, R, Wm):
    """`ahrs.filters.OLEQ.estimate`: the eigenvector of W's largest eigenvalue by the power
    iteration q <- R q / |R q|, R = 1/2 (I + a_1 W_a + a_2 W_m) (Zhou et al. 2018, "Novel Optimal
    Linear Estimator of Quaternion from Gravity and Geomagnetic Vectors", eqs. 17-24), from the
    library's random start (np.random.random(4) - 0.5, normalised) until two iterates agree to 1e-8
    or after 21 steps. start: (4,) the draw; R, Wm: (4, 4) work."""
    a_norm = _norm3(ax, ay, az)
    m_norm = _norm3(mx, my, mz)
    WW(R, ax / a_norm, ay / a_norm, az / a_norm, a_ref[0], a_ref[1], a_ref[2])
    WW(Wm, mx / m_norm, my / m_norm, mz / m_norm, m_ref[0], m_ref[1], m_ref[2])
    for i in range(4):
        for j in range(4):
            R[i, j] = 0.5 * ((1.0 if i == j else 0.0) + (a0 * R[i, j] + a1 * Wm[i, j]))
    w, x, y, z = start[0] - 0.5, start[1] - 0.5, start[2] - 0.5, start[3] - 0.5
    n = _norm4(w, x, y, z)
    w, x, y, z = w / n, x / n, y / n, z / n
    lw, lx, ly, lz = 1.0, 0.0, 0.0, 0.0
    i = 0
    while _norm4(w - lw, x - lx, y - ly, z - lz) > 1e-08 and i <= 20:
        lw, lx, ly, lz = w, x, y, z
        w, x, y, z = _mat_vec4(R, lw, lx, ly, lz)
        n = _norm4(w, x, y, z)
        w, x, y, z = w / n, x / n, y / n, z / n
        i += 1
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def oleq_kernel(acc, mag, a0, a1, a_ref, m_ref, starts, out):
    """`oleq_estimate` on every sample; starts: (M, 4) the library's draws, in order."""
    R, Wm = np.empty((4, 4)), np.empty((4, 4))
    for k in range(acc.shape[0]):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = oleq_estimate(
            acc[k, 0], acc[k, 1], acc[k, 2], mag[k, 0], mag[k, 1], mag[k, 2], a0, a1, a_ref, m_ref, starts[k], R, Wm)


# ================================================================= ahrs.filters.FQA
@_jit
def _half_angle(s, c):
    """sign(s) sqrt((1 - c) / 2), sqrt((1 + c) / 2): the half angle's sine and cosine (Yun et al.
    2008, eqs. 25-26)."""
    return _sign(s) * math.sqrt((1.0 - c) / 2.0), math.sqrt((1.0 + c) / 2.0)


@_jit
def fqa_estimate(ax, ay, az, mx, my, mz, nx, ny):
    """`ahrs.filters.FQA.estimate`: the factored quaternion q_a (x) q_e (x) q_r of elevation, roll
    and azimuth from half angles (Yun, Bachmann & McGhee 2008, "A Simplified Quaternion-Based
    Algorithm for Orientation Estimation From Earth Gravity and Magnetic Field Measurements", IEEE
    TIM 57(3), eqs. 22-44). A zero magnetometer sample (the adapter's 6-D) returns q_e (x) q_r.
    nx, ny: the library's normalised horizontal reference direction `N`."""
    a_norm = _norm3(ax, ay, az)
    if a_norm == 0.0:
        return 1.0, 0.0, 0.0, 0.0
    a_x, a_y, a_z = ax / a_norm, ay / a_norm, az / a_norm
    s_theta = _clip(a_x, -1.0, 1.0)
    c_theta = math.sqrt(1.0 - _square(s_theta))
    s_theta_2, c_theta_2 = _half_angle(s_theta, c_theta)
    ew, ex, ey, ez = _versor(c_theta_2, 0.0, s_theta_2, 0.0)  # q_e
    singular = c_theta == 0.0
    s_phi = 0.0 if singular else -a_y / c_theta
    c_phi = 0.0 if singular else -a_z / c_theta
    c_phi = _clip(c_phi, -1.0, 1.0)
    sign_s_phi = _sign(s_phi)
    if c_phi == -1.0 and s_phi == 0.0:
        sign_s_phi = 1.0
    s_phi_2, c_phi_2 = sign_s_phi * math.sqrt((1.0 - c_phi) / 2.0), math.sqrt((1.0 + c_phi) / 2.0)
    rw, rx, ry, rz = _versor(c_phi_2, s_phi_2, 0.0, 0.0)  # q_r
    qw, qx, qy, qz = _versor(*_product(ew, ex, ey, ez, rw, rx, ry, rz))  # q_er = Quaternion(q_e * q_r)
    m_norm = _norm3(mx, my, mz)
    if m_norm == 0.0:
        return qw, qx, qy, qz
    bw, bx, by, bz = _versor(0.0, mx / m_norm, my / m_norm, mz / m_norm)  # Quaternion([0, *mag])
    cw, cx, cy, cz = _versor(rw, -rx, -ry, -rz)  # Quaternion(q_r.conj)
    t = _product(cw, cx, cy, cz, ew, -ex, -ey, -ez)  # ... .product(q_e.conj)
    t = _product(bw, bx, by, bz, t[0], t[1], t[2], t[3])
    t = _product(rw, rx, ry, rz, t[0], t[1], t[2], t[3])
    em = _product(ew, ex, ey, ez, t[0], t[1], t[2], t[3])  # the field in the levelled frame (eq. 37)
    n = math.sqrt(_fma(em[2], em[2], em[1] * em[1]))
    Mx, My = em[1] / n, em[2] / n
    c_psi = _fma(Mx, nx, My * ny)  # [[Mx, My], [-My, Mx]] @ N, as OpenBLAS's dgemv
    s_psi = _fma(-My, nx, Mx * ny)
    c_psi = _clip(c_psi, -1.0, 1.0)
    s_psi_2, c_psi_2 = _half_angle(s_psi, c_psi)
    aw, ax_, ay_, az_ = _versor(c_psi_2, 0.0, 0.0, s_psi_2)  # q_a
    return _versor(*_product(aw, ax_, ay_, az_, qw, qx, qy, qz))  # Quaternion(q_a * q_er)


@_jit
def fqa_kernel(acc, mag, nx, ny, out):
    """`fqa_estimate` on every sample (mag: zero rows for the accelerometer-only mode)."""
    for k in range(acc.shape[0]):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = fqa_estimate(
            acc[k, 0], acc[k, 1], acc[k, 2], mag[k, 0], mag[k, 1], mag[k, 2], nx, ny)


# ================================================================= ahrs.filters.TRIAD
@_jit
def _cross(a0, a1, a2, b0, b1, b2):
    """`np.cross` of two 3-vectors."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@_jit
def chiaverini(A):
    """`ahrs.common.orientation.chiaverini`: the quaternion of a rotation matrix from its
    diagonal, the signs from its off-diagonal elements (Chiaverini & Siciliano 1999). A: (3, 3)."""
    tr = (A[0, 0] + A[1, 1]) + A[2, 2]
    w = 0.5 * math.sqrt(_clip(tr, -1.0, 3.0) + 1.0)
    x = 0.5 * _sign(A[2, 1] - A[1, 2]) * math.sqrt(_clip(A[0, 0] - A[1, 1] - A[2, 2], -1.0, 3.0) + 1.0)
    y = 0.5 * _sign(A[0, 2] - A[2, 0]) * math.sqrt(_clip(A[1, 1] - A[2, 2] - A[0, 0], -1.0, 3.0) + 1.0)
    z = 0.5 * _sign(A[1, 0] - A[0, 1]) * math.sqrt(_clip(A[2, 2] - A[0, 0] - A[1, 1], -1.0, 3.0) + 1.0)
    if w == 0.0 and x == 0.0 and y == 0.0 and z == 0.0:
        w = 1.0
    n = _norm4(w, x, y, z)
    return w / n, x / n, y / n, z / n


@_jit
def triad_estimate(ax, ay, az, mx, my, mz, Mr, A):
    """`ahrs.filters.TRIAD.estimate` (representation "quaternion"): the attitude matrix
    A = M_b M_r^T of the two orthonormal triads (Black 1964, "A passive system for determining the
    attitude of a satellite", AIAA J. 2(7); Shuster & Oh 1981, eqs. 6-9), as a quaternion
    (`chiaverini`). Mr: (3, 3) the library's reference triad [v1, r2, r3] as columns; A: work."""
    n = _norm3(ax, ay, az)
    w1 = (ax / n, ay / n, az / n)
    n = _norm3(mx, my, mz)
    w2 = (mx / n, my / n, mz / n)
    c = _cross(w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])
    n = _norm3(c[0], c[1], c[2])
    s2 = (c[0] / n, c[1] / n, c[2] / n)
    d = _cross(w1[0], w1[1], w1[2], c[0], c[1], c[2])
    s3 = (d[0] / n, d[1] / n, d[2] / n)
    for i in range(3):  # Mb @ Mr.T, Mb = [w1, s2, s3] as columns, as OpenBLAS's dgemm rounds it
        for j in range(3):
            A[i, j] = _fma(s3[i], Mr[j, 2], _fma(s2[i], Mr[j, 1], w1[i] * Mr[j, 0]))
    return chiaverini(A)


@_jit
def triad_kernel(acc, mag, Mr, out):
    """`triad_estimate` on every sample."""
    A = np.empty((3, 3))
    for k in range(acc.shape[0]):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = triad_estimate(
            acc[k, 0], acc[k, 1], acc[k, 2], mag[k, 0], mag[k, 1], mag[k, 2], Mr, A)


# ================================================================= ahrs.filters.FAMC
@_jit
def famc_estimate(ax, ay, az, mx, my, mz):
    """`ahrs.filters.FAMC.estimate`: the quaternion in closed form from the attitude profile
    matrix B of the two normalised vectors, by Gaussian elimination on Davenport's matrix (Liu et al.
    2018, "Fast Accelerometer-Magnetometer Combination (FAMC) for attitude estimation", IEEE Sensors
    J. 18(3), eqs. 20-39, in the library's form)."""
    a_norm = _norm3(ax, ay, az)
    m_norm = _norm3(mx, my, mz)
    ax, ay, az = ax / a_norm, ay / a_norm, az / a_norm
    mx, my, mz = mx / m_norm, my / m_norm, mz / m_norm
    m_D = ax * mx + ay * my + az * mz
    m_N = math.sqrt(1.0 - _square(m_D))
    B00, B10, B20 = (m_N * mx) * 0.5, (m_N * my) * 0.5, (m_N * mz) * 0.5
    B02, B12, B22 = (m_D * mx + ax) * 0.5, (m_D * my + ay) * 0.5, (m_D * mz + az) * 0.5
    tau = B02 + B20
    alpha0 = B22 - B00 + 1.0
    Y00 = -1.0 / alpha0
    Y01 = B10 / alpha0
    Y02 = tau / alpha0
    alpha1 = -_square(B10) / alpha0 + B00 + B22 + 1
    Y10 = -B10 / (alpha0 * alpha1)
    Y11 = -1.0 / alpha1
    Y12 = (B12 + B10 * tau / alpha0) / alpha1
    alpha2 = alpha0 - 2 + _square(tau) / alpha0 + _square(Y12) * alpha1
    Y20 = (tau / alpha0 + B10 * Y12 / alpha0) / alpha2
    Y21 = Y12 / alpha2
    Y22 = 1.0 / alpha2
    a = B12 * (Y00 + Y01 * (Y12 * Y20 + Y10) + Y02 * Y20) - (B02 - B20) * (Y12 * Y20 + Y10) - Y20 * B10
    b = B12 * (Y01 * (Y12 * Y21 + Y11) + Y02 * Y21) - (B02 - B20) * (Y12 * Y21 + Y11) - Y21 * B10
    c = B12 * (Y01 * Y12 * Y22 + Y02 * Y22) - (B02 - B20) * (Y12 * Y22) - Y22 * B10
    n = _norm4(-1.0, a, b, c)
    return -1.0 / n, a / n, b / n, c / n


@_jit
def famc_kernel(acc, mag, out):
    """`famc_estimate` on every sample."""
    for k in range(acc.shape[0]):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = famc_estimate(
            acc[k, 0], acc[k, 1], acc[k, 2], mag[k, 0], mag[k, 1], mag[k, 2])


# ================================================================= batched in numpy
# numpy computes `x ** p` of a float64 scalar with the C library's `pow`, of an array with its own
# vectorised loops (which may differ in the last bit), and `np.linalg.norm(v)` of one vector as BLAS
# `ddot`: these helpers give the library's scalar results on every row.
@_jit
def _powers(x, p, out):
    """out[k] = x[k] ** p as numpy computes it for one float64 (`_compiled_ahrs_recursive._pow`)."""
    for k in range(x.shape[0]):
        out[k] = _pow(x[k], p)


def _pw(x: np.ndarray, p: float) -> np.ndarray:
    out = np.empty(len(x))
    _powers(np.ascontiguousarray(x, dtype=float), float(p), out)
    return out


@_jit
def _unit(x, out):
    """out[k] = x[k] / np.linalg.norm(x[k]) for rows of 3 or 4 (`_norm3`, `_norm4`)."""
    for k in range(x.shape[0]):
        if x.shape[1] == 3:
            n = _norm3(x[k, 0], x[k, 1], x[k, 2])
        else:
            n = _norm4(x[k, 0], x[k, 1], x[k, 2], x[k, 3])
        for i in range(x.shape[1]):
            out[k, i] = x[k, i] / n


def _unit_rows(x: np.ndarray) -> np.ndarray:
    out = np.empty(x.shape)
    _unit(np.ascontiguousarray(x, dtype=float), out)
    return out


def _each_matrix(func, *stacks, on_error):
    """`func(*stacks)` on the whole stack; where numpy raises `LinAlgError` (one singular matrix
    stops a batched call), `func` on each matrix alone, with `on_error(k)` where that matrix raises
    (as the library's own call on that sample would)."""
    try:
        return func(*stacks)
    except np.linalg.LinAlgError:
        rows = []
        for k in range(len(stacks[0])):
            try:
                rows.append(func(*(s[k:k + 1] for s in stacks))[0])
            except np.linalg.LinAlgError:
                rows.append(on_error(k))
        return np.array(rows)


def _outer(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(M, 3, 3) `np.outer(u[k], v)` for every row k of u (M, 3); v (3,)."""
    return u[:, :, None] * v[None, None, :]


def _profile(B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sigma, z, S) of a stack of attitude profile matrices B (M, 3, 3): `B.trace()`,
    `[B12 - B21, B20 - B02, B01 - B10]` and `B + B.T` (Davenport 1968; Shuster & Oh 1981, eqs. 10-12)."""
    sigma = (B[:, 0, 0] + B[:, 1, 1]) + B[:, 2, 2]
    z = np.ascontiguousarray(np.stack([B[:, 1, 2] - B[:, 2, 1], B[:, 2, 0] - B[:, 0, 2], B[:, 0, 1] - B[:, 1, 0]],
                                      axis=1))
    return sigma, z, np.ascontiguousarray(B + np.swapaxes(B, 1, 2))


def _largest_eigenvector(K: np.ndarray, normalise: bool) -> np.ndarray:
    """The eigenvector of each matrix's largest eigenvalue (`np.linalg.eig` over the stack), as
    `v[:, np.argmax(w)]` picks it (numpy orders complex eigenvalues by real, then imaginary part),
    divided by its norm where `normalise`; the real part (the adapter's, of a complex vector)."""
    def largest(K):
        w, v = np.linalg.eig(K)
        best = np.lexsort((np.imag(w), np.real(w)), axis=-1)[:, -1] if np.iscomplexobj(w) else np.argmax(w, axis=1)
        q = np.take_along_axis(v, best[:, None, None], axis=2)[:, :, 0]
        if normalise:
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
        return np.real(q)

    return _each_matrix(largest, K, on_error=lambda k: np.full(4, np.nan))


def davenport_estimate(filt, acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """`ahrs.filters.Davenport.estimate` on every row: the eigenvector of the largest eigenvalue of
    Davenport's K (Davenport 1968, "A vector approach to the algebra of rotations with applications",
    NASA TN D-4696; Shuster & Oh 1981, eqs. 10-14), with `np.linalg.eig` over the stack. filt: the
    library's `Davenport` (its weights, g_q and m_q); acc, mag (M, 3) as the library takes them."""
    B = filt.w[0] * _outer(acc, filt.g_q) + filt.w[1] * _outer(mag, filt.m_q)
    sigma, z, S = _profile(B)
    K = np.zeros((len(acc), 4, 4))
    K[:, 0, 0] = sigma
    K[:, 1:, 1:] = S - sigma[:, None, None] * np.eye(3)
    K[:, 0, 1:] = z
    K[:, 1:, 0] = z
    return _largest_eigenvector(K, normalise=False)


@_jit
def _gemv_c3(M, x0, x1, x2, i):
    """Element i of numpy's `M @ x` for a C-ordered (3, 3) M, rounded as OpenBLAS's `dgemv` (as
    `_compiled_ahrs.mahony_updateMARG`'s `R @ m`)."""
    return _fma(M[i, 2], x2, _fma(M[i, 0], x0, M[i, 1] * x1))


@_jit
def _quest_tail(sigma, z, S, Delta, inv, w_sum, out):
    """The rest of `ahrs.filters.QUEST.estimate` from `kappa` on, per row k (the determinant and inverse of S
    computed by numpy over the stack): kappa = tr(Delta S^-1); a, b, c, d, k of the characteristic
    polynomial; Newton's iteration from sum(w) (at least 11 steps, then until a step under 1e-8);
    gamma and chi = (alpha I + beta S + S^2) z; q = [gamma, chi] / |.| (Shuster & Oh 1981, eqs.
    63-71). Vector-matrix products rounded as numpy's (`z @ S`, `S @ S`: OpenBLAS's fused chains in
    index order; `M @ z`: `_gemv_c3`)."""
    zS, zSS, SS = np.empty(3), np.empty(3), np.empty((3, 3))
    for r in range(sigma.shape[0]):
        sg, D = sigma[r], Delta[r]
        z0, z1, z2 = z[r, 0], z[r, 1], z[r, 2]
        Sr = S[r]
        kappa = (D * inv[r, 0, 0] + D * inv[r, 1, 1]) + D * inv[r, 2, 2]
        a = _pow(sg, 2.0) - kappa
        b = _pow(sg, 2.0) + _fma(z2, z2, _fma(z1, z1, z0 * z0))
        for j in range(3):  # z @ S, (z @ S) @ S
            zS[j] = _fma(z2, Sr[2, j], _fma(z1, Sr[1, j], z0 * Sr[0, j]))
        for j in range(3):
            zSS[j] = _fma(zS[2], Sr[2, j], _fma(zS[1], Sr[1, j], zS[0] * Sr[0, j]))
        c = D + _fma(zS[2], z2, _fma(zS[1], z1, zS[0] * z0))
        d = _fma(zSS[2], z2, _fma(zSS[1], z1, zSS[0] * z0))
        k = a * b + c * sg - d
        l_max = l_old = w_sum
        n = 0
        while abs(l_old - l_max) > 1e-08 or n <= 10:
            l_old = l_max
            phi = _pow(l_max, 4.0) - (a + b) * _pow(l_max, 2.0) - c * l_max + k
            phi_prime = 4.0 * _pow(l_max, 3.0) - 2.0 * (a + b) * l_max - c
            l_max -= phi / phi_prime
            n += 1
        alpha = _pow(l_max, 2.0) - _pow(sg, 2.0) + kappa
        beta = l_max - sg
        gamma = (l_max + sg) * alpha - D
        for i in range(3):  # alpha I + beta S + S @ S
            for j in range(3):
                SS[i, j] = ((alpha * (1.0 if i == j else 0.0) + beta * Sr[i, j])
                            + _fma(Sr[i, 2], Sr[2, j], _fma(Sr[i, 1], Sr[1, j], Sr[i, 0] * Sr[0, j])))
        c0, c1, c2 = _gemv_c3(SS, z0, z1, z2, 0), _gemv_c3(SS, z0, z1, z2, 1), _gemv_c3(SS, z0, z1, z2, 2)
        nq = _norm4(gamma, c0, c1, c2)
        out[r, 0], out[r, 1], out[r, 2], out[r, 3] = gamma / nq, c0 / nq, c1 / nq, c2 / nq


def quest_estimate(filt, acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """`ahrs.filters.QUEST.estimate` on every row: the largest eigenvalue of Davenport's K by
    Newton's method on its characteristic polynomial from sum(w), then the optimal quaternion
    [gamma, chi] (Shuster & Oh 1981, "Three-axis attitude determination from vector observations",
    J. Guidance 4(1), eqs. 63-71): the determinant and inverse of S over the stack, the rest per row
    (`_quest_tail`). filt: the library's `QUEST` (its weights, g_q and m_q)."""
    B = filt.w[0] * _outer(_unit_rows(acc), filt.g_q) + filt.w[1] * _outer(_unit_rows(mag), filt.m_q)
    sigma, z, S = _profile(B)
    Delta = np.linalg.det(S)
    inv = _each_matrix(np.linalg.inv, S, on_error=lambda k: np.full((3, 3), np.nan))  # (the library raises there)
    out = np.empty((len(acc), 4))
    _quest_tail(np.ascontiguousarray(sigma), z, S, np.ascontiguousarray(Delta), np.ascontiguousarray(inv),
                        float(filt.w.sum()), out)
    return out


def _flae_W(H: np.ndarray) -> np.ndarray:
    """`FLAE._P1Hx(H[0]) + FLAE._P2Hy(H[1]) + FLAE._P3Hz(H[2])` for a stack H (M, 3, 3) (Wu et al.
    2018, eq. 10)."""
    Hx, Hy, Hz = H[:, 0], H[:, 1], H[:, 2]
    z = np.zeros(len(H))

    def m(rows):
        return np.stack([np.stack(r, axis=1) for r in rows], axis=1)

    P1 = m([[Hx[:, 0], z, -Hx[:, 2], Hx[:, 1]], [z, Hx[:, 0], Hx[:, 1], Hx[:, 2]],
            [-Hx[:, 2], Hx[:, 1], -Hx[:, 0], z], [Hx[:, 1], Hx[:, 2], z, -Hx[:, 0]]])
    P2 = m([[Hy[:, 1], Hy[:, 2], z, -Hy[:, 0]], [Hy[:, 2], -Hy[:, 1], Hy[:, 0], z],
            [z, Hy[:, 0], Hy[:, 1], Hy[:, 2]], [-Hy[:, 0], z, Hy[:, 2], -Hy[:, 1]]])
    P3 = m([[Hz[:, 2], -Hz[:, 1], Hz[:, 0], z], [-Hz[:, 1], -Hz[:, 2], z, Hz[:, 0]],
            [Hz[:, 0], z, -Hz[:, 2], Hz[:, 1]], [z, Hz[:, 0], Hz[:, 1], Hz[:, 2]]])
    return P1 + P2 + P3


def _real_sqrt(x: np.ndarray) -> np.ndarray:
    """`np.emath.sqrt(x).real` of each float: sqrt(x), 0 for x < 0 (the complex root's real part)."""
    with np.errstate(invalid="ignore"):
        return np.where(x < 0.0, 0.0, np.sqrt(x))


def flae_estimate(filt, acc: np.ndarray, mag: np.ndarray, method: str) -> np.ndarray:
    """`ahrs.filters.FLAE.estimate` on every row: the eigenvector of W's eigenvalue nearest 1,
    the eigenvalue from the quartic's closed form (`symbolic`), by Newton's method (`newton`) or
    `np.linalg.eig` (`eig`), the vector by solving (W - lambda I) q = 0 (Wu, Zhou, Fourati & Sheng
    2018, "Fast Linear Quaternion Attitude Estimator Using Vector Observations", IEEE T-ASE 15(1),
    eqs. 10-37). filt: the library's `FLAE` (its weights `a` and references `ref`)."""
    M = len(acc)
    Db = np.stack([_unit_rows(acc), _unit_rows(mag)], axis=1)  # (M, 2, 3)
    H = (filt.a * np.swapaxes(Db, 1, 2)) @ filt.ref  # (M, 3, 3); each (3, 2) factor F-ordered, as the library's
    W = _flae_W(H)
    if method == "eig":
        return _largest_eigenvector(W, normalise=True)
    t1 = -2 * np.trace(H @ np.swapaxes(H, 1, 2), axis1=1, axis2=2)
    t2 = -8 * np.linalg.det(np.swapaxes(H, 1, 2))
    t3 = np.linalg.det(W)
    if method == "newton":
        lam, lam_old = np.ones(M), np.zeros(M)
        going = np.ones(M, dtype=bool)
        i = 0
        while np.any(going):
            lam_old = np.where(going, lam, lam_old)
            f = _pw(lam, 4) + t1 * _pw(lam, 2) + t2 * lam + t3
            fp = 4 * _pw(lam, 3) + 2 * t1 * lam + t2
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = np.where(going, lam - f / fp, lam)
            i += 1
            going &= (np.abs(lam_old - lam) > 1e-08) & (i < 6)
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            T0 = 2 * _pw(t1, 3) + 27 * _pw(t2, 2) - 72 * t1 * t3
            u = _pw(t1, 2) + 12 * t3
            T1 = np.cbrt(T0 + _real_sqrt(-4 * _pw(u, 3) + _pw(T0, 2)))
            T2 = np.sqrt(abs(-4 * t1 + np.cbrt(16) * (_pw(t1, 2) + 12 * t3) / T1 + np.cbrt(4) * T1))
            L = np.empty((M, 4))
            s6 = np.sqrt(6)
            L[:, 0] = T2 - np.sqrt(abs(-_pw(T2, 2) - 12 * t1 - 12 * s6 * t2 / T2))
            L[:, 1] = T2 + np.sqrt(abs(-_pw(T2, 2) - 12 * t1 - 12 * s6 * t2 / T2))
            L[:, 2] = -(T2 + np.sqrt(abs(-_pw(T2, 2) - 12 * t1 + 12 * s6 * t2 / T2)))
            L[:, 3] = -(T2 - np.sqrt(abs(-_pw(T2, 2) - 12 * t1 + 12 * s6 * t2 / T2)))
            L *= 1.0 / (2.0 * np.sqrt(6))
        lam = np.take_along_axis(L, np.abs(L - 1.0).argmin(axis=1)[:, None], axis=1)[:, 0]
    N = W - lam[:, None, None] * np.identity(4)
    singular = np.zeros(M, dtype=bool)
    try:
        np.linalg.inv(N)
    except np.linalg.LinAlgError:  # the library returns [1, 0, 0, 0] where N is singular
        for k in range(M):
            try:
                np.linalg.inv(N[k])
            except np.linalg.LinAlgError:
                singular[k] = True
    r = _each_matrix(lambda A, b: np.linalg.solve(A, b[..., None])[..., 0], N[:, 1:, :-1], N[:, 1:, -1],
                     on_error=lambda k: np.full(3, np.nan))
    q = _unit_rows(np.column_stack([r, -np.ones(M)]))
    q[singular] = np.array([1.0, 0.0, 0.0, 0.0])
    return q


_loaded = False


def load() -> None:
    """Compile the kernels now, or load them from numba's cache (`peers._compiled_ahrs.load`)."""
    global _loaded
    if _loaded:
        return
    acc, mag = np.array([[0.0, 0.1, 9.8]]), np.array([[0.02, 0.0, -0.04]])
    out, ref = np.empty((1, 4)), np.array([0.0, 1.0, 0.0])
    oleq_kernel(acc, mag, 1.0, 1.0, np.array([0.0, 0.0, 1.0]), ref, np.full((1, 4), 0.3), out)
    fqa_kernel(acc, mag, 1.0, 0.0, out)
    triad_kernel(acc, mag, np.eye(3), out)
    famc_kernel(acc, mag, out)
    _powers(np.ones(1), 2.0, np.empty(1))
    _unit(acc, np.empty((1, 3)))
    _unit(out, np.empty((1, 4)))
    one = np.ones(1)
    _quest_tail(one, acc, np.ones((1, 3, 3)), one, np.ones((1, 3, 3)), 1.0, out)
    _loaded = True
