"""A recording that cannot be scored costs only itself: a file that cannot be read, one without truth,
one whose truth is unusable, one whose alignment is undetermined. Each is listed with its one-line
reason in the table's footer, table.txt, the reports and results.json, the rest of the run goes on,
and the exit status stays 0 (a failed estimator row still exits 1; a run where nothing can be read
is an error)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from fusion.cli import main
from report_fixtures import write_csv_dataset


@pytest.fixture
def mixed(tmp_path):
    """lab/rec1, lab/rec2: good CSV recordings with truth; lab/broken: junk; lab/notruth: no truth
    columns; lab/badtruth: truth quaternions of norm 2 (a wrong layout); lab/fewtruth: truth on two
    rows only (no alignment can be fitted)."""
    root = write_csv_dataset(tmp_path / "data", count=2)
    lab = root / "lab"
    good = (lab / "rec1.csv").read_text().splitlines()
    (lab / "broken.csv").write_text("t,gx,gy,gz,ax,ay,az\n1,2\n")
    (lab / "notruth.csv").write_text("\n".join([good[0].rsplit(",", 4)[0]] + [r.rsplit(",", 4)[0] for r in good[1:]]) + "\n")
    doubled = [good[0]] + [",".join(r.split(",")[:7] + [f"{2 * float(x):.12g}" for x in r.split(",")[7:]])
                           for r in good[1:]]
    (lab / "badtruth.csv").write_text("\n".join(doubled) + "\n")
    few = [good[0]] + [r if k in (100, 101) else ",".join(r.split(",")[:7] + ["nan"] * 4)
                       for k, r in enumerate(good[1:])]
    (lab / "fewtruth.csv").write_text("\n".join(few) + "\n")
    return root


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


REASONS = {"lab/badtruth": "truth unusable: 570 of its 570 truth rows (qw,qx,qy,qz) are not unit quaternions (|q| 2)",
           "lab/broken": "cannot be read: ",
           "lab/notruth": "no truth (its files hold none)"}


def test_each_recording_scored_or_listed_with_its_reason(mixed, tmp_path, capsys):
    out_dir = tmp_path / "run"
    code, out, err = run(capsys, "compare", "--estimators", "dr,ekf", "--dataset", "all", "--data-dir", str(mixed),
                         "--no-progress", "--jobs", "1", "--out", str(out_dir))
    assert code == 0, err
    assert "Traceback" not in err and "fusion: error" not in err
    lines = out.splitlines()
    footer = lines[lines.index("not scored: 3 of 6 recordings (facts about the data: the run went on without them)"):]
    listed = dict(line.strip().split(": ", 1) for line in footer[1:])
    assert set(listed) == set(REASONS)
    for rid, reason in REASONS.items():
        assert listed[rid].startswith(reason), (rid, listed[rid])
    assert "broken.csv" in listed["lab/broken"]  # the loader's line names the file
    # the readable recordings ran every estimator: scored, or rows without scores; the unreadable one has no rows
    rows = {tuple(line.split()[:2]) for line in lines if line.startswith("lab/")}
    assert {(f"lab/{n}", e) for n in ("rec1", "rec2", "fewtruth", "badtruth", "notruth") for e in ("dr", "ekf")} == rows
    # rec1 and rec2 in the means; fewtruth is scored (without --align) on too little of it: flagged LOW
    assert [line.split()[:2] for line in lines if line.startswith("mean")] == [["mean", "(2)"]] * 2
    assert all("LOW" in line for line in lines if line.startswith("lab/fewtruth"))
    doc = json.loads((out_dir / "results.json").read_text())
    assert [e["dataset"] for e in doc["not_scored"]] == ["lab/badtruth", "lab/broken", "lab/notruth"]
    assert all(r["not_scored"] == next(e["reason"] for e in doc["not_scored"] if e["dataset"] == r["dataset"])
               for r in doc["results"] if "not_scored" in r)
    assert {r["dataset"] for r in doc["results"] if r["rmse_deg"]} == {"lab/rec1", "lab/rec2", "lab/fewtruth"}
    assert (out_dir / "table.txt").read_text().rstrip("\n") == out.rstrip("\n")
    for report in ("report.md", "report.html"):
        text = (out_dir / report).read_text()
        assert "Not scored" in text and all(rid in text for rid in REASONS)
    # the readable recordings have their figures and trajectories; the unreadable one has none
    assert not any("broken" in p.name for p in (out_dir / "figures").iterdir())
    assert (out_dir / "trajectories" / "lab" / "notruth" / "dr.tum").is_file()
    assert not (out_dir / "trajectories" / "lab" / "broken").exists()


def test_alignment_undetermined_is_a_reason_too(mixed, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "lab/rec1,lab/fewtruth", "--data-dir",
                         str(mixed), "--no-progress", "--jobs", "1", "--align")
    assert code == 0, err
    (line,) = [line for line in out.splitlines() if line.startswith("  lab/fewtruth: ")]
    assert line.startswith("  lab/fewtruth: alignment undetermined: it needs at least 3 truth steps")
    assert out.splitlines()[-2] == "not scored: 1 of 2 recordings (facts about the data: the run went on without them)"


def test_a_failed_estimator_still_exits_1(mixed, tmp_path, capsys):
    (tmp_path / "bad.py").write_text(
        "from fusion.estimators import Estimator\n"
        "class Bad(Estimator):\n"
        "    def estimate(self, imu, q0):\n"
        "        raise RuntimeError('no')\n")
    code, out, err = run(capsys, "compare", "--estimators", f"dr,{tmp_path / 'bad.py'}:Bad", "--dataset",
                         "lab/rec1,lab/broken", "--data-dir", str(mixed), "--no-progress", "--jobs", "1")
    assert code == 1
    errors = [line for line in err.splitlines() if line.startswith("fusion: error:")]
    assert len(errors) == 1 and "lab/rec1" in errors[0] and "RuntimeError" in errors[0]  # the unreadable file: no row
    assert "  lab/broken: cannot be read: " in out


def test_nothing_readable_is_an_error(mixed, capsys):
    code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "lab/broken", "--data-dir", str(mixed),
                         "--no-progress")
    assert code == 1 and out == ""
    (line,) = err.strip().splitlines()
    assert line.startswith("fusion: error: ") and "broken.csv" in line


def test_resume_does_not_meet_the_file_again(mixed, tmp_path, capsys, monkeypatch):
    """The rows of an unreadable file are journalled like the others: a resumed run does not read it again."""
    from fusion.evaluation.run import runner

    out_dir = tmp_path / "run"
    monkeypatch.setattr(runner.WorkerState, "run", _stop_after(runner.WorkerState.run, 4))
    code, _, err = run(capsys, "compare", "--estimators", "dr,ekf", "--dataset", "lab/broken,lab/rec1,lab/rec2",
                       "--data-dir", str(mixed), "--no-progress", "--jobs", "1", "--out", str(out_dir))
    assert code == 130 and "--resume" in err  # stopped after the broken file's and rec1's rows
    monkeypatch.undo()
    read = []
    monkeypatch.setattr(runner, "load_recording", _counting(runner.load_recording, read))
    code, out, err = run(capsys, "compare", "--resume", str(out_dir), "--no-progress", "--jobs", "1")
    assert code == 0, err
    assert read == ["lab/rec2"]  # the broken file's rows and rec1's came from the journal
    assert "  lab/broken: cannot be read: " in out


def _stop_after(run, n):
    calls = []

    def wrapped(self, job):
        if len(calls) == n:
            raise KeyboardInterrupt
        calls.append(job)
        return run(self, job)

    return wrapped


def _counting(load, seen):
    def wrapped(options, source):
        seen.append(source.id)
        return load(options, source)

    return wrapped


def test_tune_leaves_the_recordings_it_cannot_score_out(mixed, capsys):
    code, out, err = run(capsys, "tune", "--estimators", "ekf", "--dataset", "lab/*", "--data-dir", str(mixed),
                         "--no-progress", "--jobs", "1")
    assert code == 0, err
    (line,) = [line for line in err.splitlines() if "cannot be scored and are left out" in line]
    assert line.startswith("fusion: note: tune: 4 of 6 recordings cannot be scored and are left out: ")
    assert all(rid in line for rid in REASONS)
    assert "lab/fewtruth: its truth covers 0.17% of what is scored (at least 50%)" in line  # two truth rows
    assert "leave one recording out, 2 folds" in out
    assert "inf" not in out and "nan" not in out


def test_inspect_reports_every_readable_recording(mixed, capsys):
    code, out, err = run(capsys, "inspect", "--dataset", "lab/*", "--data-dir", str(mixed), "--no-progress")
    assert code == 0, err
    (warning,) = [line for line in err.splitlines() if "broken.csv" in line]
    assert warning.startswith("fusion: warning: ") and warning.endswith("; skipped (the other recordings go on)")
    for rid in ("lab/rec1", "lab/rec2", "lab/notruth", "lab/badtruth", "lab/fewtruth"):
        assert rid in out


def test_a_dask_run_lists_them_too(mixed, capsys):
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        code, out, err = run(capsys, "compare", "--estimators", "dr", "--dataset", "all", "--data-dir", str(mixed),
                             "--no-progress", "--scheduler", cluster.scheduler_address)
    assert code == 0, err
    assert "not scored: 3 of 6 recordings" in out and "  lab/broken: cannot be read: " in out
