"""Print the package's import graph by layer, read from the source with `ast` (imports at module
level and inside functions alike; nothing is imported or run).

    python docs/import_graph.py          # text: one box per layer, each module's imports below it
    python docs/import_graph.py --dot    # Graphviz: python docs/import_graph.py --dot | dot -Tsvg > graph.svg

Layers, top to bottom: the command line (`fusion.cli`, folder cli/, and `fusion.__main__`),
`fusion.evaluation` (evaluation/), `fusion.estimators` (estimators/), the core (the rest of fusion/). An
arrow is "imports"; `tests/test_layers.py` checks that every arrow points down (or within a
layer) and that there is no cycle.
"""
from __future__ import annotations

import argparse
import ast
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"fusion": "fusion", "estimators": "fusion.estimators", "evaluation": "fusion.evaluation", "cli": "fusion.cli"}
LAYERS = [("cli", "cli/, fusion/__main__.py"), ("evaluation", "evaluation/"),
          ("estimators", "estimators/"), ("core", "fusion/")]  # top to bottom


def modules() -> dict[str, Path]:
    """Module name -> source file, for every module of the four folders and their subpackages."""
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = [package, *path.relative_to(ROOT / folder).with_suffix("").parts]
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def layer(module: str) -> str:
    if module == "fusion.__main__":
        return "cli"
    for name in ("cli", "evaluation", "estimators"):
        if module == f"fusion.{name}" or module.startswith(f"fusion.{name}."):
            return name
    return "core"


def edges(mods: dict[str, Path]) -> set[tuple[str, str, bool]]:
    """(importer, imported, inside a function) between our modules."""

    def internal(name: str) -> str | None:
        parts = name.split(".")
        return next((".".join(parts[:n]) for n in range(len(parts), 0, -1) if ".".join(parts[:n]) in mods), None)

    out = set()
    for module, path in mods.items():
        tree = ast.parse(path.read_text())
        package = module if path.stem == "__init__" else module.rsplit(".", 1)[0]
        top = {id(n) for n in tree.body} | {id(n) for b in tree.body if isinstance(b, (ast.If, ast.Try))
                                             for n in ast.walk(b)}
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [internal(a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]) if node.level else ""
                full = ".".join(p for p in (base, node.module) if p)
                targets = [internal(f"{full}.{a.name}") or internal(full) for a in node.names]
            out |= {(module, t, id(node) not in top) for t in targets if t and t != module}
    return out


def short(module: str) -> str:
    for prefix in ("fusion.evaluation.", "fusion.estimators."):
        if module.startswith(prefix):
            return module[len(prefix):]
    return "__init__" if module in ("fusion", "fusion.evaluation", "fusion.estimators") else module.removeprefix("fusion.")


def text(mods: dict[str, Path], graph: set[tuple[str, str, bool]]) -> str:
    lines = []
    for name, folder in LAYERS:
        members = [m for m in mods if layer(m) == name]
        body = []
        for m in members:
            targets = sorted({(layer(b), short(b) + ("*" if lazy else "")) for a, b, lazy in graph if a == m},
                             key=lambda t: ([n for n, _ in LAYERS].index(t[0]), t[1]))
            grouped: dict[str, list[str]] = {}
            for lay, target in targets:
                grouped.setdefault(lay, []).append(target)
            arrows = "; ".join(f"{lay}: {', '.join(ts)}" for lay, ts in grouped.items())
            body.append(f"{short(m):<14} -> {arrows}" if arrows else short(m))
        width = max(len(line) for line in [f"{name} ({folder})", *body]) + 2
        lines += ["+" + "-" * width + "+", f"| {name + ' (' + folder + ')':<{width - 1}}|",
                  "+" + "-" * width + "+"]
        lines += [f"| {line:<{width - 1}}|" for line in body]
        lines += ["+" + "-" * width + "+"]
        below = Counter(layer(b) for a, b, _ in graph if layer(a) == name and layer(b) != name)
        if below:
            lines.append("      | imports " + ", ".join(f"{lay} ({n})" for lay, n in below.items()))
            lines.append("      v")
    lines.append("(* imported inside a function, when used)")
    return "\n".join(lines)


def dot(mods: dict[str, Path], graph: set[tuple[str, str, bool]]) -> str:
    lines = ["digraph fusion {", "  rankdir=TB; node [shape=box, fontsize=10]; compound=true;"]
    for name, folder in LAYERS:
        lines.append(f'  subgraph "cluster_{name}" {{ label="{name} ({folder})"; style=rounded;')
        lines += [f'    "{m}" [label="{short(m)}"];' for m in mods if layer(m) == name]
        lines.append("  }")
    lines += [f'  "{a}" -> "{b}"' + (" [style=dashed]" if lazy else "") + ";" for a, b, lazy in sorted(graph)]
    lines.append("}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dot", action="store_true", help="Graphviz dot instead of text (dashed: inside a function)")
    args = parser.parse_args()
    mods = modules()
    graph = edges(mods)
    # an import both at module level and in a function is drawn once, as the module-level one
    graph = {(a, b, lazy) for a, b, lazy in graph if not (lazy and (a, b, False) in graph)}
    print(dot(mods, graph) if args.dot else text(mods, graph))


if __name__ == "__main__":
    main()
