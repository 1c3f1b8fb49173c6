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

import numpy as np

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
        raise ValueError(f"{root}: no recordings found (imu/imuRawN.p|.mat or .csv); use --dataset sim for the simulated one")
    recordings = []
    for source in tqdm(sources, desc="loading", disable=args.no_progress, file=sys.stderr, leave=False):
        recordings.append(datasets.load_source(source))
    return recordings


def cmd_compare(args: argparse.Namespace) -> int:
    from evaluation.compare import compare, format_table, results_json

    recordings = load_selected(args)
    results = compare([args.estimators], recordings, init=args.init, progress=not args.no_progress,
                      panorama=args.panorama, data_dir=datasets.data_dir_from(args.data_dir))
    print(format_table(results))
    if args.json:
        settings = {"command": " ".join(["fusion", *sys.argv[1:]]), "estimators": args.estimators,
                    "dataset": args.dataset, "data_dir": str(datasets.data_dir_from(args.data_dir)),
                    "init": args.init or "default (truth where available, else accel)"}
        Path(args.json).write_text(json.dumps(results_json(results, settings), indent=2) + "\n")
    return 0


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fusion", description="Orientation estimation from gyro + accelerometer, scored against VICON.")
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors")
    p.add_argument("--estimators", default="all",
                   help="comma-separated registry names with optional parameters, e.g. 'dr,ukf:R=1e-3' (default: all)")
    _add_data_args(p)
    p.add_argument("--json", metavar="PATH", help="write the results as JSON (format: see README)")
    p.add_argument("--panorama", action="store_true",
                   help="also stitch a panorama per estimate and score it against the ground truth's (PSNR, SSIM)")
    p.set_defaults(func=cmd_compare)

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
