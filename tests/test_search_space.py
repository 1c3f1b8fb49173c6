"""Search spaces declared in the parameter dataclasses (`fusion.estimators.search`), and
`fusion list NAME`, which shows every parameter with its alias, default, unit, meaning and range."""
import dataclasses
import itertools
import typing

import pytest

from fusion.cli import main
from fusion.estimators import ESTIMATORS
from fusion.estimators.describe import FORMER_TITLE, format_parameters, meanings, parameter_table, unit_of
from fusion.estimators.filters.ekf import EKFParams
from fusion.estimators.params import FORMERLY_STD, make_params
from fusion.estimators.search import Tunable, alias_of, default_of, search_space

OURS = ("dr", "ukf", "ukf-bias", "ekf", "gd", "gn")
BIAS_FILTER = {"Q": 3e-4, "R": 3e-5, "tauc": 0.1, "taulp": 1.0, "Qb": 1e-8, "Ps0": 1e-2, "sprt": 0.1, "Psc": 1e-4,
               "Rm": 0.3}
SMOOTHER = {"Q": 1e-4, "R": 0.04, "huber": 0.1, "Qv": 1e-4, "Rv": 0.25, "Rm": 0.1}
# What our estimators tune, by alias, at their defaults: the defaults the README's tables were run with.
SPACES = {
    "dr": {},
    "ukf": {"Q": 1e-3, "R": 3e-5, "tauc": 0.5, "Qs": 2e-2},
    "ukf-bias": BIAS_FILTER,
    "ekf": {**BIAS_FILTER, "taulp": 2.0, "Qv": 1e-4, "Rv": 1.0},
    "gd": SMOOTHER,
    "gn": SMOOTHER,
}
GRIDDED = {"ukf": {"Q", "R", "tauc"}, "ukf-bias": {"Q", "R", "tauc"}, "ekf": {"Q", "R", "tauc"},
           "gd": {"Q", "R", "huber"}, "gn": {"Q", "R", "huber"}}


def _text(value: float) -> str:
    return repr(float(value))


def test_our_estimators_declare_these_spaces_at_unchanged_defaults():
    for name in OURS:
        params = ESTIMATORS[name].Params
        space = search_space(params)
        assert {alias_of(params, field): default_of(params, field) for field in space} == SPACES[name], name
        assert {alias_of(params, field) for field, t in space.items() if t.grid} == GRIDDED.get(name, set()), name
        built = params()  # the dataclass's default is the field's default (metadata changes nothing)
        assert all(getattr(built, field) == default_of(params, field) for field in space)


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_every_declared_space_is_valid(name):
    params = ESTIMATORS[name].Params
    for field, tunable in search_space(params).items():
        where = f"{name}.{field}"
        assert isinstance(tunable, Tunable), where
        assert all(tunable.low <= v <= tunable.high for v in tunable.grid), where
        default = default_of(params, field)
        assert tunable.low <= default <= tunable.high, f"{where}: default {default} outside its range"
        alias = alias_of(params, field)
        # the alias a search writes into a spec is one make_params takes, for every value of the range
        for value in (tunable.low, default, tunable.high):
            assert getattr(make_params(params, {alias: _text(value)}, owner=name), field) == value, where


@pytest.mark.parametrize("name", [n for n in ESTIMATORS if any(t.grid for t in search_space(ESTIMATORS[n].Params).values())])
def test_every_grid_point_builds_valid_params(name):
    params = ESTIMATORS[name].Params
    gridded = {alias_of(params, f): t.grid for f, t in search_space(params).items() if t.grid}
    points = list(itertools.product(*gridded.values()))
    for point in points:
        built = make_params(params, {alias: _text(v) for alias, v in zip(gridded, point)}, owner=name)
        fields = {f.metadata.get("alias", f.name): f.name for f in dataclasses.fields(params)}
        assert [getattr(built, fields[alias]) for alias in gridded] == list(point)
    assert len(points) == len(set(points))


@pytest.mark.parametrize("name", [n for n in OURS if n != "dr"])
def test_our_grid_presets_are_small_and_bracket_the_defaults(name):
    params = ESTIMATORS[name].Params
    grids = {f: t.grid for f, t in search_space(params).items() if t.grid}
    assert 2 <= len(grids) <= 3
    size = 1
    for field, grid in grids.items():
        default = default_of(params, field)
        assert len(grid) == 3 and default in grid and min(grid) < default < max(grid), (field, grid)
        size *= len(grid)
    assert size <= 27
    for field, tunable in search_space(params).items():  # noise densities: a decade or more either side
        if tunable.log and field.endswith(("_rad2_s", "_g2_s", "_m2_s", "_rad2_s3")):
            default = default_of(params, field)
            assert tunable.low <= default / 10 and tunable.high >= default * 10, field


def test_units_from_field_name_suffixes():
    cases = {"process_noise_rad2_s": "rad^2/s", "acc_noise_g2_s": "g^2 s", "init_var_rad2": "rad^2",
             "bias_walk_rad2_s3": "rad^2/s^3", "init_bias_var_rad2_s2": "rad^2/s^2", "bias_max_rad_s": "rad/s",
             "mag_dip_gate_rad": "rad", "bias_clip_deg_s": "deg/s", "acceleration_rejection_deg": "deg",
             "gate_g": "g", "velocity_bound_m2_s": "m^2/s", "rest_th_acc_m_s2": "m/s^2", "scale_walk_1_s": "1/s",
             "rest_time_s": "s", "mag_hard_iron_residual_ut": "uT", "gain": "", "s": "", "k_p": ""}
    assert {name: unit_of(name) for name in cases} == cases
    assert unit_of("mode_s", annotation=str) == ""  # a text field has no unit
    assert unit_of("mag_heading_noise_rad2_s", {"unit": "rad^2 s"}) == "rad^2 s"  # metadata overrides the suffix
    rows = {r.name: r for r in parameter_table(EKFParams)}
    assert rows["mag_heading_noise_rad2_s"].unit == "rad^2 s" and rows["rest_noise_rad2_s"].unit == "rad^2/s"


def test_meanings_come_from_the_docstring_or_the_fields_doc():
    @dataclasses.dataclass(frozen=True)
    class P:
        """Parameters of a test estimator.

        Noise is a density: see
        the literature.
        gain_rad_s (k): the correction gain, rad/s (the
            loop's bandwidth); 0 turns it off.
        lo_s, hi_s: the band's edges, s. mode (m): "a" or "b". sigma: a scheme; kappa its parameter.
        """

        gain_rad_s: float = dataclasses.field(default=0.1, metadata={"alias": "k"})
        lo_s: float = 1.0
        hi_s: float = 2.0
        mode: str = dataclasses.field(default="a", metadata={"alias": "m"})
        sigma: str = "x"
        kappa: float = 1.0
        extra_g: float = dataclasses.field(default=0.5, metadata={"doc": "what no docstring says, g. More."})
        bare: int = 3

    assert meanings(P) == {"gain_rad_s": "the correction gain, rad/s (the loop's bandwidth)",
                           "lo_s": "the band's edges, s", "hi_s": "the band's edges, s", "mode": '"a" or "b"',
                           "sigma": "a scheme", "kappa": "kappa its parameter",
                           "extra_g": "what no docstring says, g", "bare": ""}
    rows = parameter_table(P)
    assert [(r.alias, r.name, r.default, r.unit) for r in rows[:4]] == [
        ("k", "gain_rad_s", "0.1", "rad/s"), ("lo_s", "lo_s", "1", "s"), ("hi_s", "hi_s", "2", "s"), ("m", "mode", "a", "")]
    assert "no parameters" in format_parameters(ESTIMATORS["dr"].Params, "dr")


@pytest.mark.parametrize("name", [n for n in OURS if n != "dr"])
def test_every_parameter_of_ours_has_one_meaning(name):
    """Our estimators' meanings come from their fields, whole: no docstring parsing, nothing cut."""
    params = ESTIMATORS[name].Params
    rows = parameter_table(params)
    assert rows and all(r.meaning for r in rows), [r.name for r in rows if not r.meaning]
    by_field = {f.name: f.metadata for f in dataclasses.fields(params)}
    assert all(r.meaning == by_field[r.name]["meaning"] for r in rows)
    assert all(r.valid == by_field[r.name]["valid"] and r.valid for r in rows)
    assert not any(r.meaning.endswith("...") for r in rows)
    assert meanings(params) == {f: m["meaning"] for f, m in by_field.items()}


def _rows(out: str) -> tuple[dict[str, str], list[str]]:
    """The `fusion list NAME` parameter rows by their first token (the indented lines below a row, its
    meaning, valid range and reference, left out), and the lines of the former spellings."""
    lines = out.splitlines()
    end = next((i for i, line in enumerate(lines) if line.startswith(FORMER_TITLE)), len(lines))
    rows = {line.split()[0]: line for line in lines[2:end] if line.strip() and not line.startswith(" ")}
    return rows, lines[end + 1:]


def _details(out: str) -> dict[str, str]:
    """The text below each `fusion list NAME` parameter row (its indented lines joined), by the row's
    first token."""
    lines = out.splitlines()
    end = next((i for i, line in enumerate(lines) if line.startswith(FORMER_TITLE)), len(lines))
    details: dict[str, list[str]] = {}
    for line in lines[2:end]:
        if line.startswith(" "):
            details[key].append(line.strip())
        elif line.strip():
            key = line.split()[0]
            details[key] = []
    return {key: " ".join(parts) for key, parts in details.items()}


def test_fusion_list_ekf_shows_every_parameter_and_the_former_spellings_apart(capsys):
    assert main(["list", "ekf"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    count = len(dataclasses.fields(EKFParams))
    assert out.splitlines()[0].startswith(f"ekf: {count} parameters")
    assert out.splitlines()[1].split() == ["alias", "field", "default", "unit", "search", "range"]
    rows, former = _rows(out)
    details = _details(out)
    hints = typing.get_type_hints(EKFParams)
    assert len(rows) == count
    for f in dataclasses.fields(EKFParams):
        alias = f.metadata.get("alias", f.name)
        cells = rows[alias].split()
        assert cells[1] == f.name
        # the whole meaning, the valid range and the reference below the row, wrapped, never cut
        assert f.metadata["meaning"] in details[alias], alias
        assert f"valid: {f.metadata['valid']}" in details[alias], alias
        assert not f.metadata["reference"] or f"reference: {f.metadata['reference']}" in details[alias], alias
        default = f.default
        expect = str(default).lower() if isinstance(default, bool) else f"{default:g}" if isinstance(default, float) else str(default)
        assert cells[2] == expect, (alias, cells)
        unit = unit_of(f.name, f.metadata, hints[f.name])
        if unit:
            assert f"  {unit}  " in rows[alias] + "  ", (alias, unit)
        if "search" in f.metadata:
            search = f.metadata["search"]
            assert rows[alias].endswith(search.describe() + ("; 9-D only" if search.magnetometer else ""))
    assert details["Q"].startswith("Gyro (attitude process) noise density")
    assert "..." not in out and max(len(line) for line in out.splitlines() if line.startswith(" ")) <= 100
    assert rows["Q"].endswith("[3e-06, 0.03] log; grid 0.0001, 0.0003, 0.001")
    assert "  rad^2 s  " in rows["Rm"] and rows["Rm"].endswith("9-D only") and "  rad^2/s^3  " in rows["Qb"]
    # the former spellings: at the end, not among the parameters, each with what it is now
    taken = set(EKFParams.former_std)
    assert taken == {"invalid_gyr_std_rad_s", "Qbad", "velocity_acc_noise_g_sqrt_s", "sv", "velocity_bound_m_sqrt_s", "vb"}
    assert not taken & set(rows)
    listed = " ".join(former)
    for old in taken:
        new, alias = FORMERLY_STD[old]
        assert any(old in line.split(" -> ")[0] and f"{alias} ({new})" in line for line in former), old
    assert "sa" not in listed.split()  # a smoother's former spelling, not ekf's


def test_fusion_list_a_users_file(tmp_path, capsys):
    (tmp_path / "mine.py").write_text(
        "import numpy as np\n\n"
        "def complementary(t, gyro, acc, q0, gain: float = 0.02, tau_s: float = 1.5):\n"
        "    return np.tile(q0, (len(t), 1))\n")
    spec = f"{tmp_path / 'mine.py'}:complementary"
    assert main(["list", spec]) == 0
    rows, former = _rows(capsys.readouterr().out)
    assert rows["gain"].split()[:3] == ["gain", "gain", "0.02"]
    assert rows["tau_s"].split() == ["tau_s", "tau_s", "1.5", "s"]
    assert former == []


@pytest.mark.parametrize("argv, message", [
    (["list", "nonsense"], "fusion: error: unknown estimator 'nonsense'; available: dr, ukf"),
    (["list", "ekf:Q=1"], "fusion: error: 'ekf:Q=1': give one estimator's name, without parameters"),
])
def test_fusion_list_of_an_unknown_name_is_one_line(capsys, argv, message):
    assert main(argv) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(message) and err.count("\n") == 1
