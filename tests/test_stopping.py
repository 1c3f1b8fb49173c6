"""A long run stops when told and continues where it stopped.

- SIGTERM to `fusion ablate --jobs 2` ends it with one line and status 143, no worker left, its
  journal intact; `--resume` then computes only the jobs not yet done, and the final rows equal
  an uninterrupted run's.
- SIGKILL (no clean-up at all): the workers die with their parent, and `--resume` continues.
- A Python caller of `run_ablate` killed by SIGTERM or SIGKILL leaves no worker behind.

Events are ordered by files, never by sleeping: `cluster_fixtures.Gate` jobs announce that they
started and wait for a release file; the tests wait for those announcements (with a deadline
that only a broken run reaches).
"""
from __future__ import annotations

import json
import signal
import sys
from pathlib import Path

import pytest

from cluster_fixtures import alive, fusion_process, started_pids, wait_until
from report_fixtures import write_csv_dataset

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc, uses fork")


@pytest.fixture
def sweep(tmp_path):
    """Three recordings x two settings: `gate` waiting for a file that exists finishes at once, the
    other holds its worker until the release file exists. In the serial order the two workers finish two quick
    jobs, then both hold (jobs 2 and 4 of 6)."""
    data = write_csv_dataset(tmp_path / "data", count=3, n=400)
    started = tmp_path / "started"
    started.mkdir()
    release, go = tmp_path / "release", tmp_path / "go"
    go.write_text("")
    args = ["ablate", "--estimator", f"gate:started={started}", "--param", f"wait_for={go},{release}",
            "--data-dir", str(data), "--jobs", "2", "--no-progress"]
    return {"data": data, "started": started, "release": release, "go": go, "args": args, "out": tmp_path / "run"}


def _journal(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / ".fusion-run" / "journal.jsonl").read_text().splitlines()]


def _rows(doc_or_results) -> list[tuple]:
    rows = doc_or_results["results"] if isinstance(doc_or_results, dict) else doc_or_results
    return [(r["dataset"], r["estimator"], r["rmse_deg"], r["max_deg"], r["coverage"], r.get("error")) for r in rows]


def _held(sweep) -> list[int]:
    """Wait until both workers hold a gated job (four jobs started: two done, two holding)."""
    wait_until(lambda: len(list(sweep["started"].glob("started-*"))) >= 4, "four jobs starting")
    return started_pids(sweep["started"])


def _uninterrupted(sweep, tmp_path) -> dict:
    sweep["release"].write_text("")
    proc = fusion_process(*sweep["args"], "--json", str(tmp_path / "whole.json"))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    return json.loads((tmp_path / "whole.json").read_text())


def _resume_and_compare(sweep, tmp_path, before: list[dict]) -> None:
    sweep["release"].write_text("")
    for f in sweep["started"].glob("started-*"):
        f.unlink()
    proc = fusion_process("ablate", "--resume", str(sweep["out"]), "--no-progress", "--jobs", "2")
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert f"resuming {sweep['out']}: {len(before) - 1} of 6 jobs done, {7 - len(before)} to run" in err
    # only the jobs not yet done ran: one Gate start each
    assert len(list(sweep["started"].glob("started-*"))) == 7 - len(before)
    resumed = json.loads((sweep["out"] / "results.json").read_text())
    assert _rows(resumed) == _rows(_uninterrupted(sweep, tmp_path))
    assert not (sweep["out"] / ".fusion-run").exists()
    assert len((sweep["out"] / "journal.jsonl").read_text().splitlines()) == 7  # header + every job


@pytest.mark.slow
def test_sigterm_ends_the_run_keeps_the_journal_and_resume_finishes_it(sweep, tmp_path):
    proc = fusion_process(*sweep["args"], "--out", str(sweep["out"]))
    workers = _held(sweep)
    assert len(workers) == 2 and proc.pid not in workers
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip().splitlines() == [f"fusion: terminated (SIGTERM); continue with: fusion ablate --resume "
                                        f"{sweep['out']}"]
    assert not [w for w in workers if alive(w)]  # reaped before the parent exited
    journal = _journal(sweep["out"])
    assert journal[0]["format"] == "fusion-journal" and len(journal) == 3  # header + the two quick jobs
    assert all(entry["error"] is None and entry["row"]["rmse_deg"] for entry in journal[1:])
    assert not (sweep["out"] / "results.json").exists()
    _resume_and_compare(sweep, tmp_path, journal)


@pytest.mark.slow
def test_sigkill_leaves_no_worker_and_resume_finishes_it(sweep, tmp_path):
    proc = fusion_process(*sweep["args"], "--out", str(sweep["out"]))
    workers = _held(sweep)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    wait_until(lambda: not [w for w in workers if alive(w)], "the workers of a killed run ending")
    journal = _journal(sweep["out"])
    assert len(journal) == 3
    _resume_and_compare(sweep, tmp_path, journal)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_killed_library_caller_leaves_no_worker(sweep, sig):
    call = {"estimator": f"gate:started={sweep['started']}", "params": [["wait_for", [str(sweep["go"]), str(sweep["release"])]]],
            "data_dir": str(sweep["data"]), "jobs": 2}
    proc = fusion_process("--library", json.dumps(call))
    workers = _held(sweep)
    proc.send_signal(sig)
    proc.communicate(timeout=60)
    assert proc.returncode == -sig  # a library caller has no handler: the signal's default action
    wait_until(lambda: not [w for w in workers if alive(w)], "the workers of a killed library caller ending")


def test_resume_refuses_other_options_and_a_folder_without_a_run(sweep, tmp_path, capsys):
    from fusion.cli import main

    assert main(["ablate", "--resume", str(tmp_path / "nothing"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"fusion: error: {tmp_path / 'nothing' / '.fusion-run' / 'journal.jsonl'}: no unfinished run here to resume"
    assert main(["ablate", "--resume", str(tmp_path), "--dataset", "sim"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("fusion: error: --resume continues the run recorded in") and "not --dataset" in err


def test_a_new_run_on_an_unfinished_one_is_refused(sweep):
    proc = fusion_process(*sweep["args"], "--out", str(sweep["out"]))
    _held(sweep)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    again = fusion_process(*sweep["args"], "--out", str(sweep["out"]))
    _, err = again.communicate(timeout=60)
    assert again.returncode == 1
    assert err.strip() == (f"fusion: error: {sweep['out']}: holds an unfinished run (2 jobs done); continue it with "
                           f"--resume {sweep['out']}, or give --overwrite to start afresh")
    assert len(_journal(sweep["out"])) == 3  # untouched
