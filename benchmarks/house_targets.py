"""The code's shape, measured: parameters of the functions in `evaluation/` below the public
entry points, and the length of every module in `estimators/`.

    python benchmarks/house_targets.py [--max-params 8] [--max-lines 700]

Prints every function of `evaluation/` that takes more than `--max-params` parameters (`self` and
`cls` not counted; `*args` and `**kwargs` count one each) and every module of `estimators/` over
`--max-lines` lines, then one line of counts. The command entry points (`ENTRY_POINTS`: `runs.py`'s
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-params", type=int, default=8)
    parser.add_argument("--max-lines", type=int, default=700)
    args = parser.parse_args()
    over, entries = [], []
    for path in sorted((ROOT / "evaluation").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and parameters(node) > args.max_params:
                where = f"evaluation/{path.name}:{node.lineno} {node.name}: {parameters(node)} parameters"
                (entries if (path.name, node.name) in ENTRY_POINTS else over).append(where)
    long = [(len(p.read_text().splitlines()), p) for p in sorted((ROOT / "estimators").glob("*.py"))]
    long = [f"estimators/{p.name}: {n} lines" for n, p in long if n > args.max_lines]
    print(f"public entry points over {args.max_params} parameters (allowed): " + ("; ".join(entries) or "none"))
    print(f"functions below them over {args.max_params} parameters:")
    print("\n".join("  " + line for line in over) or "  none")
    print(f"modules of estimators/ over {args.max_lines} lines:")
    print("\n".join("  " + line for line in long) or "  none")
    print(f"{len(over)} functions over {args.max_params} parameters, {len(long)} modules over {args.max_lines} lines")


if __name__ == "__main__":
    main()
