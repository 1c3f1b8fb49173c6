"""Parameters documented at their fields (`fusion.estimators.params.param`): unit, meaning, valid
range and reference in each field's metadata, `fusion list NAME` printed from them whole, and the
former aliases taken with a warning that names the new one."""
import dataclasses
import re
import typing
import warnings

import numpy as np
import pytest

from fusion.cli import main
from fusion.estimators import ESTIMATORS, build
from fusion.estimators.describe import UNIT_SUFFIXES, describe, former_aliases
from fusion.estimators.params import DOC_KEYS, FormerSpellingWarning, make_params

OURS = ("ukf", "ukf-bias", "ekf", "gd", "gn")  # dr has no parameters
# Every registered peer with parameters documents them at its fields too (a user's estimator's
# docstring is read instead: tests/test_search_space.py).
PEERS = tuple(name for name, cls in ESTIMATORS.items() if name not in OURS
              and dataclasses.is_dataclass(getattr(cls, "Params", None)) and dataclasses.fields(cls.Params))
# Fields whose unit is not the one their suffix reads as: a measurement's density is in rad^2 s.
UNIT_NOT_THE_SUFFIX = {"mag_heading_noise_rad2_s": "rad^2 s"}


def _fields(name: str) -> list[dataclasses.Field]:
    return list(dataclasses.fields(ESTIMATORS[name].Params))


def _suffix_unit(name: str) -> str | None:
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix) and len(name) > len(suffix)), None)


def _text(value) -> str:
    return str(value).lower() if isinstance(value, bool) else f"{value!r}" if isinstance(value, float) else str(value)


@pytest.mark.parametrize("name", OURS + PEERS)
def test_every_parameter_of_ours_is_documented_at_its_field(name):
    params = ESTIMATORS[name].Params
    hints = typing.get_type_hints(params)
    assert ESTIMATORS["dr"].Params is None or not dataclasses.fields(ESTIMATORS["dr"].Params)
    for f in _fields(name):
        meta = f.metadata
        assert set(DOC_KEYS) <= set(meta), (name, f.name)
        meaning = meta["meaning"]
        # one sentence, whole: a capital or a name first, one full stop, at the end
        assert meaning[0].isupper() or meaning.split()[0].islower(), (f.name, meaning)
        assert meaning.endswith(".") and not re.search(r"\.\s+[A-Z]", meaning), (f.name, meaning)
        assert "..." not in meaning and meta["valid"], f.name
        kind = hints[f.name]
        if kind in (int, float) and kind is not bool:
            if kind is float:
                assert meta["unit"], f.name  # a number has a unit ("1" where it is dimensionless)
            expected = UNIT_NOT_THE_SUFFIX.get(f.name) or _suffix_unit(f.name)
            if expected:
                assert meta["unit"] == expected, (f.name, meta["unit"], expected)
        elif kind is bool:
            assert meta["unit"] == "" and meta["valid"].startswith("true | false"), f.name
        elif typing.get_origin(kind) is typing.Literal:
            assert meta["unit"] == "", f.name
            choices = re.split(r"[ |;:,()]+", meta["valid"])
            assert all(c in choices for c in typing.get_args(kind)), (f.name, meta["valid"])
        assert f.default is not dataclasses.MISSING


@pytest.mark.parametrize("name", OURS + PEERS)
def test_fusion_list_prints_every_meaning_whole(name, capsys):
    assert main(["list", name]) == 0
    out = capsys.readouterr().out
    flat = " ".join(line.strip() for line in out.splitlines())
    assert "..." not in out
    for f in _fields(name):
        assert f.metadata["meaning"] in flat, f.name
        assert f"valid: {f.metadata['valid']}" in flat, f.name
        if f.metadata["reference"]:
            assert f"reference: {f.metadata['reference']}" in flat, f.name
    assert out == describe(name) + "\n"


@pytest.mark.parametrize("name", OURS)
def test_the_field_name_is_a_spec_key_as_its_alias_is(name):
    """The readable name (the field's, with its unit) and the short alias set the same parameter."""
    params = ESTIMATORS[name].Params
    for f in _fields(name):
        if "alias" not in f.metadata or isinstance(f.default, str):
            continue
        value = not f.default if isinstance(f.default, bool) else f.default
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            try:
                by_alias = make_params(params, {f.metadata["alias"]: _text(value)}, owner=name)
            except ValueError:  # a value another option must allow: the field name must say the same
                with pytest.raises(ValueError):
                    make_params(params, {f.name: _text(value)}, owner=name)
                continue
            assert make_params(params, {f.name: _text(value)}, owner=name) == by_alias


def _sim_imu(duration_s: float):
    from fusion.calibration import calibrate
    from fusion.sim import SimSettings, simulate

    raw, truth = simulate(SimSettings(duration_s=duration_s))
    imu = calibrate(raw).apply(raw)
    q0, _ = truth.interpolate(imu.t[:1])
    return imu, q0.as_quat(scalar_first=True)[0]


@pytest.mark.parametrize("name", ["gn", "gd"])
@pytest.mark.parametrize("old, new", [("bias=xyz", "baxes=xyz"), ("scale=none", "saxes=none")])
def test_a_former_alias_gives_the_same_estimate_and_warns(name, old, new):
    imu, q0 = _sim_imu(3.0)
    with pytest.warns(FormerSpellingWarning, match=rf"parameter '{old.split('=')[0]}' is now '{new.split('=')[0]}'"):
        before = build(f"{name}:{old},progress=false,iters=5")
    with warnings.catch_warnings():
        warnings.simplefilter("error", FormerSpellingWarning)
        after = build(f"{name}:{new},progress=false,iters=5")
    assert before.params == after.params
    a, b = before.estimate(imu, q0), after.estimate(imu, q0)
    np.testing.assert_array_equal(a.quat_wxyz, b.quat_wxyz)  # to the bit


def test_the_filters_switches_keep_their_names_without_a_warning():
    """`bias` and `scale` are the filters' switches; the smoothers' axis options are baxes and saxes."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", FormerSpellingWarning)
        params = build("ekf:bias=false,scale=false").params
        assert params.estimate_bias is False and params.estimate_scale is False
        assert build("ekf:saxes=x").params.scale_axes == "x"
        assert build("gn:saxes=x,baxes=z").params.scale_axes == "x"
    assert former_aliases(ESTIMATORS["gn"].Params) == [("bias", "baxes", "bias_axes"), ("scale", "saxes", "scale_axes")]
    assert former_aliases(ESTIMATORS["ekf"].Params) == []


@pytest.mark.parametrize("spec, message", [
    ("gn:baxis=xy", "unknown parameter 'baxis'"),  # misspelt: an error, as always
    ("ekf:mhgg=0.1", "unknown parameter 'mhgg'"),
    ("ekf:baxes=xy", "unknown parameter 'baxes'"),  # the filters have no bias axes
    ("gn:scale=xy,saxes=x", "'scale' and 'saxes' are one parameter (scale_axes)"),
    ("gd:baxes=x,bias=y", "'baxes' and 'bias' are one parameter (bias_axes)"),
    ("gn:scale=true", "scale_axes='true': expected distinct letters"),  # the filters' switch, given to a smoother
])
def test_misspelt_and_doubled_names_are_errors(spec, message):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FormerSpellingWarning)
        with pytest.raises(ValueError, match=re.escape(message)):
            build(spec)


def test_fusion_list_gn_lists_the_former_aliases(capsys):
    assert main(["list", "gn"]) == 0
    out = capsys.readouterr().out
    tail = out.split("former spellings", 1)[1].splitlines()
    assert any(line.split() == ["bias", "->", "baxes", "(bias_axes)"] for line in tail)
    assert any(line.split() == ["scale", "->", "saxes", "(scale_axes)"] for line in tail)



def test_the_peers_with_parameters_are_all_there():
    assert {"vqf", "vqf-basic", "fusion-ahrs", "madgwick", "mahony", "ahrs-ekf", "aqua", "fkf", "quest",
            "qmt-oriestimu"} <= set(PEERS)


def test_the_parameters_document_is_generated_from_the_fields():
    """docs/parameters.md is `reference()` as it is now: regenerate it with
    `python -m fusion.estimators.describe > docs/parameters.md`."""
    from pathlib import Path

    from fusion.estimators.describe import reference

    doc = (Path(__file__).resolve().parents[1] / "docs" / "parameters.md").read_text()
    assert doc == reference()
    for name in OURS:
        for f in _fields(name):
            assert f.metadata["meaning"] in doc


def test_a_users_params_documented_with_param_are_listed_whole():
    from dataclasses import dataclass

    from fusion.estimators.describe import format_parameters
    from fusion.estimators.params import param

    long = "The correction gain, " + "which is said at length so that it wraps, " * 4 + "never cut."

    @dataclass(frozen=True)
    class Params:
        """Parameters (their documentation is at the fields)."""

        gain_rad_s: float = param(0.1, alias="k", unit="rad/s", valid="> 0", meaning=long,
                                  reference="Someone 2020, eq. 3")

    out = format_parameters(Params, "mine")
    assert out.splitlines()[2].split() == ["k", "gain_rad_s", "0.1", "rad/s"]
    below = " ".join(line.strip() for line in out.splitlines()[3:])
    assert below == f"{long} valid: > 0 reference: Someone 2020, eq. 3"
    assert all(len(line) <= 100 for line in out.splitlines()[3:]) and len(out.splitlines()) > 5
    assert make_params(Params, {"gain_rad_s": "0.2"}) == make_params(Params, {"k": "0.2"}) == Params(0.2)
