"""Search spaces: which parameters of an estimator are tuned, over what range, and on what scale.

A tunable parameter declares its range beside its default, in the parameter dataclass's field
metadata, so that the parameter, its default, its unit (in its name) and its range are read in
one place:

    gain: float = field(default=0.033, metadata={"alias": "beta",
                                                 "search": Tunable(1e-3, 1.0, grid=(0.01, 0.033, 0.1, 0.3))})

`low`/`high` bound a continuous search (Optuna's samplers; `log=True` searches the logarithm,
for gains and noise densities that span decades); `grid` is the small set of values the grid
preset tries (each inside the range; the default need not be one of them). A user's estimator
declares its own the same way, on its own `Params` dataclass. `search_space(Params)` collects
them in field order.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Tunable:
    """The range of one tunable parameter.

    low, high: the bounds (inclusive), in the field's unit; log: search log(value) (then low > 0);
    grid: the grid preset's values, each within [low, high]; integer: a whole number (a count);
    magnetometer: the parameter acts on the magnetometer only (not tuned in 6-D).
    """

    low: float
    high: float
    log: bool = True
    grid: tuple[float, ...] = ()
    integer: bool = False
    magnetometer: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise ValueError(f"Tunable: need finite low < high, got [{self.low}, {self.high}]")
        if self.log and self.low <= 0:
            raise ValueError(f"Tunable: a log-scaled range needs low > 0, got {self.low}")
        outside = [v for v in self.grid if not self.low <= v <= self.high]
        if outside:
            raise ValueError(f"Tunable: grid value {outside[0]} outside [{self.low}, {self.high}]")
        if len(set(self.grid)) != len(self.grid):
            raise ValueError(f"Tunable: grid {self.grid} repeats a value")

    def describe(self) -> str:
        """`[1e-3, 1] log; grid 0.01, 0.033, 0.1`, as `fusion list NAME` shows it."""
        text = f"[{self.low:g}, {self.high:g}] {'log' if self.log else 'linear'}"
        return text + (f"; grid {', '.join(f'{v:g}' for v in self.grid)}" if self.grid else "")


def search_space(params_cls: type) -> dict[str, Tunable]:
    """Field name -> `Tunable`, for every field of `params_cls` that declares one (field order);
    empty for a class that is not a dataclass or declares none."""
    if not dataclasses.is_dataclass(params_cls):
        return {}
    return {f.name: f.metadata["search"] for f in dataclasses.fields(params_cls) if "search" in f.metadata}


def alias_of(params_cls: type, name: str) -> str:
    """The short name a spec uses for field `name` (its alias, else the name itself)."""
    for f in dataclasses.fields(params_cls):
        if f.name == name:
            return f.metadata.get("alias", name)
    raise KeyError(name)


def default_of(params_cls: type, name: str) -> Any:
    """Field `name`'s default value."""
    for f in dataclasses.fields(params_cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
                return f.default_factory()  # type: ignore[misc]
            raise ValueError(f"{params_cls.__name__}.{name} has no default")
    raise KeyError(name)
