"""An estimator's parameters as a table: what `fusion list NAME` prints.

One entry per field of the estimator's `Params` dataclass: the short name a spec uses (the field's
alias, else its name), the field name, the default, the unit, the search range the field declares
(`fusion.estimators.search.Tunable`), and below them, wrapped, never cut, the field's meaning, its
valid range and its reference.

Our estimators document each parameter at its field (`fusion.estimators.params.param`: `"unit"`,
`"meaning"`, `"valid"`, `"reference"` metadata); those are printed as they are. A class without them
(a peer's adapter, a user's estimator) falls back to its docstring: an entry `name (alias): meaning
...` on a line of its own or after a full stop or a semicolon (several names may share one entry),
else the field's `"doc"` metadata, else the clause of an entry that names the field (`sigma: ...;
kappa, alpha, beta their parameters`), of which the first clause is shown; its unit then comes from
the field name's suffix (`process_noise_rad2_s`: rad^2/s, `UNIT_SUFFIXES`). The former
standard-deviation spellings a class still takes (`fusion.estimators.params.FORMERLY_STD`) and the
former aliases of its fields are listed apart.

    from fusion.estimators.describe import describe
    print(describe("ekf"))

`docs/parameters.md` is `reference()`, every registered estimator's parameters as Markdown tables,
written by `python -m fusion.estimators.describe > docs/parameters.md` (a test checks it is current).
"""
from __future__ import annotations

import dataclasses
import inspect
import re
import textwrap
import typing
from dataclasses import dataclass
from typing import Any

from .params import FORMERLY_STD, parse_specs
from .search import Tunable

# Field-name suffix -> unit, the longest suffix first (`_rad2_s3` before `_rad2_s` before `_s`).
UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_rad2_s3", "rad^2/s^3"),
    ("_rad2_s2", "rad^2/s^2"),
    ("_rad2_s", "rad^2/s"),
    ("_rad2", "rad^2"),
    ("_rad_s", "rad/s"),
    ("_rad", "rad"),
    ("_deg_s", "deg/s"),
    ("_deg", "deg"),
    ("_g2_s", "g^2 s"),
    ("_g", "g"),
    ("_m2_s", "m^2/s"),
    ("_m_s2", "m/s^2"),
    ("_m_s", "m/s"),
    ("_m", "m"),
    ("_1_s", "1/s"),
    ("_ms", "ms"),
    ("_s", "s"),
    ("_hz", "Hz"),
    ("_ut", "uT"),
    ("_frac", "fraction"),
)

WIDTH = 100  # the text below a parameter's row is wrapped at this many characters
INDENT = "    "  # ... and indented by this
FORMER_TITLE = "former spellings (taken with a warning)"

_NAME = r"[a-z_][a-z0-9_]*"
_HEAD = re.compile(rf"^({_NAME}(?: \([^()]*\))?(?:, {_NAME}(?: \([^()]*\))?)*): (.*)$")
# a full stop after these does not end a clause
_ABBREVIATION = re.compile(r"(?:^|[\s(])(?:e\.g|i\.e|etc|al|Secs?|[Ee]q|vs|cf|approx|Ch|ed)$")


@dataclass(frozen=True)
class Row:
    """One parameter. alias: the key a spec uses (the field name where there is no alias); name:
    the field name; default: the default as a spec would write it; unit: spelled out ("" where it
    has none); meaning: the field's full meaning (its docstring's first clause for a class that does
    not document its fields); search: `Tunable.describe()`, "" where the field declares no search
    range; valid, reference: the field's valid range and reference ("" where not documented)."""

    alias: str
    name: str
    default: str
    unit: str
    meaning: str
    search: str
    valid: str = ""
    reference: str = ""


def unit_of(name: str, metadata: Any = None, annotation: Any = float) -> str:
    """The unit of field `name` spelled out: its `"unit"` metadata, else its suffix's entry in
    `UNIT_SUFFIXES`; "" for an unknown suffix or a field that is not a number."""
    if metadata and "unit" in metadata:
        return str(metadata["unit"])
    if annotation not in (int, float):
        return ""
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix) and len(name) > len(suffix):
            return unit
    return ""


def _text(value: Any) -> str:
    """A value as a spec would write it (`true`, `1e-08`, `inf`, `""`)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return value if value else '""'
    return "none" if value is None else str(value)


def _split(text: str, seps: str) -> list[str]:
    """`text` cut after each separator in `seps` (";" or ". ") outside brackets and backticks,
    each part with the separator that ends it; a full stop after an abbreviation (e.g., Sec.) or in
    an ellipsis does not cut."""
    parts, depth, quoted, start = [], 0, False, 0
    for i, c in enumerate(text):
        if c == "`":
            quoted = not quoted
        elif quoted:
            continue
        elif c in "([":
            depth += 1
        elif c in ")]":
            depth = max(0, depth - 1)
        elif depth == 0 and c in seps and (i + 1 == len(text) or text[i + 1] == " "):
            if c == "." and (text[i - 1:i] == "." or _ABBREVIATION.search(text[start:i])):
                continue  # an ellipsis or an abbreviation
            parts.append(text[start:i + 1].strip())
            start = i + 1
    parts.append(text[start:].strip())
    return [p for p in parts if p]


def _clauses(text: str) -> list[str]:
    """`text`'s clauses (cut at top-level ";" and full stops), without their separators."""
    return [c.rstrip(";.").strip() for c in _split(text, ";.")]


def _one_line(text: str) -> str:
    """The first clause of `text` (to the first top-level ";" or full stop), whole."""
    return (_clauses(text) or [""])[0].rstrip(":,")


def _head_names(head: str, fields: set[str]) -> list[str] | None:
    """The field names of an entry head `name (alias), name2:`; None unless every name is a field."""
    names = [re.sub(r" \(.*\)$", "", part) for part in re.split(r", (?![^()]*\))", head)]
    return names if names and all(n in fields for n in names) else None


def _entries(doc: str, fields: set[str]) -> list[tuple[list[str], str]]:
    """The docstring's entries as (field names, text): a line `name (alias), ...: text` whose names
    are all fields, with the lines indented below it; a sentence inside an entry that starts as a
    head (`... none). scale_axes (scale): scale errors`) starts its own."""
    entries: list[tuple[list[str], int, list[str]]] = []
    current = None
    for line in inspect.cleandoc(doc).splitlines():
        indent = len(line) - len(line.lstrip())
        stripped = line.strip()
        if current is not None and stripped and indent > current[1]:
            current[2].append(stripped)
            continue
        current = None
        match = _HEAD.match(stripped)
        names = _head_names(match.group(1), fields) if match else None
        if names:
            current = (names, indent, [match.group(2)])
            entries.append(current)
    out: list[tuple[list[str], str]] = []
    for names, _, lines in entries:
        text: list[str] = []
        for part in _split(" ".join(lines), ";."):
            match = _HEAD.match(part)
            inner = _head_names(match.group(1), fields) if match and text else None
            if inner:
                out.append((names, " ".join(text)))
                names, text = inner, [match.group(2)]
            else:
                text.append(part)
        out.append((names, " ".join(text)))
    return out


def meanings(params_cls: type) -> dict[str, str]:
    """Field name -> its meaning: the field's `"meaning"` metadata where it has one, else (a class
    that does not document its fields) the first clause of its docstring entry (module docstring:
    the class's and its bases' docstrings, then the field's `"doc"` metadata); "" where nothing
    says anything."""
    if not dataclasses.is_dataclass(params_cls):
        return {}
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    out = {name: str(f.metadata["meaning"]) for name, f in fields.items() if "meaning" in f.metadata}
    if len(out) == len(fields):
        return out
    docs = [c.__doc__ for c in params_cls.__mro__ if c.__dict__.get("__doc__") and c is not object
            and not c.__doc__.startswith(c.__name__ + "(")]  # not the signature `dataclass` writes
    entries = [e for doc in docs for e in _entries(doc, set(fields))]
    for names, text in entries:  # the class's own entries first, then its bases'
        for name in names:
            out.setdefault(name, _one_line(text))
    for name, f in fields.items():
        if name in out:
            continue
        if "doc" in f.metadata:
            out[name] = _one_line(str(f.metadata["doc"]))
            continue
        mention = re.compile(rf"(?<![\w.`]){re.escape(name)}(?![\w])")
        clause = next((c for _, text in entries for c in _clauses(text) if mention.search(c)), "")
        out[name] = _one_line(clause)
    return {name: out[name] for name in fields}


def parameter_table(params_cls: type) -> list[Row]:
    """One `Row` per field of the dataclass `params_cls` (field order); [] for one without fields."""
    if not dataclasses.is_dataclass(params_cls):
        return []
    try:
        hints = typing.get_type_hints(params_cls)
    except (NameError, TypeError):  # annotations that do not resolve: no units
        hints = {}
    meaning = meanings(params_cls)
    rows = []
    for f in dataclasses.fields(params_cls):
        if f.default is not dataclasses.MISSING:
            default = _text(f.default)
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = _text(f.default_factory())  # type: ignore[misc]
        else:
            default = "(required)"
        search = f.metadata.get("search")
        rows.append(Row(alias=f.metadata.get("alias", f.name), name=f.name, default=default,
                        unit=unit_of(f.name, f.metadata, hints.get(f.name)), meaning=meaning.get(f.name, ""),
                        search=_search_text(search), valid=str(f.metadata.get("valid", "")),
                        reference=str(f.metadata.get("reference", ""))))
    return rows


def _search_text(search: Any) -> str:
    """A field's search range as the table shows it: `Tunable.describe()`, and "9-D only" for a
    parameter that acts on the magnetometer only."""
    if not isinstance(search, Tunable):
        return ""
    return search.describe() + ("; 9-D only" if getattr(search, "magnetometer", False) else "")


def former_spellings(params_cls: type) -> list[tuple[tuple[str, ...], str, str]]:
    """The former standard-deviation spellings `params_cls` still takes, as (the former names,
    the alias now, the field now), one entry per field, in `FORMERLY_STD`'s order."""
    taken = getattr(params_cls, "former_std", ())
    grouped: dict[str, list[str]] = {}
    for old in (name for name in FORMERLY_STD if name in taken):
        grouped.setdefault(FORMERLY_STD[old][0], []).append(old)
    alias = {new: a for new, a in FORMERLY_STD.values()}
    return [(tuple(sorted(olds, key=len)), alias[new], new) for new, olds in grouped.items()]


def former_aliases(params_cls: type) -> list[tuple[str, str, str]]:
    """The former aliases of `params_cls`'s fields (their `"formerly"` metadata), as (the former
    alias, the alias now, the field), in field order."""
    if not dataclasses.is_dataclass(params_cls):
        return []
    return [(old, f.metadata.get("alias", f.name), f.name)
            for f in dataclasses.fields(params_cls) for old in f.metadata.get("formerly", ())]


def _details(row: Row) -> list[str]:
    """The lines below a row: its meaning, valid range and reference, wrapped, never cut."""
    lines = []
    for text in (row.meaning, f"valid: {row.valid}" if row.valid else "",
                 f"reference: {row.reference}" if row.reference else ""):
        if text:
            lines += textwrap.wrap(text, WIDTH, initial_indent=INDENT, subsequent_indent=INDENT,
                                   break_long_words=False, break_on_hyphens=False)
    return lines


def format_parameters(params_cls: type, name: str) -> str:
    """The table `fusion list NAME` prints for the estimator `name` with parameters `params_cls`:
    a row per parameter (alias, field, default, unit, search range), its meaning, valid range and
    reference wrapped below it, then the former spellings."""
    rows = parameter_table(params_cls)
    if not rows:
        return f"{name}: no parameters"
    head = Row("alias", "field", "default", "unit", "", "search range" if any(r.search for r in rows) else "")
    widths = [max(len(getattr(r, col)) for r in (head, *rows)) for col in ("alias", "name", "default", "unit")]
    lines = [f"{name}: {len(rows)} parameters, set as {name}:ALIAS=VALUE,ALIAS=VALUE (or FIELD=VALUE)"]
    for r in (head, *rows):
        cells = (r.alias, r.name, r.default, r.unit)
        lines.append(("  ".join(f"{c:<{w}}" for c, w in zip(cells, widths)) + "  " + r.search).rstrip())
        if r is not head:
            lines += _details(r)
    former = former_spellings(params_cls)
    renamed = former_aliases(params_cls)
    if former or renamed:
        lines += ["", f"{FORMER_TITLE}; they will be removed in the next release"]
    if renamed:
        width = max(len(old) for old, _, _ in renamed)
        lines += [f"  {old:<{width}}  ->  {alias} ({field})" for old, alias, field in renamed]
    if former:
        lines.append("  standard deviations, squared into the variance that replaced them:")
        width = max(len(", ".join(olds)) for olds, _, _ in former)
        lines += [f"  {', '.join(olds):<{width}}  ->  {alias} ({new})" for olds, alias, new in former]
    return "\n".join(lines)


def estimator_class(name: str) -> type:
    """The `Estimator` class a name refers to, as `fusion.estimators.resolve` finds it: a registry
    name (even a peer whose library is not installed), an installed package's entry point, or a
    user's `FILE.py:NAME` / `module:NAME`. ValueError for an unknown name or a spec with parameters."""
    from . import ESTIMATORS, resolve

    specs = parse_specs(name)
    if len(specs) != 1 or specs[0].overrides:
        raise ValueError(f"{name!r}: give one estimator's name, without parameters (e.g. ekf, ./my_ukf.py:MyUKF)")
    if specs[0].name in ESTIMATORS:
        return ESTIMATORS[specs[0].name]
    return resolve(specs[0]).cls


def describe(name: str) -> str:
    """`format_parameters` of the estimator `name` (`estimator_class`)."""
    cls = estimator_class(name)
    return format_parameters(cls.Params, parse_specs(name)[0].name)


def _cell(text: str) -> str:
    """`text` in a Markdown table cell (a `|` escaped)."""
    return text.replace("|", "\\|")


def markdown(params_cls: type, name: str) -> str:
    """The parameters of the estimator `name` as a Markdown section: a table with each one's alias,
    field, default, unit, meaning, valid range, reference and search range."""
    rows = parameter_table(params_cls)
    if not rows:
        return f"## {name}\n\nNo parameters."
    lines = [f"## {name}", "", f"{len(rows)} parameters, set as `{name}:ALIAS=VALUE` (or `FIELD=VALUE`).", "",
             "| alias | field | default | unit | meaning | valid | reference | search range |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = (f"`{r.alias}`", f"`{r.name}`", f"`{r.default}`", r.unit, r.meaning, r.valid, r.reference, r.search)
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    renamed = former_aliases(params_cls)
    if renamed:
        lines += ["", "Former aliases, taken with a warning for one release: "
                  + ", ".join(f"`{old}` (now `{alias}`)" for old, alias, _ in renamed) + "."]
    return "\n".join(lines)


def reference() -> str:
    """`docs/parameters.md`: every registered estimator's parameters (`markdown`), in the registry's
    order."""
    from . import ESTIMATORS

    parts = ["# Parameters", "",
             "Generated from the parameter dataclasses' field metadata by `python -m fusion.estimators.describe > "
             "docs/parameters.md`; `fusion list NAME` prints the same for one estimator. A parameter is set by its "
             "alias or by its field name (ours end in their unit: `disturbance_corr_s`)."]
    for name, cls in ESTIMATORS.items():
        params = getattr(cls, "Params", None)
        if dataclasses.is_dataclass(params) and dataclasses.fields(params):
            parts += ["", markdown(params, name)]
    return "\n".join(parts) + "\n"


if __name__ == "__main__":
    print(reference(), end="")
