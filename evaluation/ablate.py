"""Ablations: one estimator over a grid of parameter values, or a named list of settings.

    fusion ablate --estimator ukf --param R=1e-4,1e-3,1e-2 --param sigma=kraft,julier --out DIR
    fusion ablate --preset sigma --out DIR

An ablation is a comparison whose estimator list is generated: `grid_specs` turns the
`--param` lists into the Cartesian product of specs (the first parameter varies slowest),
each labelled exactly as `fusion compare --estimators` would label it, so an ablation with
one value gives the same rows as `compare` with that parameter. The report then reads the
parameter values back from the labels (`fusion.evaluation.plots.label_params`).

`PRESETS` holds the seed reports' questions as spec lists (data only; edit freely).
"""
from __future__ import annotations

import itertools
from typing import Sequence

from fusion.estimators.params import EstimatorSpec, parse_specs

# The seed reports' questions. Each is a list of spec texts as `--estimators` takes them.
PRESETS: dict[str, list[str]] = {
    # UKF vs plain integration of the gyro
    "ukf-vs-dr": ["dr", "ukf"],
    # sigma-point schemes
    "sigma": ["ukf:sigma=kraft", "ukf:sigma=julier", "ukf:sigma=merwe"],
    # with and without the accelerometer update
    "accel-update": ["ukf:acc=false", "ukf:acc=true"],
    # projected gradient vs normalisation vs Gauss-Newton, on the same (seed) cost
    "smoother-solvers": ["gd", "gd:update=normalise", "gn:weighting=seed"],
    # the weight of the motion term (seed weighting: accelerometer term weight 1)
    "motion-weight": ["gn:weighting=seed,wm=1", "gn:weighting=seed,wm=3", "gn:weighting=seed,wm=10",
                      "gn:weighting=seed,wm=30"],
}


def preset_specs(name: str) -> list[EstimatorSpec]:
    """The specs of a preset, checked against the registry (a clear error for a preset
    naming an estimator this installation does not have)."""
    from fusion import estimators
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; available: {', '.join(PRESETS)}")
    specs = [spec for text in PRESETS[name] for spec in parse_specs(text)]
    missing = list(dict.fromkeys(s.name for s in specs if s.name not in estimators.ESTIMATORS))
    if missing:
        raise ValueError(f"preset {name!r} needs estimator(s) {', '.join(missing)}, not registered here "
                         f"(available: {', '.join(estimators.ESTIMATORS)})")
    for spec in specs:
        try:
            estimators.build(spec)
        except ValueError as exc:
            raise ValueError(f"preset {name!r}: {exc}") from None
    return specs


def parse_param(text: str) -> tuple[str, list[str]]:
    """`R=1e-4,1e-3` -> ("R", ["1e-4", "1e-3"])."""
    key, sep, values = text.partition("=")
    items = [v.strip() for v in values.split(",") if v.strip()]
    if not sep or not key.strip() or not items:
        raise ValueError(f"--param {text!r}: expected NAME=VALUE[,VALUE...], e.g. R=1e-4,1e-3")
    if len(set(items)) != len(items):
        raise ValueError(f"--param {text!r}: a value is repeated")
    return key.strip(), items


def grid_specs(estimator: str, params: Sequence[tuple[str, Sequence[str]]]) -> list[EstimatorSpec]:
    """Every combination of the parameter values, as specs for `estimator` (a spec text,
    possibly with fixed overrides: `ukf:Q=1e-5`). The first parameter varies slowest."""
    (base,) = _one_spec(estimator)
    keys = [k for k, _ in params]
    if len(set(keys)) != len(keys):
        raise ValueError(f"--param names a parameter twice: {', '.join(keys)}")
    fixed = [k for k, _ in base.overrides if k in keys]
    if fixed:
        raise ValueError(f"parameter {fixed[0]!r} is both fixed in --estimator and swept by --param")
    return [EstimatorSpec(base.name, base.overrides + tuple(zip(keys, combo)))
            for combo in itertools.product(*(values for _, values in params))]


def _one_spec(text: str) -> list[EstimatorSpec]:
    specs = parse_specs(text)
    if len(specs) != 1:
        raise ValueError(f"--estimator {text!r}: name one estimator (use --preset or compare for several)")
    return specs
