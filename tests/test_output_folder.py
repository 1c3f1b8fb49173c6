"""Output folders (`compare --out`, `fusion report`): only the toolkit's own files are replaced
or removed (manifest), a folder in use is refused (lock), an interrupted run leaves the folder
as it was (staging + commit, results.json last), workers are stopped on SIGTERM, and
`fusion report` refuses results.json rows and series files it did not write, in one line."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion.evaluation.run import journal, output
from fusion.evaluation.report import render as report
from fusion.cli import main

REPO = Path(__file__).resolve().parents[1]


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def compare(capsys, out: Path, estimators: str = "dr", *extra: str):
    return run(capsys, "compare", "--estimators", estimators, "--dataset", "sim", "--no-progress", "--jobs", "1",
               "--out", str(out), *extra)


def snapshot(folder: Path) -> dict[str, str]:
    """Relative path -> md5 of every file, except the lock file (it holds the last run's PID) and
    the journal of a run in progress (`.fusion-run/`: what `--resume` continues)."""
    return {p.relative_to(folder).as_posix(): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != output.LOCK and journal.RUN_DIR not in p.relative_to(folder).parts}


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A folder after one `compare --out` with gn (which draws a loss figure)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    assert main(["compare", "--estimators", "gn", "--dataset", "sim", "--no-progress", "--jobs", "1", "--out", str(out)]) == 0
    return out


def copy_of(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_manifest_lists_what_was_written(first_run):
    files = output.read_manifest(first_run)
    assert "results.json" in files and "series/000.npz" in files and "figures/rec-000-sim-loss.png" in files
    on_disk = {p.relative_to(first_run).as_posix() for p in first_run.rglob("*") if p.is_file()}
    assert on_disk - set(files) == {output.MANIFEST}  # a finished run leaves no lock file behind
    assert not list(first_run.glob(output.STAGING_PREFIX + "*"))


def test_rerun_removes_only_its_own_files(first_run, tmp_path, capsys):
    out = copy_of(first_run, tmp_path / "run")
    (out / "figures" / "mine.png").write_bytes(b"user figure")
    (out / "series" / "mine.npz").write_bytes(b"user data, not a zip")
    (out / "notes.txt").write_text("mine")
    code, _, err = compare(capsys, out, "dr", "--overwrite")  # dr draws no loss figure: the old one goes
    assert code == 0, err
    assert (out / "figures" / "mine.png").read_bytes() == b"user figure"
    assert (out / "series" / "mine.npz").read_bytes() == b"user data, not a zip"
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "figures" / "rec-000-sim-loss.png").exists()
    assert "mine.png" not in (out / "report.html").read_text()
    # the user's broken npz is not a series of the run: re-rendering ignores it
    code, _, err = run(capsys, "report", str(out), "--no-progress", "--jobs", "1")
    assert code == 0, err
    assert (out / "series" / "mine.npz").read_bytes() == b"user data, not a zip"
    assert json.loads((out / "results.json").read_text())["results"][0]["estimator"] == "dr"


def test_user_file_in_the_way_is_refused_and_nothing_changes(tmp_path, capsys):
    out = tmp_path / "run"
    (out / "figures").mkdir(parents=True)
    (out / "figures" / "summary-rmse.png").write_bytes(b"my own plot")
    before = snapshot(out)
    code, _, err = compare(capsys, out)
    assert code == 1
    assert err.strip().splitlines()[-1].startswith(f"fusion: error: {out / 'figures' / 'summary-rmse.png'}: exists and "
                                                   "was not written by fusion")
    assert snapshot(out) == before and not (out / "results.json").exists()


def test_folder_in_use_is_refused_and_a_dead_holder_does_not_block(tmp_path, capsys):
    out = tmp_path / "run"
    with output.OutputFolder(out):  # another live run holds it
        code, _, err = compare(capsys, out)
    assert code == 1 and f"fusion: error: {out}: in use by another fusion run (pid {os.getpid()})" in err
    assert len(err.strip().splitlines()) == 1
    (out / output.LOCK).write_text("999999999\n")  # a crashed run's lock file: no process holds the flock
    (out / (output.STAGING_PREFIX + "dead")).mkdir()  # and its staging folder
    code, _, err = compare(capsys, out)
    assert code == 0, err
    assert not list(out.glob(output.STAGING_PREFIX + "*"))


def test_results_json_is_moved_in_last(first_run, tmp_path, capsys, monkeypatch):
    out = copy_of(first_run, tmp_path / "run")
    moved = []
    real = os.replace

    def spy(src, dst):
        moved.append(Path(dst).name)
        return real(src, dst)

    monkeypatch.setattr(output.os, "replace", spy)
    code, _, err = compare(capsys, out, "dr", "--overwrite")
    assert code == 0, err
    assert moved[-1] == "results.json" and moved[-2] == output.MANIFEST


def test_interrupt_while_writing_leaves_the_folder_as_it_was(first_run, tmp_path, capsys, monkeypatch):
    out = copy_of(first_run, tmp_path / "run")
    before = snapshot(out)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(report.series_io, "save", interrupted)
    code, _, err = compare(capsys, out, "dr", "--overwrite")
    assert code == 130 and err.strip().splitlines()[-1] == f"fusion: interrupted; continue with: fusion compare --resume {out}"
    assert snapshot(out) == before
    assert not list(out.glob(output.STAGING_PREFIX + "*"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_stops_the_workers_and_leaves_the_folder_as_it_was(first_run, tmp_path):
    from cluster_fixtures import alive, fusion_process, started_pids, wait_until

    out = copy_of(first_run, tmp_path / "run")
    before = snapshot(out)
    started = tmp_path / "started"
    started.mkdir()
    hold = f"gate:started={started},wait_for={tmp_path / 'never'}"
    proc = fusion_process("compare", "--estimators", f"{hold},{hold},dr", "--dataset", "sim", "--no-progress",
                          "--jobs", "2", "--out", str(out), "--overwrite")
    wait_until(lambda: len(started_pids(started)) == 2, "both workers holding a job")
    workers = started_pids(started)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not [w for w in workers if alive(w)], "orphaned workers"
    assert snapshot(out) == before
    assert not list(out.glob(output.STAGING_PREFIX + "*"))
    assert (out / journal.RUN_DIR / journal.JOURNAL).is_file()  # for --resume


@pytest.mark.parametrize("edit, message", [
    (lambda doc: doc["results"][0].update(samples="many"), "results row 0: 'samples' must be a whole number"),
    (lambda doc: doc["results"][0].update(rmse_deg={"total": -1, "inclination": 1, "heading": 1}), "results row 0: 'rmse_deg'"),
    (lambda doc: doc["results"][0].update(coverage=2.0), "results row 0: 'coverage'"),
    (lambda doc: doc["results"][0].pop("dataset"), "results row 0: 'dataset' must be a string"),
    (lambda doc: doc["results"].append(7), "results row 1: not an object"),
    (lambda doc: doc["results"][0].update(alignment={"world_deg": [1]}), "results row 0: 'alignment'"),
    (lambda doc: doc["settings"].update(estimator_details={"dr": 3}), "'settings.estimator_details'"),
])
def test_report_refuses_rows_it_did_not_write(first_run, tmp_path, capsys, edit, message):
    out = copy_of(first_run, tmp_path / "run")
    doc = json.loads((out / "results.json").read_text())
    edit(doc)
    (out / "results.json").write_text(json.dumps(doc))
    before = snapshot(out)
    code, _, err = run(capsys, "report", str(out), "--no-progress", "--jobs", "1")
    assert code == 1
    (line,) = err.strip().splitlines()
    assert line.startswith(f"fusion: error: {out / 'results.json'}: ") and message in line
    assert snapshot(out) == before


@pytest.mark.parametrize("content", [b"", b"not json", b"[" * 100_000 + b"]" * 100_000, b"\xff\xfe{}"])
def test_report_refuses_unreadable_results(first_run, tmp_path, capsys, content):
    out = copy_of(first_run, tmp_path / "run")
    (out / "results.json").write_bytes(content)
    code, _, err = run(capsys, "report", str(out), "--no-progress", "--jobs", "1")
    assert code == 1
    (line,) = err.strip().splitlines()
    assert line.startswith(f"fusion: error: {out / 'results.json'}: not a results document")


@pytest.mark.parametrize("corrupt", ["truncated", "garbage", "wrong-shape"])
def test_report_refuses_a_corrupt_series_file(first_run, tmp_path, capsys, corrupt):
    out = copy_of(first_run, tmp_path / "run")
    path = out / "series" / "000.npz"
    if corrupt == "truncated":
        path.write_bytes(path.read_bytes()[:5000])
    elif corrupt == "garbage":
        path.write_bytes(b"\x00" * 100)
    else:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["quat"] = arrays["quat"][:, :-5]
        np.savez(path, **arrays)
    before = snapshot(out)
    code, _, err = run(capsys, "report", str(out), "--no-progress", "--jobs", "1")
    assert code == 1
    (line,) = err.strip().splitlines()
    assert line.startswith(f"fusion: error: {path}: ")
    assert snapshot(out) == before


def test_out_naming_a_file_is_refused(tmp_path, capsys):
    target = tmp_path / "results"
    target.write_text("mine")
    code, _, err = compare(capsys, target)
    assert code == 1 and f"{target}: exists and is not a folder" in err
    assert target.read_text() == "mine"


def files_of_kind(folder: Path) -> dict[str, list[str]]:
    """The files of an --out folder by kind (top-level name or folder)."""
    kinds: dict[str, list[str]] = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != output.LOCK:
            rel = p.relative_to(folder)
            kinds.setdefault(rel.parts[0] if len(rel.parts) > 1 else rel.name, []).append(rel.as_posix())
    return kinds


def test_report_rewrites_only_what_it_draws(first_run, tmp_path, capsys):
    """`fusion report` re-renders table, figures and reports; every other kind of file an --out
    folder holds (results, command, journal, series, exported trajectories, the manifest's
    other entries, the user's files) is there afterwards, byte for byte."""
    out = copy_of(first_run, tmp_path / "run")
    (out / "notes.txt").write_text("mine")
    (out / "trajectories" / "mine").mkdir(parents=True)
    (out / "trajectories" / "mine" / "by-hand.tum").write_text("0 0 0 0 0 0 0 1\n")
    kinds = files_of_kind(out)
    for kind in ("results.json", "table.txt", "command.txt", "journal.jsonl", "report.html", "report.md",
                 "series", "figures", "trajectories", output.MANIFEST, "notes.txt"):
        assert kind in kinds, kind  # the fixture's folder holds every kind
    assert any(f.endswith(".tum") and "/sim/" in f for f in kinds["trajectories"])
    before = snapshot(out)
    (out / "table.txt").write_text("stale")
    code, _, err = run(capsys, "report", str(out), "--no-progress", "--jobs", "1")
    assert code == 0, err
    after = snapshot(out)
    rendered = [rel for rel in before if rel in report.RENDERED or rel.startswith("figures/")]
    kept = [rel for rel in before if rel not in rendered and rel != output.MANIFEST]
    assert kept and all(after.get(rel) == before[rel] for rel in kept), [r for r in kept if after.get(r) != before[r]]
    assert all(rel in after for rel in rendered)
    assert after["table.txt"] == before["table.txt"]  # drawn again from results.json
    assert set(output.read_manifest(out)) == set(output.read_manifest(first_run))


def test_compare_into_a_folder_holding_a_run_is_refused_without_overwrite(first_run, tmp_path, capsys):
    out = copy_of(first_run, tmp_path / "run")
    before = snapshot(out)
    code, _, err = compare(capsys, out, "dr")
    assert code == 1
    assert err.strip().splitlines() == [f"fusion: error: {out}: holds an earlier run (results.json); give --overwrite "
                                        "to replace it, or choose another output folder (nothing was changed)"]
    assert snapshot(out) == before
    code, _, err = run(capsys, "ablate", "--estimator", "ukf", "--param", "R=1e-4,1e-3", "--dataset", "sim",
                       "--no-progress", "--jobs", "1", "--out", str(out))
    assert code == 1 and "holds an earlier run" in err and snapshot(out) == before
    code, _, err = compare(capsys, out, "dr", "--overwrite")
    assert code == 0, err
    assert [row["estimator"] for row in json.loads((out / "results.json").read_text())["results"]] == ["dr"]


def test_overwrite_discards_an_unfinished_run(tmp_path, capsys):
    out = tmp_path / "run"
    header = {"call": {"kind": "compare"}, "data_dir": "", "calibration": None, "command": "", "jobs_total": 1}
    journal.Journal.start(out, header).close()  # a run stopped before its first job ended
    code, _, err = compare(capsys, out, "dr")
    assert code == 1 and "holds an unfinished run" in err and "--resume" in err and "--overwrite" in err
    code, _, err = compare(capsys, out, "dr", "--overwrite")
    assert code == 0, err
    assert (out / "results.json").is_file() and not (out / journal.RUN_DIR).exists()
