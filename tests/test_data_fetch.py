"""`fusion data fetch` / `list` (`fusion.fetch`) without the network: a local HTTP server in a
thread serves fixture files as a mirror (`URL/<dataset>/<path>`).

Fetched and verified by git object id, a corrupted download refused and removed, a download cut
off mid-file leaving nothing under the final name and completed by the next fetch, a second fetch
that downloads and hashes nothing, two processes fetching the same files at once, a file only in
its `.mat` form, files the mirror lacks named in one line, and the offline message.
"""
import hashlib
import multiprocessing
import os
import shutil
from pathlib import Path

import pytest

from fusion import fetch
from fusion.cli import main
from fusion.fetch import Entry

from http_mirror import Mirror


def blob_id(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


# Fixture "BROAD": two trials (the first published as .hdf5 and .mat, the second too), an index, a licence.
FILES = {
    "data_hdf5/01_slow_A.hdf5": os.urandom(300_000),
    "data_mat/01_slow_A.mat": os.urandom(200_000),
    "data_hdf5/02_fast_B.hdf5": os.urandom(250_000),
    "data_mat/02_fast_B.mat": os.urandom(150_000),
    "data_hdf5/trials.json": b'{"trials": {}}',
    "LICENSE": b"CC BY 4.0\n",
}


def registry(base="http://127.0.0.1:9/pinned") -> list[Entry]:
    return [Entry("broad", path, f"{base}/{path}", blob_id(data), len(data), hashlib.sha256(data).hexdigest())
            for path, data in FILES.items()]


@pytest.fixture
def mirror(tmp_path):
    m = Mirror(tmp_path / "mirror")
    for path, data in FILES.items():
        if path != "data_hdf5/01_slow_A.hdf5":  # trial 01 only as .mat on this mirror
            m.put(path, data)
    yield m
    m.close()


def leftovers(folder: Path) -> list[str]:
    """Files in `folder` that are neither fetched files nor the state file (pooch's temporaries)."""
    names = {"01_slow_A.mat", "01_slow_A.hdf5", "02_fast_B.hdf5", "trials.json", "LICENSE", fetch.STATE}
    return sorted(p.name for p in folder.iterdir() if p.name not in names)


def test_fetch_verifies_and_a_second_fetch_downloads_and_hashes_nothing(mirror, tmp_path, monkeypatch):
    report = fetch.fetch("broad", to=tmp_path / "data", mirror=mirror.url, registry=registry())
    folder = tmp_path / "data" / "broad"
    assert report.ok and len(report.by("fetched")) == 4
    assert (folder / "01_slow_A.mat").read_bytes() == FILES["data_mat/01_slow_A.mat"]  # no .hdf5 on the mirror
    assert (folder / "02_fast_B.hdf5").read_bytes() == FILES["data_hdf5/02_fast_B.hdf5"]
    assert not (folder / "02_fast_B.mat").exists()  # the .hdf5 was there: the .mat is not fetched
    assert leftovers(folder) == []
    umask = os.umask(0o022)
    os.umask(umask)
    assert (folder / "LICENSE").stat().st_mode & 0o777 == 0o666 & ~umask  # not pooch's private temporary mode
    assert "2 of 2 recordings and 2 of 2 other files" in report.summary()

    mirror.requests.clear()
    hashed = []
    monkeypatch.setattr(fetch, "git_blob_sha1", lambda p: hashed.append(p) or blob_id(Path(p).read_bytes()))
    again = fetch.fetch("broad", to=tmp_path / "data", mirror=mirror.url, registry=registry())
    assert again.ok and len(again.by("local")) == 4 and mirror.requests == [] and hashed == []


def test_a_file_changed_after_fetching_is_hashed_again_and_left_alone(mirror, tmp_path):
    fetch.fetch("broad", to=tmp_path, mirror=mirror.url, registry=registry())
    (tmp_path / "broad" / "LICENSE").write_bytes(b"my own notes\n")  # the user's file now
    report = fetch.fetch("broad", to=tmp_path, mirror=mirror.url, registry=registry())
    (bad,) = report.by("conflict")
    assert bad.item.key == "LICENSE" and (tmp_path / "broad" / "LICENSE").read_bytes() == b"my own notes\n"
    (line,) = report.errors()
    assert "LICENSE: exists and is not the published file" in line and "left as it is" in line


def test_corrupted_download_is_refused_and_removed(mirror, tmp_path):
    mirror.put("data_hdf5/02_fast_B.hdf5", FILES["data_hdf5/02_fast_B.hdf5"][:-1] + b"\0")
    report = fetch.fetch("broad/02*", to=tmp_path, mirror=mirror.url, registry=registry())
    (refused,) = report.by("refused")
    assert refused.item.key == "02_fast_B" and not report.ok
    assert not (tmp_path / "broad" / "02_fast_B.hdf5").exists() and leftovers(tmp_path / "broad") == []
    (line,) = report.errors()
    assert "02_fast_B.hdf5" in line and "not the published" in line and "refused and removed" in line


def test_download_cut_off_keeps_nothing_and_the_next_fetch_completes_it(mirror, tmp_path):
    mirror.cut.add("/broad/data_hdf5/02_fast_B.hdf5")
    report = fetch.fetch("broad/02*", to=tmp_path, mirror=mirror.url, registry=registry())
    (failed,) = report.by("failed")
    assert "broke off" in failed.detail and "run the fetch again" in failed.detail
    assert not (tmp_path / "broad" / "02_fast_B.hdf5").exists() and leftovers(tmp_path / "broad") == []
    report = fetch.fetch("broad/02*", to=tmp_path, mirror=mirror.url, registry=registry())
    assert report.ok and (tmp_path / "broad" / "02_fast_B.hdf5").read_bytes() == FILES["data_hdf5/02_fast_B.hdf5"]


def _fetch_in_process(to, url, queue):
    report = fetch.fetch("broad", to=to, mirror=url, registry=registry(), jobs=2)
    queue.put((report.ok, sorted(o.status for o in report.outcomes)))


def test_two_processes_fetching_the_same_files_at_once(mirror, tmp_path):
    mirror.slow = 0.01  # both are mid-download at the same time
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_fetch_in_process, args=(tmp_path, mirror.url, queue)) for _ in range(2)]
    for p in procs:
        p.start()
    results = [queue.get(timeout=30) for _ in procs]
    for p in procs:
        p.join(timeout=30)
    assert [ok for ok, _ in results] == [True, True]
    folder = tmp_path / "broad"
    for path, data in FILES.items():
        if path not in ("data_hdf5/01_slow_A.hdf5", "data_mat/02_fast_B.mat"):
            assert (folder / Path(path).name).read_bytes() == data
    assert leftovers(folder) == []
    again = fetch.fetch("broad", to=tmp_path, mirror=mirror.url, registry=registry())
    assert len(again.by("local")) == 4


def test_files_missing_from_the_mirror_named_in_one_line(mirror, tmp_path):
    (mirror.root / "broad" / "data_mat" / "01_slow_A.mat").unlink()
    report = fetch.fetch("broad", to=tmp_path, mirror=mirror.url, registry=registry())
    assert [o.item.key for o in report.by("missing")] == ["01_slow_A"]
    (line,) = report.errors()
    assert line.startswith(f"broad: 1 files not at {mirror.url}/broad/") and line.endswith(": 01_slow_A")


def test_offline_one_line_with_the_url_and_the_folder(tmp_path):
    report = fetch.fetch("broad/02*", to=tmp_path, registry=registry())  # the pinned URLs: nothing listens
    assert {o.status for o in report.outcomes} == {"offline"}
    (line,) = report.errors()
    assert "cannot reach http://127.0.0.1:9/pinned/" in line and f"place them by hand in {tmp_path / 'broad'}" in line


def test_cli_offline_and_unknown_name(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("FUSION_MIRROR", "http://127.0.0.1:9")
    assert main(["data", "fetch", "broad/03*", "--to", str(tmp_path), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot reach http://127.0.0.1:9/broad/data_hdf5/03_undisturbed_slow_rotation_C.hdf5" in err[0]
    assert main(["data", "fetch", "euroc", "--to", str(tmp_path)]) == 1
    assert "unknown dataset 'euroc'" in capsys.readouterr().err


def test_list_shows_what_is_local(mirror, tmp_path):
    fetch.fetch("broad/02*", to=tmp_path, mirror=mirror.url, registry=registry())
    text = fetch.list_datasets(tmp_path, registry=registry())
    assert "broad    4 files" in text and "licence: CC BY 4.0; local: 3 of 4 (3 verified)" in text
    assert "doi:10.3390/data6070072" in text


def test_packaged_registry_pins_both_datasets():
    entries = fetch.read_registry()
    assert len(fetch.items("broad", entries)) == 41  # 39 trials, trials.json, LICENSE
    assert len(fetch.items("repoimu", entries)) == 96
    assert all(len(e.git_blob_sha1) == 40 for e in entries)
    assert {i.entries[0].local_name for i in fetch.items("repoimu", entries)} >= {
        "pendulum/Pendulum_Test02a_Trial1_Segment_1.csv", "tstick/TStick_Test02_Trial1.csv", "README.md"}


@pytest.fixture
def broad_mirror(tmp_path):
    """A mirror of the shared BROAD trial 03 and the index, laid out as the registry says."""
    root = Path(os.environ.get("FUSION_DATA", "data")) / "broad"
    trial = root / "03_undisturbed_slow_rotation_C.hdf5"
    if not trial.is_file():
        pytest.skip(f"no BROAD trial 03 in {root}")
    m = Mirror(tmp_path / "mirror")
    (m.root / "broad" / "data_hdf5").mkdir(parents=True)
    shutil.copy(trial, m.root / "broad" / "data_hdf5" / trial.name)
    shutil.copy(root / "trials.json", m.root / "broad" / "data_hdf5" / "trials.json")
    yield m
    m.close()


def test_fetched_trial_found_by_name_in_the_cache(broad_mirror, tmp_path, capsys, monkeypatch):
    """`fusion data fetch` into the user cache, then `--dataset 'broad/03*'` with no data folder
    holding it finds the cache; the licence the mirror lacks is named."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("FUSION_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    assert main(["data", "fetch", "broad/03*", "--mirror", broad_mirror.url, "--no-progress"]) == 1
    out, err = capsys.readouterr()
    assert "broad: 1 of 1 recordings and 1 of 2 other files" in out
    assert err.strip().endswith("files not at " + broad_mirror.url + "/broad/ (fetch them from elsewhere, or place "
                                "them by hand): LICENSE")
    assert main(["inspect", "--dataset", "broad/03*", "--no-progress"]) == 0
    assert "broad/03_undisturbed_slow_rotation_C: 58412 samples" in capsys.readouterr().out
    assert main(["inspect", "--dataset", "broad/04*", "--no-progress"]) == 1
    assert "fetch it with: fusion data fetch broad" in capsys.readouterr().err
