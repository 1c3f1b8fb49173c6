"""The `fusion` command: a thin layer over the library (no maths here).

    fusion compare --estimators dr,ukf --dataset all --data-dir ../shared/data/ece276a

Everything a command does is a couple of library calls (see each `cmd_*`). Bad input gives
one line `fusion: error: ...` and exit code 1, never a traceback.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import warnings
from pathlib import Path

from . import datasets


def _add_data_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", default="all",
                        help="'all', comma-separated ids (ece276a/3), globs ('ece276a/*') or file paths; "
                             "'sim' is the built-in simulated recording (default: all)")
    parser.add_argument("--data-dir", default=None,
                        help="folder with recordings (default: $FUSION_DATA, else ./data)")
    parser.add_argument("--init", choices=datasets.INIT_MODES, default=None,
                        help="initial orientation: truth (default with ground truth), accel (default without), identity")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def select_sources(args: argparse.Namespace) -> list:
    """The dataset `Source`s `--dataset` names (not loaded yet)."""
    user_dir = args.data_dir or os.environ.get("FUSION_DATA")
    root = datasets.data_dir_from(args.data_dir)
    if user_dir and not root.is_dir():
        raise FileNotFoundError(f"{root}: data directory does not exist")
    sources = datasets.select(args.dataset, args.data_dir)
    if user_dir and args.dataset == "all" and [s.id for s in sources] == [datasets.SIM_ID]:
        raise ValueError(f"{root}: no recordings found (imu/imuRawN.p|.mat, .csv, or BROAD .hdf5/.mat trials); use --dataset sim for the simulated one")
    return sources


def load_selected(args: argparse.Namespace) -> list:
    """The recordings `--dataset` names, loaded and calibrated (a progress bar per recording)."""
    from tqdm import tqdm

    recordings = []
    for source in tqdm(select_sources(args), desc="loading", disable=args.no_progress, file=sys.stderr, leave=False):
        recordings.append(datasets.load_source(source))
    return recordings


def _run(args: argparse.Namespace, specs: list, settings: dict, per_recording: bool = True) -> int:
    """Run `specs` on the selected recordings; print the table; write --json and --out."""
    from evaluation.compare import format_table, results_json
    from evaluation.runner import describe_specs, run

    sources = select_sources(args)
    out = getattr(args, "out", None)
    results, infos = run(specs, sources, args.init, jobs=args.jobs, progress=not args.no_progress,
                         with_info=bool(out) and per_recording, protocol=args.protocol)
    print(format_table(results))
    if not (args.json or out):
        return 0
    settings = {"command": shlex.join(["fusion", *args.argv]), **settings, "dataset": args.dataset,
                "data_dir": str(datasets.data_dir_from(args.data_dir).resolve()),
                "init": args.init or "default (truth where available, else accel)",
                "protocol": args.protocol or "default (broad for recordings with a movement mask, else full)",
                "estimator_details": describe_specs(specs)}
    doc = results_json(results, settings)
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    if out:
        from evaluation.report import git_commit, write_run

        doc["settings"]["git_commit"] = git_commit()
        report = write_run(out, doc, results, infos, jobs=args.jobs, progress=not args.no_progress,
                           per_recording=per_recording)
        print(f"report: {report}", file=sys.stderr)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from evaluation.compare import _as_specs, expand_all

    specs = expand_all(_as_specs([args.estimators]))
    return _run(args, specs, {"kind": "compare", "estimators": args.estimators})


def cmd_ablate(args: argparse.Namespace) -> int:
    from evaluation import ablate

    if bool(args.preset) == bool(args.estimator):
        raise ValueError("ablate: give either --preset NAME or --estimator NAME with --param NAME=V1,V2,...")
    if args.preset:
        if args.param:
            raise ValueError("ablate: --param applies to --estimator, not to --preset")
        specs = ablate.preset_specs(args.preset)
        settings = {"kind": "ablate", "preset": args.preset, "estimators": ",".join(s.label for s in specs)}
    else:
        if not args.param:
            raise ValueError("ablate: --estimator needs at least one --param NAME=V1,V2,...")
        params = [ablate.parse_param(p) for p in args.param]
        specs = ablate.grid_specs(args.estimator, params)
        settings = {"kind": "ablate", "estimator": args.estimator, "params": dict(params),
                    "estimators": ",".join(s.label for s in specs)}
    return _run(args, specs, settings, per_recording=args.per_recording)


def cmd_report(args: argparse.Namespace) -> int:
    from evaluation.report import render

    print(render(args.folder, jobs=args.jobs, progress=not args.no_progress))
    return 0


def _jobs(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def _add_run_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--protocol", choices=("full", "broad"), default=None,
                        help="scoring: full (every sample with truth) or broad (movement phases only, mean heading "
                             "offset removed); default: broad for recordings with a movement mask (BROAD trials), else full")
    parser.add_argument("--json", metavar="PATH", help="write the results as JSON (format: see README)")
    parser.add_argument("--out", metavar="DIR", help="write results.json, table, figures, report.html and "
                        "report.md to DIR (re-render later with `fusion report DIR`)")
    parser.add_argument("--jobs", type=_jobs, default=0, metavar="N",
                        help="worker processes; 0 = all cores (default); results do not depend on it")


def build_parser() -> argparse.ArgumentParser:
    from evaluation.ablate import PRESETS

    parser = argparse.ArgumentParser(prog="fusion", description="Orientation estimation from gyro + accelerometer, scored against VICON.")
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors")
    p.add_argument("--estimators", default="all",
                   help="comma-separated registry names with optional parameters, e.g. 'dr,ukf:R=1e-3' (default: all)")
    _add_data_args(p)
    _add_run_args(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("ablate", help="sweep estimator parameters (or run a preset) over recordings")
    p.add_argument("--estimator", help="the estimator to sweep, optionally with fixed parameters: 'ukf:Q=1e-5'")
    p.add_argument("--param", action="append", default=[], metavar="NAME=V1,V2",
                   help="a parameter and its values; repeat for a grid, e.g. --param R=1e-4,1e-3 --param sigma=kraft,julier")
    p.add_argument("--preset", metavar="NAME", help=f"a named ablation: {', '.join(PRESETS)}")
    p.add_argument("--per-recording", action="store_true",
                   help="with --out, also draw each recording's figures for every setting")
    _add_data_args(p)
    _add_run_args(p)
    p.set_defaults(func=cmd_ablate)

    p = sub.add_parser("report", help="re-render the report of an --out folder from its results.json and series")
    p.add_argument("folder", metavar="DIR")
    p.add_argument("--jobs", type=_jobs, default=0, metavar="N", help="worker processes; 0 = all cores (default)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_report)
    return parser


def _one_line_warnings(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fusion: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    if args.command is None:  # plain `fusion` runs the main job
        argv = ["compare", *argv]
        args = parser.parse_args(argv)
    args.argv = argv
    warnings.showwarning = _one_line_warnings
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:  # bad input: one line, exit 1
        print(f"fusion: error: {exc}", file=sys.stderr)
        return 1
    except ImportError as exc:  # an optional package (peers, h5py) is missing: the message says which
        print(f"fusion: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("fusion: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
