"""The journal of a run (`fusion.evaluation.journal`): what a stopped run leaves for `--resume`,
what resuming reuses and what it computes again, and what a run keeps in memory (rows only)."""
from __future__ import annotations

import json

import pytest

from fusion.evaluation import journal, runs
from fusion.evaluation.journal import Journal
from report_fixtures import toy, write_csv_dataset  # noqa: F401 (toy is a fixture)


@pytest.fixture
def data(tmp_path):
    return write_csv_dataset(tmp_path / "data", count=3, n=300)


def _stop_after(monkeypatch, jobs: int) -> None:
    """Interrupt the run (as Ctrl-C would) once `jobs` jobs are journalled."""
    real = Journal.record
    count = [0]

    def record(self, *args, **kwargs):
        if count[0] == jobs:
            raise KeyboardInterrupt
        count[0] += 1
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Journal, "record", record)


def test_a_run_keeps_rows_not_trajectories(toy, data, tmp_path):
    run = runs.run_ablate("toy", ["g=0.9,1.1"], dataset="all", data_dir=data, out=tmp_path / "abl")
    assert len(run.results) == 6 and all(r.trajectory is None and r.score is None for r in run.results)
    assert not (tmp_path / "abl" / journal.RUN_DIR).exists()  # finished: the journal was committed
    lines = (tmp_path / "abl" / journal.JOURNAL).read_text().splitlines()
    assert json.loads(lines[0])["call"]["kind"] == "ablate" and len(lines) == 7
    assert [json.loads(line)["row"] for line in lines[1:]] == [r.to_json() for r in run.results]
    assert all(json.loads(line)["part"] is False for line in lines[1:])  # no figures asked: no plot data


def test_resume_reuses_done_jobs_and_ends_with_the_uninterrupted_rows(toy, data, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    with monkeypatch.context() as mp:
        _stop_after(mp, 4)
        with pytest.raises(KeyboardInterrupt):
            runs.run_compare("toy,dr", "all", data, out=out)
    assert len(journal.read(out / journal.RUN_DIR / journal.JOURNAL)[1]) == 4
    whole = runs.run_compare("toy,dr", "all", data)
    capsys.readouterr()
    resumed = runs.run_resume(out)
    assert "4 of 6 jobs done, 2 to run" in capsys.readouterr().err
    assert [r.to_json() for r in resumed.results[:4]] == [json.loads(line)["row"] for line in
                                                          (out / journal.JOURNAL).read_text().splitlines()[1:5]]
    strip = [{k: v for k, v in r.to_json().items() if k != "seconds"} for r in whole.results]
    assert [{k: v for k, v in r.to_json().items() if k != "seconds"} for r in resumed.results] == strip
    assert (out / "series" / "002.npz").is_file() and (out / "report.html").is_file()


def test_a_changed_recording_is_computed_again(toy, data, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    with monkeypatch.context() as mp:
        _stop_after(mp, 4)  # both jobs of recordings 1 and 2
        with pytest.raises(KeyboardInterrupt):
            runs.run_compare("toy,dr", "all", data, out=out, progress=False)
    csv = data / "lab" / "rec2.csv"
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(lines[:-1]) + "\n")  # one sample less
    capsys.readouterr()
    run = runs.run_resume(out)
    assert "resuming" in (err := capsys.readouterr().err) and "2 of 6 jobs done, 4 to run" in err
    assert [r.samples for r in run.results if r.dataset == "lab/rec2"] == [len(lines) - 2] * 2


def test_a_half_written_last_line_is_ignored_and_a_broken_one_is_an_error(toy, data, tmp_path, monkeypatch):
    out = tmp_path / "run"
    with monkeypatch.context() as mp:
        _stop_after(mp, 2)
        with pytest.raises(KeyboardInterrupt):
            runs.run_compare("toy,dr", "all", data, out=out)
    path = out / journal.RUN_DIR / journal.JOURNAL
    text = path.read_text()
    path.write_text(text + '{"key": "abc", "row": {"data')  # killed in the middle of a line
    assert len(journal.read(path)[1]) == 2
    path.write_text(text.replace('"row"', '"rows"', 1))
    with pytest.raises(ValueError, match=r"journal.jsonl: line 2 is not a journal entry \(KeyError\)"):
        journal.read(path)
    path.write_text("not json\n")
    with pytest.raises(ValueError, match="journal.jsonl: not a fusion journal"):
        journal.read(path)


def test_resume_with_another_call_is_refused(toy, data, tmp_path, monkeypatch):
    out = tmp_path / "run"
    with monkeypatch.context() as mp:
        _stop_after(mp, 2)
        with pytest.raises(KeyboardInterrupt):
            runs.run_compare("toy,dr", "all", data, out=out)
    with pytest.raises(ValueError, match="was started with another call"):
        runs.run_compare("toy", "all", data, out=out, resume=True)
    assert len(journal.read(out / journal.RUN_DIR / journal.JOURNAL)[1]) == 2  # untouched
