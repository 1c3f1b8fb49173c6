"""A FilterPy filter of your own, as the course builds it, in the table without rewriting it.

FilterPy (Labbe, "Kalman and Bayesian Filters in Python") is a library you compose: an
`UnscentedKalmanFilter` with your state transition `fx(x, dt, **fx_args)` and measurement
`hx(x, **hx_args)`, or an `ExtendedKalmanFilter` with your Jacobians. `from_filterpy` turns the
function that builds yours into an estimator (a class, `fusion.estimators.Estimator`), in your
own file:

    from fusion.estimators.adapters.filterpy import from_filterpy

    def make_ukf(q0, dt, gyro_noise=1e-3, acc_noise=0.5):   # your filter, built as you build it
        ukf = UnscentedKalmanFilter(dim_x=4, dim_z=3, dt=dt, fx=fx, hx=hx, points=...)
        ukf.x = q0.copy()
        ...
        return ukf

    MyUKF = from_filterpy(make_ukf, quaternion=lambda x: x[:4])

    $ fusion compare --estimators ./my_ukf.py:MyUKF,ekf --dataset ece276a/1
    $ fusion ablate --estimator ./my_ukf.py:MyUKF --param acc_noise=0.1,0.5,2

The estimator runs, for each sample k >= 1 (the function contract of `fusion.estimators.adapters.user`:
gyro[k] the rate over (t[k-1], t[k]] in rad/s, acc[k] in m/s^2, both body frame),

    predict(filter, gyro[k], dt)    default: filter.predict(dt=dt, gyro=gyro), i.e. fx(x, dt, gyro=gyro)
    update(filter, acc[k])          default: filter.update(acc), i.e. hx(x) against acc
    quaternion(filter.x)            the (4,) scalar-first R_world_body of the state

skipping the step where the toolkit marked the gyro invalid (a freeze: the filter holds its state;
FilterPy's `update` needs a `predict` before it). `make_filter(q0, dt,
**params)` gets the initial orientation (4,) and the recording's median step, s; its keyword
parameters with defaults become the estimator's parameters on the command line. Give other
`predict`/`update` functions when yours are called differently (an `ExtendedKalmanFilter`:
`update=lambda f, acc: f.update(acc, HJacobian=H, Hx=h)`). The adapter adds a few microseconds
per sample to FilterPy's own cost (`benchmarks/bench_user.py` measures it).
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from fusion.types import ImuSamples, Trajectory

from ..base import Estimator
from .user import check_output, function_inputs, params_dataclass


def _predict(f: Any, gyro: np.ndarray, dt: float) -> None:
    f.predict(dt=dt, gyro=gyro)


def _update(f: Any, acc: np.ndarray) -> None:
    f.update(acc)


class FilterPyEstimator(Estimator):
    """A FilterPy filter run over a recording (module docstring); classes made by `from_filterpy`
    set `make_filter`, `quaternion`, `predict`, `update` and `Params`."""

    make_filter: Callable[..., Any]
    quaternion: Callable[[np.ndarray], np.ndarray]
    predict: Callable[[Any, np.ndarray, float], None]
    update: Callable[[Any, np.ndarray], None]

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        import dataclasses

        cls = type(self)
        t, gyro, acc, q0 = function_inputs(imu, init_quat_wxyz)
        dt = np.diff(t)
        params = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        filt = cls.make_filter(q0, float(np.median(dt)) if len(dt) else 0.0, **params)
        predict, update, quaternion = cls.predict, cls.update, cls.quaternion
        valid = np.all(np.isfinite(gyro), axis=1)
        out = np.empty((len(t), 4))
        out[0] = q0
        for k in range(1, len(t)):
            if valid[k]:  # FilterPy's update reuses the sigma points of the last predict: both or neither
                predict(filt, gyro[k], dt[k - 1])
                update(filt, acc[k])
            out[k] = quaternion(filt.x)
        return Trajectory(imu.t, check_output(out, len(t)))


def from_filterpy(make_filter: Callable[..., Any], quaternion: Callable[[np.ndarray], np.ndarray], *,
                  predict: Callable[[Any, np.ndarray, float], None] = _predict,
                  update: Callable[[Any, np.ndarray], None] = _update, name: str | None = None,
                  causal: bool = True) -> type[FilterPyEstimator]:
    """An estimator class for the FilterPy filter `make_filter(q0, dt, **params)` builds (module
    docstring). quaternion: the state's orientation, (4,) scalar-first `R_world_body`;
    predict, update: how one step calls your filter; name: the class's name (default: from
    `make_filter`'s)."""
    params = params_dataclass(make_filter, ("q0", "dt"), getattr(make_filter, "__name__", "filter"))
    title = name or params.__name__.removesuffix("Params")
    return type(title, (FilterPyEstimator,), {
        "Params": params, "causal": causal, "make_filter": staticmethod(make_filter),
        "quaternion": staticmethod(quaternion), "predict": staticmethod(predict), "update": staticmethod(update),
        "__module__": getattr(make_filter, "__module__", __name__), "__doc__": make_filter.__doc__})
