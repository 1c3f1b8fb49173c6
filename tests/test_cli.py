"""The command line: its output is checked, not only its exit code."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fusion.cli import main
from settings_fixtures import not_default

KEYS = {"dataset", "estimator", "samples", "seconds", "rmse_deg", "max_deg", "scored_samples", "coverage", "alignment",
        "magnetometer"}


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_compare_on_sim_without_data(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)  # no ./data here: the built-in recording runs
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--no-progress", "--json", "r.json")
    assert code == 0, err
    row = [line.split() for line in out.splitlines() if line.startswith("sim ")]
    assert len(row) == 1 and row[0][1] == "dr"
    doc = json.loads((tmp_path / "r.json").read_text())
    (result,) = doc["results"]
    assert set(result) == KEYS
    assert result["dataset"] == "sim" and result["samples"] == 18000
    assert result["alignment"] is None  # --align is off by default
    assert set(result["rmse_deg"]) == {"total", "inclination", "heading"}
    # the table prints the same numbers as the JSON
    assert float(row[0][2]) == pytest.approx(result["rmse_deg"]["total"], abs=0.006)
    assert "numpy" in doc["versions"] and doc["settings"]["estimators"] == "dr"
    # the fallback is said, once, on stderr
    assert err.count("fusion: note: no recordings found in ") == 1
    assert "running on the built-in simulated recording `sim`" in err
    # settings say what shaped the numbers, --json as --out does
    assert doc["settings"]["dropouts"] == "on" and doc["settings"]["calibration"] is None
    assert doc["settings"]["git_commit"] and doc["settings"]["merged"] == {}


def test_compare_real_recordings(data_dir, tmp_path, capsys):
    # the reference range is for plain integration: without dropout handling
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "all", "--data-dir",
                         str(data_dir / "ece276a"), "--json", str(tmp_path / "r.json"), "--no-progress",
                         "--dropouts", "off")
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    assert [r["dataset"] for r in doc["results"]] == [f"ece276a/{n}" for n in range(1, 10)]
    incl = np.mean([r["rmse_deg"]["inclination"] for r in doc["results"]])
    total = np.mean([r["rmse_deg"]["total"] for r in doc["results"]])
    assert 10 < incl < 20 and 15 < total < 30  # the expected range for dead reckoning
    mean_line = [line for line in out.splitlines() if line.startswith("mean (9)")]
    assert mean_line and float(mean_line[0].split()[4]) == pytest.approx(incl, abs=0.006)


def test_recording_without_truth_still_runs(data_dir, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "ece276a-2018/3",
                         "--data-dir", str(data_dir), "--no-progress")
    assert code == 0, err
    (row,) = [line.split() for line in out.splitlines() if line.startswith("ece276a-2018/3")]
    assert row[2:5] == ["-", "-", "-"]


@pytest.mark.parametrize("argv, message", [
    (["--estimators", "nope", "--dataset", "sim"], "unknown estimator 'nope'; available: dr"),
    (["--estimators", "dr:x=1", "--dataset", "sim"], "unknown parameter 'x'"),
    (["--estimators", "dr", "--dataset", "nothing/9"], "dataset 'nothing/9' not found"),
    (["--estimators", "dr", "--dataset", "sim", "--init", "truth", "--data-dir", "/no/such/dir"], "/no/such/dir: data directory does not exist"),
    (["--estimators", "ukf:R=-1", "--dataset", "sim"], "parameter 'R' (acc_noise_g2_s)"),
    (["--estimators", "dr", "--dataset", "sim", "--data-dir", __file__], "data directory is a file"),
])
def test_bad_input_is_one_line_and_exit_1(capsys, argv, message):
    code, out, err = run(capsys, "compare", "--no-progress", *argv)
    assert code == 1
    assert err.count("\n") == 1 and err.startswith("fusion: error: ") and message in err
    assert "Traceback" not in err


def test_empty_data_dir_is_an_error(tmp_path, capsys):
    code, out, err = run(capsys, "compare", "--data-dir", str(tmp_path), "--no-progress")
    assert code == 1 and "no recordings found" in err


def test_truncated_file_from_the_cli(tmp_path, capsys):
    (tmp_path / "lab" / "imu").mkdir(parents=True)
    (tmp_path / "lab" / "imu" / "imuRaw1.p").write_bytes(b"\x80\x04garbage")
    code, out, err = run(capsys, "compare", "--data-dir", str(tmp_path), "--dataset", "lab/1", "--estimators", "dr", "--no-progress")
    assert code == 1 and "imuRaw1.p: not a readable pickle" in err and err.count("\n") == 1


def test_python_dash_m_entry_point(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "FUSION_DATA"}
    proc = subprocess.run([sys.executable, "-m", "fusion", "compare", "--estimators", "dr", "--dataset", "sim", "--no-progress"],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "sim" in proc.stdout and "RMSE in degrees" in proc.stdout


@pytest.mark.slow
def test_dataset_all_over_shared_data_counts_each_recording_once(data_dir, tmp_path, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "all", "--data-dir", str(data_dir),
                         "--json", str(tmp_path / "r.json"), "--no-progress")
    assert code == 0, err
    doc = json.loads((tmp_path / "r.json").read_text())
    ids = [r["dataset"] for r in doc["results"]]
    assert [i for i in ids if i.startswith("ece")] == [f"ece276a/{n}" for n in range(1, 10)]
    assert len([i for i in ids if i.startswith("broad/")]) == 14
    assert len([i for i in ids if i.startswith("repoimu/")]) == 89 and len(ids) == 9 + 14 + 89
    # the truth-less 2018 copies are merged away; every recording is scored or listed with its reason
    # (RepoIMU's static files hold no truth; a few of its trials cannot be aligned)
    unscored = {e["dataset"]: e["reason"] for e in doc["not_scored"]}
    assert all(r["rmse_deg"] or r["not_scored"] == unscored[r["dataset"]] for r in doc["results"])
    assert unscored and all(rid.startswith("repoimu/") for rid in unscored)
    assert {rid for rid, why in unscored.items() if why.startswith("no truth")} == {
        *(f"repoimu/Pendulum/Pendulum_Test01{ab}_Static_Segment_{n}" for ab in "ab" for n in (1, 2, 3)),
        "repoimu/TStick/TStick_Test01_Static"}
    assert out.splitlines()[-len(unscored) - 1].startswith(f"not scored: {len(unscored)} of {len(ids)} recordings")
    merged = doc["settings"]["merged"]
    assert merged["ece276a/4"] == ["ece276a-2018/4", "ese650/4"] and len(merged) == 9
    notes = [line for line in err.splitlines() if "identical recordings counted once" in line]
    assert notes == ["fusion: note: identical recordings counted once: "
                     "ece276a/N = ece276a-2018/N, ese650/N for N = 1-9"]
    lines = out.splitlines()
    # one mean per folder (recordings of different sensors and protocols are never pooled), then the
    # mean of the folders' means, each folder counted once
    means = [line.split() for line in lines if line.startswith("mean ")]
    scored = {"repoimu/Pendulum": sum(i.startswith("repoimu/Pendulum/") and i not in unscored for i in ids),
              "repoimu/TStick": sum(i.startswith("repoimu/TStick/") and i not in unscored for i in ids)}
    assert [m[:4] for m in means] == [["mean", "broad", "(14)", "dr"], ["mean", "ece276a", "(9)", "dr"],
                                      ["mean", "repoimu/Pendulum", f"({scored['repoimu/Pendulum']})", "dr"],
                                      ["mean", "repoimu/TStick", f"({scored['repoimu/TStick']})", "dr"],
                                      ["mean", "all", "datasets", "(4)"]]
    assert float(means[4][5]) == pytest.approx(np.mean([float(m[4]) for m in means[:4]]), abs=0.011)
    (together,) = doc["datasets"]["all"]
    assert together["datasets"] == 4 and together["recordings"] == 23 + sum(scored.values())
    first_mean = next(i for i, line in enumerate(lines) if line.startswith("mean "))
    first_row = next(i for i, line in enumerate(lines) if line.startswith(("broad/", "ece276a/")))
    assert first_mean < first_row  # the summary comes first


def test_rows_without_truth_come_after_the_scored_ones(data_dir, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "ece276a-2018/3,sim",
                         "--data-dir", str(data_dir), "--no-progress")
    assert code == 0, err
    lines = out.splitlines()
    order = [i for key in ("mean (1)", "sim ", "not scored (the reasons below)", "ece276a-2018/3")
             for i, line in enumerate(lines) if line.startswith(key)]
    assert len(order) == 4 and order == sorted(order)


def test_bare_number_folder_name_and_imu_folder(data_dir, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "3", "--data-dir", str(data_dir),
                         "--no-progress")
    assert code == 0, err
    assert [line.split()[0] for line in out.splitlines() if "  dr  " in line] == ["ece276a/3"]
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "ese650", "--data-dir",
                         str(data_dir), "--no-progress")
    assert code == 0, err
    assert [line.split()[0] for line in out.splitlines() if line.startswith("ese650/")] == \
        [f"ese650/{n}" for n in range(1, 10)]
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "2",
                         "--data-dir", str(data_dir / "ece276a" / "imu"), "--no-progress")
    assert code == 0, err
    assert "is a course's imu/ folder; reading recordings from its parent" in err
    assert [line.split()[0] for line in out.splitlines() if "  dr  " in line] == ["ece276a/2"]


def test_estimator_spellings_on_every_command():
    from fusion.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["compare", "--estimator", "dr"]).estimators == "dr"
    assert parser.parse_args(["compare", "--estimators", "dr"]).estimators == "dr"
    assert parser.parse_args(["ablate", "--estimators", "ukf"]).estimator == "ukf"
    assert parser.parse_args(["ablate", "--estimator", "ukf"]).estimator == "ukf"
    assert parser.parse_args(["panorama", "--estimators", "gn", "--out", "x.png"]).estimator == "gn"
    assert parser.parse_args(["calibrate", "--estimator", "ekf"]).estimators == "ekf"


def test_inspect_and_calibrate_record_the_argv_given_and_restore_warnings(tmp_path, capsys, monkeypatch):
    import warnings

    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["pytest", "--something-else"])
    before = warnings.showwarning
    assert main(["inspect", "--dataset", "sim", "--json", "i.json", "--no-progress"]) == 0
    assert json.loads((tmp_path / "i.json").read_text())["command"] == "fusion inspect --dataset sim --json i.json --no-progress"
    assert main(["calibrate", "--dataset", "sim", "--out", "c.json", "--no-progress"]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["info"]["command"].startswith("fusion calibrate --dataset sim")
    assert warnings.showwarning is before
    capsys.readouterr()


def test_calibrate_without_out_prints_the_result_and_how_to_save_it(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    code, out, err = run(capsys, "calibrate", "--dataset", "sim", "--no-progress")
    assert code == 0 and list(tmp_path.iterdir()) == []
    doc = json.loads(out[out.index("{"):])
    assert doc["format"] == "fusion-gyro-calibration" and len(doc["gyro_scale_factor"]) == 3
    assert "--out FILE writes this calibration file" in err


def test_list_names_the_estimators_and_points_at_list_name(capsys):
    code, out, err = run(capsys, "list")
    assert code == 0 and err == ""
    names = [line.split()[0] for line in out.splitlines() if line.startswith("  ")]  # grouped, indented
    assert names[:4] == ["dr", "ukf", "ukf-bias", "ekf"]
    assert names.index("gd") + 1 == names.index("gn") and names.index("gd") > names.index("ekf")
    assert out.splitlines()[-1] == ("an estimator's parameters, with their units, defaults, meanings, valid and search "
                                    "ranges: fusion list NAME")


@pytest.mark.parametrize("spec, message", [
    ("ekf:Qbad=1e308", "fusion: error: estimator 'ekf' parameter 'Qbad' (invalid_gyr_var_rad2_s2): Qbad=1e+308 "
                       "(a standard deviation) is too large"),
    ("ukf:iters=inf", "fusion: error: estimator 'ukf' parameter 'iters': 'inf' is not a whole number"),
    ("gn:level=1e-308", "fusion: error: estimator 'gn' parameter 'level' (init_level_s): init_level_s=1e-308"),
])
def test_a_hostile_parameter_value_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, spec, message):
    monkeypatch.chdir(tmp_path)
    code, out, err = run(capsys, "compare", "--estimators", spec, "--dataset", "sim", "--no-progress")
    assert code == 1 and out == ""
    assert err.startswith(message) and err.count("\n") == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_primary_chooses_the_metric_of_the_interval_column_and_is_recorded(data_dir, tmp_path, capsys):
    """`--primary inclination`: the table's interval and mark are the inclination's, results.json
    says so, and `fusion report` re-renders the same table."""
    out = tmp_path / "run"
    argv = ["compare", "--estimators", "dr,vqf-basic", "--dataset", "ece276a/*", "--data-dir", str(data_dir),
            "--mag", "off", "--no-progress", "--jobs", "1", "--no-tum"]
    assert main([*argv, "--primary", "inclination", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "inclination 95% CI" in table and "total 95% CI" not in table
    assert json.loads((out / "results.json").read_text())["settings"]["primary"] == "inclination"
    assert main(["report", str(out), "--no-progress", "--jobs", "1"]) == 0
    assert (out / "table.txt").read_text().strip() == table.strip()
    with pytest.raises(SystemExit):  # argparse refuses it, with its usage line
        main([*argv, "--primary", "yaw"])



@pytest.mark.parametrize("command", ["compare", "ablate"])
def test_every_run_setting_has_an_option_that_reaches_it(command):
    """Every field of `RunSettings` has a command-line option (or says it has none: `API_ONLY`), and
    each option the command offers, given a value other than the default, arrives in the settings
    the command builds (a field added with an `Option` is covered here by construction)."""
    import dataclasses

    from fusion import cli
    from fusion.evaluation.run.settings import API_ONLY, Option, RunSettings

    fields = dataclasses.fields(RunSettings)
    assert [f.name for f in fields if f.metadata.get("cli") == API_ONLY] == ["command"]
    assert all(isinstance(f.metadata.get("cli"), Option) for f in fields if f.name != "command")
    offered = [(f, o) for f in fields if isinstance(o := f.metadata["cli"], Option) and command in o.commands]
    only_the_other = {"compare": "per_recording", "ablate": "panorama"}[command]
    assert {f.name for f, _ in offered} == {f.name for f in fields} - {"command", only_the_other}
    argv, expected = [command], {}
    for f, option in offered:
        if f.name != "resume":  # `--resume DIR` continues a run instead (test_the_options_of_a_resumed_run)
            words, expected[f.name] = not_default(f, option)
            argv += words
    args = cli.build_parser().parse_args(argv)
    args.argv = argv
    settings = RunSettings(dataset=args.dataset, **cli._run_options(args))
    assert {name: getattr(settings, name) for name in expected} == expected
    assert all(value != getattr(RunSettings(), name) for name, value in expected.items() if name != "progress")
    assert settings.command == "fusion " + " ".join(argv)


def test_the_options_of_a_resumed_run_are_how_it_runs(tmp_path, monkeypatch, capsys):
    from fusion.evaluation import runs

    seen = []
    monkeypatch.setattr(runs, "run_resume", lambda out, **how: seen.append((out, how)) or runs.Run([], "table"))
    code, out, err = run(capsys, "compare", "--resume", str(tmp_path), "--jobs", "2", "--no-progress", "--scheduler",
                         "tcp://10.0.0.5:8786", "--scatter", "--json", "r.json")
    assert code == 0, err
    assert seen == [(str(tmp_path), {"jobs": 2, "progress": False, "scheduler": "tcp://10.0.0.5:8786", "scatter": True,
                                     "json_path": "r.json"})]
    code, _, err = run(capsys, "ablate", "--resume", str(tmp_path), "--init", "accel")
    assert code == 1 and "not --init" in err and len(seen) == 1
