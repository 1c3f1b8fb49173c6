"""Trajectories as files (`fusion.trajectory_files`, `--trajectory NAME=PATH`, the `--out`
folder's `trajectories/`): another program's trajectory in the table, our estimates checked by
evo, the field's own tool."""
from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.cli import main
from fusion.trajectory_files import read_trajectory, write_tum


@pytest.fixture
def quiet_data(monkeypatch, tmp_path):
    """No data directory: `sim` is the recording."""
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def exported(quiet_data, capsys):
    """`compare --out` on sim with dr and ekf: its folder, and its rows by estimator."""
    out = quiet_data / "run"
    assert main(["compare", "--estimators", "dr,ekf", "--dataset", "sim", "--no-progress", "--out", str(out)]) == 0
    capsys.readouterr()
    rows = {r["estimator"]: r for r in json.loads((out / "results.json").read_text())["results"]}
    return out, rows


def test_tum_is_scalar_last_and_reads_back_bit_for_bit(tmp_path):
    rot = Rotation.random(50, random_state=3)
    t = 1.7e9 + np.arange(50) * 0.01
    path = tmp_path / "a.tum"
    write_tum(path, t, rot.as_quat(scalar_first=True))
    first = path.read_text().splitlines()[1].split()
    np.testing.assert_array_equal([float(v) for v in first[4:]], rot[0].as_quat())  # x y z w: scalar last
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t, t)
    np.testing.assert_allclose(back.quat_wxyz, rot.as_quat(scalar_first=True), rtol=0, atol=1e-15)
    csv = tmp_path / "a.csv"
    csv.write_text("t,qw,qx,qy,qz\n" + "\n".join(",".join(repr(float(v)) for v in (ti, *q))
                                                 for ti, q in zip(t, rot.as_quat(scalar_first=True))) + "\n")
    np.testing.assert_allclose(read_trajectory(csv).quat_wxyz, back.quat_wxyz, rtol=0, atol=1e-15)


def test_an_exported_trajectory_read_back_scores_as_its_row(exported, capsys):
    out, rows = exported
    assert main(["compare", "--estimators", "dr", "--trajectory", f"again={out}/trajectories/sim/ekf.tum",
                 "--dataset", "sim", "--no-progress", "--json", "r.json"]) == 0
    again = next(r for r in json.loads(open("r.json").read())["results"] if r["estimator"] == "again")
    for kind in ("total", "inclination", "heading"):
        assert again["rmse_deg"][kind] == pytest.approx(rows["ekf"]["rmse_deg"][kind], abs=1e-6)
    assert again["scored_samples"] == rows["ekf"]["scored_samples"]


@pytest.mark.skipif(shutil.which("evo_ape") is None, reason="evo is in the test extra")
@pytest.mark.parametrize("estimator", ["dr", "ekf"])
def test_evo_scores_our_export_as_we_do(exported, estimator):
    """evo's APE (rotation angle, deg) on the exported estimate and truth equals our total RMSE."""
    out, rows = exported
    folder = out / "trajectories" / "sim"
    proc = subprocess.run(["evo_ape", "tum", str(folder / "truth.tum"), str(folder / f"{estimator}.tum"),
                           "--pose_relation", "angle_deg"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rmse = float(re.search(r"^\s*rmse\s+([0-9.eE+-]+)", proc.stdout, re.M).group(1))
    assert rmse == pytest.approx(rows[estimator]["rmse_deg"]["total"], abs=1e-4)


def test_no_tum_leaves_the_trajectories_out(quiet_data, exported, capsys):
    out = quiet_data / "lean"
    assert main(["compare", "--estimators", "dr,ekf", "--dataset", "sim", "--no-progress", "--out", str(out), "--no-tum"]) == 0
    capsys.readouterr()
    assert (out / "report.html").exists() and not (out / "trajectories").exists()
    with_tum, _ = exported
    assert sorted(p.name for p in (with_tum / "trajectories" / "sim").iterdir()) == ["dr.tum", "ekf.tum", "truth.tum"]
    rows = [json.loads((folder / "results.json").read_text())["results"] for folder in (out, with_tum)]
    assert [r["rmse_deg"] for r in rows[0]] == [r["rmse_deg"] for r in rows[1]]


def test_a_partial_trajectory_is_scored_where_it_is_and_never_extrapolated(exported, capsys):
    out, rows = exported
    full = read_trajectory(out / "trajectories" / "sim" / "ekf.tum")
    half = len(full.t) // 2
    write_tum("half.tum", full.t[:half], full.quat_wxyz[:half])
    assert main(["compare", "--estimators", "ekf", "--trajectory", "half=half.tum", "--dataset", "sim",
                 "--no-progress", "--json", "r.json"]) == 0
    row = next(r for r in json.loads(open("r.json").read())["results"] if r["estimator"] == "half")
    assert row["scored_samples"] == half and row["coverage"] == pytest.approx(half / rows["ekf"]["samples"])
    write_tum("late.tum", full.t + 1e4, full.quat_wxyz)
    assert main(["compare", "--estimators", "ekf", "--trajectory", "late=late.tum", "--dataset", "sim",
                 "--no-progress"]) == 1
    (line,) = [e for e in capsys.readouterr().err.splitlines() if e.startswith("fusion: error:")]
    assert "late.tum: its time span" in line and "does not overlap the recording's" in line


def test_a_folder_holds_one_trajectory_per_recording(exported, capsys):
    out, rows = exported
    (out.parent / "mine").mkdir()
    shutil.copy(out / "trajectories" / "sim" / "dr.tum", out.parent / "mine" / "sim.tum")
    assert main(["compare", "--estimators", "dr", "--trajectory", f"mine={out.parent / 'mine'}", "--dataset", "sim",
                 "--no-progress", "--json", "r.json"]) == 0
    doc = json.loads(open("r.json").read())
    mine = next(r for r in doc["results"] if r["estimator"] == "mine")
    assert mine["rmse_deg"]["total"] == pytest.approx(rows["dr"]["rmse_deg"]["total"], abs=1e-6)
    assert doc["settings"]["estimator_details"]["mine"]["origin"]["kind"] == "trajectory"
    (out.parent / "mine" / "sim.tum").unlink()
    assert main(["compare", "--estimators", "dr", "--trajectory", f"mine={out.parent / 'mine'}", "--dataset", "sim",
                 "--no-progress"]) == 1
    assert "no trajectory for recording 'sim' (looked for sim.tum, sim.txt, sim.csv" in capsys.readouterr().err


@pytest.mark.parametrize("content, message", [
    ("# nothing\n", "no data rows"),
    ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n", "unreadable CSV row"),
    ("0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n", "TUM rows have 8 columns"),
    ("0 0 0 0 0 0 0 2\n1 0 0 0 0 0 0 2\n", "its orientations are not unit quaternions"),
    ("0 0 0 0 nan nan nan nan\n1 0 0 0 nan nan nan nan\n", "no finite orientation"),
    ("a b c\n", "unreadable CSV row"),
])
def test_a_bad_trajectory_file_is_one_line(quiet_data, capsys, content, message):
    (quiet_data / "bad.tum").write_text(content)
    code = main(["compare", "--estimators", "dr", "--trajectory", "bad=bad.tum", "--dataset", "sim", "--no-progress"])
    errors = [e for e in capsys.readouterr().err.splitlines() if e.startswith("fusion: error:")]
    assert code == 1 and len(errors) == 1 and "bad.tum" in errors[0] and message in errors[0], errors


def test_trajectory_names_and_paths_are_checked(quiet_data, capsys):
    for argv, message in ((["--trajectory", "ekf=x.tum"], "the name must be new"),
                          (["--trajectory", "t=nowhere.tum"], "nowhere.tum: no such trajectory file or folder"),
                          (["--trajectory", "noequals"], "expected NAME=PATH")):
        with pytest.raises(SystemExit) if "NAME=PATH" in message else _nothing():
            code = main(["compare", "--estimators", "dr", "--dataset", "sim", "--no-progress", *argv])
            assert code == 1
        assert message in capsys.readouterr().err


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
