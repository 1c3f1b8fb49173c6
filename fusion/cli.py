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
    parser.add_argument("--dropouts", choices=("on", "off"), default="on" if datasets.DROPOUTS_DEFAULT else "off",
                        help="mark detected gyro freezes and ADC-saturated samples invalid so that no estimator "
                             "integrates them (default: on; off for ablations)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="apply a calibration file written by 'fusion calibrate' (gyro scale factors, "
                             "and per-recording clock offsets if it holds them)")


def load_selected(args: argparse.Namespace) -> list:
    """The recordings `--dataset` names, loaded and calibrated (a progress bar per recording)."""
    from tqdm import tqdm

    user_dir = args.data_dir or os.environ.get("FUSION_DATA")
    root = datasets.data_dir_from(args.data_dir)
    if user_dir and not root.is_dir():
        raise FileNotFoundError(f"{root}: data directory does not exist")
    sources = datasets.select(args.dataset, args.data_dir)
    if user_dir and args.dataset == "all" and [s.id for s in sources] == [datasets.SIM_ID]:
        raise ValueError(f"{root}: no recordings found (imu/imuRawN.p|.mat or .csv); use --dataset sim for the simulated one")
    from .calibration import BoardModel

    calib_file = None
    if getattr(args, "calibration", None):
        from . import gyro_fit

        calib_file = gyro_fit.read(args.calibration)
    board = calib_file.board() if calib_file else BoardModel()
    dropouts = getattr(args, "dropouts", "on") == "on"
    recordings = []
    for source in tqdm(sources, desc="loading", disable=args.no_progress, file=sys.stderr, leave=False):
        offset = calib_file.offset_for(source.id) if calib_file else 0.0
        recordings.append(datasets.load_source(source, board, dropouts=dropouts, truth_offset_s=offset))
    return recordings


def cmd_inspect(args: argparse.Namespace) -> int:
    from .checks import check_recording, format_check

    recordings = load_selected(args)
    checks = [check_recording(rec) for rec in recordings]
    print("\n\n".join(format_check(c) for c in checks))
    if args.json:
        doc = {"command": " ".join(["fusion", *sys.argv[1:]]), "recordings": [c.to_json() for c in checks]}
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    if args.out:
        from evaluation.inspect_plots import plot_check

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for rec, check in zip(recordings, checks):
            path = out / f"inspect_{rec.id.replace('/', '_')}.png"
            plot_check(rec, check, path)
            print(f"wrote {path}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from . import gyro_fit

    recordings = load_selected(args)
    if args.leave_one_out:
        from evaluation.compare import format_table
        from evaluation.loo import format_folds, leave_one_out

        folds = leave_one_out([args.estimators], recordings, init=args.init, progress=not args.no_progress)
        print(format_folds(folds))
        print()
        print(format_table([r for f in folds for r in f.results]))
    result = gyro_fit.fit_recordings(recordings)
    print(f"fit on {len(result.fitted_on)} recordings ({result.samples} samples): gyro_scale_factor "
          + ", ".join(f"{x:.4f}" for x in result.gyro_scale_factor)
          + " (sensitivity vs nominal " + ", ".join(f"{100 * (x - 1):+.1f} %" for x in result.sensitivity_ratio)
          + f"); misalignment {', '.join(f'{x:+.2f}' for x in result.misalignment_deg)} deg; "
          f"residual {result.residual_rms_deg_s:.2f} deg/s")
    if args.clock_offset:
        for rid, off in result.clock_offset_s.items():
            print(f"  clock offset {rid}: VICON lags by {off * 1e3:+.1f} ms")
    if args.out:
        gyro_fit.write(args.out, result, with_clock_offset=args.clock_offset, command=" ".join(["fusion", *sys.argv[1:]]))
        print(f"wrote {args.out}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from evaluation.compare import compare, format_table, results_json

    recordings = load_selected(args)
    results = compare([args.estimators], recordings, init=args.init, progress=not args.no_progress)
    print(format_table(results))
    if args.json:
        settings = {"command": " ".join(["fusion", *sys.argv[1:]]), "estimators": args.estimators,
                    "dataset": args.dataset, "data_dir": str(datasets.data_dir_from(args.data_dir)),
                    "init": args.init or "default (truth where available, else accel)"}
        Path(args.json).write_text(json.dumps(results_json(results, settings), indent=2) + "\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fusion", description="Orientation estimation from gyro + accelerometer, scored against VICON.")
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors")
    p.add_argument("--estimators", default="all",
                   help="comma-separated registry names with optional parameters, e.g. 'dr,ukf:R=1e-3' (default: all)")
    _add_data_args(p)
    p.add_argument("--json", metavar="PATH", help="write the results as JSON (format: see README)")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("inspect", help="sensor checks per recording: rests, bias drift, gyro freezes, range, "
                                       "time stamps, VICON gaps and clock offset")
    _add_data_args(p)
    p.add_argument("--json", metavar="PATH", help="write the checks as JSON")
    p.add_argument("--out", metavar="DIR", help="write a figure per recording into DIR")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("calibrate", help="fit gyro scale factors (and clock offsets) against VICON")
    _add_data_args(p)
    p.add_argument("--out", metavar="FILE", help="write the calibration file (JSON, see README)")
    p.add_argument("--clock-offset", action="store_true",
                   help="also store each recording's measured IMU-VICON clock offset (applied to that recording's truth)")
    p.add_argument("--leave-one-out", action="store_true",
                   help="score each recording with the scales fitted on the others, and print the fitted scales per fold")
    p.add_argument("--estimators", default="dr", help="estimators scored by --leave-one-out (default: dr)")
    p.set_defaults(func=cmd_calibrate)
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
    except KeyboardInterrupt:
        print("fusion: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
