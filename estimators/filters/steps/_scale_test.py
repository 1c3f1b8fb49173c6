"""Wald's sequential test on the gyro's scale factors (`ekf`, `ukf-bias`, 6-D): a scale error the
size of a datasheet's, or a calibrated gyro?

Contract: `ScaleTest.step` takes the scale estimate s (3,) and the error covariance P of a
filter whose error state has the scale in rows `first`..`first + 3`, and while undecided returns
the pseudo-measurement's correction and covariance when it accepts the calibrated gyro.

Paper: Wald 1945, "Sequential tests of statistical hypotheses", Ann. Math. Stat. 16(2), Sec. 3
(the boundaries (1 - beta) / alpha and beta / (1 - alpha) of the likelihood ratio); the update is
in Joseph form (Sola 2017, Sec. 6.1-6.3).

`ScaleTest.state()` packs `[on, decision, ln L]` (the `TEST_*` offsets below), the state the
compiled filters carry (`_compiled_scale_test`).
"""
from __future__ import annotations

import math

import numpy as np

from ._error_state import ATTITUDE, BIAS, SCALE_AT

# The layout of `ScaleTest.state()`: offsets into the (TEST_STATE,) float64 array.
TEST_ON = 0  # flag: the test runs
TEST_DECISION = 1  # 0 undecided, 1 a scale error (H1), -1 calibrated (H0)
TEST_LLR = 2  # ln L of the last step (nan: off)
TEST_STATE = 3


class ScaleTest:
    """Wald's sequential probability ratio test ("Sequential tests of statistical hypotheses",
    Ann. Math. Stat. 16(2), 1945, Sec. 3, with its approximate boundaries (1 - beta) / alpha and
    beta / (1 - alpha) for the likelihood ratio) on the gyro's scale factors: is the scale error
    the size a gyro read with its datasheet sensitivity may have, or is the gyro calibrated?

    H1: the scale corrections s of the estimated axes have the prior N(0, P1 I) the filter starts
    from (`init_scale_var`, 10 %). H0: they have N(0, P0 I), P0 < P1 (`calibrated_scale_var`,
    1 %). The filter runs under H1, and its posterior (s, C) of the estimated axes (k of them)
    summarises what the data say. Changing the prior from P1 to P0 adds the information
    1/P0 - 1/P1: it is the pseudo-measurement `s = 0` with the variance r I, 1/r = 1/P0 - 1/P1
    (exact for the linear Gaussian model), so the likelihood ratio of the data under the two
    priors is that pseudo-measurement's innovation likelihood, up to constants:

        ln L = ln p(data | H1) - ln p(data | H0)
             = 1/2 s^T S^-1 s + 1/2 ln det S + k/2 ln((1 - P0 / P1) / P1),   S = C + r I

    (0 at the start, where C = P1 I and s = 0; it grows when the data show a scale error the
    calibrated prior does not allow, and falls as they pin s near zero). With the error
    probabilities alpha = beta = e, Wald's boundaries are +-ln((1 - e) / e): above the upper one
    the test accepts H1 and stops, the scale states going on as they are; below the lower one it
    accepts H0 and conditions the filter on it, making that pseudo-measurement update once
    (`update`): the scale posterior is then the one the prior P0 would have given. The
    smoothers answer the same question with a likelihood-ratio test of their cost
    (`fusion.estimators.smoothers.smoother`); this is its sequential form, for a causal filter.
    (`_compiled_scale_test.step` is the same in the kernels.)
    """

    def __init__(self, prior_var: float, calibrated_var: float, error: float, axes: np.ndarray,
                 first: int = SCALE_AT):
        self.axes = np.flatnonzero(axes)
        self.rows = first + self.axes  # the scale states' rows in the error state
        self.on = bool(error > 0.0 and len(self.axes) and calibrated_var < prior_var)  # else nothing to test
        self.r = 1.0 / (1.0 / calibrated_var - 1.0 / prior_var) if self.on else math.inf
        self.const = 0.5 * len(self.axes) * math.log((1.0 - calibrated_var / prior_var) / prior_var) if self.on else 0.0
        self.bound = math.log((1.0 - error) / error) if self.on else math.inf
        self.decision = 0  # 0 undecided, 1 a scale error (H1), -1 calibrated (H0)
        self.llr = 0.0 if self.on else math.nan  # ln L of the last step (frozen once decided)

    @classmethod
    def off(cls) -> "ScaleTest":
        """A test that never runs (a filter without scale states)."""
        return cls(1.0, 1.0, 0.0, np.zeros(3, dtype=bool))

    def stop(self) -> None:
        """End the test undecided (a filter given a magnetometer sample; "Scale test" in `ekf`)."""
        if self.decision == 0:
            self.on, self.llr = False, math.nan

    def state(self) -> np.ndarray:
        """(TEST_STATE,) `[on, decision, ln L]` (the `TEST_*` offsets): the state the kernels read
        and write (`_compiled_scale_test.step`)."""
        st = np.zeros(TEST_STATE)
        st[TEST_ON], st[TEST_DECISION], st[TEST_LLR] = float(self.on), float(self.decision), self.llr
        return st

    def set_state(self, state: np.ndarray) -> None:
        self.on, self.decision = bool(state[TEST_ON]), int(state[TEST_DECISION])
        self.llr = float(state[TEST_LLR])

    def log_likelihood_ratio(self, s: np.ndarray, P: np.ndarray) -> float:
        """ln L (class docstring) for the scale estimate s (3,) and the error covariance P."""
        y = s[self.axes]
        S = P[np.ix_(self.rows, self.rows)] + self.r * np.eye(len(y))
        return 0.5 * float(y @ np.linalg.solve(S, y) + np.linalg.slogdet(S)[1]) + self.const

    def step(self, s: np.ndarray, P: np.ndarray, vertical: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        """One step of the test while undecided: `(dx, P)`, dx the correction of the error state
        when the test accepts H0 now (the pseudo-measurement update, P in Joseph form), else
        `(None, P)` unchanged. vertical: the body-frame vertical h (3,) of a heading-free filter,
        whose gain then makes no turn about h on the attitude and bias rows (as its
        accelerometer update), or None."""
        if not self.on or self.decision != 0:
            return None, P
        self.llr = self.log_likelihood_ratio(s, P)
        if self.llr >= self.bound:
            self.decision = 1
        elif self.llr <= -self.bound:
            self.decision = -1
            return self.update(s, P, vertical)
        return None, P

    def update(self, s: np.ndarray, P: np.ndarray, vertical: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The pseudo-measurement `s = 0` of variance r I on the tested axes, which turns the
        prior P1 into P0: `(dx, P)` (Joseph form; `vertical` as in `step`)."""
        rows = self.rows
        S = P[np.ix_(rows, rows)] + self.r * np.eye(len(rows))
        K = np.linalg.solve(S, P[rows]).T  # P H^T S^-1, H selecting the rows
        if vertical is not None:
            K[ATTITUDE] -= np.outer(vertical, vertical @ K[ATTITUDE])
            K[BIAS] -= np.outer(vertical, vertical @ K[BIAS])
        dx = K @ -s[self.axes]
        IKH = np.eye(len(P))
        IKH[:, rows] -= K
        return dx, IKH @ P @ IKH.T + self.r * (K @ K.T)
