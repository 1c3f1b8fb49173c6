"""Resource bounds decided before allocation, and plausibility of physical values.

Bombs (small files declaring huge arrays) are refused by what they declare, with one line
naming the file; `test_bombs_refused_under_a_memory_limit` shows it is not luck: the same
files are refused in a subprocess whose address space is limited to far less than they
would take.
"""
from __future__ import annotations

import os
import pickle
import re
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fusion import format_checks as loaders
from fusion.formats import course, generic_csv

from optional_helpers import optional_module, require_module

REPO = Path(__file__).resolve().parents[1]


# --- bombs ---------------------------------------------------------------------------------

def shared_list_bomb(levels: int = 30, width: int = 10) -> list:
    """`l = [l] * width`, `levels` times: a few hundred bytes pickled, width**levels values."""
    nested: list = [0]
    for _ in range(levels):
        nested = [nested] * width
    return nested


def write_pickle_bomb(path: Path, levels: int = 30, width: int = 10) -> Path:
    path.write_bytes(pickle.dumps({"vals": shared_list_bomb(levels, width), "ts": [0.0, 0.01]}))
    return path


def write_hdf5_bomb(path: Path, rows: int = 30_000_000) -> Path:
    """A ~2 KB BROAD trial declaring `rows` compressed (never written) rows per array."""
    h5py = require_module("h5py")
    with h5py.File(path, "w") as f:
        for key, cols in (("imu_gyr", 3), ("imu_acc", 3), ("opt_quat", 4)):
            f.create_dataset(key, shape=(rows, cols), dtype="f8", chunks=(100_000, cols), compression="gzip")
        f.attrs["sampling_rate"] = 286.0
    return path


def write_mat_bomb(path: Path, rows: int = 12_000_000) -> Path:
    """A compressed .mat of zeros, (6, rows) `vals` (uint8 to keep the writer's memory small)."""
    scipy.io.savemat(path, {"vals": np.zeros((6, rows), np.uint8), "ts": np.zeros((1, 2))}, do_compression=True)
    return path


def test_pickle_bomb_is_tiny_and_refused_by_structure(tmp_path):
    assert len(pickle.dumps(shared_list_bomb())) < 700
    path = write_pickle_bomb(tmp_path / "imuRaw1.p")
    with pytest.raises(ValueError, match=r"imuRaw1\.p: containers nested more than 8 deep"):
        course.load_imu_pickle(path)


def test_pickle_bomb_within_depth_is_refused_by_count(tmp_path):
    path = write_pickle_bomb(tmp_path / "imuRaw1.p", levels=6, width=40)  # 4e9 values, depth 7
    with pytest.raises(ValueError, match=r"imuRaw1\.p: nested containers hold 4.1e\+09 values"):
        course.load_imu_pickle(path)


def test_check_structure_shared_references_counted_once_per_reference():
    inner = [1.0, 2.0, 3.0]
    doc = {"vals": [inner] * 6, "ts": [inner] * 2}  # 24 values once materialised
    loaders.check_structure(doc, "x.p", max_values=24)  # exactly at the limit: accepted
    with pytest.raises(ValueError, match=r"x\.p: nested containers hold 24 values, .* \(limit 23\)"):
        loaders.check_structure(doc, "x.p", max_values=23)
    with pytest.raises(ValueError, match="x.p: nested containers hold 1.8e\\+08"):
        loaders.check_structure([np.zeros(3_000_000)] * 60, "x.p")  # arrays count their size


def test_check_structure_refuses_cycles_and_deep_chains():
    cycle: list = []
    cycle.append(cycle)
    with pytest.raises(ValueError, match="holds itself"):
        loaders.check_structure({"vals": cycle}, "c.p")
    deep: list = [0]
    for _ in range(100_000):  # deeper than Python's recursion limit: the check is iterative
        deep = [deep]
    with pytest.raises(ValueError, match="nested more than 8 deep"):
        loaders.check_structure(deep, "d.p")


def nested(obj, levels: int):
    for _ in range(levels):
        obj = [obj]
    return obj


@pytest.mark.parametrize("layout, depth, values", [
    ({"rots": np.zeros((3, 3, 5000)).tolist(), "ts": [list(range(5000))]}, 4, 50_000),  # VICON pickle as lists
    ({"vals": np.zeros((6, 5000)).tolist(), "ts": [list(range(5000))]}, 3, 35_000),  # 2018 IMU dict as lists
])
def test_real_layouts_pass_the_structure_check(layout, depth, values):
    """A real layout is accepted, and sits where the limits say: `depth` levels deep (accepted up
    to MAX_NESTING when wrapped in more lists, refused one level beyond) and `values` values
    (accepted with exactly that limit, refused one below)."""
    loaders.check_structure(layout, "v.p")
    margin = loaders.MAX_NESTING - depth
    loaders.check_structure(nested(layout, margin), "v.p")
    with pytest.raises(ValueError, match=f"v.p: containers nested more than {loaders.MAX_NESTING} deep"):
        loaders.check_structure(nested(layout, margin + 1), "v.p")
    loaders.check_structure(layout, "v.p", max_values=values)
    with pytest.raises(ValueError, match=re.escape(f"v.p: nested containers hold {values:.3g} values")):
        loaders.check_structure(layout, "v.p", max_values=values - 1)


def test_hdf5_declaring_huge_shapes_is_refused_from_the_header(tmp_path):
    from fusion.broad import load_broad

    path = write_hdf5_bomb(tmp_path / "trial01.hdf5")
    assert path.stat().st_size < 20_000
    with pytest.raises(ValueError, match=r"trial01\.hdf5: 'imu_\w+' declares shape \(30000000, 3\)"):
        load_broad(path)


def test_mat_declaring_huge_shapes_is_refused_from_the_header(tmp_path):
    path = write_mat_bomb(tmp_path / "imuRaw1.mat")
    assert path.stat().st_size < 200_000
    with pytest.raises(ValueError, match=r"imuRaw1\.mat: 'vals' declares shape \(6, 12000000\)"):
        course.load_imu_mat(path)


def test_check_declared_limits_are_exact():
    """Each limit accepts its value and refuses one more: samples along an axis, values per
    array, and bytes (as float64) over all of a file's arrays."""
    n = loaders.MAX_SAMPLES
    loaders.check_declared("f", [("a", (n, 3))])
    with pytest.raises(ValueError, match=rf"f: 'a' declares shape \({n + 1}, 3\)"):
        loaders.check_declared("f", [("a", (n + 1, 3))])
    cols = loaders.MAX_VALUES // n  # 16 channels of MAX_SAMPLES
    loaders.check_declared("f", [("a", (n, cols))])
    with pytest.raises(ValueError, match=rf"f: 'a' declares shape \(2, {loaders.MAX_VALUES // 2 + 1}\)"):
        loaders.check_declared("f", [("a", (2, loaders.MAX_VALUES // 2 + 1))])  # short axes, too many values
    half = loaders.MAX_BYTES // 8 // 2  # values in half the byte limit
    two_halves = [("a", (half // 16, 16)), ("b", (half // 16, 16))]
    loaders.check_declared("f", two_halves)  # exactly MAX_BYTES
    with pytest.raises(ValueError, match="f: the arrays declare 2 GiB, more than the 2 GiB limit"):
        loaders.check_declared("f", [*two_halves, ("c", (1,))])
    with pytest.raises(ValueError, match="f: the arrays declare .* GiB"):
        loaders.check_declared("f", [(f"a{i}", (9_000_000, 16)) for i in range(3)])


def test_bombs_refused_under_a_memory_limit(tmp_path):
    """Refused, not survived by luck: under a 1.5 GiB address-space limit (the HDF5 bomb alone
    would take 2.4 GB, the pickle 10**30 values), each file gives its one-line error."""
    require_module("resource")  # POSIX only
    paths = [write_pickle_bomb(tmp_path / "imuRaw1.p"), write_mat_bomb(tmp_path / "imuRaw2.mat")]
    if optional_module("h5py") is not None:  # BROAD's .hdf5 needs the optional h5py (a failure under CI without it)
        paths.append(write_hdf5_bomb(tmp_path / "trial01.hdf5"))
    script = textwrap.dedent(f"""
        import importlib.util, resource, sys
        import numpy, scipy.io
        if importlib.util.find_spec("h5py"):  # its libraries loaded before the limit, as numpy's are
            import h5py
        from fusion.broad import load_broad
        from fusion.formats import course
        limit = {int(1.5 * 1024**3)}
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        try:  # the limit is real: a 2 GB array cannot be had
            numpy.ones(2 * 1024**3, numpy.uint8)
            print("LIMIT NOT ENFORCED")
        except MemoryError:
            pass
        for path in sys.argv[1:]:
            fn = load_broad if path.endswith(".hdf5") else (course.load_imu_mat if path.endswith(".mat") else course.load_imu_pickle)
            try:
                fn(path)
                print("LOADED", path)
            except ValueError as exc:
                print("REFUSED", exc)
    """)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-c", script, *map(str, paths)], capture_output=True, text=True,
                          timeout=120, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert "LIMIT NOT ENFORCED" not in lines
    assert len(lines) == len(paths), lines
    for line, path in zip(lines, paths):
        assert line.startswith(f"REFUSED {path}:") and ("declares shape" in line or "nested more than" in line), line


# --- physical plausibility (CSV, BROAD) -------------------------------------------------------

def csv_text(n: int = 300, gyr_scale: float = 1.0, acc_scale: float = 1.0, t=None, header: str | None = None) -> str:
    rng = np.random.default_rng(0)
    t = np.arange(n) * 0.01 if t is None else t
    gyr = rng.normal(0, 0.5, (n, 3)) * gyr_scale
    acc = (np.array([0, 0, 9.80665]) + rng.normal(0, 0.2, (n, 3))) * acc_scale
    header = header or "t,gx,gy,gz,ax,ay,az"
    rows = np.column_stack([t, gyr, acc])
    return header + "\n" + "\n".join(",".join(repr(float(x)) for x in r) for r in rows) + "\n"


def load(tmp_path, text: str):
    path = tmp_path / "walk.csv"
    path.write_text(text)
    return generic_csv.load_csv(path)


def test_plausible_csv_loads_without_warning(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        imu, _ = load(tmp_path, csv_text())
    assert len(imu) == 300


def test_gyro_in_deg_s_is_an_error_with_the_fix(tmp_path):
    with pytest.raises(ValueError, match=r"walk\.csv: column 'g[xyz]' reaches .* rad/s, beyond any MEMS gyro .* "
                                         r"in deg/s\? convert to rad/s"):
        load(tmp_path, csv_text(gyr_scale=np.degrees(1.0)))


def test_slow_motion_in_deg_s_warns(tmp_path):
    text = csv_text(gyr_scale=0.0)  # replace the gyro by a constant 20 deg/s turn on all axes, in deg/s
    lines = [ln.split(",") for ln in text.splitlines()]
    body = [",".join([r[0], "20.0", "-20.0", "20.0", *r[4:]]) for r in lines[1:]]
    with pytest.warns(UserWarning, match=r"walk\.csv: columns gx,gy,gz: the median angular rate is 34.6 rad/s"):
        load(tmp_path, "\n".join([",".join(lines[0]), *body]) + "\n")


def turning_csv(rate: float, unit_scale: float, seconds: float = 60.0) -> str:
    """A board turning about its body x axis at `rate` rad/s, the gyro column written times
    `unit_scale` (1: rad/s, 180/pi: deg/s), the accelerometer reading gravity as it turns."""
    t = np.arange(0.0, seconds, 0.01)
    angle = rate * t
    acc = 9.80665 * np.column_stack([np.zeros_like(t), np.sin(angle), np.cos(angle)])  # R_x(angle)^T e_z
    gyr = np.column_stack([np.full_like(t, rate), np.zeros_like(t), np.zeros_like(t)]) * unit_scale
    rows = np.column_stack([t, gyr, acc])
    return "t,gx,gy,gz,ax,ay,az\n" + "\n".join(",".join(repr(float(x)) for x in r) for r in rows) + "\n"


def test_gyro_consistent_with_the_accelerometer_loads_quietly(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        imu, _ = load(tmp_path, turning_csv(0.1, 1.0))
    assert len(imu) == 6000


def test_slow_turn_in_deg_s_warns_from_the_accelerometer(tmp_path):
    """5.7 deg/s read as rad/s: below every range and median limit, but the gyro turns gravity
    57 times as far as the accelerometer sees it turn."""
    with pytest.warns(UserWarning, match=r"walk\.csv: columns gx,gy,gz: the gyro turns the gravity direction 5[67] times "
                                         r"as far as the accelerometer \(ax,ay,az\) sees it turn; if they are in deg/s"):
        load(tmp_path, turning_csv(0.1, np.degrees(1.0)))


def test_values_times_1e6_are_an_error(tmp_path):
    with pytest.raises(ValueError, match="walk.csv: column 'g[xyz]' reaches"):
        load(tmp_path, csv_text(gyr_scale=1e6))
    with pytest.raises(ValueError, match="walk.csv: column 'a[xyz]' reaches .* beyond any accelerometer range"):
        load(tmp_path, csv_text(acc_scale=1e6))


def test_acc_1e308_is_an_error_not_an_overflow_warning(tmp_path):
    text = csv_text().splitlines()
    fields = text[5].split(",")
    fields[5] = "1e308"
    text[5] = ",".join(fields)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy overflow RuntimeWarning would fail here
        with pytest.raises(ValueError, match="walk.csv: column 'ay' reaches 1e\\+308 m/s\\^2"):
            load(tmp_path, "\n".join(text) + "\n")


def test_sample_numbers_as_time_stamps_are_an_error(tmp_path):
    with pytest.raises(ValueError, match=r"walk\.csv: time stamps 0, 1, 2 \.\.\. look like sample numbers"):
        load(tmp_path, csv_text(t=np.arange(300.0)))


def test_milliseconds_are_an_error_with_the_fix(tmp_path):
    with pytest.raises(ValueError, match=r"walk\.csv: median time step 10 s .* \(milliseconds\? divide by 1000\)"):
        load(tmp_path, csv_text(t=np.arange(300) * 10.0))


def test_duplicate_column_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="walk.csv: the header names column 'gx' more than once"):
        load(tmp_path, csv_text(header="t,gx,gx,gz,ax,ay,az"))


def test_duplicated_stamps_are_repaired_with_a_warning(tmp_path):
    """Real datasets repeat a stamp now and then: repaired (the later row dropped), not refused."""
    t = np.arange(300) * 0.01
    t[[50, 120, 121]] = t[[49, 119, 119]]
    with pytest.warns(UserWarning, match=r"walk\.csv: dropped 3 samples with non-finite, duplicate"):
        imu, _ = load(tmp_path, csv_text(t=t))
    assert len(imu) == 297 and np.all(np.diff(imu.t) > 0)


def test_broad_gyro_beyond_range_is_an_error(tmp_path):
    from fusion.broad import load_broad

    n = 300
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    data = {"imu_gyr": np.full((n, 3), 100.0), "imu_acc": np.tile([0, 0, 9.81], (n, 1)), "opt_quat": q,
            "sampling_rate": 286.0}
    scipy.io.savemat(tmp_path / "trial.mat", data)
    with pytest.raises(ValueError, match=r"trial\.mat: column 'imu_gyr x' reaches 100 rad/s"):
        load_broad(tmp_path / "trial.mat")
