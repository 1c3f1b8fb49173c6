"""Test-only helpers for the smoother tests."""
from __future__ import annotations

import numpy as np


def dense_normal_matrix(lin) -> np.ndarray:
    """The Gauss-Newton matrix of a `smoothers.cost.Linearization` as one dense symmetric array:
    (B T + P) square, sample blocks first (B = 3, or 5 with velocities), calibration last."""
    T, B = lin.diag.shape[:2]
    P = lin.cross.shape[2]
    H = np.zeros((B * T + P, B * T + P))
    for t in range(T):
        H[B * t:B * t + B, B * t:B * t + B] = lin.diag[t]
        H[B * t:B * t + B, B * T:] = lin.cross[t]
        if t < T - 1:
            H[B * t:B * t + B, B * t + B:B * t + 2 * B] = lin.off[t]
    H[B * T:, B * T:] = lin.theta_block
    return np.triu(H) + np.triu(H, 1).T
