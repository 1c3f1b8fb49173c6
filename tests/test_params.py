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

    from fusion.estimators.filters.ekf import EKFParams
    from fusion.estimators.filters.filter_params import BiasFilterParams, FilterParams
    from fusion.estimators.filters.ukf import UKFBiasParams, UKFParams

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

    from fusion.estimators.filters.ekf import EKFParams
    from fusion.estimators.params import FORMERLY_STD
    from fusion.estimators.smoothers.smoother import SmootherParams

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
    from fusion.estimators.smoothers.smoother import SmootherParams
    from fusion.estimators.smoothers.cost import Weights

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

    from fusion.estimators.filters.ekf import EKFParams
    from fusion.estimators.smoothers.smoother import SmootherParams

    params = SmootherParams()
    with pytest.warns(FutureWarning, match="^acc_noise_g_sqrt_s .* is now acc_noise_g2_s"):
        assert params.acc_noise_g_sqrt_s == pytest.approx(0.2, rel=1e-15)
    with pytest.warns(FutureWarning):
        assert EKFParams().invalid_gyr_std_rad_s == 2.0
    with pytest.raises(AttributeError):  # an alias was never an attribute
        params.sa
    assert pickle.loads(pickle.dumps(params)) == params


@pytest.mark.parametrize("spec, named, problem", [
    ("ekf:Q=nan", "'Q' (process_noise_rad2_s)", "must be a finite number >= 0, got nan"),
    ("gd:iters=nan", "'iters'", "'nan' is not a whole number"),
    ("ekf:Qbad=1e308", "'Qbad' (invalid_gyr_var_rad2_s2)", "Qbad=1e+308 (a standard deviation) is too large: its square"),
    ("ekf:vb=1e200", "'vb' (velocity_bound_m2_s)", "is too large"),  # its square would be inf: no velocity states
    ("gn:sg=1e200", "'sg' (process_noise_rad2_s)", "is too large"),
    ("ukf:R=1e400", "'R'", "'1e400' exceeds the largest float"),
    ("gn:Rv=1e400", "'Rv'", "write inf for infinity"),  # an overflow is not taken for the switch Rv=inf
    ("ukf:iters=inf", "'iters'", "'inf' is not a whole number"),
    ("ukf:iters=1e19", "'iters'", "too large for a count"),
    ("gn:Q=inf", "'Q' (process_noise_rad2_s)", "process_noise_rad2_s=inf: must be finite"),
    ("gd:P0=inf", "'P0' (init_var_rad2)", "must be finite"),
    ("gn:Rrest=inf", "'Rrest' (rest_noise_rad2_s)", "must be finite"),
    ("gn:tol=inf", "'tol'", "must be >= 0 and finite"),
    ("gn:rest_gyr_rad_s=inf", "'rest_gyr_rad_s'", "must be finite"),
    ("gn:level=1e-308", "'level' (init_level_s)", "must be 0 (off) or at least 0.1 s"),
])
def test_hostile_values_are_one_line_errors_naming_estimator_and_parameter(spec, named, problem):
    """Values that overflow, or are not finite where a finite value is needed, are refused when the
    spec is read (not as an OverflowError, nor a failure deep in a run, nor silently taken)."""
    with pytest.raises(ValueError) as info:
        resolve(spec)
    message = str(info.value)
    assert message.startswith(f"estimator {spec.split(':')[0]!r} parameter {named}: ")
    assert problem in message and "\n" not in message


@pytest.mark.parametrize("spec, name, value", [
    ("ekf:Q=inf", "process_noise_rad2_s", None),  # refused by the filter's own check, as before
    ("gn:huber=-1", "loss_scale_g", None),
    ("ekf:vb=inf", "velocity_bound_m2_s", float("inf")),  # inf where it switches a term off
    ("gn:R=inf", "acc_noise_g2_s", float("inf")),
    ("gn:huber=inf", "loss_scale_g", float("inf")),
    ("gn:Rv=-inf", "velocity_bound_m2_s", None),
    ("ukf:iters=1e18", "mean_max_iter", 10**18),
    ("ekf:rest_time_s=Infinity", "rest_time_s", float("inf")),
])
def test_infinity_is_taken_only_where_it_means_off(spec, name, value):
    import warnings

    if value is None:
        with pytest.raises(ValueError, match=r"^estimator '\w+' parameter '\w+' \(\w+\): "):
            resolve(spec)
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        assert getattr(resolve(spec).params, name) == value
