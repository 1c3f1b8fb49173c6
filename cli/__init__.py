"""The `fusion` command: a thin layer over the library (no maths here).

    fusion compare --estimators dr,ukf --dataset all --data-dir ../shared/data/ece276a

Each `cmd_*` makes one library call with the parsed arguments and prints what it
returns (`fusion.evaluation.runs.run_compare`, `run_ablate`, `run_inspect`, `run_calibrate`,
`run_panorama`, `fusion.evaluation.report.render.render`). Bad input gives
one line `fusion: error: ...` and exit code 1, never a traceback; SIGTERM stops a run as Ctrl-C does.
"""
from __future__ import annotations

from fusion import check_package_name

check_package_name(__name__, "fusion.cli")

import argparse
import contextlib
import shlex
import signal
import sys
import warnings
from pathlib import Path
from typing import Sequence

from fusion.selection import note


# The loading options of every command that reads recordings, in this order in `--help`
# (`fusion.evaluation.run.settings.RunSettings`' fields: their options are described there).
_DATA_FIELDS = ("dataset", "data_dir", "init", "progress", "dropouts", "mag", "imu_topic", "truth_topic", "calibration")


def _settings_class(command: str | None):
    """The settings dataclass of `command`: `TuneSettings` for tune, `StressSettings` for stress,
    else `RunSettings`."""
    if command == "tune":
        from fusion.evaluation.sweeps.tune import TuneSettings

        return TuneSettings
    if command == "stress":
        from fusion.evaluation.sweeps.stress import StressSettings

        return StressSettings
    from fusion.evaluation.run.settings import RunSettings

    return RunSettings


def _settings_options(names: Sequence[str] | None = None, command: str | None = None) -> list:
    """(field, `Option`) of each settings field (`_settings_class`) in `names` (in that order), or of
    each that `command` offers (in field order); `stress` offers compare's (but those a stress run has
    no use for, `fusion.evaluation.sweeps.stress.NOT_OFFERED`) and its own (`StressSettings`')."""
    import dataclasses

    from fusion.evaluation.run.settings import Option
    from fusion.evaluation.sweeps.stress import NOT_OFFERED

    fields = {f.name: f for f in dataclasses.fields(_settings_class(command)) if isinstance(f.metadata["cli"], Option)}

    def offered(name: str) -> bool:
        commands = fields[name].metadata["cli"].commands
        return command in commands or (command == "stress" and "compare" in commands and name not in NOT_OFFERED)

    chosen = names if names is not None else [n for n in fields if offered(n)]
    return [(fields[name], fields[name].metadata["cli"]) for name in chosen]


def _add_settings_args(parser: argparse.ArgumentParser, names: Sequence[str] | None = None,
                       command: str | None = None) -> None:
    """One option per settings field (`_settings_options`), as its metadata (`Option`) says."""
    from fusion.evaluation.run.settings import AS_FIELD

    for f, option in _settings_options(names, command):
        default = f.default if option.default == AS_FIELD else option.default
        kind = {"switch": dict(action="store_true"), "negated": dict(action="store_true"),
                "on_off": dict(choices=("on", "off"), default="on" if default else "off"),
                "auto_on_off": dict(choices=("auto", "on", "off"),
                                    default="auto" if default is None else "on" if default else "off"),
                "choices": dict(choices=option.choices, default=default),
                "append": dict(action="append", default=None),
                "value": dict(type=_TYPES[option.type] if option.type else None, default=default)}[option.kind]
        parser.add_argument(option.flag, help=option.help, **kind,
                            **({"metavar": option.metavar} if option.metavar else {}))


def _setting(args: argparse.Namespace, f, option) -> object:
    """A field's value from its parsed option (`Option.kind`)."""
    value = getattr(args, option.dest)
    if option.kind == "switch":
        return True if value else f.default
    if option.kind == "negated":
        return not value
    if option.kind == "on_off":
        return value == "on"
    if option.kind == "auto_on_off":
        return None if value == "auto" else value == "on"
    if option.kind == "append":
        return None if value is None else tuple(value)
    return value  # "value", "choices": as parsed


def _add_data_args(parser: argparse.ArgumentParser) -> None:
    _add_settings_args(parser, _DATA_FIELDS)


def _data(args: argparse.Namespace) -> dict:
    """The options every command shares, as the library's keyword arguments (the selection and
    `--init` apart)."""
    return {f.name: _setting(args, f, option) for f, option in _settings_options(_DATA_FIELDS)
            if f.name not in ("dataset", "init")}


def _command(args: argparse.Namespace) -> str:
    return shlex.join(["fusion", *args.argv])


def _run_options(args: argparse.Namespace) -> dict:
    """The options of `compare`, `ablate` and `tune`: every field of the command's settings
    (`fusion.evaluation.run.settings.RunSettings`, tune's `TuneSettings`) the command offers an
    option for, and the loading options, but the selection (given by position) and `resume`
    (`_resume`), and the command line itself (`command`); a field the command has no option for
    keeps its default."""
    options = {f.name: _setting(args, f, option) for f, option in _settings_options(command=args.command)}
    options.update({f.name: _setting(args, f, option) for f, option in _settings_options(_DATA_FIELDS)})
    return {**{name: value for name, value in options.items() if name not in ("dataset", "resume")},
            "command": _command(args)}


def _print_run(run, verbose: bool = False) -> int:
    """Print the table, then one line per failed job (with `verbose`, under it the traceback of the
    user's own code, as results.json keeps it); exit status 1 if a job failed."""
    import textwrap

    print(run.table)
    if run.report is not None:
        print(f"report: {run.report}", file=sys.stderr)
    for r in run.failed:
        print(f"fusion: error: {r.error}", file=sys.stderr)
        if verbose and r.traceback:
            print(textwrap.indent(r.traceback.rstrip("\n"), "    "), file=sys.stderr)
    return 1 if run.failed else 0


# what `--resume DIR` may be combined with: how the run runs, not what it computes
_RESUME_OPTIONS = ("jobs", "no_progress", "scheduler", "scatter", "json", "resume", "func", "command", "argv",
                   "verbose")


def _check_resume_options(args: argparse.Namespace) -> None:
    """`--resume DIR` comes with how the run runs only (`_RESUME_OPTIONS`), for every command."""
    defaults = vars(build_parser().parse_args([args.command]))
    given = [name for name, value in vars(args).items() if name not in _RESUME_OPTIONS and value != defaults.get(name)]
    if given:
        raise ValueError(f"--resume continues the run recorded in {args.resume}: give it with --jobs, --scheduler, "
                         f"--scatter, --json or --no-progress only (not --{given[0].replace('_', '-')})")


def _resume(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_resume

    _check_resume_options(args)
    from fusion.evaluation.run.settings import HOW, RunSettings

    options = _run_options(args)
    how = {name: options[name] for name in (*RunSettings.part(HOW), "json_path") if name not in ("resume", "overwrite")}
    printer = _print_stress if args.command == "stress" else _print_run
    return printer(run_resume(args.resume, **how), args.verbose)


def cmd_compare(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_compare

    if args.resume:
        return _resume(args)
    return _print_run(run_compare(args.estimators, args.dataset, trajectories=args.trajectory, tuned=args.tuned,
                                  **_run_options(args)), args.verbose)


def cmd_stress(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_stress

    if args.resume:
        return _resume(args)
    return _print_stress(run_stress(args.estimators, args.dataset, **_run_options(args)), args.verbose)


def _print_stress(run, verbose: bool = False) -> int:
    """Print a stress run's table; a failure on a clean recording as `_print_run` does (exit status
    1), the cells that failed under a fault in one line (they are results: the table counts them)."""
    clean = [r for r in run.failed if not r.fault or r.fault.get("kind") == "none"]
    status = _print_run(type(run)(clean, run.table, run.document, run.report), verbose)
    faulted = len(run.failed) - len(clean)
    if faulted:
        note(f"{faulted} cells failed under a fault (estimator x recording x fault x severity; counted in the "
             "tables as xN, each error in results.json: --out or --json)")
    return status


def cmd_tune(args: argparse.Namespace) -> int:
    from fusion.evaluation.sweeps.tune import run_tune

    if args.resume:
        _check_resume_options(args)
        run = run_tune(out=args.resume, resume=True, json_path=args.json, jobs=args.jobs,
                       progress=not args.no_progress, scheduler=args.scheduler)
    else:
        run = run_tune(args.estimators, args.dataset, **_run_options(args))
    print(run.table)
    if run.report is not None:
        print(f"report: {run.report}", file=sys.stderr)
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_ablate

    if args.resume:
        return _resume(args)
    return _print_run(run_ablate(args.estimator, args.param, args.preset, args.dataset, tuned=args.tuned,
                                 **_run_options(args)), args.verbose)


def cmd_report(args: argparse.Namespace) -> int:
    from fusion.evaluation.report.render import render

    print(render(args.folder, jobs=args.jobs, progress=not args.no_progress))
    return 0


def cmd_panorama(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_panorama

    print(run_panorama(args.dataset, args.estimator, args.out, init=args.init, size=args.size, rate_hz=args.rate,
                           scene=args.scene, blend=args.blend, reference=args.reference, **_data(args)).text)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from fusion.estimators import available

    if args.name:
        from fusion.estimators.describe import describe

        print(describe(args.name))
        return 0
    from fusion.estimators import GROUPS

    rows = available()
    width = max(len(row.name) for row in rows)
    for group, meaning in GROUPS.items():
        members = [row for row in rows if row.group == group]
        if members:
            print(f"{group} ({meaning}):")
        for row in members:
            imu = "6-D/9-D" if row.nine_d else "6-D"
            print(f"  {row.name:<{width}}  {imu:<7}  {row.what}" + ("" if row.origin == "fusion" else f"  [{row.origin}]"))
    print("6-D/9-D: fuses the magnetometer where a recording has one; 6-D: gyro and accelerometer only")
    print("\nyour own: FILE.py:NAME or package.module:NAME, with parameters as for ours, e.g. "
          "./my_ukf.py:MyUKF:R=1e-3 (README, 'Your estimator in the table')")
    print("an estimator's parameters, with their units, defaults, meanings, valid and search ranges: fusion list NAME")
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_inspect

    print(run_inspect(args.dataset, json_path=args.json, out=args.out, command=_command(args), **_data(args)).text)
    return 0


def cmd_data(args: argparse.Namespace) -> int:
    """`fusion data list` / `fusion data fetch NAME...` (`fusion.fetch`)."""
    from fusion import fetch

    if args.data_command == "list":
        print(fetch.list_datasets(args.to))
        return 0
    if args.data_command != "fetch":
        raise ValueError("fusion data: give a command: list, or fetch NAME (fusion data --help)")
    status = 0
    for name in args.names:
        report = fetch.fetch(name, to=args.to, mirror=args.mirror, jobs=args.jobs, progress=not args.no_progress)
        print(report.summary())
        for line in report.errors():
            print(f"fusion: error: {line}", file=sys.stderr)
        status = status or (0 if report.ok else 1)
    return status


def _add_data_command(sub) -> None:
    p = sub.add_parser("data", help="public datasets by name: list them, fetch them (verified file by file)",
                       epilog="examples:\n  fusion data list\n  fusion data fetch broad\n"
                              "  fusion data fetch 'broad/03*' --to ~/data\n  fusion data fetch repoimu --mirror "
                              "https://data.example.org/imu\n  fusion compare --estimators ekf,vqf --dataset 'broad/*'",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    data_sub = p.add_subparsers(dest="data_command")
    for name, help_text in (("list", "each dataset's files, size, licence, citation and what is already local"),
                            ("fetch", "download datasets (NAME, or NAME/GLOB for part of one: 'broad/03*'), check "
                                      "every file against its published git object id")):
        q = data_sub.add_parser(name, help=help_text)
        q.add_argument("--to", metavar="DIR", default=None,
                       help="the data folder (files go to DIR/<dataset>/...; default: $FUSION_DATA, else the user "
                            "cache, where --dataset finds them without --data-dir)")
        if name == "fetch":
            q.add_argument("names", nargs="+", metavar="NAME", help="broad, repoimu, or NAME/GLOB")
            q.add_argument("--mirror", metavar="URL", default=None,
                           help="fetch from a copy serving the files at URL/<dataset>/<path> (default: "
                                "$FUSION_MIRROR, else the pinned repository)")
            q.add_argument("--jobs", type=int, default=4, metavar="N", help="parallel downloads (default: 4)")
            q.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_data, data_command=None)


def cmd_calibrate(args: argparse.Namespace) -> int:
    from fusion.evaluation.runs import run_calibrate

    print(run_calibrate(args.dataset, out=args.out, clock_offset=args.clock_offset, leave_one_out=args.leave_one_out,
                        estimators=args.estimators, init=args.init, align=args.align, command=_command(args),
                        **_data(args)).text)
    if not args.out:
        note("not saved: --out FILE writes this calibration file (then use it with --calibration FILE)")
    return 0


def _jobs(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative")
    return value


def _trajectory(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep or not name.strip() or not path.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: expected NAME=PATH, e.g. orbslam=runs/orb.tum")
    return name.strip(), path.strip()


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text} is not a positive, finite number of seconds")
    return value


_TYPES = {"int": int, "float": float, "count": _jobs, "seconds": _seconds}  # converters `Option.type` names


def _add_run_args(parser: argparse.ArgumentParser, command: str) -> None:
    """The options of `command` (compare, ablate) besides the loading ones: the other `RunSettings`
    fields it offers, and --verbose."""
    _add_settings_args(parser, [f.name for f, _ in _settings_options(command=command) if f.name not in _DATA_FIELDS],
                       command)
    parser.add_argument("--verbose", action="store_true",
                        help="under each failed row's error, the traceback of your estimator's own code (results.json "
                             "keeps it as the row's 'traceback')")


def build_parser() -> argparse.ArgumentParser:
    from fusion.evaluation.sweeps.ablate import PRESETS

    parser = argparse.ArgumentParser(
        prog="fusion", description="Orientation estimation from gyroscope, accelerometer and magnetometer, estimators "
                                   "side by side (ours, the community's and yours) against motion-capture truth.",
        epilog="examples:\n"
               "  fusion compare --estimators ukf,gd --dataset all      # the main job (the simulated recording without data)\n"
               "  fusion compare --estimators ./my_ukf.py:MyUKF,ekf --dataset ece276a/1\n"
               "  fusion ablate --preset broad-sweep --data-dir ../shared/data/broad --out runs/sweep\n"
               "  fusion stress --estimators ekf,vqf --dataset 'broad/*' --out runs/stress   # under sensor faults\n"
               "  fusion inspect --dataset ece276a/1\n"
               "  fusion list\n"
               "  fusion data fetch broad && fusion compare --estimators ekf,vqf --dataset 'broad/*'\n"
               "`fusion COMMAND --help` for each command's options.", formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("compare", help="run estimators on recordings and print a table of errors",
                       epilog="examples:\n"
                              "  fusion compare --estimators ukf,gd --dataset all\n"
                              "  fusion compare --estimators ./student.py:complementary,ekf --dataset ece276a/1\n"
                              "  fusion compare --estimators all --dataset 'broad/*' --out runs/broad --jobs 2\n"
                              "  fusion compare --resume runs/broad",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--estimators", "--estimator", dest="estimators", default="all",
                   help="comma-separated estimators with optional parameters: names (`fusion list`), or your own as "
                        "FILE.py:NAME or package.module:NAME, e.g. 'dr,ukf:R=1e-3,./my_ukf.py:MyUKF:R=0.5' "
                        "(default: all)")
    _add_data_args(p)
    _add_run_args(p, "compare")
    p.add_argument("--trajectory", action="append", default=[], type=_trajectory, metavar="NAME=PATH",
                   help="a trajectory another program wrote, in the table as the row NAME: a TUM (.tum, .txt: "
                        "t tx ty tz qx qy qz qw) or CSV (t,qw,qx,qy,qz) file with one recording selected, or a folder "
                        "with one file per recording named by its id (FOLDER/ece276a/3.tum); repeatable")
    p.add_argument("--tuned", metavar="FILE", default=None,
                   help="run each estimator the file holds with its tuned setting (the tuned.json of "
                        "`fusion tune --out DIR`); parameters given in a spec win")
    p.set_defaults(func=cmd_compare)

    from fusion.evaluation.sweeps.stress import fault_table

    p = sub.add_parser("stress", help="every estimator under controlled sensor faults, at graded severities: "
                                      "dose-response curves and each estimator's robustness",
                       epilog="examples:\n"
                              "  fusion stress --estimators ekf,vqf,madgwick,mahony,gn --dataset 'broad/*' --out "
                              "runs/stress --jobs 2\n"
                              "  fusion stress --estimators ekf,vqf --dataset 'ece276a/*' --fault gyro-bias-step=1,2,5 "
                              "--fault drops\n"
                              "  fusion stress --resume runs/stress\n\n"
                              "faults (severity unit, the five run by default, the sensor, the model):\n"
                              + fault_table() + "\n\n"
                              "A cell (estimator x recording x fault x severity) that fails costs that cell: the "
                              "tables "
                              "count it, results.json keeps its error; the exit status is 1 only when an estimator "
                              "fails on a clean recording.",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--estimators", "--estimator", dest="estimators", default="all",
                   help="comma-separated estimators with optional parameters, as for compare (default: all)")
    _add_data_args(p)
    _add_run_args(p, "stress")
    next(a for a in p._actions if a.dest == "rerun").help = (
        "also write a Rerun recording (fusion.evaluation.report.rerun_log.write_stress): each fault's "
        "dose-response, and the first recording's sensor clean and at the fault's worst severity; open it with "
        "`rerun FILE.rrd` (needs pip install 'fusion[viz]')")
    p.set_defaults(func=cmd_stress)

    p = sub.add_parser("tune", help="tune estimators by one protocol and score them out of sample",
                       epilog="examples:\n"
                              "  fusion tune --estimators madgwick,mahony,vqf --dataset 'broad/*' --out runs/tune\n"
                              "  fusion tune --estimators all --dataset 'broad/*' --by group --jobs 2\n"
                              "  fusion tune --estimators ekf --train 'broad/*' --test 'ece276a/*' --metric inclination\n"
                              "  fusion tune --estimators madgwick --dataset 'broad/*' --search tpe --budget 40\n"
                              "  fusion compare --estimators madgwick,ekf --dataset 'broad/*' --tuned runs/tune/tuned.json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--estimators", "--estimator", dest="estimators", default="all",
                   help="the estimators to tune (`fusion list NAME` shows each one's search space); a parameter "
                        "given in a spec is fixed, not tuned (default: all)")
    _add_data_args(p)
    _add_settings_args(p, command="tune")  # `TuneSettings`' fields: its own and the `RunSettings` it offers
    p.set_defaults(func=cmd_tune)

    p = sub.add_parser("ablate", help="sweep estimator parameters (or run a preset) over recordings",
                       epilog="examples:\n"
                              "  fusion ablate --estimator ukf --param R=1e-4,1e-3,1e-2 --param sigma=kraft,julier\n"
                              "  fusion ablate --estimator ./student.py:complementary --param gain=0.01,0.02,0.05\n"
                              "  fusion ablate --preset broad-sweep --data-dir ../shared/data/broad --out runs/sweep\n"
                              "  fusion ablate --resume runs/sweep",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--estimator", "--estimators", dest="estimator",
                   help="the estimator to sweep (ours or your own FILE.py:NAME), optionally with fixed parameters: "
                        "'ukf:Q=1e-5'")
    p.add_argument("--param", action="append", default=[], metavar="NAME=V1,V2",
                   help="a parameter and its values; repeat for a grid, e.g. --param R=1e-4,1e-3 --param sigma=kraft,julier")
    p.add_argument("--preset", metavar="NAME", help=f"a named ablation: {', '.join(PRESETS)}")
    p.add_argument("--tuned", metavar="FILE", default=None,
                   help="run the swept estimator with its tuned setting (the tuned.json of `fusion tune --out DIR`) "
                        "for every parameter --param does not sweep")
    _add_data_args(p)
    _add_run_args(p, "ablate")
    p.set_defaults(func=cmd_ablate)

    p = sub.add_parser("list", help="the estimators a spec can name: ours and those installed packages register; "
                                    "with NAME, that estimator's parameters",
                       epilog="examples:\n  fusion list\n  fusion list ekf\n  fusion list ./my_ukf.py:MyUKF",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", metavar="NAME",
                   help="an estimator (a name of `fusion list`, or FILE.py:NAME): one line per parameter with its "
                        "alias, field name, default, unit, meaning and search range")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("report", help="re-render the report of an --out folder from its results.json and series",
                       epilog="example:\n  fusion report runs/all      # no estimator runs", formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", metavar="DIR")
    p.add_argument("--jobs", type=_jobs, default=0, metavar="N", help="worker processes; 0 = all cores (default)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("panorama", help="stitch camera frames (or frames rendered from a scene) into a panorama",
                       epilog="examples:\n  fusion panorama --dataset ece276a/1 --estimator ukf --out pano.png --reference\n"
                              "  fusion panorama --dataset sim --estimator ./student.py:complementary --out pano.png",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--estimator", "--estimators", dest="estimator", default="dr", help="one estimator spec, e.g. 'ukf:R=1e-3' (default: dr)")
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
                                       "time stamps, magnetometer, truth gaps and clock offset",
                       epilog="examples:\n  fusion inspect --dataset ece276a/1\n"
                              "  fusion inspect --dataset 'broad/*' --data-dir ../shared/data --json checks.json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_data_args(p)
    p.add_argument("--json", metavar="PATH", help="write the checks as JSON")
    p.add_argument("--out", metavar="DIR", help="write a figure per recording into DIR")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("calibrate", help="fit gyro scale factors (and clock offsets) against the truth",
                       epilog="examples:\n  fusion calibrate --dataset ece276a --out calib.json\n"
                              "  fusion compare --estimators ekf --dataset all --calibration calib.json",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_data_args(p)
    p.add_argument("--out", metavar="FILE", help="write the calibration file (JSON, see README, Commands)")
    p.add_argument("--clock-offset", action="store_true",
                   help="also store each recording's measured IMU-VICON clock offset (applied to that recording's truth)")
    p.add_argument("--leave-one-out", action="store_true",
                   help="score each recording with the scales fitted on the others, and print the fitted scales per fold")
    p.add_argument("--estimators", "--estimator", dest="estimators", default="dr", help="estimators scored by --leave-one-out (default: dr)")
    _add_settings_args(p, ("align",))
    p.set_defaults(func=cmd_calibrate)

    _add_data_command(sub)
    return parser


def _one_line_warnings(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"fusion: warning: {message}", file=sys.stderr)


@contextlib.contextmanager
def one_line_warnings():
    """Warnings as one `fusion: warning: ...` line on stderr, while the block runs (the previous
    `warnings.showwarning` is restored after it)."""
    previous = warnings.showwarning
    warnings.showwarning = _one_line_warnings
    try:
        yield
    finally:
        warnings.showwarning = previous


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    if args.command is None:  # plain `fusion` runs the main job
        argv = ["compare", *argv]
        args = parser.parse_args(argv)
    args.argv = argv
    previous = _terminate_as_interrupt()
    try:
        with one_line_warnings():
            return args.func(args)
    except (ValueError, OSError) as exc:  # bad input: one line, exit 1
        print(f"fusion: error: {exc}", file=sys.stderr)
        return 1
    except ImportError as exc:  # an optional package (peers, h5py) is missing: the message says which
        print(f"fusion: error: {exc}", file=sys.stderr)
        return 1
    except Terminated:
        print(f"fusion: terminated (SIGTERM){_resume_hint(args)}", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print(f"fusion: interrupted{_resume_hint(args)}", file=sys.stderr)
        return 128 + signal.SIGINT
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C raises KeyboardInterrupt."""


def _resume_hint(args: argparse.Namespace) -> str:
    folder = getattr(args, "resume", None) or getattr(args, "out", None)
    if args.command not in ("compare", "ablate", "tune", "stress") or not folder:
        return ""
    from fusion.evaluation.run.journal import JOURNAL, RUN_DIR

    if not (Path(folder) / RUN_DIR / JOURNAL).is_file():
        return ""
    return f"; continue with: fusion {args.command} --resume {shlex.quote(str(folder))}"


def _terminate_as_interrupt():
    """SIGTERM raises `Terminated` (a KeyboardInterrupt), as Ctrl-C raises KeyboardInterrupt, so that
    worker processes are stopped and an --out folder is left as it was, with its journal (returns
    the previous handler; None off the main thread)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None

    def terminate(signum, frame):
        raise Terminated

    return signal.signal(signal.SIGTERM, terminate)


if __name__ == "__main__":
    sys.exit(main())
