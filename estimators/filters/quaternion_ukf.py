"""Kraft's quaternion UKF on FilterPy: the sigma points, the iterative quaternion mean and
`QuaternionUKF`, the step that `ukf` and `ukf-bias` (`fusion.estimators.filters.ukf`) run.

The numbered steps are those of the `ukf` module's docstring (Kraft 2003: E. Kraft, "A
quaternion-based unscented Kalman filter for orientation tracking", Proc. 6th Int. Conf.
Information Fusion, pp. 47-54). This module is imported when a UKF is built, not with the
estimator registry: FilterPy imports SciPy's statistics package (about 34 MB resident and
0.4 s), which a process that runs no UKF (a smoother on a Dask worker, say) need not hold.

What FilterPy (2.0.0) provides and what is replaced
----------------------------------------------------
`QuaternionUKF` subclasses `filterpy.kalman.UnscentedKalmanFilter` and keeps its
bookkeeping (`x`, `P`, `R`, `K`, `y`, `S`, `sigmas_f`, `sigmas_h`, `x_prior`/`x_post`...) and
its hooks: `QuaternionSigmaPoints` has FilterPy's sigma-point interface (`n`, `num_sigmas()`,
`sigma_points(x, P)`, `Wm`, `Wc`), `x_mean_fn` is the iterative quaternion mean,
`residual_x` the quaternion log difference, `state_add` composition with the exponential
map, `fx`/`hx` the process and measurement models. Traps worked around:

* `UnscentedKalmanFilter.predict()` re-draws sigma points from the predicted (x, P)
  after the transform, so `update` would not use the propagated points as Kraft does, and
  it adds Q *after* the transform. `QuaternionUKF.predict_kraft` is Kraft's instead (draws from
  P + Q, keeps the propagated points and their error vectors for the update).
* FilterPy's `predict`/`update` stay as FilterPy wrote them (our steps are `predict_kraft`
  and `update_kraft`), so the object is still a working FilterPy filter.
* FilterPy's `unscented_transform` and `cross_variance` size the covariance from the state
  vector (4 or 7 entries) and fail for a 3x3 / 6x6 error covariance:
  `unscented_transform_state` (passed as `UT=`) and an overridden `cross_variance` size it
  from the residuals. FilterPy's own `unscented_transform` is still used for the
  (Euclidean) measurement side.
* `batch_filter` cannot pass the gyro to `fx`: `RecursiveEstimator` loops the steps and
  passes the gyro sample as a keyword argument.
* FilterPy's sigma-point classes check `size(x) == n`; ours take the (n+1)-entry state
  with an n x n covariance.
"""
from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import UnscentedKalmanFilter

from fusion import quaternion as quat
from fusion.quaternion import exp_floats, left_matrix, multiply_floats, right_matrix, unit_array

from ..kernels._linalg import inv_sym3, sqrt_psd
from .steps._error_state import (ATTITUDE, BIAS, CALIBRATION_AT, SCALE, X_BIAS, X_CALIBRATION, X_QUAT, X_SCALE,
                                 ErrorLayout)


# --------------------------------------------------------------------------- sigma points
class QuaternionSigmaPoints:
    """Sigma points on the n-dimensional error state, with FilterPy's interface.

    n: error dimension (3: attitude; 6: attitude and gyro bias).
    scheme: "kraft" | "julier" | "merwe". Points are `W_0 = 0` and `+-` the columns of
    `sqrt(c P)` (c = n, n + kappa, n + lambda); `Wm`, `Wc` (2n + 1,) weights, centre first.
    `sigma_points(x, P)` maps them onto the state: x (n + 1,) = [q_wxyz, b...], P (n, n).
    """

    def __init__(self, n: int, scheme: str = "kraft", kappa: float = 1.0, alpha: float = 1.0, beta: float = 2.0) -> None:
        if n not in (3, 6, 9):
            raise ValueError(f"sigma points: error dimension must be 3, 6 or 9, got {n}")
        self.n, self.scheme = n, scheme
        self.kappa, self.alpha, self.beta = float(kappa), float(alpha), float(beta)
        m = 2 * n + 1
        if scheme == "kraft":  # step 2: +-sqrt(n P), 2n points, equal weights
            c = float(n)
            wm0 = wc0 = 0.0  # the centre only starts the iterative mean
        elif scheme == "julier":  # Julier & Uhlmann 1997
            c = n + self.kappa
            if not (self.kappa >= 0.0 and math.isfinite(self.kappa)):
                raise ValueError(
                    f"sigma points julier: kappa = {kappa} gives the centre point the negative weight "
                    f"{self.kappa / c if c else float('-inf'):.3g}; the quaternion mean needs kappa >= 0"
                )
            wm0 = wc0 = self.kappa / c
        elif scheme == "merwe":  # van der Merwe 2004, scaled points
            if not (self.alpha > 0.0 and math.isfinite(self.alpha) and math.isfinite(self.kappa) and math.isfinite(self.beta)):
                raise ValueError(f"sigma points merwe: alpha must be > 0 and all parameters finite, got alpha={alpha}, kappa={kappa}, beta={beta}")
            lam = self.alpha**2 * (n + self.kappa) - n
            c = n + lam
            if c <= 0.0 or lam < 0.0:
                raise ValueError(
                    f"sigma points merwe: alpha={alpha}, kappa={kappa} give lambda = {lam:.4g} and a centre "
                    f"mean weight {lam / c if c > 0 else float('-inf'):.4g} < 0; the iterative quaternion mean "
                    f"needs non-negative weights: choose kappa >= n / alpha^2 - n = {n / self.alpha**2 - n:.4g}"
                )
            wm0 = lam / c
            wc0 = wm0 + 1.0 - self.alpha**2 + self.beta
            if wc0 < 0.0:
                raise ValueError(f"sigma points merwe: covariance centre weight {wc0:.4g} < 0 (alpha={alpha}, beta={beta}); choose beta >= alpha^2 - 1 - lambda/(n+lambda)")
        else:
            raise ValueError(f"sigma points: scheme must be kraft, julier or merwe, got {scheme!r}")
        self.c = c
        self.sqrt_c = math.sqrt(c)
        self.Wm = np.full(m, 0.5 / c)
        self.Wc = np.full(m, 0.5 / c)
        self.Wm[0], self.Wc[0] = wm0, wc0
        self.last_sqrt_recovered = False

    def num_sigmas(self) -> int:
        return 2 * self.n + 1

    def offsets(self, P: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(2n + 1, n) error-state offsets: 0, then +- the columns of sqrt(c P) (step 2)."""
        n = self.n
        L, self.last_sqrt_recovered = sqrt_psd(P)
        L = L * self.sqrt_c
        if out is None:
            out = np.zeros((2 * n + 1, n))
        out[1 : n + 1] = L.T
        out[n + 1 :] = -L.T
        return out

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """(2n + 1, n + 1) state sigma points `[q exp(W_i / 2), b + W_i^b]` (steps 2-3)."""
        x = np.asarray(x, dtype=float)
        P = np.asarray(P, dtype=float)
        if x.shape != (self.n + 1,) or P.shape != (self.n, self.n):
            raise ValueError(f"sigma points: expected x ({self.n + 1},) and P ({self.n}, {self.n}), got {x.shape} and {P.shape}")
        off = self.offsets(P)
        out = np.empty((len(off), self.n + 1))
        out[:, X_QUAT] = quat.from_rotvec(off[:, ATTITUDE]) @ left_matrix(*x[X_QUAT]).T  # step 3: q * exp(W_i)
        out[:, X_CALIBRATION] = x[X_CALIBRATION] + off[:, CALIBRATION_AT:]
        return out


# --------------------------------------------------------------------------- UT hooks
def quaternion_mean(
    quats: np.ndarray, weights: np.ndarray, start: np.ndarray, tol: float = 1e-9, max_iter: int = 20
) -> tuple[np.ndarray, np.ndarray, int]:
    """Iterative weighted mean of unit quaternions (step 5; Kraft 2003).

    quats: (m, 4) wxyz; weights: (m,) summing to 1, >= 0; start: (4,) first guess.
    Repeats `e_i = log(q_t^-1 q_i)` (wrapped: q_i and -q_i give the same e_i),
    `e = sum w_i e_i`, `q_t <- q_t exp(e / 2)` until `|e| < tol` or `max_iter` passes.
    Returns `(mean (4,), residuals (m, 3) rad about the mean, iterations used)`; when the
    cap is hit the last iterate is returned (the caller counts it).
    """
    qw, qx, qy, qz = start.tolist()
    for it in range(1, max_iter + 1):
        err = quat.to_rotvec(quats @ left_matrix(qw, -qx, -qy, -qz).T)  # q_t^-1 * q_i
        e = weights @ err
        qw, qx, qy, qz = quat.normalize_floats(multiply_floats((qw, qx, qy, qz), exp_floats(e[0], e[1], e[2])))
        if math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]) < tol:
            break
    # Residuals about the final mean, to first order (the last step was below tol).
    return np.array([qw, qx, qy, qz]), err - e, it


def state_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """FilterPy `residual_x`: error-state difference a - b, `[log(b_q^-1 a_q), a_b - b_b]`."""
    dq = left_matrix(b[0], -b[1], -b[2], -b[3]) @ a[:4]
    rot = quat.to_rotvec(dq)
    return np.concatenate([rot, a[X_CALIBRATION] - b[X_CALIBRATION]])


def state_add(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """FilterPy `state_add`: `[q exp(dx_rot / 2), b + dx_b]` (step 9), renormalised."""
    q = left_matrix(*x[X_QUAT]) @ np.array(exp_floats(dx[0], dx[1], dx[2]))
    return np.concatenate([q / np.linalg.norm(q), x[X_CALIBRATION] + dx[CALIBRATION_AT:]])


def unscented_transform_state(sigmas, Wm, Wc, noise_cov=None, mean_fn=None, residual_fn=None):
    """FilterPy-signature UT for the quaternion state (passed as `UT=`; step 5).

    sigmas: (m, n + 1) state points; the covariance is sized from the residuals (n, n),
    which FilterPy's `unscented_transform` cannot do for a 4-vector with a 3x3 P.
    """
    x = mean_fn(sigmas, Wm) if mean_fn is not None else Wm @ sigmas  # Euclidean (measurement side)
    residual_fn = residual_fn if residual_fn is not None else np.subtract
    res = np.array([residual_fn(s, x) for s in sigmas])
    P = res.T @ (Wc[:, None] * res)
    if noise_cov is not None:
        P = P + noise_cov
    return x, P


# --------------------------------------------------------------------------- the filter
class QuaternionUKF(UnscentedKalmanFilter):
    """FilterPy's `UnscentedKalmanFilter` with a quaternion (+ bias) state.

    x: (4,), (7,) or (10,) `[q_wxyz, b_rad_s, s]`; P: (n, n) error covariance, n = 3, 6 or 9.
    `predict_kraft(dt, gyr_rad_s, Q)` / `update_kraft(z, R)` are Kraft's steps, vectorised;
    `predict_reference` / `update_reference` run the same steps through the per-point hooks
    and FilterPy's own `update`. FilterPy's `predict` and `update` are not overridden: they
    work on this object as FilterPy defines them (pass `UT=unscented_transform_state`, whose
    covariance is sized from the error state, and the gyro as `gyr_rad_s=`). FilterPy's
    `predict` is not Kraft's (it adds Q after the transform and re-draws the sigma points
    before the update), which is why the estimator uses `predict_kraft`. `batch_filter` and
    `rts_smoother` cannot apply to a quaternion state: both size covariances by the state
    vector's length (4 or 7, not the error state's 3 or 6), `batch_filter` cannot pass the gyro
    to `fx`, and `rts_smoother` adds `K (x' - x)` to the state in Euclidean space (`gn` is the
    smoother here).
    """

    def __init__(self, points: QuaternionSigmaPoints, mean_tol_rad: float = 1e-9, mean_max_iter: int = 20) -> None:
        n = points.n
        self.n_err = n
        self.layout = ErrorLayout.of(n)
        self.mean_tol, self.mean_max_iter = mean_tol_rad, int(mean_max_iter)
        super().__init__(
            dim_x=n + 1,
            dim_z=3,
            dt=None,
            hx=self.hx_gravity,
            fx=self.fx_rotate,
            points=points,
            x_mean_fn=self.state_mean,
            residual_x=state_residual,
            state_add=state_add,
        )
        # FilterPy sizes P, Q, K from dim_x; the error state is one smaller.
        self.P = np.eye(n)
        self.Q = np.zeros((n, n))
        self.K = np.zeros((n, 3))
        self.x = np.zeros(n + 1)
        self.x[0] = 1.0
        self._offsets = np.zeros((2 * n + 1, n))
        self._residuals = np.zeros((2 * n + 1, n))
        self._Wc_col = self.Wc[:, None].copy()
        self.mean_iterations = 0
        self.sqrt_recovered = False
        self.heading_free = False

    # -- models (per point, used by the reference path) --
    def fx_rotate(self, x: np.ndarray, dt: float, gyr_rad_s: np.ndarray | None = None) -> np.ndarray:
        """Process model for one state point: `q exp(diag(1 + s) (w - b) dt / 2)` (steps 1, 4).

        gyr_rad_s None: an invalid gyro sample, nothing is integrated.
        """
        if gyr_rad_s is None:
            return x.copy()
        w = gyr_rad_s - x[X_BIAS] if self.layout.bias else gyr_rad_s
        if self.layout.scale:
            w = w * (1.0 + x[X_SCALE])
        q = right_matrix(*exp_floats(*(w * dt))) @ x[X_QUAT]
        return np.concatenate([q, x[X_CALIBRATION]])

    @staticmethod
    def hx_gravity(x: np.ndarray) -> np.ndarray:
        """Measurement model: gravity in the body frame, g (step 6)."""
        return quat.gravity_in_body(x[X_QUAT])

    def state_mean(self, sigmas: np.ndarray, Wm: np.ndarray) -> np.ndarray:
        """FilterPy `x_mean_fn`: iterative quaternion mean, weighted bias mean (step 5)."""
        q, _, self.mean_iterations = quaternion_mean(sigmas[:, X_QUAT], Wm, sigmas[0, X_QUAT], self.mean_tol, self.mean_max_iter)
        return np.concatenate([q, Wm @ sigmas[:, X_CALIBRATION]])

    def cross_variance(self, x, z, sigmas_f, sigmas_h):
        """P_xz sized (n, dim_z) from the residuals (FilterPy sizes it from x). Step 8."""
        Pxz = np.zeros((self.n_err, sigmas_h.shape[1]))
        for i in range(sigmas_f.shape[0]):
            Pxz += self.Wc[i] * np.outer(self.residual_x(sigmas_f[i], x), self.residual_z(sigmas_h[i], z))
        return Pxz

    # -- numpy path --
    def predict_kraft(self, dt: float, gyr_rad_s: np.ndarray | None, Q: np.ndarray) -> None:
        """Steps 1-5 for all sigma points at once. gyr_rad_s: (3,) rad/s, body, or None
        (invalid sample: nothing integrated); Q: (n, n)."""
        pts: QuaternionSigmaPoints = self.points_fn
        x = self.x
        off = pts.offsets(self.P + Q, self._offsets)  # step 2
        self.sqrt_recovered = pts.last_sqrt_recovered
        X = quat.from_rotvec(off[:, ATTITUDE]) @ left_matrix(x[0], x[1], x[2], x[3]).T  # step 3
        sig = self.sigmas_f
        if gyr_rad_s is None:
            sig[:, X_QUAT] = X
            sig[:, X_CALIBRATION] = x[X_CALIBRATION] + off[:, CALIBRATION_AT:]
        elif self.layout.bias:
            b = x[X_BIAS] + off[:, BIAS]
            rv = gyr_rad_s - b
            if self.layout.scale:
                s = x[X_SCALE] + off[:, SCALE]
                rv *= 1.0 + s
                sig[:, X_SCALE] = s
            rv *= dt  # step 1, per point
            d = quat.from_rotvec(rv)
            sig[:, X_QUAT] = quat.multiply(X, d)  # step 4: Y_i = X_i * q_delta_i, row-wise
            sig[:, X_BIAS] = b
        else:
            w = gyr_rad_s * dt
            sig[:, X_QUAT] = X @ right_matrix(*exp_floats(w[0], w[1], w[2])).T  # steps 1, 4
        Y = sig[:, X_QUAT]
        q, err, self.mean_iterations = quaternion_mean(Y, self.Wm, Y[0], self.mean_tol, self.mean_max_iter)  # step 5
        res = self._residuals
        res[:, ATTITUDE] = err
        if self.layout.bias:
            bm = self.Wm @ sig[:, X_CALIBRATION]
            res[:, CALIBRATION_AT:] = sig[:, X_CALIBRATION] - bm
            self.x = np.concatenate([q, bm])
        else:
            self.x = q
        self.P = res.T @ (self._Wc_col * res)  # step 5: P_pred (Q entered in step 2)
        self.x_prior = self.x
        self.P_prior = self.P

    def update_kraft(self, z: np.ndarray, R: np.ndarray, lag: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Steps 6-9 with the propagated points. z: (3,) accelerometer, g; R: (3, 3) g^2;
        lag: the low-passed sample's calibration Jacobians `(H_b, H_s)` (`_accel.LowpassLag`),
        None for the raw sample."""
        Z = quat.gravity_in_body(self.sigmas_f[:, X_QUAT])  # step 6
        if lag is not None:  # the low-pass's lag behind the frame drift of each point's calibration
            res = self._residuals
            Z = Z + res[:, BIAS] @ lag[0].T
            if self.layout.scale:
                Z = Z + res[:, SCALE] @ lag[1].T
        zp = self.Wm @ Z  # step 7
        dZ = Z - zp
        WdZ = self._Wc_col * dZ
        S = dZ.T @ WdZ + R  # step 8: P_zz
        Pxz = self._residuals.T @ WdZ  # step 8: P_xz
        K = Pxz @ inv_sym3(S)  # step 9
        if self.heading_free:
            # Not in Kraft 2003: drop the correction about the predicted vertical (see UKFBiasParams).
            h = zp / math.sqrt(zp @ zp)
            K[ATTITUDE] -= np.outer(h, h @ K[ATTITUDE])
            if self.layout.bias:
                K[BIAS] -= np.outer(h, h @ K[BIAS])
            # Covariance for a general gain: P - K Pxz^T - Pxz K^T + K S K^T.
            KPxz = K @ Pxz.T
            self.P = self.P - KPxz - KPxz.T + K @ S @ K.T
        else:
            self.P = self.P - Pxz @ K.T  # step 9: P - K P_zz K^T, with K P_zz = P_xz
        y = z - zp
        dx = (K @ y).tolist()
        x = self.x
        q = unit_array(multiply_floats(x[X_QUAT].tolist(), exp_floats(dx[0], dx[1], dx[2])))  # step 9: q exp(K y / 2)
        if self.layout.bias:
            self.x = np.concatenate([q, x[X_CALIBRATION] + dx[CALIBRATION_AT:]])
        else:
            self.x = q
        self.K, self.S, self.y = K, S, y

    # -- reference path: FilterPy hooks, one point at a time --
    def predict_reference(self, dt: float, gyr_rad_s: np.ndarray, Q: np.ndarray) -> None:
        """Steps 1-5 through the hooks: sigma_points(x, P + Q), fx per point, own UT."""
        sigmas = self.points_fn.sigma_points(self.x, self.P + Q)  # steps 2-3 (Q before the UT)
        for i, s in enumerate(sigmas):
            self.sigmas_f[i] = self.fx(s, dt, gyr_rad_s=gyr_rad_s)  # steps 1, 4
        self.x, self.P = unscented_transform_state(self.sigmas_f, self.Wm, self.Wc, None, self.x_mean, self.residual_x)  # step 5
        # No re-draw of sigma points here (FilterPy's predict would): Kraft's update uses Y_i.
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update_reference(self, z: np.ndarray, R: np.ndarray, lag: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Steps 6-9 by FilterPy's own `UnscentedKalmanFilter.update` (Euclidean UT for z);
        lag as in `update_kraft`, added to the measurement model per point."""
        if lag is None:
            UnscentedKalmanFilter.update(self, z, R=R)
            return
        mean = self.x.copy()

        def hx_lagged(x: np.ndarray) -> np.ndarray:
            z_x = quat.gravity_in_body(x[X_QUAT]) + lag[0] @ (x[X_BIAS] - mean[X_BIAS])
            return z_x + lag[1] @ (x[X_SCALE] - mean[X_SCALE]) if self.layout.scale else z_x

        UnscentedKalmanFilter.update(self, z, R=R, hx=hx_lagged)
