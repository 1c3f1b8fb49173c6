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


def test_filters_and_smoothers_spell_each_noise_one_way():
    """Every noise and prior parameter is a variance, and one physical quantity has one name and
    alias in the filters and the smoothers alike."""
    import dataclasses as dc

    from fusion.estimators.ekf import EKFParams
    from fusion.estimators.params import FORMERLY_STD
    from fusion.estimators.smoother import SmootherParams

    filt = {f.name: f.metadata.get("alias") for f in dc.fields(EKFParams)}
    smooth = {f.name: f.metadata.get("alias") for f in dc.fields(SmootherParams)}
    shared = {"process_noise_rad2_s", "acc_noise_g2_s", "init_var_rad2", "init_bias_var_rad2_s2", "init_scale_var",
              "rest_noise_rad2_s", "mag_heading_noise_rad2_s", "velocity_acc_noise_g2_s", "velocity_bound_m2_s"}
    assert shared <= set(filt) & set(smooth)
    assert all(filt[name] == smooth[name] for name in shared)
    # No field of either is still a standard deviation of a noise or prior.
    assert not (set(filt) | set(smooth)) & set(FORMERLY_STD)


@pytest.mark.parametrize("old, new, name, value", [
    ("gn:sa=0.2", "gn:R=0.04", "acc_noise_g2_s", 0.04),
    ("gn:vb=0.5,sg=0.01", "gn:Rv=0.25,Q=1e-4", "velocity_bound_m2_s", 0.25),
    ("gd:bias_prior_rad_s=0.1", "gd:Pb0=0.01", "init_bias_var_rad2_s2", 0.01),
    ("ekf:Qbad=2", "ekf:Qinvalid=4", "invalid_gyr_var_rad2_s2", 4.0),
    ("ekf:vb=inf", "ekf:Rv=inf", "velocity_bound_m2_s", float("inf")),
])
def test_former_standard_deviations_are_squared_with_a_warning(old, new, name, value):
    from fusion.estimators import build

    with pytest.warns(FutureWarning, match=r"\(a standard deviation\) is now .* removed in the next release"):
        params = build(old).params
    assert getattr(params, name) == pytest.approx(value, rel=1e-15)
    assert getattr(build(new).params, name) == pytest.approx(value, rel=1e-15)


def test_former_spellings_in_python_and_their_errors():
    from fusion.estimators import build
    from fusion.estimators.smoother import SmootherParams
    from fusion.estimators.smoother_cost import Weights

    with pytest.warns(FutureWarning, match="^gn: gyro_noise_rad_sqrt_s=0.02"):
        assert SmootherParams(gyro_noise_rad_sqrt_s=0.02).process_noise_rad2_s == pytest.approx(4e-4, rel=1e-15)
    with pytest.warns(FutureWarning):
        assert Weights(acc_noise_g_sqrt_s=0.1).acc_noise_g2_s == pytest.approx(0.01, rel=1e-15)
    with pytest.raises(ValueError, match="'sa'.* must be a number >= 0 \\(a standard deviation\\), got -1.0"):
        build("gn:sa=-1")
    with pytest.raises(ValueError, match="one parameter: give R only"):
        build("gn:sa=0.2,R=0.04")
    with pytest.raises(ValueError, match="unknown parameter 'sa'"):  # ukf never had it
        build("ukf:sa=0.2")


def test_former_attributes_read_as_standard_deviations_with_a_warning():
    import pickle

    from fusion.estimators.ekf import EKFParams
    from fusion.estimators.smoother import SmootherParams

    params = SmootherParams()
    with pytest.warns(FutureWarning, match="^acc_noise_g_sqrt_s .* is now acc_noise_g2_s"):
        assert params.acc_noise_g_sqrt_s == pytest.approx(0.2, rel=1e-15)
    with pytest.warns(FutureWarning):
        assert EKFParams().invalid_gyr_std_rad_s == 2.0
    with pytest.raises(AttributeError):  # an alias was never an attribute
        params.sa
    assert pickle.loads(pickle.dumps(params)) == params
