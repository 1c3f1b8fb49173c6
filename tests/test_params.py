"""Estimator specs from text: one syntax, strict names."""
from dataclasses import dataclass, field
from typing import Literal

import pytest

from fusion.estimators import resolve
from fusion.estimators.params import EstimatorSpec, make_params, parse_specs


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
        parse_specs("ukf:Q=1:R")
    assert parse_specs("ukf:R") == [EstimatorSpec("ukf:R")]  # FILE.py:NAME or module:NAME: `resolve` checks it
    with pytest.raises(ValueError, match="estimator 'ukf': expected key=value, got 'R'"):
        resolve("ukf:R")


def test_filter_params_share_one_base_with_one_alias_per_field():
    import dataclasses as dc

    from fusion.estimators.ekf import EKFParams
    from fusion.estimators.filter_params import BiasFilterParams, FilterParams
    from fusion.estimators.ukf import UKFBiasParams, UKFParams

    assert issubclass(UKFParams, FilterParams) and not issubclass(UKFParams, BiasFilterParams)
    assert issubclass(UKFBiasParams, BiasFilterParams) and issubclass(EKFParams, BiasFilterParams)
    base = {f.name: f.metadata.get("alias") for f in dc.fields(BiasFilterParams)}
    for cls in (UKFParams, UKFBiasParams, EKFParams):
        for f in dc.fields(cls):
            if f.name in base:
                assert f.metadata.get("alias") == base[f.name], (cls.__name__, f.name)
    # The bias filters keep the base defaults; ukf keeps its own.
    assert UKFBiasParams().process_noise_rad2_s == EKFParams().process_noise_rad2_s == 3e-4
    assert UKFParams().process_noise_rad2_s == 1e-3 and UKFParams().disturbance_corr_s == 0.5
    assert UKFParams().gate_g == 0.1 and UKFParams().heading_free is False
    assert make_params(UKFParams, {"Q": "2e-3", "tauc": "0"}) == UKFParams(process_noise_rad2_s=2e-3, disturbance_corr_s=0.0)
    # One place for the shared checks, with each filter's name in the message.
    for cls, owner in ((UKFParams, "ukf"), (UKFBiasParams, "ukf-bias"), (EKFParams, "ekf")):
        with pytest.raises(ValueError, match=f"^{owner}: process_noise_rad2_s must be a finite number >= 0"):
            cls(process_noise_rad2_s=-1.0)
    with pytest.raises(ValueError, match="^ekf: scale_max must be in"):
        EKFParams(scale_max=1.5)
