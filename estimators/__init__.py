"""Orientation estimators behind one interface, and their registry.

`ESTIMATORS` maps the CLI name to the class; a new estimator is one module and one line here.
"""
from __future__ import annotations

from .base import Estimator, RecursiveEstimator
from .dr import DeadReckoning
from .ekf import EKF
from .gd import GradientDescentSmoother
from .gn import GaussNewtonSmoother
from .peers import (  # optional libraries, imported when built: pip install -e '.[peers]'
    AhrsEKFPeer, BasicVQFPeer, FusionPeer, MadgwickPeer, MahonyPeer, OfflineVQFPeer, VQFPeer,
)
from .params import EstimatorSpec, make_params, parse_specs
from .ukf import UKF, UKFBias

ESTIMATORS: dict[str, type[Estimator]] = {
    "dr": DeadReckoning,
    "ukf": UKF,
    "ukf-bias": UKFBias,
    "ekf": EKF,
    "gd": GradientDescentSmoother,
    "gn": GaussNewtonSmoother,
    "vqf": VQFPeer,
    "vqf-basic": BasicVQFPeer,
    "vqf-offline": OfflineVQFPeer,
    "madgwick": MadgwickPeer,
    "mahony": MahonyPeer,
    "ahrs-ekf": AhrsEKFPeer,
    "fusion-ahrs": FusionPeer,
}


def build(spec: EstimatorSpec | str) -> Estimator:
    """An estimator instance from a spec (or spec text such as `"ukf:R=1e-3"`)."""
    if isinstance(spec, str):
        (spec,) = parse_specs(spec)
    try:
        cls = ESTIMATORS[spec.name]
    except KeyError:
        raise ValueError(f"unknown estimator {spec.name!r}; available: {', '.join(ESTIMATORS)}") from None
    return cls(make_params(cls.Params, spec.overrides, owner=spec.name))


__all__ = ["ESTIMATORS", "Estimator", "RecursiveEstimator", "EstimatorSpec", "build", "parse_specs", "make_params"]
