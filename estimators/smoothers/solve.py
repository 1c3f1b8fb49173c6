"""The normal equations of the batch smoother's cost, solved in numpy: the reference solves.

A `Linearization` of `fusion.estimators.smoothers.cost` holds the Gauss-Newton matrix H as its
blocks: block-tridiagonal in the per-sample variables (B = 3 rotation + V velocity, each motion
residual touching two neighbours) with a dense border for the P calibration variables. Here it
is written to LAPACK's band storage (`banded_lower`) and solved in O(T) by a banded Cholesky
factorisation (`scipy.linalg.solveh_banded`, LAPACK pbsv; Golub & Van Loan 2013, "Matrix
Computations", 4th ed., sec. 4.3), the border as P further right-hand sides and then eliminated
by its Schur complement (ibid., sec. 3.2.10; Triggs et al. 2000, "Bundle adjustment - a modern
synthesis", sec. 6.1). `solve_normal_equations` gives `gn`'s damped Gauss-Newton step, the
Levenberg-Marquardt system (H + lambda diag(H)) x = -g (Marquardt 1963); `theta_posterior_std`
the calibration variables' posterior std, from the inverse of their Schur complement.

These are the references of the compiled elimination
(`fusion.estimators.smoothers._compiled_linearize`), which eliminates the same matrix block by
block in the linearisation's own pass.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import solveh_banded


def banded_lower(diag: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Block-tridiagonal symmetric matrix -> LAPACK lower band storage (2B, B T) for solveh_banded.

    diag: (T, B, B) blocks H[t, t]; off: (T-1, B, B) blocks H[t, t+1] (so H[t+1, t] = off^T).
    Entry H[r, c] (r >= c) goes to ab[r - c, c].
    """
    T, B = diag.shape[0], diag.shape[1]
    ab = np.zeros((2 * B, B * T))
    cols = B * np.arange(T)
    for i in range(B):
        for j in range(i + 1):
            ab[i - j, cols + j] = diag[:, i, j]
    cols = cols[:-1]
    for i in range(B):
        for j in range(B):
            # H[B(t+1) + i, B t + j] = H[t+1, t][i, j] = off[t][j, i]
            ab[B + i - j, cols + j] = off[:, j, i]
    return ab


def solve_normal_equations(lin, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve (H + damping diag(H)) [delta; dtheta] = -[g_q; g_theta] in O(T).

    H is block-tridiagonal in the per-sample variables (B = 3 rotation + V velocity) with a
    dense border for the P calibration variables; the border is eliminated by a Schur
    complement. Returns ((T, B), (P,)).
    """
    T, B = lin.diag.shape[:2]
    diag = lin.diag.copy()
    idx = np.arange(B)
    diag[:, idx, idx] *= 1.0 + damping
    ab = banded_lower(diag, lin.off)
    P = lin.cross.shape[2]
    rhs = np.concatenate([-lin.grad_q.reshape(-1, 1), lin.cross.reshape(B * T, P)], axis=1)
    sol = solveh_banded(ab, rhs, lower=True, check_finite=False)
    x0, X1 = sol[:, 0], sol[:, 1:]
    if P == 0:
        return x0.reshape(T, B), np.zeros(0)
    G = lin.theta_block.copy()
    G[np.arange(P), np.arange(P)] *= 1.0 + damping
    C = lin.cross.reshape(B * T, P)
    schur = G - C.T @ X1
    dtheta = np.linalg.solve(schur, -lin.grad_theta - C.T @ x0)
    return (x0 - X1 @ dtheta).reshape(T, B), dtheta


def theta_posterior_std(lin) -> np.ndarray:
    """(P,) marginal std of the calibration variables: sqrt(diag((G - C^T A^-1 C)^-1))."""
    P = lin.cross.shape[2]
    if P == 0:
        return np.zeros(0)
    C = lin.cross.reshape(-1, P)
    X1 = solveh_banded(banded_lower(lin.diag, lin.off), C, lower=True, check_finite=False)
    return np.sqrt(np.diag(np.linalg.inv(lin.theta_block - C.T @ X1)))
