"""Values of `fusion.evaluation.run.settings.RunSettings`' fields other than their defaults, derived from
each field's command-line option (`Option`), so that a field added with an option is covered by the
tests of the command line and of the journal without naming it there."""
from __future__ import annotations

import dataclasses
from typing import Any

# a value of each `Option.type`: as typed, and as the field then holds it
_TYPED = {None: ("x/y", "x/y"), "int": ("3", 3), "count": ("3", 3), "float": ("2.5", 2.5), "seconds": ("2.5", 2.5)}


def not_default(f: dataclasses.Field, option: Any) -> tuple[list[str], Any]:
    """The words of a command line giving `option` a value other than its field's default, and the
    field's value then."""
    if option.kind == "switch":
        return [option.flag], True
    if option.kind == "negated":
        return [option.flag], False
    if option.kind == "on_off":
        return [option.flag, "off" if f.default else "on"], not f.default
    if option.kind == "auto_on_off":  # the default is auto (None)
        return [option.flag, "off"], False
    if option.kind == "choices":
        choice = next(c for c in option.choices if c != f.default)
        return [option.flag, choice], choice
    text, value = _TYPED[option.type]
    return [option.flag, text], value


def not_default_values(names: Any) -> dict[str, Any]:
    """A value other than the default for each of the `RunSettings` fields named."""
    from fusion.evaluation.run.settings import RunSettings

    fields = {f.name: f for f in dataclasses.fields(RunSettings)}
    return {name: not_default(fields[name], fields[name].metadata["cli"])[1] for name in names}
