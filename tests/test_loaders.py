"""Loaders: the three formats agree on real recordings; broken files give one clear line."""
import os
import pickle
import signal
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fusion import datasets
from fusion import format_checks as loaders
from fusion.formats import course, generic_csv

NUMBERS = range(1, 10)


@pytest.mark.parametrize("n", NUMBERS)
def test_three_formats_give_identical_calibrated_samples(data_dir, n):
    a = datasets.load(f"ece276a/{n}", data_dir)
    b = datasets.load(f"ece276a-2018/{n}", data_dir)
    c = datasets.load(f"ese650/{n}", data_dir)
    for other in (b, c):
        assert np.array_equal(a.raw.counts, other.raw.counts)
        assert np.array_equal(a.imu.t, other.imu.t)
        assert np.array_equal(a.imu.gyr_rad_s, other.imu.gyr_rad_s)
        assert np.array_equal(a.imu.acc_g, other.imu.acc_g)
    assert b.truth is None  # the 2018 release has no VICON; it still loads
    np.testing.assert_allclose(a.truth.quat_wxyz, c.truth.quat_wxyz, equal_nan=True)


def test_discovery_ids_and_order(data_dir):
    ids = list(datasets.discover(data_dir))
    assert [i for i in ids if i.startswith("ece276a/")] == [f"ece276a/{n}" for n in NUMBERS]  # natural order
    assert ids[-1] == "sim"
    assert set(f"ese650/{n}" for n in NUMBERS) <= set(ids)
    # pointing at a course folder itself keeps its name in the ids
    assert list(datasets.discover(data_dir / "ese650"))[:2] == ["ese650/1", "ese650/2"]
    assert [s.id for s in datasets.select("ece276a/[12],ese650/3", data_dir)] == ["ece276a/1", "ece276a/2", "ese650/3"]


@pytest.mark.parametrize("n", [6, 7])
def test_vicon_gaps_are_kept_as_nan(data_dir, n):
    truth = course.load_vicon(data_dir / f"ece276a/vicon/viconRot{n}.p")
    missing = (~truth.valid).sum()
    assert 100 < missing < 200  # the README: some 130 missing samples


def test_canonical_counts_layout(data_dir):
    raw = course.load_imu_mat(data_dir / "ese650/imu/imuRaw1.mat")
    mat = scipy.io.loadmat(data_dir / "ese650/imu/imuRaw1.mat")
    np.testing.assert_array_equal(raw.counts[:, 3], mat["vals"][4])  # wx is the 5th row of vals
    np.testing.assert_array_equal(raw.counts[:, 5], mat["vals"][3])  # wz the 4th


# --- broken files -------------------------------------------------------------------------

def write_pickle(path, obj):
    with open(path, "wb") as f:
        pickle.dump(obj, f)
    return path


def good_array(n=300):
    t = 1.3e9 + np.arange(n) * 0.01
    vals = np.tile([-511.0, -501.0, 605.0, 373.0, 375.0, 369.0], (n, 1)).T
    return np.vstack([t, vals])


def test_good_synthetic_pickle_loads(tmp_path):
    raw = course.load_imu_pickle(write_pickle(tmp_path / "imuRaw1.p", good_array()))
    assert raw.counts.shape == (300, 6)
    assert raw.counts[0, 0] == 511.0  # the release's negation undone


@pytest.mark.parametrize("obj, message", [
    (np.zeros((6, 10)), "expected a 7 x T array"),
    ({"ts": np.zeros((1, 5))}, "expected a field 'vals'"),
    ({"vals": np.zeros((5, 5)), "ts": np.zeros((1, 5))}, "'vals' must be 6 x T"),
    ({"vals": np.zeros((6, 5)), "ts": np.zeros((1, 4))}, "4 time stamps for 5 samples"),
    ("a string", "expected a 7 x T array or a dict"),
    (np.array([["a"] * 5] * 7), "not numeric"),
])
def test_wrong_structure_pickles(tmp_path, obj, message):
    path = write_pickle(tmp_path / "imuRaw1.p", obj)
    with pytest.raises(ValueError, match=message) as info:
        course.load_imu_pickle(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_truncated_and_empty_files(tmp_path):
    data = pickle.dumps(good_array())
    (tmp_path / "cut.p").write_bytes(data[: len(data) // 2])
    (tmp_path / "empty.p").write_bytes(b"")
    (tmp_path / "cut.mat").write_bytes(b"MATLAB 5.0 MAT-file" + b"\0" * 50)
    with pytest.raises(ValueError, match="not a readable pickle"):
        course.load_imu_pickle(tmp_path / "cut.p")
    with pytest.raises(ValueError, match="file is empty"):
        course.load_imu_pickle(tmp_path / "empty.p")
    with pytest.raises(ValueError, match="not a readable MATLAB file"):
        course.load_imu_mat(tmp_path / "cut.mat")
    with pytest.raises(FileNotFoundError, match="no such file"):
        course.load_imu_mat(tmp_path / "missing.mat")


def test_restricted_unpickler_refuses_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = write_pickle(tmp_path / "imuRaw1.p", Evil())
    with pytest.raises(ValueError, match="refusing to load builtins.print"):
        course.load_imu_pickle(path)


def test_nan_time_stamps_and_values(tmp_path):
    arr = good_array()
    arr[0, :] = np.nan
    with pytest.raises(ValueError, match="time stamps are not increasing"):
        course.load_imu_pickle(write_pickle(tmp_path / "a.p", arr))
    arr = good_array()
    arr[3, 10] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        course.load_imu_pickle(write_pickle(tmp_path / "b.p", arr))


@pytest.mark.parametrize("n, message", [(3, "median time step inf s is outside"),  # the median overflows
                                        (6, "gaps cover more than half of the inf s span")])  # the gaps' sum does
def test_stamps_at_the_float_limits_are_one_clear_error(tmp_path, n, message):
    arr = good_array()[:, :n]
    arr[0, 0], arr[0, -1] = -1e308, 1e308
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way to the error
        with pytest.raises(ValueError, match=message):
            course.load_imu_pickle(write_pickle(tmp_path / "imuRaw1.p", arr))


def test_duplicate_and_backward_stamps_are_repaired_with_a_warning(tmp_path):
    arr = good_array()
    arr[0, 100] = arr[0, 99]  # duplicate
    arr[0, 200] = arr[0, 150]  # backwards
    with pytest.warns(UserWarning, match="dropped 2 samples"):
        raw = course.load_imu_pickle(write_pickle(tmp_path / "a.p", arr))
    assert len(raw.t) == 298 and np.all(np.diff(raw.t) > 0)


def test_vicon_wrong_layout(tmp_path):
    path = write_pickle(tmp_path / "viconRot1.p", {"rots": np.random.default_rng(0).normal(size=(3, 3, 20)), "ts": 0.01 * np.arange(20.0)[None]})
    with pytest.raises(ValueError, match="not rotation matrices"):
        course.load_vicon(path)


def test_csv_roundtrip_and_errors(tmp_path):
    n = 50
    t = np.arange(n) * 0.01
    rows = np.column_stack([t, np.full((n, 3), 0.1), np.tile([0, 0, 9.80665], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1))])
    path = tmp_path / "walk.csv"
    np.savetxt(path, rows, delimiter=",", header="t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz", comments="")
    imu, truth = generic_csv.load_csv(path)
    np.testing.assert_allclose(imu.acc_g[:, 2], 1.0)
    assert truth is not None and len(truth) == n
    bad = tmp_path / "bad.csv"
    bad.write_text("time,gx\n0,1\n")
    with pytest.raises(ValueError, match="missing CSV columns t, gy"):
        generic_csv.load_csv(bad)


def test_vicon_without_overlap(tmp_path):
    arr = good_array()
    imu_dir, vicon_dir = tmp_path / "lab" / "imu", tmp_path / "lab" / "vicon"
    imu_dir.mkdir(parents=True)
    vicon_dir.mkdir()
    write_pickle(imu_dir / "imuRaw1.p", arr)
    write_pickle(vicon_dir / "viconRot1.p", {"rots": np.tile(np.eye(3)[..., None], (1, 1, 10)), "ts": (arr[0, -1] + 100 + np.arange(10.0))[None]})
    rec = datasets.load("lab/1", tmp_path)  # the IMU is still a recording: only its truth is unusable
    assert rec.truth is None and len(rec.imu) == arr.shape[1]
    assert rec.truth_problem.startswith("truth unusable: viconRot1.p's time span") and "does not overlap" in rec.truth_problem


@pytest.mark.parametrize("timing, marked", [("start", 99), ("end", 100)])
def test_gap_invalidates_the_gyro_sample_standing_for_it(timing, marked):
    """The sample whose interval spans the gap: the one before it ("start"), after it ("end")."""
    from fusion.types import ImuSamples

    t = np.arange(200) * 0.01
    t[100:] += 2.0  # a 2 s gap between samples 99 and 100
    imu = ImuSamples(t, np.ones((200, 3)), np.tile([0.0, 0.0, 1.0], (200, 1)), gyr_timing=timing)
    out = loaders.invalidate_gaps(imu)
    assert np.flatnonzero(~out.gyr_valid).tolist() == [marked]
    rate, valid = out.interval_rates()
    assert not valid[99] and valid.sum() == 198  # interval 99 is the gap


def test_csv_gyro_rows_cover_the_interval_ending_at_their_stamp(tmp_path):
    """Generic CSV: gyro row k is the rate over (t[k-1], t[k]] (the common convention)."""
    path = tmp_path / "w.csv"
    t = np.arange(5) * 0.1
    gyr = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])
    np.savetxt(path, np.column_stack([t, gyr, np.tile([0, 0, 9.80665], (5, 1))]), delimiter=",",
               header="t,gx,gy,gz,ax,ay,az", comments="")
    imu, _ = generic_csv.load_csv(path)
    assert imu.gyr_timing == "end"
    np.testing.assert_array_equal(imu.interval_rates()[0][:, 0], [1.0, 2.0, 3.0, 4.0])


def test_isolated_read_returns_the_arrays_exactly_aligned_and_writable(tmp_path):
    """Arrays come back from the reading child through shared memory: every dtype, memory order
    and size as the reader made it (a non-contiguous one in band), each aligned and writable,
    and a write in a process forked later stays in that process (copy-on-write)."""
    rng = np.random.default_rng(3)
    made = {
        "odd": np.arange(7, dtype=np.uint8),  # an odd length before a float64 array
        "f64": rng.normal(size=(5, 4)),
        "fortran": np.asfortranarray(rng.normal(size=(3, 6))),
        "strided": rng.normal(size=(8, 8))[::2, 1::3],
        "empty": np.zeros((0, 3)),
        "flags": rng.random(9) > 0.5,
    }
    path = tmp_path / "any.bin"
    path.write_bytes(b"x")
    got = loaders.read_isolated(path, lambda p: made, "test")
    assert set(got) == set(made)
    for name, array in made.items():
        assert got[name].dtype == array.dtype and got[name].shape == array.shape, name
        np.testing.assert_array_equal(got[name], array)
        assert got[name].flags.writeable, name
        assert got[name].size == 0 or got[name].ctypes.data % 8 == 0, name
    assert got["fortran"].flags.f_contiguous
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        got["f64"][0, 0] = 1e6
        os._exit(0)
    os.waitpid(pid, 0)
    assert got["f64"][0, 0] == made["f64"][0, 0]


def test_isolated_read_reports_a_crashing_reader_in_one_line(tmp_path):
    path = tmp_path / "any.bin"
    path.write_bytes(b"x")

    def crash(p):
        os.kill(os.getpid(), signal.SIGSEGV)

    with pytest.raises(ValueError, match=r"any.bin: not a readable test file \(the reader crashed on it: signal 11\)"):
        loaders.read_isolated(path, crash, "test")


def test_isolated_read_of_empty_arrays_only():
    made = {"none": np.zeros((0, 3)), "also": np.zeros(0, np.uint8)}
    got = loaders.read_isolated(Path(__file__), lambda p: made, "test")
    for name, array in made.items():
        assert got[name].shape == array.shape and got[name].dtype == array.dtype and got[name].flags.writeable


def test_the_former_name_of_the_format_checks_still_imports_with_a_warning():
    """`fusion.loaders` (which held no loaders) is now `fusion.format_checks`; for one release the old
    name imports, with a DeprecationWarning, as the same module."""
    import importlib
    import sys

    from fusion import format_checks

    sys.modules.pop("fusion.loaders", None)
    with pytest.warns(DeprecationWarning, match="fusion.loaders is now fusion.format_checks"):
        module = importlib.import_module("fusion.loaders")
    assert module is format_checks
