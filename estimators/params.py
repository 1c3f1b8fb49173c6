"""Estimator parameters from text: `ukf:R=1e-3,Q=1e-5,gn:huber=0.1`.

One syntax for every command. A spec is a registry name, optionally followed by
`:key=value` pairs; further `key=value` tokens after a comma belong to the estimator
before them. Keys are the parameter dataclass's field names or their short aliases
(declared as `field(metadata={"alias": "R"})`). An unknown key is an error that lists the
valid ones; values are converted to the field's type and validated by the dataclass. A number
that overflows a float (`1e400`) is an error, never taken for infinity: `inf` is written as such,
where a parameter takes it to switch a term off; a count must fit in 64 bits.

Each parameter of our estimators is documented at its field (`param`): its unit, a one-sentence
meaning, the published reference it implements where there is one, and its valid range, as VQF's
params struct documents each field; `fusion list NAME` (`fusion.estimators.describe`) prints them.
A spec names a parameter by its short alias (`tauc`, the spelling the tables, journals and search
spaces use) or by its field name (`disturbance_corr_s`, readable, with its unit); a field's former
aliases (`"formerly"`) are taken for one release with a `FormerSpellingWarning`.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import typing
import warnings
from dataclasses import dataclass
from typing import Any

# The metadata keys a documented parameter (`param`) carries.
DOC_KEYS = ("unit", "meaning", "valid", "reference")


class FormerSpellingWarning(DeprecationWarning):
    """A parameter given by a former alias, taken for one release; the message names the new one."""


# Shown (once per place), not hidden as Python hides a library's DeprecationWarning by default: the
# spelling is typed by the user, on the command line as often as in Python.
warnings.filterwarnings("default", category=FormerSpellingWarning)


def param(default: Any, *, unit: str, meaning: str, valid: str, reference: str = "", alias: str | None = None,
          formerly: tuple[str, ...] = (), search: Any = None) -> Any:
    """A parameter's dataclass field, documented where it lives.

    unit: spelled out (`rad^2/s`; "1" for a dimensionless number, "" for a switch or a choice);
    meaning: one full sentence (never cut where it is shown); valid: the values it takes (`> 0,
    finite; inf: off`); reference: the paper and equation it implements, where there is one;
    alias: the short key a spec uses; formerly: former aliases, taken with a warning for one
    release; search: its `fusion.estimators.search.Tunable` range, where it is tuned.
    """
    metadata: dict[str, Any] = {"unit": unit, "meaning": meaning, "valid": valid, "reference": reference}
    if alias is not None:
        metadata["alias"] = alias
    if formerly:
        metadata["formerly"] = tuple(formerly)
    if search is not None:
        metadata["search"] = search
    return dataclasses.field(default=default, metadata=metadata)


def param_as(base: type, name: str, default: Any, **changes: Any) -> Any:
    """Field `name` of the dataclass `base` with another default (and `changes` to its metadata:
    `search=...`), for a subclass whose default differs: one text per parameter."""
    source = next(f for f in dataclasses.fields(base) if f.name == name)
    metadata = {**source.metadata, **changes}
    return dataclasses.field(default=default, metadata={k: v for k, v in metadata.items() if v is not None})


# Noise and prior parameters are variances (variance densities for continuous-time noise), in
# the filters and the smoothers alike: the Q and R of the Kalman literature. Those that used to
# be standard deviations, by their former name and alias -> (their name and alias now); a former
# spelling is accepted for one release, with a FutureWarning, and its value squared.
FORMERLY_STD: dict[str, tuple[str, str]] = {
    "gyro_noise_rad_sqrt_s": ("process_noise_rad2_s", "Q"), "sg": ("process_noise_rad2_s", "Q"),
    "acc_noise_g_sqrt_s": ("acc_noise_g2_s", "R"), "sa": ("acc_noise_g2_s", "R"),
    "prior_std_rad": ("init_var_rad2", "P0"), "p0": ("init_var_rad2", "P0"),
    "dropout_noise_rad_sqrt_s": ("dropout_noise_rad2_s", "Qdrop"), "sdrop": ("dropout_noise_rad2_s", "Qdrop"),
    "bias_prior_rad_s": ("init_bias_var_rad2_s2", "Pb0"),
    "scale_prior": ("init_scale_var", "Ps0"),
    "velocity_acc_noise_g_sqrt_s": ("velocity_acc_noise_g2_s", "Qv"), "sv": ("velocity_acc_noise_g2_s", "Qv"),
    "velocity_bound_m_sqrt_s": ("velocity_bound_m2_s", "Rv"), "vb": ("velocity_bound_m2_s", "Rv"),
    "rest_noise_rad_sqrt_s": ("rest_noise_rad2_s", "Rrest"), "srest": ("rest_noise_rad2_s", "Rrest"),
    "mag_heading_walk_rad_sqrt_s": ("mag_heading_walk_rad2_s", "Qm"), "mwalk": ("mag_heading_walk_rad2_s", "Qm"),
    "invalid_gyr_std_rad_s": ("invalid_gyr_var_rad2_s2", "Qinvalid"), "Qbad": ("invalid_gyr_var_rad2_s2", "Qinvalid"),
}

# The former spellings of the smoothers (`SmootherParams`, `Weights`): all but the filters' own.
SMOOTHER_FORMER_STD = tuple(name for name in FORMERLY_STD if name not in ("invalid_gyr_std_rad_s", "Qbad"))


def former_spellings(cls: type, values: dict[str, Any]) -> dict[str, Any]:
    """`values` with every former standard-deviation spelling that `cls` had (its `former_std`,
    names and aliases of `FORMERLY_STD`) replaced by the variance it stands for, each with a
    FutureWarning."""
    out = dict(values)
    for old in [key for key in values if key in getattr(cls, "former_std", ())]:
        new, alias = FORMERLY_STD[old]
        value = out.pop(old)
        if new in out:
            raise ValueError(f"{old} and {new} ({alias}) are one parameter: give {alias} only")
        if not (isinstance(value, (int, float)) and value >= 0.0):
            raise ValueError(f"{old} must be a number >= 0 (a standard deviation), got {value!r}")
        out[new] = float(value) * float(value)  # inf for inf (a model switched off), never an OverflowError
        if math.isfinite(value) and not math.isfinite(out[new]):
            raise ValueError(f"{old}={value:g} (a standard deviation) is too large: its square, {alias} ({new}), "
                             f"exceeds the largest float, {sys.float_info.max:.4g}")
        owner = getattr(cls, "owner", cls.__name__)
        warnings.warn(f"{owner}: {old}={value:g} (a standard deviation) is now {alias}={out[new]:g} ({new}, its square, "
                      f"as every noise and prior parameter); {old} will be removed in the next release",
                      FutureWarning, stacklevel=3)
    return out


class AcceptsFormerSpellings(type):
    """Metaclass of `FormerSpellings`: `Params(old_name=std)` builds `Params(new_name=std**2)`
    with a FutureWarning (`former_spellings`)."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        return super().__call__(*args, **former_spellings(cls, kwargs))


class FormerSpellings(metaclass=AcceptsFormerSpellings):
    """Base of the parameter dataclasses whose former standard-deviation spellings (the class's
    `former_std`) are still taken for one release: as keywords (squared) and as attributes
    (the square root of the variance), each with a FutureWarning."""

    __slots__ = ()
    former_std: tuple[str, ...] = ()

    def __getattr__(self, name: str) -> Any:  # only called for names the instance does not have
        if name not in type(self).former_std or "_" not in name:  # field names only, not aliases
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        new, alias = FORMERLY_STD[name]
        warnings.warn(f"{name} (a standard deviation) is now {new} ({alias}), its square; {name} will be "
                      "removed in the next release", FutureWarning, stacklevel=2)
        return getattr(self, new) ** 0.5


@dataclass(frozen=True)
class EstimatorSpec:
    """A registry name plus parameter overrides, as text. `label` names it in tables."""

    name: str
    overrides: tuple[tuple[str, str], ...] = ()

    @property
    def label(self) -> str:
        if not self.overrides:
            return self.name
        return self.name + ":" + ",".join(f"{k}={v}" for k, v in self.overrides)


def parse_specs(text: str) -> list[EstimatorSpec]:
    """Split `ukf:R=1e-3,Q=1e-5,gn` into specs (names are not checked here).

    A name may refer to user code, `FILE.py:NAME` or `package.module:NAME`
    (`fusion.estimators.adapters.user`): a part after the first `:` without `=` belongs to the name, so
    `./my_ukf.py:MyUKF:R=1e-3` is the estimator `./my_ukf.py:MyUKF` with R=1e-3.
    """
    specs: list[tuple[str, list[tuple[str, str]]]] = []
    for token in (tok.strip() for tok in text.split(",")):
        if not token:
            continue
        head, *pairs = token.split(":")
        if "=" in head:  # a further key=value for the previous estimator
            if not specs:
                raise ValueError(f"estimator list {text!r}: {token!r} has no estimator before it")
            pairs = [head, *pairs]
        else:
            if pairs and "=" not in pairs[0]:  # FILE.py:NAME or module:NAME
                head = f"{head.strip()}:{pairs.pop(0).strip()}"
            specs.append((head.strip(), []))
        for pair in pairs:
            key, sep, value = pair.partition("=")
            if not sep or not key.strip() or not value.strip():
                raise ValueError(f"estimator list {text!r}: expected key=value, got {pair!r}")
            specs[-1][1].append((key.strip(), value.strip()))
    if not specs:
        raise ValueError(f"estimator list {text!r} names no estimator")
    return [EstimatorSpec(name, tuple(pairs)) for name, pairs in specs]


def _convert(value: str, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        choices = typing.get_args(annotation)
        if value not in choices:
            raise ValueError(f"{where}: {value!r} is not one of {', '.join(map(str, choices))}")
        return value
    if annotation is bool:
        low = value.lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"{where}: {value!r} is not a boolean (true/false)")
    if annotation in (int, float):
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"{where}: {value!r} is not a number") from None
        if math.isinf(number) and value.strip().lstrip("+-").lower() not in ("inf", "infinity"):
            raise ValueError(f"{where}: {value!r} exceeds the largest float, {sys.float_info.max:.4g} "
                             "(write inf for infinity where a parameter takes it)")
        if annotation is int:
            if not math.isfinite(number) or number != int(number):
                raise ValueError(f"{where}: {value!r} is not a whole number")
            if not -2**63 <= number < 2**63:  # the compiled kernels take counts as 64-bit integers
                raise ValueError(f"{where}: {value!r} is too large for a count (at most 2^63 - 1)")
            return int(number)
        return number
    if annotation is str:
        return value
    raise ValueError(f"{where}: parameters of type {annotation} cannot be set from text")


def make_params(params_cls: type, overrides: tuple[tuple[str, str], ...] | dict[str, str], owner: str = "") -> Any:
    """Build `params_cls` with text overrides applied; unknown keys are an error."""
    items = overrides.items() if isinstance(overrides, dict) else overrides
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    aliases = {f.metadata["alias"]: f.name for f in fields.values() if "alias" in f.metadata}
    former = {old: f.name for f in fields.values() for old in f.metadata.get("formerly", ())}
    hints = typing.get_type_hints(params_cls)
    values: dict[str, Any] = {}
    typed: dict[str, str] = {}  # field name -> the key as typed (a field name or its alias)
    for key, text in items:
        name = aliases.get(key, key)
        if name not in fields and key in former:  # a former alias, taken for one release
            name = former[key]
            new = fields[name].metadata.get("alias", name)
            warnings.warn(f"estimator {owner!r}: parameter {key!r} is now {new!r} ({name}); {key!r} will be "
                          "removed in the next release", FormerSpellingWarning, stacklevel=2)
        if name in typed and (key in former or typed[name] in former):
            raise ValueError(f"estimator {owner!r}: {typed[name]!r} and {key!r} are one parameter ({name})")
        if key in getattr(params_cls, "former_std", ()):  # a former spelling, converted by the class
            values[key] = _convert(text, float, f"estimator {owner!r} parameter {key!r}")
            typed[FORMERLY_STD[key][0]] = key
            continue
        if name not in fields:
            valid = sorted(set(fields) | set(aliases))
            raise ValueError(
                f"estimator {owner!r}: unknown parameter {key!r}; valid: {', '.join(valid) or '(none)'}"
            )
        values[name] = _convert(text, hints[name], f"estimator {owner!r} parameter {key!r}")
        typed[name] = key
    try:
        return params_cls(**values)
    except ValueError as exc:  # the dataclass names its field: name what the user typed as well
        message = str(exc)
        named = [f"{key!r}" + (f" ({name})" if key != name else "") for name, key in typed.items() if name in message]
        named = named or [f"{key!r}" for key in typed.values()]
        raise ValueError(f"estimator {owner!r} parameter {', '.join(named)}: {message}") from None

