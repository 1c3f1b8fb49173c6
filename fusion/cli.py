"""The `fusion` command: a thin layer over the library (no maths here).

    fusion compare --estimators dr,ukf --dataset all --data-dir ../shared/data/ece276a

Everything a command does is a couple of library calls (see each `cmd_*`). Bad input gives
one line `fusion: error: ...` and exit code 1, never a traceback.
"""
from __future__ import annotations

import argparse
import json
import os
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


def load_selected(args: argparse.Namespace) -> list:
    """The recordings `--dataset` names, loaded and calibrated (a progress bar per recording)."""
    from tqdm import tqdm

    user_dir = args.data_dir or os.environ.get("FUSION_DATA")
    root = datasets.data_dir_from(args.data_dir)
    if user_dir and not root.is_dir():
        raise FileNotFoundError(f"{root}: data directory does not exist")
    sources = datasets.select(args.dataset, args.data_dir)
    if user_dir and args.dataset == "all" and [s.id for s in sources] == [datasets.SIM_ID]:
        raise ValueError(f"{root}: no recordings found (imu/imuRawN.p|.mat, .csv, or BROAD .hdf5/.mat trials); use --dataset sim for the simulated one")
    recordings = []
    for source in tqdm(sources, desc="loading", disable=args.no_progress, file=sys.stderr, leave=False):
        recordings.append(datasets.load_source(source))
    return recordings


def cmd_compare(args: argparse.Namespace) -> int:
    from evaluation.compare import compare, format_table, results_json

    recordings = load_selected(args)
    results = compare([args.estimators], recordings, init=args.init, progress=not args.no_progress,
                      protocol=args.protocol)
    print(format_table(results))
    if args.json:
        settings = {"command": " ".join(["fusion", *sys.argv[1:]]), "estimators": args.estimators,
                    "dataset": args.dataset, "data_dir": str(datasets.data_dir_from(args.data_dir)),
                    "init": args.init or "default (truth where available, else accel)",
                    "protocol": args.protocol or "default (broad for recordings with a movement mask, else full)"}
        Path(args.json).write_text(json.dumps(results_json(results, settings), indent=2) + "\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fusion", description="Orientation estimation from gyro + accelerometer, scored against VICON.")
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors")
    p.add_argument("--estimators", default="all",
                   help="comma-separated registry names with optional parameters, e.g. 'dr,ukf:R=1e-3' (default: all)")
    _add_data_args(p)
    p.add_argument("--protocol", choices=("full", "broad"), default=None,
                   help="scoring: full (every sample with truth) or broad (movement phases only, mean heading "
                        "offset removed); default: broad for recordings with a movement mask (BROAD trials), else full")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON (format: see README)")
    p.set_defaults(func=cmd_compare)
    return parser


def _one_line_warnings(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fusion: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:  # plain `fusion` runs the main job
        args = parser.parse_args(["compare", *(argv or [])])
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
