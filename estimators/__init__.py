"""Orientation estimators behind one interface, and their registry.

`ESTIMATORS` maps the CLI name to the class; a new estimator is one module and one line here.
A spec (`"ukf:R=1e-3"`) is parsed once (`parse_specs`) and resolved once (`resolve`) into a
`ResolvedSpec`: the class it names, its validated parameters and the label its rows carry.
Every later stage (the runner, its workers, the reports) uses that object.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Iterable

from .base import Estimator, RecursiveEstimator
from .dr import DeadReckoning
from .ekf import EKF
from .gd import GradientDescentSmoother
from .gn import GaussNewtonSmoother
from .peers import (  # optional libraries, imported when built: pip install -e '.[peers]'
    AhrsEKFPeer, BasicVQFPeer, FusionPeer, MadgwickPeer, MahonyPeer, OfflineVQFPeer, PeerUnavailable, VQFPeer,
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


@dataclass(frozen=True, eq=False)
class ResolvedSpec:
    """A spec resolved to what builds it, once, before any work.

    spec: the spec as given; cls: the `Estimator` class it names; params: its parameters,
    built and validated from the spec's overrides; label: the name of its rows in tables and
    results.json (the spec's text for the registry's estimators).
    """

    spec: EstimatorSpec
    cls: type[Estimator]
    params: Any
    label: str

    def build(self) -> Estimator:
        """A fresh estimator (no state is shared between jobs)."""
        return self.cls(self.params)

    def describe(self) -> dict[str, Any]:
        """For results.json's settings: the class, whether it is causal, every parameter's value
        after the overrides (defaults included), so that a run can be repeated."""
        params = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        return {"name": self.spec.name, "class": self.cls.__name__, "causal": bool(self.cls.causal),
                "params": {k: v if isinstance(v, (bool, int, float, str)) or v is None else repr(v)
                           for k, v in params.items()}}


def resolve(spec: EstimatorSpec | str) -> ResolvedSpec:
    """The `ResolvedSpec` of one spec (or spec text such as `"ukf:R=1e-3"`); an unknown name or a
    bad parameter is a ValueError naming it, a missing optional library `PeerUnavailable`."""
    if isinstance(spec, str):
        (spec,) = parse_specs(spec)
    try:
        cls = ESTIMATORS[spec.name]
    except KeyError:
        raise ValueError(f"unknown estimator {spec.name!r}; available: {', '.join(ESTIMATORS)}") from None
    params = make_params(cls.Params, spec.overrides, owner=spec.name)
    cls(params)  # a peer whose library is missing says so here, before any work
    return ResolvedSpec(spec, cls, params, spec.label)


def resolve_all(specs: str | Iterable[EstimatorSpec | str | ResolvedSpec]) -> list[ResolvedSpec]:
    """Specs, spec texts (`"dr,ukf:R=1e-3"`) or resolved specs, each resolved once, with the name
    `all` replaced by every registered estimator (registry order). `all` leaves out peers whose
    optional library is not installed (with a warning); naming such a peer is an error that says
    what to install."""
    import warnings

    if isinstance(specs, (str, EstimatorSpec, ResolvedSpec)):
        specs = [specs]
    out: list[ResolvedSpec] = []
    for item in specs:
        if isinstance(item, ResolvedSpec):
            out.append(item)
            continue
        for spec in parse_specs(item) if isinstance(item, str) else [item]:
            if spec.name != "all":
                out.append(resolve(spec))
                continue
            missing = []
            for name in ESTIMATORS:
                try:
                    out.append(resolve(EstimatorSpec(name, spec.overrides)))
                except PeerUnavailable:
                    missing.append(name)
            if missing:
                warnings.warn(f"'all' leaves out {', '.join(missing)}: optional packages not installed "
                              f"(pip install -e '.[peers]')", stacklevel=2)
    return out


def build(spec: EstimatorSpec | str) -> Estimator:
    """An estimator instance from a spec (or spec text such as `"ukf:R=1e-3"`)."""
    return resolve(spec).build()


__all__ = ["ESTIMATORS", "Estimator", "RecursiveEstimator", "EstimatorSpec", "ResolvedSpec", "build", "resolve",
           "resolve_all", "parse_specs", "make_params"]
