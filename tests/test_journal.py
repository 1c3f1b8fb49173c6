"""The journal of a run (`fusion.evaluation.run.journal`): what a stopped run leaves for `--resume`,
what resuming reuses and what it computes again, and what a run keeps in memory (rows only)."""
from __future__ import annotations

import json

import pytest

from fusion.evaluation.run import journal
from fusion.evaluation import runs
from fusion.evaluation.run.journal import Journal
from report_fixtures import toy, write_csv_dataset  # noqa: F401 (toy is a fixture)
from settings_fixtures import not_default_values


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


# A value other than its default for every journalled RunSettings field but the selection (the `how`
# part is not journalled), from its command-line option (`settings_fixtures`).
_NOT_DEFAULT = not_default_values(name for name in runs.JOURNALLED if name != "dataset")


def test_every_journalled_setting_survives_the_journal_and_resume(toy, data, tmp_path, monkeypatch):
    """Each field of `RunSettings` that decides the results is recorded in the journal's call and
    comes back on `--resume` (an option added to the settings is covered here by construction)."""
    from fusion.evaluation.run.settings import COMPUTED, WRITTEN, RunSettings

    assert set(runs.JOURNALLED) == (set(RunSettings.part(COMPUTED)) | set(RunSettings.part(WRITTEN))) - {
        "data_dir", "calibration", "out", "json_path", "command"}
    assert set(runs.JOURNALLED) - {"dataset"} == set(_NOT_DEFAULT)
    assert all(value != getattr(RunSettings(), name) for name, value in _NOT_DEFAULT.items())
    settings = RunSettings(dataset="all", data_dir=str(data), **_NOT_DEFAULT)
    kind = {"kind": "ablate", "estimator": "toy", "params": [["g", ["1"]]], "preset": None}
    call = runs._journal_call(kind, settings)
    back = RunSettings.from_json(json.loads(json.dumps(call)))
    assert all(getattr(back, name) == getattr(settings, name) for name in runs.JOURNALLED)

    seen = []
    monkeypatch.setattr(runs, "_execute", lambda entries, kind, document, s: seen.append(s))
    out = tmp_path / "run"
    header = {"call": call, "data_dir": str(data), "calibration": None, "command": "fusion ablate ...",
              "jobs_total": 3}
    Journal.start(out, header).close()
    runs.run_resume(out, jobs=2)
    (resumed,) = seen
    assert all(getattr(resumed, name) == getattr(settings, name) for name in runs.JOURNALLED)
    assert (resumed.jobs, resumed.resume, resumed.out, resumed.command) == (2, True, str(out), "fusion ablate ...")


def test_every_setting_comes_back_on_resume_or_is_how_it_runs(toy, data, tmp_path, monkeypatch):
    """Every field of `RunSettings`, not only the journalled ones: the paths are recorded beside the
    call (data_dir, calibration: resolved), the command too, the folder is the one resumed, and the
    `how` part and json_path are what `--resume` is given (a new field must be put in one of these)."""
    from fusion.evaluation.run.settings import HOW, RunSettings

    calibration = str(tmp_path / "calib.json")
    settings = RunSettings(dataset="all", data_dir=str(data), calibration=calibration, **_NOT_DEFAULT)
    call = runs._journal_call({"kind": "compare", "estimators": "toy", "trajectories": []}, settings)
    out = tmp_path / "run"
    Journal.start(out, {"call": call, "data_dir": str(data), "calibration": calibration, "command": "fusion compare x",
                        "jobs_total": 3}).close()
    how = {"jobs": 3, "progress": True, "scheduler": "tcp://10.0.0.5:8786", "scatter": True, "overwrite": True}
    assert set(how) == set(RunSettings.part(HOW)) - {"resume"}, "give the new `how` field a value here"
    seen = []
    monkeypatch.setattr(runs, "_execute", lambda entries, kind, document, s: seen.append(s))
    runs.run_resume(out, json_path=str(tmp_path / "r.json"), **how)
    (resumed,) = seen
    expected = {**{name: getattr(settings, name) for name in runs.JOURNALLED}, "data_dir": str(data),
                "calibration": calibration, "command": "fusion compare x", "out": str(out),
                "json_path": str(tmp_path / "r.json"), "per_recording": True, "resume": True, **how}
    assert set(expected) == set(RunSettings.__dataclass_fields__)
    assert {name: getattr(resumed, name) for name in expected} == expected


def test_an_older_journal_without_the_newer_settings_resumes_with_their_defaults(toy, data, tmp_path, monkeypatch):
    from fusion.evaluation.run.settings import RunSettings

    seen = []
    monkeypatch.setattr(runs, "_execute", lambda entries, kind, document, s: seen.append(s))
    out = tmp_path / "run"
    old_call = {"kind": "compare", "estimators": "toy", "dataset": "all", "init": None, "protocol": None,
                "align": False, "dropouts": True, "panorama": False, "timeout_s": None}  # before tum, mag, topics
    Journal.start(out, {"call": old_call, "data_dir": str(data), "calibration": None, "command": "c",
                        "jobs_total": 3}).close()
    runs.run_resume(out)
    (resumed,) = seen
    defaults = RunSettings()
    assert (resumed.tum, resumed.mag, resumed.imu_topic) == (defaults.tum, defaults.mag, defaults.imu_topic)
    with pytest.raises(ValueError, match="--resume changes only how a run runs, not 'mag'"):
        RunSettings.from_json(old_call, mag=False)
