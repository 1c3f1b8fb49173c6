"""Batch quaternion algebra on raw scalar-first arrays.

Quaternions are `(..., 4)` arrays `[w, x, y, z]` (Hamilton product, `R_world_body`
convention of STYLE.md). Everything here broadcasts over leading axes, so a whole
recording is one call.

Why not SciPy's `Rotation` everywhere? Conversions, slerp and scoring do use it. These
few functions exist for the inner loops of the filters and the smoother, where building a
`Rotation` object per call costs more than the arithmetic; `tests/test_quaternion.py`
cross-checks each one against SciPy.
"""
from __future__ import annotations

import numpy as np

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product `p * q`. p, q: (..., 4) wxyz, broadcast."""
    pw, px, py, pz = np.moveaxis(np.asarray(p, dtype=float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


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
    """Unit quaternion of a rotation vector: `exp([0, v / 2])`.

    rotvec: (..., 3) axis * angle, rad. Exact at zero angle (no division by |v|).
    """
    v = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    # sin(angle / 2) / angle, written with np.sinc (sin(pi x) / (pi x)) so it is 1/2 at 0.
    half_sinc = 0.5 * np.sinc(angle / (2.0 * np.pi))
    return np.concatenate([np.cos(0.5 * angle), v * half_sinc], axis=-1)


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a unit quaternion: `2 log(q)`, shortest path, angle in [0, pi].

    q: (..., 4) wxyz; q and -q give the same result.
    """
    q = canonical(q)
    vec = q[..., 1:]
    s = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    # angle / s -> 2 / w as s -> 0; w >= 1/sqrt(2) there, so no division by zero.
    scale = np.divide(angle, s, out=2.0 / np.maximum(q[..., :1], 1e-300), where=s > 1e-12)
    return vec * scale


def relative_rotvec(q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """Body-frame rotation vector `e` with `q_to = q_from * exp(e / 2)`. (..., 4) -> (..., 3)."""
    return to_rotvec(multiply(conjugate(q_from), q_to))


def gravity_in_body(q: np.ndarray) -> np.ndarray:
    """World up `[0, 0, 1]` expressed in the body frame: `R(q)^T e_z`. q: (..., 4) -> (..., 3).

    This is what a resting accelerometer reads, in g.
    """
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), w * w - x * x - y * y + z * z], axis=-1
    )


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
