"""Orientation estimators behind one interface, and their registry.

`ESTIMATORS` maps the CLI name to the class; a new estimator is one module and one line here.
A spec (`"ukf:R=1e-3"`) is parsed once (`parse_specs`) and resolved once (`resolve`) into a
`ResolvedSpec`: the class it names, its validated parameters and the label its rows carry.
Every later stage (the runner, its workers, the reports) uses that object.
"""
from __future__ import annotations

from fusion import check_package_name

check_package_name(__name__, "fusion.estimators")

import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, NamedTuple

from .base import Estimator, RecursiveEstimator
from .dr import DeadReckoning
from .filters.ekf import EKF
from .filters.ukf import UKF, UKFBias
from .params import EstimatorSpec, make_params, parse_specs
from .peers.ahrs_filters import AhrsEKFPeer, MadgwickPeer, MahonyPeer
from .peers.ahrs_recursive import (
    AhrsUKFPeer, AngularRatePeer, AQUAPeer, ComplementaryPeer, FKFPeer, FouratiPeer, ROLEQPeer,
)
from .peers.ahrs_single import (
    DavenportPeer, FAMCPeer, FLAEPeer, FQAPeer, OLEQPeer, QUESTPeer, SAAMPeer, TiltPeer, TRIADPeer,
)
from .peers.qmt_filters import OriEstIMUPeer, QmtMadgwickPeer, QmtMahonyPeer
from .peers.vqf_fusion import (  # optional libraries, imported when built: pip install -e '.[peers]'
    BasicVQFPeer, FusionPeer, OfflineVQFPeer, PeerUnavailable, VQFPeer,
)
from .smoothers.gd import GradientDescentSmoother
from .smoothers.gn import GaussNewtonSmoother

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
    "aqua": AQUAPeer,
    "complementary": ComplementaryPeer,
    "fkf": FKFPeer,
    "fourati": FouratiPeer,
    "roleq": ROLEQPeer,
    "ahrs-ukf": AhrsUKFPeer,
    "ahrs-angular": AngularRatePeer,
    "qmt-oriestimu": OriEstIMUPeer,
    "qmt-madgwick": QmtMadgwickPeer,
    "qmt-mahony": QmtMahonyPeer,
    "davenport": DavenportPeer,
    "quest": QUESTPeer,
    "oleq": OLEQPeer,
    "flae": FLAEPeer,
    "fqa": FQAPeer,
    "saam": SAAMPeer,
    "triad": TRIADPeer,
    "famc": FAMCPeer,
    "tilt": TiltPeer,
}


@dataclass(frozen=True, eq=False)
class ResolvedSpec:
    """A spec resolved to what builds it, once, before any work.

    spec: the spec as given; cls: the `Estimator` class it names; params: its parameters,
    built and validated from the spec's overrides; label: the name of its rows in tables and
    results.json (the spec's text for the registry's estimators; `my_ukf.MyUKF:R=0.001` for
    `./my_ukf.py:MyUKF:R=0.001`); origin: where a user's estimator comes from
    (`fusion.estimators.adapters.user.Origin`), None for the registry's.
    """

    spec: EstimatorSpec
    cls: type[Estimator]
    params: Any
    label: str
    origin: Any = None

    @property
    def user(self) -> bool:
        """A user's estimator (a file, a module or an installed package's entry point)."""
        return self.origin is not None

    def build(self) -> Estimator:
        """A fresh estimator (no state is shared between jobs)."""
        return self.cls(self.params)

    def describe(self) -> dict[str, Any]:
        """For results.json's settings: the class, whether it is causal, every parameter's value
        after the overrides (defaults included), so that a run can be repeated, and where a user's
        estimator comes from (its file's path and sha256)."""
        params = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        out = {"name": self.spec.name, "class": self.cls.__name__, "causal": bool(self.cls.causal),
               "params": {k: v if isinstance(v, (bool, int, float, str)) or v is None else repr(v)
                          for k, v in params.items()}}
        if self.origin is not None:
            out["origin"] = self.origin.describe()
        return out

    def __reduce__(self):
        """Sent to another process (spawned workers, Dask) as the spec to resolve there; a user's
        file travels as its contents, so the workers need not see it."""
        kind = self.origin.kind if self.origin is not None else None
        if kind == "file":
            return _resolve_file, (self.spec, self.origin.where, self.origin.source)
        if kind in ("module", "entry point"):
            return resolve, (self.spec,)
        return ResolvedSpec, (self.spec, self.cls, self.params, self.label, self.origin)


def resolve(spec: EstimatorSpec | str, file: tuple[str, bytes] | None = None) -> ResolvedSpec:
    """The `ResolvedSpec` of one spec (or spec text such as `"ukf:R=1e-3"`): a registered name, an
    installed package's entry point, or a user's `FILE.py:NAME` / `module:NAME`
    (`fusion.estimators.adapters.user`). An unknown name or a bad parameter is a ValueError naming it, a
    missing optional library `PeerUnavailable`. file: a user's file as (path, contents), read
    elsewhere (another process's copy)."""
    from .adapters import user

    if isinstance(spec, str):
        (spec,) = parse_specs(spec)
    origin = None
    if spec.name in ESTIMATORS:
        cls, label = ESTIMATORS[spec.name], spec.label
    elif user.is_reference(spec.name):
        target, _, part = spec.name.rpartition(":")
        if target in ESTIMATORS:
            raise ValueError(f"estimator {target!r}: expected key=value, got {part!r}")
        obj, origin = user.load_reference(spec.name, file)
        cls = user.estimator_class(obj, spec.name)
        stem = Path(origin.where).stem if origin.kind == "file" else origin.where
        label = EstimatorSpec(f"{stem}.{origin.attribute}", spec.overrides).label
    elif spec.name in (plugins := user.entry_points()):
        obj, origin = user.load_entry_point(plugins[spec.name])
        cls, label = user.estimator_class(obj, spec.name), spec.label
    else:
        known = [*ESTIMATORS, *plugins]
        raise ValueError(f"unknown estimator {spec.name!r}; available: {', '.join(known)}, or your own as "
                         "FILE.py:NAME or package.module:NAME")
    params = make_params(cls.Params, spec.overrides, owner=spec.name)
    cls(params)  # a peer whose library is missing says so here, before any work
    return ResolvedSpec(spec, cls, params, label, origin)


def resolve_trajectory(name: str, path: str | Path) -> ResolvedSpec:
    """A trajectory another program wrote (a file, or a folder with one file per recording:
    `fusion.estimators.adapters.trajectory_file`) as an estimator whose rows are named `name`."""
    from .adapters import user
    from .adapters.trajectory_file import TrajectoryFile, TrajectoryFileParams

    if not name or any(c in name for c in ",:=/") or name in ESTIMATORS or name == "truth":
        raise ValueError(f"--trajectory {name}=...: the name must be new, not 'truth', and hold no ',', ':', '=' or '/'")
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such trajectory file or folder (--trajectory {name}=...)")
    sha = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    params = TrajectoryFileParams(str(path.resolve()))
    return ResolvedSpec(EstimatorSpec(name), TrajectoryFile, params, name,
                        user.Origin("trajectory", str(path.resolve()), "", sha))


def _resolve_file(spec: EstimatorSpec, path: str, source: bytes) -> ResolvedSpec:
    """`resolve` in another process, from a user's file's path and contents (`ResolvedSpec.__reduce__`)."""
    return resolve(spec, file=(path, source))


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
    labels = [e.label for e in out]
    twice = [label for label in dict.fromkeys(labels) if labels.count(label) > 1]
    if twice and any(out[labels.index(label)].user for label in twice):
        raise ValueError(f"two estimators would both be named {twice[0]!r} in the table: rename one of the files or "
                         "functions")
    return out


class Listed(NamedTuple):
    """One row of `fusion list`: the name a spec uses, what it is (its docstring's first line), where
    it comes from ("fusion" or an installed package), its group (`GROUPS`) and whether it fuses the
    magnetometer where a recording has one (9-D)."""

    name: str
    what: str
    origin: str
    group: str
    nine_d: bool


# `fusion list`'s groups, in its order: a filter updates from the past samples (ours, VQF, Fusion,
# the `ahrs` and `qmt` filters, dead reckoning); a smoother sees the whole recording (`causal =
# False`); a single-sample method determines each sample's orientation from that sample alone
# (`single_sample = True`: the `ahrs` attitude determinations); an installed package's estimator is
# not imported to be listed.
GROUPS = {"recursive filters": "causal: each sample's orientation from the samples up to it",
          "smoothers": "see the whole recording",
          "single-sample methods": "each sample's orientation from its own accelerometer and magnetometer",
          "installed packages": "entry points, not imported here"}


def group_of(cls: type[Estimator]) -> str:
    """The `GROUPS` key of a registered estimator class."""
    if not cls.causal:
        return "smoothers"
    return "single-sample methods" if getattr(cls, "single_sample", False) else "recursive filters"


def available() -> list[Listed]:
    """Every estimator a spec can name by itself, grouped (`GROUPS`, registry order within a group):
    the registry's, then those installed packages register in the entry-point group
    `fusion.estimators` (not imported here)."""
    from .adapters import user

    import re

    rows = [Listed(name, re.sub(r"^`[^`]+`:\s*", "", (cls.__doc__ or cls.__name__).strip().splitlines()[0]), "fusion",
                   group_of(cls), bool(cls.magnetometer))
            for name, cls in ESTIMATORS.items()]
    rows += [Listed(name, ep.value, f"entry point of {user._package(ep)}", "installed packages", False)
             for name, ep in user.entry_points().items() if name not in ESTIMATORS]
    order = list(GROUPS)
    return sorted(rows, key=lambda row: order.index(row.group))


def build(spec: EstimatorSpec | str) -> Estimator:
    """An estimator instance from a spec (or spec text such as `"ukf:R=1e-3"`)."""
    return resolve(spec).build()


__all__ = ["ESTIMATORS", "GROUPS", "Estimator", "Listed", "RecursiveEstimator", "EstimatorSpec", "ResolvedSpec", "available", "build",
           "resolve", "resolve_all", "resolve_trajectory", "parse_specs", "make_params"]
