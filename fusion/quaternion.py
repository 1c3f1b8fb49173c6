"""The rotation module: quaternion and SO(3) algebra on raw scalar-first arrays.

Quaternions are `[w, x, y, z]` (Hamilton product) and describe `R_world_body` (body vectors
into the world frame, world z up); rotation vectors are axis * angle in rad; perturbations are
on the right (body frame), `q_true = q * exp(e / 2)`. Product, exponential and logarithm as in Sola 2017 ("Quaternion
kinematics for the error-state Kalman filter", arXiv:1711.02508, Secs. 1.2.2, 1.3.4 and 1.3.6);
the SO(3) Jacobians as in Sola, Deray & Atchuthan 2018 ("A micro Lie theory for state
estimation in robotics", arXiv:1812.01537, eqs. 143-146).

Two paths, one definition of each operation:

* **batch path** (`multiply`, `from_rotvec`, `to_rotvec`, `gravity_in_body`,
  `rotation_matrix`, `skew`, `right_jacobian`, `right_jacobian_inv`, ...): `(..., 4)` /
  `(..., 3)` arrays, broadcasting over leading axes, so a whole recording is one call. Used by
  the smoothers, dead reckoning, the UKF's sigma points and the scoring.
* **scalar path** (`*_floats`, `left_matrix`, `right_matrix`): one quaternion as plain Python
  floats, for the recursive filters' inner loops, where building an array per call costs more
  than the arithmetic. `left_matrix(q) @ p == q * p` turns "one quaternion times a batch" into
  one matmul.

Small-angle rules (one each, shared by both paths):

* exp: `sin(a / 2) / a` is taken as exactly 1/2 for `a <= SMALL_ANGLE` (1e-12 rad); the next
  Taylor term, a^2 / 48, is then below 1e-25, far under the rounding of 1/2.
* log: `2 atan2(s, |w|) / s` (s = |vector part|) with no special case: for small s,
  atan2(s, |w|) = s / |w| in floating point, so the quotient is its limit 2 / |w| to rounding;
  s is floored at 1e-300 only so that s = 0 (where the vector part is 0) gives 0, not 0/0.
  The sign of w is folded in, so q and -q give the same rotation vector, of angle in [0, pi].
* SO(3) Jacobians: the closed forms above `JACOBIAN_SERIES_RAD` (1e-3 rad), their Taylor series
  (three terms, error below 1e-19) below it, where the closed forms lose digits to cancellation.

Conversions and slerp use SciPy's `Rotation` (the scoring uses the batch path: SciPy's products
are some 15x slower on whole recordings); `tests/test_quaternion.py` cross-checks
every function here against SciPy and the scalar path against the batch path.
"""
from __future__ import annotations

import math

import numpy as np

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
SMALL_ANGLE = 1e-12  # rad: below it exp uses its limit (see the module docstring)
JACOBIAN_SERIES_RAD = 1e-3  # rad: below it the SO(3) Jacobians use their Taylor series


# ============================================================================ batch path
def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product `p * q`. p, q: (..., 4) wxyz, broadcast (`multiply_floats` on the components)."""
    return np.stack(multiply_floats(_parts(p), _parts(q)), axis=-1)


def _parts(q: np.ndarray) -> tuple[np.ndarray, ...]:
    """The four components of (..., 4) quaternions, each (...,): the scalar path's functions take
    them as they take four floats, and so run on whole arrays."""
    q = np.asarray(q, dtype=float)
    return q[..., 0], q[..., 1], q[..., 2], q[..., 3]


def conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion). q: (..., 4) wxyz."""
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def normalize(q: np.ndarray) -> np.ndarray:
    """Scale to unit norm. q: (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def canonical(q: np.ndarray) -> np.ndarray:
    """Pick the representative with w >= 0 (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=float)
    return np.where(q[..., :1] < 0.0, -q, q)


def from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """exp: unit quaternion `exp([0, v / 2])` of rotation vectors. (..., 3) rad -> (..., 4).

    Exact at zero angle (the exp rule of the module docstring: no division by |v|); `exp_floats`
    on the components.
    """
    v = np.asarray(rotvec, dtype=float)
    return np.stack(exp_floats(v[..., 0], v[..., 1], v[..., 2]), axis=-1)


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """log: rotation vectors `2 log(q)` of unit quaternions, shortest path. (..., 4) -> (..., 3) rad.

    Angle in [0, pi]; q and -q give the same result (the log rule of the module docstring);
    `log_floats` on the components.
    """
    return np.stack(log_floats(_parts(q)), axis=-1)


def relative_rotvec(q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """Body-frame rotation vector `e` with `q_to = q_from * exp(e / 2)`. (..., 4) -> (..., 3)."""
    return to_rotvec(multiply(conjugate(q_from), q_to))


# g_j(q) = q^T G_j q for the three components of R(q)^T e_z: one matmul and one einsum.
_GRAVITY_FORMS = np.zeros((4, 3, 4))
_GRAVITY_FORMS[[3, 1, 2, 0], 0, [1, 3, 0, 2]] = [1.0, 1.0, -1.0, -1.0]  # 2 (xz - wy)
_GRAVITY_FORMS[[3, 2, 1, 0], 1, [2, 3, 0, 1]] = 1.0  # 2 (yz + wx)
_GRAVITY_FORMS[[0, 1, 2, 3], 2, [0, 1, 2, 3]] = [1.0, -1.0, -1.0, 1.0]  # w^2 - x^2 - y^2 + z^2
_GRAVITY_FORMS = _GRAVITY_FORMS.reshape(4, 12)


# `gravity_in_body` takes long stacks in blocks of this many rows: one matrix product over a whole
# recording makes OpenBLAS wake a worker thread, which then spins for about 0.1 s of CPU time after
# the call; below 65,536 * 4 multiply-adds (rows * 12 * 4) it stays on the calling thread.
GRAVITY_ROWS = 4096


def gravity_in_body(q: np.ndarray) -> np.ndarray:
    """World up `[0, 0, 1]` in the body frame, `R(q)^T e_z`. q: (..., 4) unit -> (..., 3).

    This is what a resting accelerometer reads, in g. Each row is its own: the blocks of
    `GRAVITY_ROWS` give the numbers of one product, bit for bit.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 2 and len(q) > GRAVITY_ROWS:
        return np.concatenate([gravity_in_body(q[i:i + GRAVITY_ROWS]) for i in range(0, len(q), GRAVITY_ROWS)])
    forms = (q @ _GRAVITY_FORMS).reshape(q.shape[:-1] + (3, 4))
    return np.einsum("...jk,...k->...j", forms, q)


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """R(q), (..., 4) unit wxyz -> (..., 3, 3) (maps body to world; `rotation_floats` on the components)."""
    q = np.asarray(q, dtype=float)
    return np.stack(rotation_floats(_parts(q)), axis=-1).reshape(q.shape[:-1] + (3, 3))


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices `[v]x`: `skew(a) @ b = a x b`."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _series(theta: np.ndarray, exact, coeffs: tuple[float, ...]) -> np.ndarray:
    """exact(theta) where theta > JACOBIAN_SERIES_RAD, else the Taylor series sum c_i theta^(2i)."""
    t2 = theta * theta
    approx = np.zeros_like(theta)
    for c in reversed(coeffs):
        approx = approx * t2 + c
    big = theta > JACOBIAN_SERIES_RAD
    return np.where(big, exact(np.where(big, theta, 1.0)), approx)


# Coefficients of J_r = I - A [phi]x + B [phi]x^2 and J_r^-1 = I + [phi]x / 2 + C [phi]x^2, as
# series in theta^2 (Sola et al. 2018, eqs. 143-146).
_A = (lambda t: (1.0 - np.cos(t)) / t**2, (1 / 2, -1 / 24, 1 / 720))
_B = (lambda t: (t - np.sin(t)) / t**3, (1 / 6, -1 / 120, 1 / 5040))
_C = (lambda t: 1.0 / t**2 - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t)), (1 / 12, 1 / 720, 1 / 30240))


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3) right Jacobian, (..., 3) -> (..., 3, 3): Exp(phi + d) ~ Exp(phi) Exp(J_r(phi) d).

    Sola et al. 2018, eq. 143. A rate error dw over a step moves its end attitude by
    J_r(w dt) dw dt in the body frame.
    """
    phi = np.asarray(phi, dtype=float)
    th = np.linalg.norm(phi, axis=-1)
    S = skew(phi)
    return np.eye(3) - _series(th, *_A)[..., None, None] * S + _series(th, *_B)[..., None, None] * (S @ S)


def right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """J_r^-1(phi): Log(Exp(phi) Exp(d)) ~ phi + J_r^-1(phi) d. Sola et al. 2018, eq. 144.

    The left one is J_l^-1(phi) = J_r^-1(-phi).
    """
    phi = np.asarray(phi, dtype=float)
    th = np.linalg.norm(phi, axis=-1)
    S = skew(phi)
    return np.eye(3) + 0.5 * S + _series(th, *_C)[..., None, None] * (S @ S)


def retract(q: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """`q * exp([0, delta / 2])`, renormalised. q: (..., 4), delta: (..., 3) rad, body frame."""
    return normalize(multiply(q, from_rotvec(delta)))


def cumulative_product(q: np.ndarray) -> np.ndarray:
    """Running products `q_0, q_0 q_1, q_0 q_1 q_2, ...` of (N, 4) unit quaternions.

    A Hillis-Steele scan: ceil(log2 N) vectorised passes instead of N Python steps.
    The product is associative, so the result equals the sequential loop up to rounding;
    rows are re-normalised after each pass.
    """
    out = np.array(q, dtype=float, copy=True)
    shift = 1
    while shift < len(out):
        out[shift:] = normalize(multiply(out[:-shift], out[shift:]))
        shift *= 2
    return out


# ============================================================================ scalar path
Floats4 = tuple[float, float, float, float]


def multiply_floats(a: tuple, b: tuple) -> Floats4:
    """Hamilton product `a * b` of two quaternions given as 4 floats each (or 4 arrays each:
    `multiply` calls it so; the compiled kernels compile it)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def exp_floats(vx: float, vy: float, vz: float, small: float = SMALL_ANGLE) -> Floats4:
    """`exp([0, v / 2])` of one rotation vector v (rad), as four floats (or of arrays of them:
    `from_rotvec` calls it so; the compiled kernels compile it). The exp rule without a branch:
    below `small` (`SMALL_ANGLE`, an argument so that the kernels take it as their other
    constants) the angle in the ratio is `small` itself, where sin(a / 2) / a is 1/2 exactly."""
    angle = np.sqrt(vx * vx + vy * vy + vz * vz)
    floor = np.maximum(angle, small)
    ratio = np.sin(0.5 * floor) / floor
    return np.cos(0.5 * angle), vx * ratio, vy * ratio, vz * ratio


def log_floats(q: tuple) -> tuple[float, float, float]:
    """`2 log(q)`: the rotation vector (rad) of one quaternion given as 4 floats (or 4 arrays:
    `to_rotvec` calls it so; the compiled kernels compile it), shortest path, q and -q alike
    (the log rule)."""
    w, x, y, z = q
    s = np.sqrt(x * x + y * y + z * z)
    scale = np.copysign(2.0 * np.arctan2(s, np.abs(w)) / np.maximum(s, 1e-300), w)
    return x * scale, y * scale, z * scale


def normalize_floats(q: tuple) -> Floats4:
    """A quaternion given as 4 floats, scaled to unit norm."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return w / n, x / n, y / n, z / n


def unit_array(q: tuple) -> np.ndarray:
    """(4,) array of a quaternion given as floats, renormalised."""
    return np.array(normalize_floats(q))


def rotation_floats(q: tuple) -> tuple:
    """The nine entries of R(q), row by row, of a unit quaternion given as 4 floats (or 4 arrays:
    `rotation_matrix` calls it so; the compiled kernels compile it)."""
    w, x, y, z = q
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def rotate_floats(q: tuple, v: tuple) -> tuple[float, float, float]:
    """`R(q) v` for a unit quaternion q (4 floats) and a vector v (3 floats): body -> world."""
    r = rotation_floats(q)
    a, b, c = v
    return r[0] * a + r[1] * b + r[2] * c, r[3] * a + r[4] * b + r[5] * c, r[6] * a + r[7] * b + r[8] * c


def gravity_floats(q: tuple) -> tuple[float, float, float]:
    """`R(q)^T e_z`, world up in the body frame, of a unit quaternion given as 4 floats (the
    compiled kernels compile it)."""
    w, x, y, z = q
    return 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z


def gravity_in_body_floats(w: float, x: float, y: float, z: float) -> np.ndarray:
    """(3,) `R(q)^T e_z` of one unit quaternion, g (the scalar path of `gravity_in_body`)."""
    return np.array(gravity_floats((w, x, y, z)))


def rotation_matrix_floats(w: float, x: float, y: float, z: float) -> np.ndarray:
    """(3, 3) R(q) of one unit quaternion (the scalar path of `rotation_matrix`)."""
    return np.array(rotation_floats((w, x, y, z))).reshape(3, 3)


def skew_floats(x: float, y: float, z: float) -> np.ndarray:
    """(3, 3) `[v]x` of one vector (the scalar path of `skew`)."""
    return np.array(((0.0, -z, y), (z, 0.0, -x), (-y, x, 0.0)))


def _series_float(t: float, exact, coeffs: tuple[float, ...]) -> float:
    if t > JACOBIAN_SERIES_RAD:
        return float(exact(t))
    t2, acc = t * t, 0.0
    for c in reversed(coeffs):
        acc = acc * t2 + c
    return acc


def right_jacobian_floats(tx: float, ty: float, tz: float) -> np.ndarray:
    """(3, 3) SO(3) right Jacobian of one rotation vector (the scalar path of `right_jacobian`)."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    S = skew_floats(tx, ty, tz)
    a = _series_float(t, lambda u: (1.0 - math.cos(u)) / (u * u), _A[1])
    b = _series_float(t, lambda u: (u - math.sin(u)) / (u * u * u), _B[1])
    return np.eye(3) - a * S + b * (S @ S)


def left_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """4x4 matrix `M` with `q * p = M @ p` for q = [w, x, y, z] (left multiplication).

    `batch @ left_matrix(*q).T` is `q * batch` row-wise, one matmul.
    """
    return np.array(((w, -x, -y, -z), (x, w, -z, y), (y, z, w, -x), (z, -y, x, w)))


def right_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """4x4 matrix `M` with `p * q = M @ p` for q = [w, x, y, z] (right multiplication)."""
    return np.array(((w, -x, -y, -z), (x, w, z, -y), (y, -z, w, x), (z, y, -x, w)))
