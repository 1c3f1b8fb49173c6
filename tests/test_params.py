"""Estimator specs from text: one syntax, strict names."""
from dataclasses import dataclass, field
from typing import Literal

import pytest

from fusion.estimators.params import make_params, parse_specs


@dataclass(frozen=True)
class P:
    accel_noise_g: float = field(default=0.1, metadata={"alias": "R"})
    sigma: Literal["kraft", "julier"] = "kraft"
    iterations: int = 10
    gating: bool = True


def test_parse_specs_groups_pairs_with_their_estimator():
    specs = parse_specs("ukf:R=1e-3,Q=1e-5,gn:huber=0.1,dr")
    assert [s.name for s in specs] == ["ukf", "gn", "dr"]
    assert specs[0].overrides == (("R", "1e-3"), ("Q", "1e-5"))
    assert specs[0].label == "ukf:R=1e-3,Q=1e-5"
    assert specs[2].label == "dr"


def test_make_params_converts_and_checks():
    p = make_params(P, {"R": "1e-3", "sigma": "julier", "iterations": "5", "gating": "off"})
    assert p == P(1e-3, "julier", 5, False)
    with pytest.raises(ValueError, match="unknown parameter 'Rr'; valid: R, accel_noise_g, gating, iterations, sigma"):
        make_params(P, {"Rr": "1"}, owner="ukf")
    with pytest.raises(ValueError, match="not one of kraft, julier"):
        make_params(P, {"sigma": "merwe"})
    with pytest.raises(ValueError, match="not a whole number"):
        make_params(P, {"iterations": "2.5"})
    with pytest.raises(ValueError, match="expected key=value"):
        parse_specs("ukf:R")
