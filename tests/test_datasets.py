"""Dataset discovery and selection (`fusion.datasets`): identical recordings in several formats
are counted once, folder names and bare numbers select, a course's imu/ folder as data dir."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from fusion import datasets

T = 400


def _counts(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(t (T,), counts (T, 6) in the canonical order ax ay az wx wy wz)."""
    rng = np.random.default_rng(seed)
    t = 1.0e9 + 0.01 * np.arange(T)
    counts = np.column_stack([rng.integers(490, 530, (T, 2)), rng.integers(600, 620, T),
                              rng.integers(370, 390, (T, 3))]).astype(float)
    return t, counts


def write_2018(path, seed: int) -> None:
    """An ECE276A-2018 pickle: dict `vals` 6 x T (ax ay az wz wx wy), `ts` 1 x T."""
    t, counts = _counts(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    vals = counts[:, [0, 1, 2, 5, 3, 4]].T.astype(np.uint16)
    path.write_bytes(pickle.dumps({"vals": vals, "ts": t[None, :]}))


def write_7xT(path, seed: int) -> None:
    """An ECE276A pickle: 7 x T, row 0 time, then ax ay az wx wy wz with ax, ay negated."""
    t, counts = _counts(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    counts = counts.copy()
    counts[:, :2] *= -1
    path.write_bytes(pickle.dumps(np.vstack([t, counts.T])))


def write_vicon(path, seed: int) -> None:
    t, _ = _counts(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps({"rots": np.repeat(np.eye(3)[:, :, None], T, axis=2), "ts": t[None, :]}))


@pytest.fixture
def three_formats(tmp_path):
    """old/N (2018 dict, no truth) and new/N (7 x T with VICON) hold the same sessions 1 and 2;
    other/1 is a different session."""
    for n in (1, 2):
        write_2018(tmp_path / "old" / "imu" / f"imuRaw{n}.p", seed=n)
        write_7xT(tmp_path / "new" / "imu" / f"imuRaw{n}.p", seed=n)
        write_vicon(tmp_path / "new" / "vicon" / f"viconRot{n}.p", seed=n)
    write_7xT(tmp_path / "other" / "imu" / "imuRaw1.p", seed=99)
    return tmp_path


def test_identical_recordings_are_merged_keeping_the_one_with_truth(three_formats):
    sources = datasets.select("all", three_formats)
    assert [s.id for s in sources] == ["new/1", "new/2", "other/1"]
    assert sources[0].vicon is not None and sources[0].aliases == ("old/1",)
    assert datasets.merged_ids(sources) == {"new/1": ["old/1"], "new/2": ["old/2"]}
    assert datasets.describe_merged(sources) == "new/N = old/N for N = 1-2"
    # without dedupe, all five are there
    assert len(datasets.select("all", three_formats, dedupe=False)) == 5
    # naming both formats explicitly still counts the session once
    assert [s.id for s in datasets.select("old/2,new/2", three_formats)] == ["new/2"]


def test_a_different_session_is_not_merged(three_formats):
    assert datasets.fingerprint(datasets.discover(three_formats)["other/1"]) != \
        datasets.fingerprint(datasets.discover(three_formats)["new/1"])
    assert datasets.fingerprint(datasets.discover(three_formats)["old/1"]) == \
        datasets.fingerprint(datasets.discover(three_formats)["new/1"])


def test_folder_name_and_bare_number(three_formats):
    assert [s.id for s in datasets.select("old", three_formats)] == ["old/1", "old/2"]
    assert [s.id for s in datasets.select("2", three_formats)] == ["new/2"]  # old/2 is the same session
    with pytest.raises(ValueError, match=r"dataset '1' is ambiguous: new/1, other/1"):
        datasets.select("1", three_formats)
    with pytest.raises(ValueError, match="dataset '7' not found"):
        datasets.select("7", three_formats)


def test_imu_folder_as_data_dir_reads_its_course_folder(three_formats):
    assert [s.id for s in datasets.select("all", three_formats / "new" / "imu")] == ["new/1", "new/2"]
    assert datasets.course_root(three_formats / "new" / "imu") == three_formats / "new"


def test_unreadable_file_is_not_merged_and_fails_when_loaded(three_formats):
    (three_formats / "bad" / "imu").mkdir(parents=True)
    (three_formats / "bad" / "imu" / "imuRaw1.p").write_bytes(b"\x80\x04garbage")
    sources = datasets.select("all", three_formats)
    (bad,) = [s for s in sources if s.id == "bad/1"]
    with pytest.raises(ValueError, match="not a readable pickle"):
        datasets.load_source(bad)


def test_shared_data_counts_the_nine_course_sessions_once(data_dir):
    sources = datasets.select("all", data_dir)
    ids = [s.id for s in sources]
    assert [i for i in ids if i.startswith("ece")] == [f"ece276a/{n}" for n in range(1, 10)]
    assert len([i for i in ids if i.startswith("broad/")]) == 14  # BROAD trials are distinct
    # RepoIMU as published: every one of its 89 files is a recording (29 T-stick, 60 pendulum segments)
    repoimu = [s for s in sources if s.id.startswith("repoimu/")]
    assert {s.kind for s in repoimu} == {"repoimu"} and len(repoimu) == 89
    assert sum(s.id.startswith("repoimu/TStick/") for s in repoimu) == 29
    assert len(ids) == 9 + 14 + 89
    for s in (s for s in sources if s.id.startswith("ece")):
        assert s.vicon is not None
        n = s.id.split("/")[1]
        assert s.aliases == (f"ece276a-2018/{n}", f"ese650/{n}")
    assert [s.id for s in datasets.select("5", data_dir)] == ["ece276a/5"]


def test_a_new_format_is_one_class_and_one_registry_line(tmp_path, monkeypatch):
    """A format registered in `fusion.formats.FORMATS` is found, selected, loaded (through the
    shared post-step: a time gap marks its gyro sample invalid) and described like the others."""
    from fusion.formats import FORMATS, Format, Holds, Source, recording_id
    from fusion.types import ImuSamples, Recording

    class Npz(Format):
        kind = "npz"
        describe = ".npz (t, gyr, acc)"

        def find(self, root, paths):
            return (Source(recording_id(root, p), self.kind, p) for p in paths if p.suffix == ".npz")

        def read(self, source, options):
            data = np.load(source.imu)
            return Recording(source.id, ImuSamples(data["t"], data["gyr"], data["acc"], source=str(source.imu)))

        def holds(self, source):
            return Holds(truth=False, movement=False, magnetometer=False, gyr_timing="end", raw_counts=False)

    monkeypatch.setitem(FORMATS, "npz", Npz())
    t = np.concatenate([np.arange(100) * 0.01, 5.0 + np.arange(100) * 0.01])  # a 4 s gap after sample 99
    (tmp_path / "lab").mkdir()
    np.savez(tmp_path / "lab" / "run.npz", t=t, gyr=np.zeros((200, 3)), acc=np.tile([0, 0, 1.0], (200, 1)))
    (source,) = datasets.select("all", tmp_path)
    assert (source.id, source.kind) == ("lab/run", "npz")
    rec = datasets.LoadOptions().load(source)
    assert np.flatnonzero(~rec.imu.gyr_valid).tolist() == [100]  # gyr_timing "end": the sample after the gap
    assert datasets.select(str(tmp_path / "lab" / "run.npz"))[0].kind == "npz"
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"x.txt: not a recording this toolkit reads \(.*\.npz \(t, gyr, acc\)\)"):
        datasets.select(str(tmp_path / "x.txt"))


def test_what_each_format_holds(three_formats):
    from fusion.formats import FORMATS

    found = datasets.discover(three_formats)
    holds = {rid: FORMATS[s.kind].holds(s) for rid, s in found.items()}
    assert holds["new/1"].truth and not holds["old/1"].truth
    assert all(h.raw_counts and h.gyr_timing == "start" and not h.magnetometer for h in holds.values())
    (three_formats / "walk.csv").write_text("t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz,movement\n")
    csv = FORMATS["csv"].holds(datasets.discover(three_formats)["walk"])
    assert (csv.truth, csv.movement, csv.raw_counts, csv.gyr_timing) == (True, True, False, "end")
