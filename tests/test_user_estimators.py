"""Your estimator in the table (`fusion.estimators.adapters.user`, `fusion.estimators.adapters.filterpy`):
a function or an `Estimator` class in a file of yours, a module, an installed package's entry
point, or a FilterPy filter, run, scored, ablated and reported like ours; what it returns
checked; bad code one line naming it, the other rows intact, exit status 1."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion import datasets
from fusion.cli import main
from fusion.estimators import resolve, resolve_all
from fusion.estimators.adapters import user
from fusion.evaluation.run import runner
from fusion.evaluation.scoring.metrics import score
from fusion.types import STANDARD_GRAVITY_M_S2
from report_fixtures import recording

HERE = Path(__file__).resolve().parent

# A student's first filter: numpy only, a loop over the samples, the contract's conventions.
STUDENT = '''
import numpy as np


def _mul(a, b):
    w0, x0, y0, z0 = a
    w1, x1, y1, z1 = b
    return np.array([w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1, w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                     w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1, w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1])


def complementary(t, gyro, acc, q0, gain=0.02):
    """Integrate the gyro; turn the tilt towards the accelerometer's gravity by `gain` per sample."""
    q = np.array(q0, dtype=float)
    out = np.empty((len(t), 4))
    out[0] = q
    for k in range(1, len(t)):
        if np.all(np.isfinite(gyro[k])):  # NaN rows: samples the toolkit marked invalid
            v = gyro[k] * (t[k] - t[k - 1])
            angle = np.linalg.norm(v)
            q = _mul(q, np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * v / angle])) if angle > 0 else q
        w, x, y, z = q
        g = np.array([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z])  # R^T e_z
        c = np.cross(acc[k] / np.linalg.norm(acc[k]), g)
        q = _mul(q, np.concatenate([[1.0], 0.5 * gain * c]))
        q /= np.linalg.norm(q)
        out[k] = q
    return out
'''

STUDENT_CLASS = STUDENT + '''

from dataclasses import dataclass

from fusion.estimators import Estimator
from fusion.types import Trajectory


@dataclass(frozen=True)
class ComplementaryParams:
    gain: float = 0.02


class Complementary(Estimator):
    """The same filter as a class: gets `ImuSamples` (accelerometer in g) like ours."""

    Params = ComplementaryParams

    def estimate(self, imu, init_quat_wxyz):
        rates, valid = imu.interval_rates()
        gyro = np.vstack([imu.gyr_rad_s[:1], np.where(valid[:, None], rates, np.nan)])
        return Trajectory(imu.t, complementary(imu.t, gyro, imu.acc_g * 9.80665, init_quat_wxyz, self.params.gain))
'''

BAD = '''
import time
import numpy as np
from student import complementary  # a file beside this one


def raises(t, gyro, acc, q0):
    raise RuntimeError("my filter broke")


def transposed(t, gyro, acc, q0):
    return complementary(t, gyro, acc, q0).T


def nans(t, gyro, acc, q0):
    out = complementary(t, gyro, acc, q0)
    out[len(t) // 2:] = np.nan
    return out


def scalar_last(t, gyro, acc, q0):
    return complementary(t, gyro, acc, q0)[:, [1, 2, 3, 0]]


def inverted(t, gyro, acc, q0):
    return complementary(t, gyro, acc, q0) * np.array([1.0, -1.0, -1.0, -1.0])


def unnormalised(t, gyro, acc, q0):
    return 1.001 * complementary(t, gyro, acc, q0)


def hangs(t, gyro, acc, q0):
    time.sleep(600)
'''


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """A student's folder outside the repository: their filters, and data in it nowhere (a relative
    FUSION_DATA made absolute, as tests change into this folder)."""
    if os.environ.get("FUSION_DATA"):
        monkeypatch.setenv("FUSION_DATA", str(Path(os.environ["FUSION_DATA"]).resolve()))
    (tmp_path / "student.py").write_text(STUDENT)
    (tmp_path / "student_class.py").write_text(STUDENT_CLASS)
    (tmp_path / "bad.py").write_text(BAD)
    return tmp_path


def fusion_in(folder: Path, *argv: str, data_dir: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, MPLBACKEND="Agg")
    if data_dir is not None:
        env["FUSION_DATA"] = str(data_dir)
    return subprocess.run([sys.executable, "-m", "fusion", *argv], cwd=folder, env=env, capture_output=True, text=True,
                          timeout=600)


def contract_inputs(rec) -> tuple[np.ndarray, ...]:
    """The function contract's arrays, built here by hand from the recording (README)."""
    imu = rec.imu
    rates, valid = imu.interval_rates()
    gyro = np.vstack([imu.gyr_rad_s[:1] if imu.gyr_timing == "end" else rates[:1],
                      np.where(valid[:, None], rates, np.nan)])
    q0 = datasets.initial_orientation(rec)
    return np.array(imu.t), gyro, np.asarray(imu.acc_g) * STANDARD_GRAVITY_M_S2, q0


@pytest.mark.slow
def test_a_student_file_beside_ours_from_any_folder(folder, data_dir):
    proc = fusion_in(folder, "compare", "--estimators", "./student.py:complementary,ekf", "--dataset", "ece276a/1",
                     "--no-progress", "--json", "r.json", data_dir=data_dir)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((folder / "r.json").read_text())
    rows = {r["estimator"]: r for r in doc["results"]}
    assert list(rows) == ["student.complementary", "ekf"]
    assert 0 < rows["student.complementary"]["rmse_deg"]["inclination"] < 5  # a working filter, on real data
    origin = doc["settings"]["estimator_details"]["student.complementary"]["origin"]
    assert origin["kind"] == "file" and origin["where"] == str(folder / "student.py")
    assert origin["sha256"] == __import__("hashlib").sha256((folder / "student.py").read_bytes()).hexdigest()
    assert doc["settings"]["estimator_details"]["student.complementary"]["params"] == {"gain": 0.02}


def test_the_row_equals_the_function_run_by_hand(folder, data_dir, monkeypatch):
    """The harness adds nothing: the row's scores equal the function called on the contract's
    arrays and scored directly (to 1e-12 deg)."""
    monkeypatch.chdir(folder)
    rec = datasets.load("ece276a/1", data_dir)
    (row,) = runner.run(["./student.py:complementary:gain=0.03"], [rec])
    module = user.load_source(folder / "student.py", (folder / "student.py").read_bytes())
    quat = module.complementary(*contract_inputs(rec), gain=0.03)
    from fusion.types import Trajectory

    direct = score(rec.truth, Trajectory(rec.imu.t, quat)).rmse_deg
    assert row.estimator == "student.complementary:gain=0.03"
    for kind in direct:
        assert row.rmse_deg[kind] == pytest.approx(direct[kind], abs=1e-12)


@pytest.mark.slow
def test_a_class_in_a_file_is_swept_by_ablate(folder, data_dir, monkeypatch):
    proc = fusion_in(folder, "ablate", "--estimator", "./student_class.py:Complementary", "--param",
                     "gain=0.01,0.02,0.05", "--dataset", "ece276a/1,ece276a/3", "--no-progress", "--json", "a.json",
                     data_dir=data_dir)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((folder / "a.json").read_text())
    labels = list(dict.fromkeys(r["estimator"] for r in doc["results"]))
    assert labels == [f"student_class.Complementary:gain={g}" for g in ("0.01", "0.02", "0.05")]
    assert doc["sweep"]["settings"] == 3 and doc["sweep"]["recordings"] == 2
    assert "best common setting" in proc.stdout
    # the class and the function are the same filter: the same numbers
    monkeypatch.chdir(folder)
    (fn_row,) = runner.run(["./student.py:complementary:gain=0.02"], datasets.select("ece276a/3", data_dir))
    class_row = next(r for r in doc["results"] if r["dataset"] == "ece276a/3" and r["estimator"].endswith("0.02"))
    assert fn_row.rmse_deg == pytest.approx(class_row["rmse_deg"], abs=1e-12)


def test_a_function_parameter_is_typed_and_checked(folder, monkeypatch):
    monkeypatch.chdir(folder)
    assert resolve("./student.py:complementary:gain=0.5").params.gain == 0.5
    with pytest.raises(ValueError, match=r"parameter 'gain': 'much' is not a number"):
        resolve("./student.py:complementary:gain=much")
    with pytest.raises(ValueError, match=r"unknown parameter 'gian'; valid: gain"):
        resolve("./student.py:complementary:gian=1")


@pytest.mark.parametrize("spec, message", [
    ("./nowhere.py:f", "nowhere.py: no such file (estimator './nowhere.py:f')"),
    ("./student.py:kalman", "has no 'kalman' (it defines: complementary)"),
    ("no_such_module_here:f", "cannot import 'no_such_module_here'"),
    ("ukf:R", "estimator 'ukf': expected key=value, got 'R'"),
])
def test_a_bad_reference_is_one_line(folder, monkeypatch, capsys, spec, message):
    monkeypatch.chdir(folder)
    assert main(["compare", "--estimators", spec, "--dataset", "sim", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_two_files_with_one_label_are_refused(folder, monkeypatch):
    monkeypatch.chdir(folder)
    (folder / "other").mkdir()
    (folder / "other" / "student.py").write_text(STUDENT)
    with pytest.raises(ValueError, match="two estimators would both be named 'student.complementary'"):
        resolve_all("./student.py:complementary,./other/student.py:complementary")


@pytest.mark.slow
def test_bad_user_code_fails_its_rows_only(folder, monkeypatch, capsys):
    """An exception, a wrong shape, NaN output, a scalar-last or inverted trajectory, a hang past
    --timeout: each one line naming the estimator and the recording, the other rows computed,
    exit status 1."""
    monkeypatch.chdir(folder)
    specs = ",".join(f"./bad.py:{name}" for name in ("raises", "transposed", "nans", "scalar_last", "inverted",
                                                      "hangs", "unnormalised")) + ",dr"
    code = main(["compare", "--estimators", specs, "--dataset", "sim", "--no-progress", "--timeout", "20",
                 "--json", "r.json"])
    out, err = capsys.readouterr()
    assert code == 1
    errors = [line for line in err.splitlines() if line.startswith("fusion: error: ")]
    expected = {
        "bad.raises": "raised RuntimeError: my filter broke",
        "bad.transposed": "returned shape (4, ",
        "bad.nans": "non-finite rows (the first at row",
        "bad.scalar_last": "read as scalar-last [x, y, z, w]",
        "bad.inverted": "read as world-to-body (the inverse)",
        "bad.hangs": "still running after 20 s; stopped",
    }
    assert len(errors) == len(expected)
    for label, message in expected.items():
        (line,) = [e for e in errors if f"'{label}'" in e]
        assert line.startswith("fusion: error: sim: estimator") and message in line, line
    rows = {r["estimator"]: r for r in json.loads((folder / "r.json").read_text())["results"]}
    assert all(rows[label]["rmse_deg"] is None and message.split(" (")[0] in rows[label]["error"]
               for label, message in expected.items())
    assert rows["dr"]["rmse_deg"]["total"] > 0 and rows["bad.unnormalised"]["rmse_deg"]["total"] > 0
    assert "quaternion norms differ from 1 by up to 0.001; renormalised" in err
    assert "failed (no result; the errors say why): 6 rows" in out


def test_function_inputs_follow_the_contract():
    """gyro[k] is the rate over (t[k-1], t[k]] whatever the recording's timing convention, NaN where
    the toolkit marked the gyro invalid; acc in m/s^2; fresh arrays."""
    rec = recording(50, bad_gyro=(10, 13))
    for timing in ("end", "start"):
        imu = rec.imu.replace(gyr_timing=timing)
        t, gyro, acc, q0 = user.function_inputs(imu, np.array([1.0, 0, 0, 0]))
        rates, valid = imu.interval_rates()
        expect = np.where(valid[:, None], rates, np.nan)
        np.testing.assert_array_equal(gyro[1:], expect)
        assert np.isnan(gyro[1:][~valid]).all() and (~valid).sum() == 3
        np.testing.assert_array_equal(acc, imu.acc_g * STANDARD_GRAVITY_M_S2)
        assert all(a.flags.writeable for a in (t, gyro, acc, q0))


def test_an_installed_package_registers_an_estimator(folder, monkeypatch, capsys):
    dist = folder / "site" / "student_filters-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: student-filters\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[fusion.estimators]\ncomp = student_filters:complementary\n")
    (folder / "site" / "student_filters.py").write_text(STUDENT)
    monkeypatch.syspath_prepend(str(folder / "site"))
    assert main(["list"]) == 0
    listed = [line for line in capsys.readouterr().out.splitlines() if line.split()[:1] == ["comp"]]
    assert listed and "student_filters:complementary" in listed[0] and "student-filters 1.0" in listed[0]
    assert main(["compare", "--estimators", "comp:gain=0.05,dr", "--dataset", "sim", "--no-progress",
                 "--json", str(folder / "r.json")]) == 0
    doc = json.loads((folder / "r.json").read_text())
    assert [r["estimator"] for r in doc["results"]] == ["comp:gain=0.05", "dr"]
    assert doc["settings"]["estimator_details"]["comp:gain=0.05"]["origin"]["kind"] == "entry point"


def test_a_spawned_worker_gets_the_file_it_cannot_see(folder, monkeypatch):
    """A user's estimator reaches workers that do not share the parent's memory as its file's
    contents (`ResolvedSpec.__reduce__`): here spawned processes, the file deleted before they
    start."""
    import multiprocessing

    from fusion.evaluation.run import pool

    monkeypatch.chdir(folder)
    entries = resolve_all("./student.py:complementary")
    rec = recording(200)
    serial = runner.run(entries, [rec], keep=True)
    (folder / "student.py").unlink()
    monkeypatch.setattr(pool, "pool_context", lambda: multiprocessing.get_context("spawn"))
    spawned = runner.run(entries, [rec, rec], jobs=2, keep=True)
    assert [r.error for r in spawned] == [None, None]
    np.testing.assert_array_equal(spawned[1].trajectory.quat_wxyz, serial[0].trajectory.quat_wxyz)


def test_a_filterpy_ukf_through_the_adapter_equals_its_own_loop(folder, monkeypatch):
    """The adapter runs the student's FilterPy filter exactly as a hand-written loop would."""
    (folder / "my_ukf.py").write_text((HERE / "user_fixtures" / "my_ukf.py").read_text())
    monkeypatch.chdir(folder)
    rec = recording(300)
    (row,) = runner.run(["./my_ukf.py:MyUKF:acc_noise=1.0"], [rec], keep=True)
    assert row.error is None and row.rmse_deg["inclination"] < 2.0
    module = user.load_source(folder / "my_ukf.py", (folder / "my_ukf.py").read_bytes())
    t, gyro, acc, q0 = user.function_inputs(rec.imu, datasets.initial_orientation(rec))
    ukf = module.make_ukf(q0, float(np.median(np.diff(t))), acc_noise=1.0)
    by_hand = [q0]
    for k in range(1, len(t)):
        ukf.predict(dt=t[k] - t[k - 1], gyro=gyro[k])
        ukf.update(acc[k])
        by_hand.append(ukf.x / np.linalg.norm(ukf.x))
    np.testing.assert_allclose(row.trajectory.quat_wxyz, np.array(by_hand), rtol=0, atol=1e-12)


def test_the_readme_function_runs_as_written(folder, monkeypatch):
    """README, "Your estimator in the table": its complementary filter, copied into a file, runs
    in the table and tracks the simulated recording's tilt."""
    import re

    readme = (HERE.parent / "README.md").read_text()
    section = readme[readme.index("## Your estimator in the table"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (folder / "readme_filter.py").write_text(code)
    monkeypatch.chdir(folder)
    (row,) = runner.run(["./readme_filter.py:complementary"], datasets.select("sim"))
    (dr,) = runner.run(["dr"], datasets.select("sim"))
    assert row.error is None and row.rmse_deg["inclination"] < 0.5 * dr.rmse_deg["inclination"]


@pytest.mark.slow
def test_reports_and_panoramas_take_a_user_estimator(folder, monkeypatch, capsys):
    monkeypatch.chdir(folder)
    assert main(["compare", "--estimators", "./student.py:complementary,dr", "--dataset", "sim", "--no-progress",
                 "--out", "run"]) == 0
    page = (folder / "run" / "report.html").read_text()
    assert "student.complementary" in page and str(folder / "student.py") in page
    capsys.readouterr()
    assert main(["panorama", "--estimator", "./student.py:complementary", "--dataset", "sim", "--out", "p.png",
                 "--size", "240x120", "--rate", "2", "--no-progress"]) == 0
    assert capsys.readouterr().out.startswith("sim student.complementary: ") and (folder / "p.png").is_file()


# A student's bug, in a file and in a helper beside it: the row says where.
BUGGY = '''
import numpy as np
from buggy_helper import rotate_all


def indexes(t, gyro, acc, q0):
    out = np.tile(q0, (len(t), 1))
    out[0] = q0[[0, 1, 2, 3]]
    return out[:, [0, 1, 2, 4]]  # IndexError: a fifth column


def in_helper(t, gyro, acc, q0):
    return rotate_all(q0, len(t))


def skips_nan_but_divides(t, gyro, acc, q0):
    out = np.tile(q0, (len(t), 1))
    out[len(t) - 5:] = out[len(t) - 5:] / 0.0 * 0.0  # NaN where the gyro is fine
    return out


def integrates_nan(t, gyro, acc, q0):
    out = np.tile(q0, (len(t), 1))
    angle = np.cumsum(gyro[:, 2] * np.r_[0.0, np.diff(t)])  # a NaN gyro row poisons every row after it
    out[:, 0], out[:, 3] = np.cos(angle / 2), np.sin(angle / 2)
    return out
'''
HELPER = '''
import numpy as np


def rotate_all(q0, n):
    table = np.zeros((n, 4))
    return table / table.sum(axis=1)[:, None] + q0[7]
'''


def test_a_users_bug_has_a_place(folder, monkeypatch):
    """An exception in the user's code: the error names the file and line where it was raised (the
    innermost frame of the user's own code, a helper file beside it included); the row's
    `traceback` holds the user's frames only, innermost last, and results.json keeps it."""
    (folder / "buggy.py").write_text(BUGGY)
    (folder / "buggy_helper.py").write_text(HELPER)
    monkeypatch.chdir(folder)
    rec = recording(300)
    rows = {r.estimator: r for r in runner.run(["./buggy.py:indexes", "./buggy.py:in_helper", "dr"], [rec])}
    line = BUGGY.splitlines().index("    return out[:, [0, 1, 2, 4]]  # IndexError: a fifth column") + 1
    indexes = rows["buggy.indexes"]
    assert indexes.error.startswith("toy/1: estimator 'buggy.indexes' raised IndexError: index 4 is out of bounds")
    assert f" at buggy.py:{line} in indexes; its traceback: --verbose, or the row's \"traceback\" in results.json" \
        in indexes.error
    trace = indexes.traceback.splitlines()
    assert trace[0] == "Traceback (the estimator's own code, innermost last):"
    assert trace[1] == f'  File "{folder / "buggy.py"}", line {line}, in indexes'
    assert trace[-1].startswith("IndexError: index 4 is out of bounds")
    assert not any("fusion" in t and "buggy" not in t for t in trace if t.startswith("  File"))  # no frame of ours
    helper = rows["buggy.in_helper"]
    helper_line = HELPER.splitlines().index("    return table / table.sum(axis=1)[:, None] + q0[7]") + 1
    assert "raised IndexError: index 7 is out of bounds" in helper.error
    assert f" at buggy_helper.py:{helper_line} in rotate_all;" in helper.error
    files = [t for t in helper.traceback.splitlines() if t.startswith("  File")]
    assert [f.split('"')[1] for f in files] == [str(folder / "buggy.py"), str(folder / "buggy_helper.py")]
    assert rows["dr"].error is None and rows["dr"].traceback is None
    assert indexes.to_json()["traceback"] == indexes.traceback and "traceback" not in rows["dr"].to_json()
    from fusion.evaluation.run.job import Result

    assert Result.from_json(indexes.to_json()).traceback == indexes.traceback


def test_the_nan_hint_only_when_the_nan_came_from_the_invalid_gyro(folder, monkeypatch):
    """"skip them in your filter, or --dropouts off" only when the output's first NaN row is where
    the gyro was passed as NaN, not for a filter that skipped them and failed elsewhere."""
    (folder / "buggy.py").write_text(BUGGY)
    (folder / "buggy_helper.py").write_text(HELPER)
    monkeypatch.chdir(folder)
    rec = recording(300, gap=None, bad_gyro=(100, 120))
    specs = ["./buggy.py:skips_nan_but_divides", "./buggy.py:integrates_nan"]
    rows = {r.estimator: r for r in runner.run(specs, [rec])}
    divides, integrates = rows["buggy.skips_nan_but_divides"].error, rows["buggy.integrates_nan"].error
    assert "returned 5 non-finite rows (the first at row 295)" in divides and "--dropouts off" not in divides
    assert "(the first at row 100); the gyro there is NaN, one of 20 samples the toolkit marked invalid" in integrates
    assert integrates.endswith("skip them in your filter, or pass the raw samples with --dropouts off")
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (10, 1))
    quat[4:] = np.nan
    nan_gyro = np.zeros(10, bool)
    nan_gyro[7] = True
    with pytest.raises(ValueError) as caught:
        user.check_output(quat, 10, nan_gyro_rows=nan_gyro)
    assert "--dropouts" not in str(caught.value)
    nan_gyro[4] = True
    with pytest.raises(ValueError, match="the gyro there is NaN, one of 2 samples"):
        user.check_output(quat, 10, nan_gyro_rows=nan_gyro)


def test_verbose_prints_the_users_traceback_under_its_row(folder, monkeypatch, capsys):
    from fusion.cli import main

    (folder / "buggy.py").write_text(BUGGY)
    (folder / "buggy_helper.py").write_text(HELPER)
    monkeypatch.chdir(folder)
    argv = ["compare", "--estimators", "./buggy.py:indexes,dr", "--dataset", "sim", "--no-progress", "--jobs", "1"]
    assert main(argv) == 1
    quiet = capsys.readouterr().err
    assert "Traceback" not in quiet and "its traceback: --verbose" in quiet
    assert main([*argv, "--verbose"]) == 1
    lines = capsys.readouterr().err.splitlines()
    at = next(i for i, text in enumerate(lines) if "raised IndexError" in text)
    assert lines[at + 1] == "    Traceback (the estimator's own code, innermost last):"
    assert lines[at + 2].startswith(f'      File "{folder / "buggy.py"}", line ')
