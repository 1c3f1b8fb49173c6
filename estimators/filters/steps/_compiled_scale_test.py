"""`_scale_test` compiled: Wald's sequential test on the gyro's scale factors (Wald 1945).

`step` is `ScaleTest.step` on the packed state of `ScaleTest.state()` (the `TEST_*` offsets),
with the pseudo-measurement's update (`ScaleTest.update`) inline in Joseph form; the equations
are in `_scale_test`.
"""
from __future__ import annotations

import math
from typing import Any, NamedTuple

from ...kernels._compiled_linalg import _nis, _project_heading, inv_sym3, joseph
from ...kernels._compiled_quaternion import gravity_floats
from ...kernels._numba import forget_stale, mirrors
from ._error_state import BIAS_AT, SCALE_AT
from ._scale_test import TEST_DECISION, TEST_LLR

forget_stale(__file__)

HELPERS = ()


class ScaleTestSettings(NamedTuple):
    """A `ScaleTest`'s constants, as the kernels read them."""

    axes: int  # the tested axes as bits (x 1, y 2, z 4); 0: the test is off
    r: float  # the pseudo-measurement's variance
    const: float  # the constant of ln L
    bound: float  # Wald's boundary ln((1 - e) / e)


def scale_test_settings(test: Any) -> ScaleTestSettings:
    """The `ScaleTestSettings` of a `ScaleTest` (or None: off)."""
    if test is None or not test.on:
        return ScaleTestSettings(axes=0, r=math.inf, const=0.0, bound=math.inf)
    return ScaleTestSettings(axes=int(sum(1 << int(a) for a in test.axes)), r=float(test.r), const=float(test.const),
                             bound=float(test.bound))


@mirrors("fusion.estimators.filters.steps._scale_test.ScaleTest.step", leaf=True)
def step(P, s, st, q, o, heading_free, N, w):
    """`ScaleTest.step` on its packed state st (`ScaleTest.state`) while on and undecided, with the
    attitude q and o its `ScaleTestSettings`: -> whether it accepted H0 now, with the
    pseudo-measurement's correction in w.dx (N,) and P updated in place (Joseph form; with
    heading_free, no turn about the vertical, as `KalmanFilter.step`). The
    axes not tested (`o.axes`) take a unit diagonal in S, so that its inverse and
    determinant are those of the tested block, and zero columns in K and PHt (w: the filter's
    work arrays; K, PHt, D: N x 3, S, Sinv: 3 x 3)."""
    K, PHt, S, Sinv, D, dx = w.K, w.PHt, w.S, w.Sinv, w.D, w.dx
    c = SCALE_AT
    r = o.r
    for i in range(3):
        on_i = (o.axes >> i) & 1
        for j in range(3):
            on_j = (o.axes >> j) & 1
            S[i, j] = P[c + i, c + j] + (r if i == j else 0.0) if on_i and on_j else (1.0 if i == j else 0.0)
    y0 = -s[0] if o.axes & 1 else 0.0
    y1 = -s[1] if o.axes & 2 else 0.0
    y2 = -s[2] if o.axes & 4 else 0.0
    det = inv_sym3(S, Sinv)
    llr = 0.5 * (_nis(y0, y1, y2, Sinv) + math.log(det)) + o.const
    st[TEST_LLR] = llr
    if llr >= o.bound:
        st[TEST_DECISION] = 1.0
        return False
    if llr > -o.bound:
        return False
    st[TEST_DECISION] = -1.0
    for i in range(3):  # H selects the tested scale rows: P H^T = P[:, 6 + i]; S's dummy rows to zero
        on_i = (o.axes >> i) & 1
        if not on_i:
            S[i, i] = 0.0
        for a in range(N):
            PHt[a, i] = P[a, c + i] if on_i else 0.0
    for a in range(N):
        for j in range(3):
            K[a, j] = PHt[a, 0] * Sinv[0, j] + PHt[a, 1] * Sinv[1, j] + PHt[a, 2] * Sinv[2, j]
    if heading_free:  # no turn about the vertical h on the attitude and bias rows
        hx, hy, hz = gravity_floats(q)
        _project_heading(K, 0, hx, hy, hz)
        _project_heading(K, BIAS_AT, hx, hy, hz)
    for a in range(N):
        dx[a] = K[a, 0] * y0 + K[a, 1] * y1 + K[a, 2] * y2
    joseph(P, K, PHt, S, N, D)
    return True
