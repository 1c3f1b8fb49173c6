"""The code's shape, measured: parameters of the functions in `evaluation/` and `estimators/` (every
room) below the public entry points, the positional parameters of the compiled kernels, and the
length of every module in `estimators/`.

    python benchmarks/house_targets.py [--max-params 8] [--max-positional 12] [--max-lines 700]

Prints every function that takes more than `--max-params` parameters (`self` and `cls` not counted;
`*args` and `**kwargs` count one each), every function of a `_compiled_*` module with more than
`--max-positional` positional parameters and every module of `estimators/` over `--max-lines` lines,
then one line of counts. The command entry points (`ENTRY_POINTS`: `runs.py`'s
`run_*` and `tune.run_tune`, the keyword APIs the commands call) are listed apart; everything below
them counts, `fusion.evaluation.run.runner.run` included (it takes the run's settings as one
`RunSettings`, or their fields as keywords).
"""
from __future__ import annotations

import argparse
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRY_POINTS = {("runs.py", "run_compare"), ("runs.py", "run_ablate"), ("runs.py", "run_resume"),
                ("runs.py", "run_panorama"), ("runs.py", "run_inspect"), ("runs.py", "run_calibrate"),
                ("tune.py", "run_tune")}


def parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    args = node.args
    names = [a.arg for a in args.posonlyargs + args.args + args.kwonlyargs]
    names += [a.arg for a in (args.vararg, args.kwarg) if a is not None]
    return len([n for n in names if n not in ("self", "cls")])


def positional(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    args = node.args
    return len([a.arg for a in args.posonlyargs + args.args if a.arg not in ("self", "cls")])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-params", type=int, default=8)
    parser.add_argument("--max-positional", type=int, default=12, help="for the compiled kernels (_compiled_*)")
    parser.add_argument("--max-lines", type=int, default=700)
    args = parser.parse_args()
    over, entries, kernels, long = [], [], [], []
    for room in ("evaluation", "estimators"):
        for path in sorted((ROOT / room).rglob("*.py")):
            text = path.read_text()
            where_file = path.relative_to(ROOT)
            if room == "estimators" and len(text.splitlines()) > args.max_lines:
                long.append(f"{where_file}: {len(text.splitlines())} lines")
            for node in ast.walk(ast.parse(text)):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                where = f"{where_file}:{node.lineno} {node.name}"
                if parameters(node) > args.max_params:
                    (entries if (path.name, node.name) in ENTRY_POINTS else over).append(
                        f"{where}: {parameters(node)} parameters")
                if path.name.startswith("_compiled") and positional(node) > args.max_positional:
                    kernels.append(f"{where}: {positional(node)} positional")
    print(f"public entry points over {args.max_params} parameters (allowed): " + ("; ".join(entries) or "none"))
    for title, lines in ((f"functions below them over {args.max_params} parameters", over),
                         (f"compiled functions over {args.max_positional} positional parameters", kernels),
                         (f"modules of estimators/ over {args.max_lines} lines", long)):
        print(f"{title}:")
        print("\n".join("  " + line for line in lines) or "  none")
    print(f"{len(over)} functions over {args.max_params} parameters ({sum('/peers/' in o for o in over)} of them "
          f"in the peers' twins, whose signatures follow their libraries'), {len(kernels)} compiled functions over "
          f"{args.max_positional} positional, {len(long)} modules over {args.max_lines} lines")


if __name__ == "__main__":
    main()
