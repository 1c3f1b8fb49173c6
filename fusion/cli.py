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

import numpy as np

from . import datasets


def _add_data_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", default="all",
                        help="'all', comma-separated ids (ece276a/3), globs ('ece276a/*') or file paths; "
                             "'sim' is the built-in simulated recording (default: all)")
    parser.add_argument("--data-dir", default=None,
                        help="folder with recordings (default: $FUSION_DATA, else ./data)")
    parser.add_argument("--init", choices=datasets.INIT_MODES, default=None,
                        help="initial orientation: truth (default with ground truth; with --align the aligned truth), "
                             "accel (default without), identity")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--dropouts", choices=("on", "off"), default="on" if datasets.DROPOUTS_DEFAULT else "off",
                        help="mark detected gyro freezes and ADC-saturated samples invalid so that no estimator "
                             "integrates them (default: on; off for ablations)")
    parser.add_argument("--calibration", metavar="FILE", default=None,
                        help="apply a calibration file written by 'fusion calibrate' (gyro scale factors, "
                             "and per-recording clock offsets if it holds them)")


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

    options = load_options(args)
    recordings = []
    for source in tqdm(select_sources(args), desc="loading", disable=args.no_progress, file=sys.stderr, leave=False):
        recordings.append(options.load(source))
    return recordings


def load_options(args: argparse.Namespace) -> datasets.LoadOptions:
    """`--calibration` and `--dropouts` as the loading options every command uses."""
    dropouts = getattr(args, "dropouts", "on") == "on"
    if not getattr(args, "calibration", None):
        return datasets.LoadOptions(dropouts=dropouts)
    from . import gyro_fit

    calib_file = gyro_fit.read(args.calibration)
    return datasets.LoadOptions(calib_file.board(), dropouts, tuple(sorted(calib_file.clock_offset_s.items())))


def cmd_panorama(args: argparse.Namespace) -> int:
    import cv2

    from estimators.params import parse_specs
    from evaluation.compare import run_one
    from evaluation.panorama import PanoramaGrid, comparison_image, estimate_panorama, reference_panorama

    recordings = load_selected(args)
    if len(recordings) != 1:
        raise ValueError(f"--dataset {args.dataset!r} names {len(recordings)} recordings; panorama takes one")
    (recording,) = recordings
    specs = parse_specs(args.estimator)
    if len(specs) != 1:
        raise ValueError(f"--estimator {args.estimator!r}: give exactly one estimator")
    if args.reference and recording.truth is None:
        raise ValueError(f"{recording.id}: --reference needs ground truth, and this recording has none")
    width, _, height = args.size.partition("x")
    try:
        grid = PanoramaGrid(int(width), int(height))
    except ValueError as exc:
        raise ValueError(f"--size {args.size!r}: expected WIDTHxHEIGHT in px, e.g. 1920x960 ({exc})") from exc
    trajectory = run_one(recording, specs[0], args.init).trajectory
    data_dir = datasets.data_dir_from(args.data_dir)
    options = dict(data_dir=data_dir, scene=args.scene, grid=grid, blend=args.blend, rate_hz=args.rate)
    pano, scores = estimate_panorama(recording, trajectory, progress=not args.no_progress, **options)
    image = pano.bgr()
    if args.reference:
        image = comparison_image(pano, reference_panorama(recording, **options).truth)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image):
        raise ValueError(f"{out}: could not write the image (use a .png or .jpg name)")
    print(f"{recording.id} {specs[0].label}: {pano.frames_used} frames ({pano.frames_skipped} skipped) -> {out}")
    print(f"PSNR {scores['psnr_db']:.2f} dB, SSIM {scores['ssim']:.4f} against the ground-truth panorama; "
          f"covered {scores['covered_fraction']:.3f} of the sphere")
    if np.isfinite(scores["scene_psnr_db"]):
        print(f"PSNR {scores['scene_psnr_db']:.2f} dB, SSIM {scores['scene_ssim']:.4f} against the scene")
    return 0


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

        folds = leave_one_out([args.estimators], recordings, init=args.init, progress=not args.no_progress,
                              align=args.align)
        print(format_folds(folds))
        print()
        print(format_table([r for f in folds for r in f.results], align=args.align))
    elif args.align:
        raise ValueError("calibrate: --align applies to the scores of --leave-one-out (the fit itself assumes "
                         "the truth's frames are the IMU's)")
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


def _run(args: argparse.Namespace, specs: list, settings: dict, per_recording: bool = True) -> int:
    """Run `specs` on the selected recordings; print the table; write --json and --out."""
    from evaluation.compare import format_table, results_json
    from evaluation.runner import describe_specs, run

    sources = select_sources(args)
    out = getattr(args, "out", None)
    results, infos = run(specs, sources, args.init, jobs=args.jobs, progress=not args.no_progress, load=load_options(args),
                         panorama_data_dir=str(datasets.data_dir_from(args.data_dir)) if getattr(args, "panorama", False) else None,
                         with_info=bool(out) and per_recording, protocol=args.protocol, align=args.align)
    print(format_table(results, align=args.align))
    if not (args.json or out):
        return 0
    settings = {"command": shlex.join(["fusion", *args.argv]), **settings, "dataset": args.dataset,
                "data_dir": str(datasets.data_dir_from(args.data_dir).resolve()),
                "init": args.init or ("default (the aligned truth where available, else accel)" if args.align
                                      else "default (truth where available, else accel)"),
                "align": bool(args.align),
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
    _add_align_arg(parser)


def _add_align_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--align", action="store_true",
                        help="for ground truth given in other frames: fit a constant world tilt and a constant "
                             "body rotation once per recording from its gyro, accelerometer and truth (never from "
                             "an estimate), print them, and score every estimator against the same aligned truth; "
                             "--init truth then starts from the aligned truth (see README)")


def build_parser() -> argparse.ArgumentParser:
    from evaluation.ablate import PRESETS

    parser = argparse.ArgumentParser(prog="fusion", description="Orientation estimation from gyro + accelerometer, scored against VICON.")
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors")
    p.add_argument("--estimators", default="all",
                   help="comma-separated registry names with optional parameters, e.g. 'dr,ukf:R=1e-3' (default: all)")
    _add_data_args(p)
    _add_run_args(p)
    p.add_argument("--panorama", action="store_true",
                   help="also stitch a panorama per estimate (camera frames, or frames rendered from a scene with the "
                        "ground truth) and score it against the ground truth's panorama (PSNR, SSIM)")
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

    p = sub.add_parser("panorama", help="stitch camera frames (or frames rendered from a scene) into a panorama")
    p.add_argument("--estimator", default="dr", help="one estimator spec, e.g. 'ukf:R=1e-3' (default: dr)")
    _add_data_args(p)
    p.add_argument("--out", required=True, help="output image (.png, .jpg)")
    p.add_argument("--reference", action="store_true",
                   help="write the estimate, the ground-truth panorama and their difference, stacked")
    p.add_argument("--blend", choices=("last", "average", "feather"), default="feather", help="blending (default: feather)")
    p.add_argument("--size", default="1920x960", help="panorama WIDTHxHEIGHT in px (default: 1920x960)")
    p.add_argument("--rate", type=float, default=10.0, help="frame rate of rendered frames, Hz (default: 10)")
    p.add_argument("--scene", default=None, help="equirectangular scene image to render frames from "
                                                 "(default: <data-dir>/scenes/room_equirect.jpg; procedural for sim)")
    p.set_defaults(func=cmd_panorama)

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
    _add_align_arg(p)
    p.set_defaults(func=cmd_calibrate)
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
