"""The command line: its output is checked, not only its exit code."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fusion.cli import main

KEYS = {"dataset", "estimator", "samples", "seconds", "rmse_deg", "max_deg", "alignment"}


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
