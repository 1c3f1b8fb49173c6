"""Estimator parameters from text: `ukf:R=1e-3,Q=1e-5,gn:huber=0.1`.

One syntax for every command. A spec is a registry name, optionally followed by
`:key=value` pairs; further `key=value` tokens after a comma belong to the estimator
before them. Keys are the parameter dataclass's field names or their short aliases
(declared as `field(metadata={"alias": "R"})`). An unknown key is an error that lists the
valid ones; values are converted to the field's type and validated by the dataclass.
"""
from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any


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
    (`fusion.estimators.user`): a part after the first `:` without `=` belongs to the name, so
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
        if annotation is int:
            if number != int(number):
                raise ValueError(f"{where}: {value!r} is not a whole number")
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
    hints = typing.get_type_hints(params_cls)
    values: dict[str, Any] = {}
    typed: dict[str, str] = {}  # field name -> the key as typed (a field name or its alias)
    for key, text in items:
        name = aliases.get(key, key)
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

