"""The layers of the package, read from the source with `ast` (module-level and function-level
imports alike): imports point down only, the module graph has no cycle, and the core knows no
plotting or image library.

    fusion.cli (cli/), fusion.__main__  the command line
    fusion.evaluation.*  (evaluation/)  scoring, runs, reports, plots, panoramas
    fusion.estimators.*  (estimators/)  the estimators and their registry
    fusion.*             (fusion/)      core: types, quaternions, loaders, calibration, datasets

Each folder is one layer; `fusion/__main__.py` (`python -m fusion`, which has to sit in the
package's own folder) is the one command-line module outside `cli/`.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"fusion": "fusion", "estimators": "fusion.estimators", "evaluation": "fusion.evaluation", "cli": "fusion.cli"}
LAYERS = ("core", "estimators", "evaluation", "cli")  # bottom to top
MAIN = "fusion.__main__"
PLOTTING_AND_IMAGES = {"matplotlib", "cv2"}

# Cycles in folders this branch does not own, to be removed by their owners; an entry that is no
# longer needed fails `test_known_cycles_are_still_there`, so the list only shrinks.
KNOWN_CYCLE_EDGES: set[tuple[str, str]] = set()


def modules() -> dict[str, Path]:
    """Module name -> source file, for every module of the three folders and their subpackages
    (`fusion/formats/`)."""
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = [package, *path.relative_to(ROOT / folder).with_suffix("").parts]
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = modules()
TOP = sorted(m for m in MODULES if m == MAIN or m == "fusion.cli" or m.startswith("fusion.cli."))  # the command line


def layer(module: str) -> int:
    if module == MAIN:
        return LAYERS.index("cli")
    for name in ("cli", "evaluation", "estimators"):
        if module == f"fusion.{name}" or module.startswith(f"fusion.{name}."):
            return LAYERS.index(name)
    return LAYERS.index("core")


def _internal(name: str) -> str | None:
    """The longest prefix of a dotted name that is one of our modules."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in MODULES:
            return ".".join(parts[:n])
    return None


def imports(module: str) -> list[tuple[str, int, bool]]:
    """(imported name, line, at module level) for every import statement in the module; names
    of our own modules are resolved (relative imports, `from package import module`)."""
    path = MODULES[module]
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.stem == "__init__" else module.rsplit(".", 1)[0]
    top_level = {id(node) for node in tree.body}
    for node in tree.body:  # `if TYPE_CHECKING:` / `try:` blocks at module level are module level too
        if isinstance(node, (ast.If, ast.Try)):
            top_level |= {id(n) for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in ast.walk(tree):
        here = id(node) in top_level
        if isinstance(node, ast.Import):
            out += [(_internal(a.name) or a.name, node.lineno, here) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                full = f"{base}.{node.module}" if node.module else base
            else:
                full = node.module
            for alias in node.names:
                target = _internal(f"{full}.{alias.name}") or _internal(full) or full
                out.append((target, node.lineno, here))
    return out


def edges() -> dict[tuple[str, str], str]:
    """(importer, imported) between our modules -> where: 'path:line (module level|in a function)'."""
    out = {}
    for module, path in MODULES.items():
        for target, line, top in imports(module):
            if target in MODULES and target != module:
                out.setdefault((module, target), f"{path.relative_to(ROOT)}:{line} "
                                                  f"({'module level' if top else 'in a function'})")
    return out


def cycles(graph_edges) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    graph: dict[str, list[str]] = {m: [] for m in MODULES}
    for a, b in graph_edges:
        graph[a].append(b)
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_three_folders_are_found():
    assert {"fusion.cli", "fusion.types", "fusion.estimators", "fusion.estimators.filters.ukf", "fusion.evaluation.run.runner",
            "fusion.evaluation.compare"} <= set(MODULES)
    assert layer("fusion.cli") > layer("fusion.evaluation.runs") > layer("fusion.estimators.filters.ekf") > layer("fusion.types")
    assert ("fusion.evaluation.compare", "fusion.evaluation.run.runner") in edges()  # resolution works


def test_imports_point_down_only():
    upward = [f"{a} ({LAYERS[layer(a)]}) -> {b} ({LAYERS[layer(b)]}) at {where}"
              for (a, b), where in sorted(edges().items()) if layer(b) > layer(a)]
    assert not upward, "imports pointing to a higher layer:\n" + "\n".join(upward)


def test_no_import_cycles():
    graph_edges = edges()
    found = cycles(set(graph_edges) - KNOWN_CYCLE_EDGES)
    lines = []
    for component in found:
        lines.append(" <-> ".join(component) + ":")
        lines += [f"  {a} -> {b} at {where}" for (a, b), where in sorted(graph_edges.items())
                  if a in component and b in component]
    assert not found, "import cycles:\n" + "\n".join(lines)


# Rooms within a layer (subpackages), and the rooms each may import from besides its own and the core:
# a filter never imports a smoother or a peer, a filter's steps no filter, the kernels no estimator.
ROOM_RULES = {
    "fusion.estimators.kernels": set(),
    "fusion.estimators.filters.steps": {"fusion.estimators.kernels"},
    "fusion.estimators.filters": {"fusion.estimators.filters.steps", "fusion.estimators.kernels", "fusion.estimators"},
    "fusion.estimators.smoothers": {"fusion.estimators.filters", "fusion.estimators.filters.steps",
                                    "fusion.estimators.kernels", "fusion.estimators"},
    "fusion.estimators.peers": {"fusion.estimators.kernels", "fusion.estimators"},
    "fusion.estimators.adapters": {"fusion.estimators"},
    "fusion.evaluation.panorama": set(),
}
MAX_MODULES_PER_FOLDER = 15


def room(module: str) -> str:
    """The room (subpackage) a module is in: the longest `ROOM_RULES` key or package it lies in;
    `fusion.estimators` for the estimators' top folder, `core` for the core."""
    if layer(module) == LAYERS.index("core"):
        return "core"
    for name in sorted(ROOM_RULES, key=len, reverse=True):
        if module == name or module.startswith(name + "."):
            return name
    return ".".join(module.split(".")[:3]) if module.count(".") >= 3 else ".".join(module.split(".")[:2])


def test_rooms_point_down():
    """Within a layer, each room imports only the rooms `ROOM_RULES` allows it (and the core)."""
    wrong = [f"{a} -> {b} at {where}" for (a, b), where in sorted(edges().items())
             if room(a) in ROOM_RULES and room(b) not in {room(a), "core", *ROOM_RULES[room(a)]}]
    assert not wrong, "imports across rooms that ROOM_RULES does not allow:\n" + "\n".join(wrong)


def test_rooms_hold_a_readable_number_of_modules():
    """No folder of estimators/ or evaluation/ holds more than `MAX_MODULES_PER_FOLDER` modules directly."""
    for folder in ("estimators", "evaluation"):
        for path in [ROOT / folder, *(p for p in (ROOT / folder).rglob("*") if p.is_dir() and p.name != "__pycache__")]:
            count = len([p for p in path.glob("*.py") if p.name != "__init__.py"])
            assert count <= MAX_MODULES_PER_FOLDER, f"{path.relative_to(ROOT)} holds {count} modules"


def test_the_room_rules_catch_what_they_look_for():
    assert room("fusion.estimators.filters.steps._rest") == "fusion.estimators.filters.steps"
    assert room("fusion.estimators.filters.ekf") == "fusion.estimators.filters"
    assert room("fusion.estimators.smoothers.gn") == "fusion.estimators.smoothers"
    assert room("fusion.estimators.base") == "fusion.estimators" and room("fusion.types") == "core"
    assert "fusion.estimators.smoothers" not in ROOM_RULES["fusion.estimators.filters"]


def test_known_cycles_are_still_there():
    graph_edges = edges()
    stale = [edge for edge in KNOWN_CYCLE_EDGES
             if edge not in graph_edges or not any(set(edge) <= set(c) for c in cycles(graph_edges))]
    assert not stale, f"no longer a cycle, remove from KNOWN_CYCLE_EDGES: {stale}"


@pytest.mark.parametrize("module", [m for m in MODULES if layer(m) in (LAYERS.index("core"), LAYERS.index("estimators"))]
                         + TOP)
def test_core_estimators_and_cli_import_no_plotting_or_image_library(module):
    found = [f"{name} at {MODULES[module].relative_to(ROOT)}:{line}" for name, line, _ in imports(module)
             if name.split(".")[0] in PLOTTING_AND_IMAGES]
    assert not found, f"{module} imports " + ", ".join(found)


def test_cli_uses_only_public_library_names():
    """The command line calls the library as a Python user would (no `_private` names)."""
    private = []
    for module in TOP:
        tree = ast.parse(MODULES[module].read_text())
        private += [f"{module}:{node.lineno} {node.module}.{a.name}" for node in ast.walk(tree)
                    if isinstance(node, ast.ImportFrom) for a in node.names if a.name.startswith("_")]
    assert not private, "private names imported by the CLI: " + ", ".join(private)


def test_the_checks_catch_what_they_look_for():
    """The cycle finder and the layer map on a made-up graph (a test that could fail)."""
    made_up = {("fusion.types", "fusion.cli"), ("fusion.cli", "fusion.types"), ("fusion.sim", "fusion.types")}
    assert cycles(made_up) == [["fusion.cli", "fusion.types"]]
    assert layer("fusion.evaluation") == layer("fusion.evaluation.report.plots") == LAYERS.index("evaluation")
    assert layer("fusion") == LAYERS.index("core")
    assert layer("fusion.cli") == layer(MAIN) == LAYERS.index("cli")


def test_the_core_folder_is_the_floor():
    """Every module of `fusion/` but `__main__` is core: the command line lives in `cli/`."""
    above = [m for m, path in MODULES.items() if path.is_relative_to(ROOT / "fusion") and m != MAIN
             and layer(m) != LAYERS.index("core")]
    assert not above, f"modules of fusion/ above the core layer: {above}"
    assert MODULES["fusion.cli"] == ROOT / "cli" / "__init__.py"


@pytest.mark.parametrize("folder", ["estimators", "evaluation", "cli"])
def test_a_folder_imported_under_its_own_name_is_refused(folder):
    """From the project's root, `import estimators` would find the folder as a second package:
    refused with a line naming the package to import (its kernels would otherwise write types
    under a name other processes cannot import into numba's disk cache)."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", f"import {folder}"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines()[-1] == \
        f"ImportError: {folder}: this folder is the package fusion.{folder}; import fusion.{folder} instead"


def test_filterpy_and_scipy_stats_are_imported_only_for_a_ukf():
    """FilterPy imports SciPy's statistics package (about 34 MB resident): a process that builds
    and runs a smoother or `ekf` does not hold it (`fusion.estimators.filters.quaternion_ukf` is
    imported when a UKF is built), one that builds a UKF does."""
    import subprocess
    import sys

    code = ("import sys\n"
            "from fusion import estimators\n"
            "from fusion.calibration import calibrate\n"
            "from fusion.sim import SimSettings, simulate\n"
            "raw, truth = simulate(SimSettings(duration_s=3.0))\n"
            "for name in ('gn', 'gd', 'ekf'):\n"
            "    estimators.build(name).estimate(calibrate(raw).apply(raw), truth.quat_wxyz[0])\n"
            "print(sorted(m for m in ('filterpy', 'scipy.stats') if m in sys.modules))\n"
            "estimators.build('ukf')\n"
            "print(sorted(m for m in ('filterpy', 'scipy.stats') if m in sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["[]", "['filterpy', 'scipy.stats']"]
