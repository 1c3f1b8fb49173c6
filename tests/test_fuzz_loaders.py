"""Hostile files: every broken input ends in a clean load, a documented repair with a warning,
or one line of `ValueError`/`FileNotFoundError` naming the file; never another traceback.

Two parts:
- a corpus of named broken files (truncated pickles and .mat files, wrong dtypes and shapes,
  resource bombs (nested shared-reference pickles, HDF5/.mat headers declaring huge shapes),
  implausible physical values and duplicate CSV columns,
  empty arrays, NaN/Inf, non-monotonic and duplicated stamps, time gaps, a VICON file with no
  overlap, pickles of the wrong structure, CSVs with junk; EuRoC/TUM-VI folders with broken
  stamps, values, truth and sensor.yaml files (YAML bombs and tags included); ROS 1 and ROS 2
  bags with ambiguous or missing topics, wrong message bytes, broken stamps, truncated storage),
  each with its expected outcome, run through the loaders and through `fusion compare` in-process;
- hypothesis-generated cases: random bytes, random mutations of valid files of every format
  (bags: their .bag/.db3/.mcap bytes), random CSV and ASL text, and whole recordings (IMU + VICON)
  through `fusion.datasets.load` and the CLI.

Every case is counted; the terminal summary prints `fuzz: N cases, M tracebacks` (conftest.py).
A case "tracebacks" when it raises anything else, or an error without the file name or on
several lines, or warns with something other than a one-line `UserWarning` naming the file.
"""
from __future__ import annotations

import contextlib
import io
import itertools
import pickle
import traceback
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fusion import datasets
from fusion import format_checks as loaders
from fusion.formats import course, generic_csv
from fusion.cli import main
from fusion.types import ImuSamples, RawImu, Recording, Trajectory
from optional_helpers import require_module

FUZZ = settings(derandomize=True, database=None, deadline=None, print_blob=False,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])

_counter = itertools.count()


def fresh_dir(root: Path) -> Path:
    """A new lab folder `<root>/<n>/lab` with `imu/` and `vicon/` (hypothesis cannot use tmp_path)."""
    lab = root / str(next(_counter)) / "lab"
    (lab / "imu").mkdir(parents=True)
    (lab / "vicon").mkdir()
    return lab


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# --- valid files, to be broken ------------------------------------------------------------

REST_COUNTS = np.array([511.0, 501.0, 605.0, 373.0, 375.0, 369.0])  # native ax ay az wx wy wz


def good_counts(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n,) unix stamps at 100 Hz with jitter and (n, 6) native counts: rest, then motion."""
    rng = np.random.default_rng(seed)
    t = 1.3e9 + np.arange(n) * 0.01 + rng.uniform(-1e-3, 1e-3, n)
    counts = np.tile(REST_COUNTS, (n, 1)) + rng.integers(-1, 2, (n, 6))
    rest = min(n, 80)
    counts[rest:] += np.round(rng.normal(0, 20, (n - rest, 6)))
    return t, np.clip(counts, 0, 1023)


def imu_2018(t, counts):
    return {"vals": counts[:, [0, 1, 2, 5, 3, 4]].T.astype(np.uint16), "ts": t[None]}  # ax ay az wz wx wy


def imu_276a(t, counts):
    arr = np.vstack([t, counts.T]).astype(float)
    arr[1:3] *= -1  # the release negated ax, ay
    return arr


def vicon_dict(t, seed=0):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (len(t), 3)), axis=0))
    return {"rots": np.moveaxis(rot.as_matrix(), 0, 2), "ts": np.asarray(t, float)[None]}


def broad_trial(n: int, seed: int = 0) -> dict:
    """A valid BROAD trial (see `fusion.broad`): slow rotation, movement mask, 286 Hz."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.002, (n, 3)), axis=0))
    return {"imu_gyr": rng.normal(0, 0.1, (n, 3)), "imu_acc": rot.inv().apply([0, 0, 9.81]),
            "imu_mag": rot.inv().apply([0.0, 19.0, -45.0]) + rng.normal(0, 1, (n, 3)),  # uT
            "opt_quat": rot.as_quat(scalar_first=True),
            "movement": (np.arange(n) > n // 3).astype(np.uint8), "sampling_rate": 286.0}


def write(path: Path, obj) -> Path:
    if isinstance(obj, bytes):
        path.write_bytes(obj)
    elif path.suffix == ".mat":
        with warnings.catch_warnings():  # writing odd objects warns; the file is what matters
            warnings.simplefilter("ignore")
            scipy.io.savemat(path, obj)
    elif path.suffix == ".csv":
        path.write_text(obj)
    else:
        path.write_bytes(pickle.dumps(obj))
    return path


def load_file(path: Path):
    """The loader for a file, by name (what discovery would pick)."""
    if path.suffix in (".hdf5", ".h5") or (path.suffix == ".mat" and path.name.startswith("trial")):
        from fusion.broad import load_broad

        return load_broad(path)
    if path.suffix == ".csv":
        return generic_csv.load_csv(path)
    if path.name.startswith("viconRot"):
        return course.load_vicon(path)
    return course.load_imu_mat(path) if path.suffix == ".mat" else course.load_imu_pickle(path)


# --- the judge ----------------------------------------------------------------------------

def check_loaded(obj, path: Path) -> None:
    """Invariants of whatever a loader returned."""
    items = obj if isinstance(obj, tuple) else (obj,)
    if isinstance(obj, Recording):
        items = (obj.imu, obj.truth, obj.raw)
    for item in items:
        if item is None:
            continue
        assert isinstance(item, (RawImu, ImuSamples, Trajectory, np.ndarray)), type(item)
        if isinstance(item, np.ndarray):
            assert item.dtype == bool
            continue
        t = item.t
        assert len(t) >= 2 and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0), path
        assert not t.flags.writeable
        if isinstance(item, RawImu):
            assert np.all(np.isfinite(item.counts))
        elif isinstance(item, ImuSamples):
            assert np.all(np.isfinite(item.gyr_rad_s)) and np.all(np.isfinite(item.acc_g))
        else:
            q = item.quat_wxyz[item.valid]
            assert len(q) and np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)


def judge(stats: dict, fn, paths: list[Path], *, expect: str | None = None):
    """Run `fn()`; return ("ok"|"warn"|"error", message). Counts the case; fails on a traceback.

    expect: None (any clean outcome), or "ok", "warn:<text>", "error:<text>".
    """
    stats["cases"] += 1
    names = [str(p) for p in paths]
    problem = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result = fn()
        except (ValueError, FileNotFoundError) as exc:
            message = str(exc)
            outcome = ("error", message)
            if "\n" in message or not any(n in message for n in names):
                problem = f"{type(exc).__name__} not naming the file in one line: {message!r}"
        except Exception:  # anything else is what this test hunts
            problem = traceback.format_exc()
        else:
            outcome = ("warn", " | ".join(str(w.message) for w in caught)) if caught else ("ok", "")
            try:
                check_loaded(result, paths[0])
            except AssertionError:
                problem = "loaded but broke an invariant:\n" + traceback.format_exc()
    for w in caught:
        text = str(w.message)
        if problem is None and (not issubclass(w.category, UserWarning) or issubclass(w.category, DeprecationWarning)
                                or "\n" in text or not any(n in text for n in names)):
            problem = f"undocumented warning {w.category.__name__}: {text!r}"
    if problem is not None:
        stats["tracebacks"] += 1
        pytest.fail(f"{paths[0]}: {problem}")
    stats[outcome[0]] = stats.get(outcome[0], 0) + 1
    if expect is not None:
        kind, _, text = expect.partition(":")
        assert outcome[0] == kind and text in outcome[1], f"{paths[0]}: expected {expect!r}, got {outcome}"
    return outcome


def run_cli(stats: dict, argv: list[str], paths: list[Path], *, expect_code: int | None = None,
            expect_out: str | None = None) -> int:
    """`fusion.cli.main(argv)` in-process: exit 0, or exit 1 with one `fusion: error:` line
    (plus `fusion: warning:` lines for documented repairs) and no traceback. expect_out: a text the
    table must hold (a recording not scored: its reason in the footer)."""
    stats["cases"] += 1
    out, err = io.StringIO(), io.StringIO()
    problem = None
    with warnings.catch_warnings(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except Exception:  # main must catch what users can cause
            code, problem = None, traceback.format_exc()
    lines = err.getvalue().splitlines()
    if problem is None:
        errors = [ln for ln in lines if ln.startswith("fusion: error:")]
        others = [ln for ln in lines if not ln.startswith(("fusion: error:", "fusion: warning:"))]
        if "Traceback" in err.getvalue() or others:
            problem = f"unexpected stderr: {lines}"
        elif code == 1 and (len(errors) != 1 or not any(str(p) in errors[0] for p in paths)):
            problem = f"exit 1 needs one error line naming the file, got {lines}"
        elif code == 0 and (errors or "RMSE" not in out.getvalue()):
            problem = f"exit 0 without a table: {lines} {out.getvalue()!r}"
        elif code not in (0, 1):
            problem = f"exit code {code}: {lines}"
    if problem is not None:
        stats["tracebacks"] += 1
        pytest.fail(f"fusion {' '.join(argv)}: {problem}")
    kind = "error" if code == 1 else ("warn" if lines else "ok")
    stats[kind] = stats.get(kind, 0) + 1
    if expect_code is not None:
        assert code == expect_code, (code, lines)
    if expect_out is not None:
        assert expect_out in out.getvalue(), (expect_out, out.getvalue()[-600:])
    return code


def cli_args(imu_path: Path) -> list[str]:
    return ["compare", "--estimators", "dr", "--no-progress", "--dataset", str(imu_path),
            "--data-dir", str(imu_path.parent.parent)]


# --- the corpus of named broken files -----------------------------------------------------

def _evil():
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))
    return Evil()


def _corpus():
    """(name, file name, object or bytes, vicon object or None, expected loader outcome, CLI exit)."""
    t, c = good_counts(300)
    a = imu_276a(t, c)
    v = vicon_dict(t)
    good = pickle.dumps(a)
    cases = []

    def add(name, fname, obj, expect, code, vicon=v):
        cases.append(pytest.param(fname, obj, vicon, expect, code, id=name))

    def mod(fn):
        arr = a.copy()
        fn(arr)
        return arr

    add("valid-276a", "imuRaw1.p", a, "ok", 0)
    add("valid-2018", "imuRaw1.p", imu_2018(t, c), "ok", 0, vicon=None)
    add("valid-mat", "imuRaw1.mat", imu_2018(t, c), "ok", 0)
    add("truncated-pickle", "imuRaw1.p", good[: len(good) // 2], "error:not a readable pickle", 1)
    add("truncated-pickle-header", "imuRaw1.p", good[:5], "error:not a readable pickle", 1)
    add("empty-file", "imuRaw1.p", b"", "error:file is empty", 1)
    add("text-as-pickle", "imuRaw1.p", b"hello, world\n", "error:not a readable pickle", 1)
    add("evil-reduce", "imuRaw1.p", _evil(), "error:refusing to load builtins.print", 1)
    add("set", "imuRaw1.p", {1, 2}, "error:found set", 1)
    add("list", "imuRaw1.p", [1, 2, 3], "error:found list", 1)
    add("none", "imuRaw1.p", None, "error:found NoneType", 1)
    add("numpy-scalar", "imuRaw1.p", np.float64(1.0), "error:found float64", 1)
    add("dict-wrong-keys", "imuRaw1.p", {"values": 1, "time": 2}, "error:expected a field 'vals'", 1)
    add("dict-mixed-keys", "imuRaw1.p", {1: 2, "a": 3}, "error:expected a field 'vals'", 1)
    add("dict-nested", "imuRaw1.p", {"vals": {"vals": 1}, "ts": {"ts": 2}}, "error:not numeric", 1)
    add("ragged-lists", "imuRaw1.p", {"vals": [[1, 2], [3]], "ts": [1, 2]}, "error:not a numeric array", 1)
    add("string-array", "imuRaw1.p", a.astype(str), "error:not numeric", 1)
    add("complex-array", "imuRaw1.p", a.astype(complex), "error:complex", 1)
    add("object-array", "imuRaw1.p", a.astype(object), "error:not numeric", 1)
    add("structured-array", "imuRaw1.p", np.zeros((7, 5), dtype=[("x", float)]), "error:not numeric", 1)
    add("float32-ok", "imuRaw1.p", a.astype(np.float32), None, None)  # stamps lose precision: either outcome
    add("6xT", "imuRaw1.p", a[1:], "error:expected a 7 x T", 1)
    add("Tx7", "imuRaw1.p", a.T.copy(), "error:expected a 7 x T", 1)
    add("3d", "imuRaw1.p", a[None], "error:expected a 7 x T", 1)
    add("7x0", "imuRaw1.p", np.zeros((7, 0)), "error:0 IMU samples", 1)
    add("7x1", "imuRaw1.p", a[:, :1], "error:1 IMU samples", 1)
    add("vals-6x0", "imuRaw1.p", {"vals": np.zeros((6, 0)), "ts": np.zeros((1, 0))}, "error:0 IMU samples", 1)
    add("ts-length", "imuRaw1.p", {"vals": np.zeros((6, 5)), "ts": np.zeros((1, 4))}, "error:4 time stamps for 5", 1)
    add("nan-value", "imuRaw1.p", mod(lambda x: x.__setitem__((3, 150), np.nan)), "error:NaN or Inf", 1)
    add("inf-value", "imuRaw1.p", mod(lambda x: x.__setitem__((5, 10), -np.inf)), "error:NaN or Inf", 1)
    add("nan-stamps-all", "imuRaw1.p", mod(lambda x: x.__setitem__(0, np.nan)), "error:not increasing", 1)
    add("nan-stamps-few", "imuRaw1.p", mod(lambda x: x.__setitem__((0, [100, 200]), np.nan)), "warn:dropped 2", 0)
    add("duplicated-stamps", "imuRaw1.p", mod(lambda x: x.__setitem__((0, 120), x[0, 119])), "warn:dropped 1", 0)
    add("backwards-stamp", "imuRaw1.p", mod(lambda x: x.__setitem__((0, 150), x[0, 100])), "warn:dropped 1", 0)
    add("reversed-stamps", "imuRaw1.p", mod(lambda x: x.__setitem__(0, x[0, ::-1])), "error:not increasing", 1)
    add("constant-stamps", "imuRaw1.p", mod(lambda x: x.__setitem__(0, 1.3e9)), "error:not increasing", 1)
    add("milliseconds", "imuRaw1.p", mod(lambda x: x.__setitem__(0, x[0] * 1000)), "error:must be in seconds", 1)
    add("gap-1s", "imuRaw1.p", mod(lambda x: x.__setitem__((0, slice(200, None)), x[0, 200:] + 1)), "warn:1 gaps", 0)
    add("gap-5s-in-3s", "imuRaw1.p", mod(lambda x: x.__setitem__((0, slice(200, None)), x[0, 200:] + 5)),
        "error:gaps cover more than half", 1)
    add("gap-huge", "imuRaw1.p", mod(lambda x: x.__setitem__((0, slice(200, None)), x[0, 200:] + 1e6)),
        "error:gaps cover more than half", 1)
    add("one-stamp-far-future", "imuRaw1.p", mod(lambda x: x.__setitem__((0, 299), 1e12)), "error:gaps cover", 1)
    cut_mat = io.BytesIO()
    scipy.io.savemat(cut_mat, imu_2018(t, c))
    add("truncated-mat", "imuRaw1.mat", cut_mat.getvalue()[:300], "error:not a readable MATLAB file", 1)
    add("mat-header-only", "imuRaw1.mat", cut_mat.getvalue()[:128], "error:expected a field 'vals'", 1)
    complex_flag = bytearray(cut_mat.getvalue())
    complex_flag[0x91] |= 0x08  # 'complex' bit of vals' array flags, no imaginary part: SciPy 1.17 segfaults
    add("mat-complex-flag-segfault", "imuRaw1.mat", bytes(complex_flag), "error:not a readable MATLAB file", 1)
    add("mat-garbage", "imuRaw1.mat", bytes(range(256)) * 4, "error:not a readable MATLAB file", 1)
    add("mat-string-vals", "imuRaw1.mat", {"vals": np.array(["abc"]), "ts": 1.0}, "error:not numeric", 1)
    add("mat-struct-vals", "imuRaw1.mat", {"vals": {"a": 1}, "ts": t}, "error:not numeric", 1)
    add("mat-empty", "imuRaw1.mat", {"vals": np.zeros((6, 0)), "ts": np.zeros((1, 0))}, "error:0 IMU samples", 1)
    add("mat-wrong-rows", "imuRaw1.mat", {"vals": np.zeros((5, 10)), "ts": np.zeros((1, 10))}, "error:must be 6 x T", 1)
    # VICON files (the loader outcome is the IMU's; the CLI runs the IMU with the VICON file: one that
    # cannot be used costs the truth, not the recording, and the table's footer says why: `out:<text>`)
    vt = v["ts"]
    add("vicon-no-overlap", "imuRaw1.p", a, "ok", "out:truth unusable: viconRot1.p's time span", vicon={"rots": v["rots"], "ts": vt + 1e4})
    add("vicon-truncated", "imuRaw1.p", a, "ok", "out:truth unusable: ", vicon=pickle.dumps(v)[:200])
    add("vicon-reflection", "imuRaw1.p", a, "ok", "out:are reflections (determinant -1)", vicon={"rots": v["rots"] * np.array([1, 1, -1])[:, None, None], "ts": vt})
    add("vicon-not-rotations", "imuRaw1.p", a, "ok", "out:are not rotation matrices", vicon={"rots": v["rots"] * 2, "ts": vt})
    add("vicon-all-nan", "imuRaw1.p", a, "ok", "out:no truth: its 'rots' matrices hold no orientation", vicon={"rots": v["rots"] * np.nan, "ts": vt})
    add("vicon-some-nan", "imuRaw1.p", a, "ok", 0,
        vicon={"rots": np.where(np.arange(300) % 7 == 3, np.nan, v["rots"]), "ts": vt})
    add("vicon-wrong-shape", "imuRaw1.p", a, "ok", "out:'rots' must be 3 x 3 x K", vicon={"rots": v["rots"][:2], "ts": vt})
    add("vicon-ts-length", "imuRaw1.p", a, "ok", "out:truth unusable: ", vicon={"rots": v["rots"], "ts": vt[:, :-3]})
    add("vicon-list", "imuRaw1.p", a, "ok", "out:truth unusable: ", vicon=[v])
    add("no-rest-at-start", "imuRaw1.p", imu_276a(t, c[::-1].copy()), "ok", 1)
    # resource bombs: tiny files declaring huge arrays, refused by structure or header before allocation
    add("nested-shared-refs-10**30", "imuRaw1.p", {"vals": shared_list_bomb(30, 10), "ts": [0.0, 0.01]},
        "error:nested more than 8 deep", 1)
    add("nested-shared-refs-wide", "imuRaw1.p", {"vals": shared_list_bomb(6, 40), "ts": [0.0, 0.01]},
        "error:nested containers hold", 1)
    add("nested-shared-refs-array", "imuRaw1.p", [np.zeros((7, 100_000))] * 300, "error:nested containers hold", 1)
    cycle: list = [1.0]
    cycle.append(cycle)
    add("pickle-cycle", "imuRaw1.p", {"vals": cycle, "ts": [0.0]}, "error:holds itself", 1)
    add("mat-declares-huge-shape", "imuRaw1.mat", huge_mat({"vals": (6, 10_000_001), "ts": (1, 2)}),
        "error:declares shape (6, 10000001)", 1)
    add("vicon-nested-shared-refs", "imuRaw1.p", a, "ok", "out:containers nested more than 8 deep",
        vicon={"rots": shared_list_bomb(30, 10), "ts": vt})
    add("vicon-mat-declares-huge", "imuRaw1.p", a, "ok", "out:viconRot1.p: not a readable pickle",
        vicon=huge_mat({"rots": (3, 3, 10_000_001), "ts": (1, 2)}))
    return cases


def shared_list_bomb(levels: int, width: int) -> list:
    """`l = [l] * width`, `levels` times: a few hundred bytes pickled, width**levels values."""
    nested: list = [0]
    for _ in range(levels):
        nested = [nested] * width
    return nested


def huge_mat(shapes: dict) -> bytes:
    """A compressed .mat of uint8 zeros with these shapes (a few hundred KB for 60 M values)."""
    buf = io.BytesIO()
    scipy.io.savemat(buf, {k: np.zeros(v, np.uint8) for k, v in shapes.items()}, do_compression=True)
    return buf.getvalue()


def _csv_corpus():
    n = 200
    t = np.arange(n) * 0.01
    rows = np.column_stack([t, np.zeros((n, 3)), np.tile([0, 0, 9.80665], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1))])
    body = "\n".join(",".join(f"{x:.6g}" for x in r) for r in rows)
    hdr = "t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz"
    lines = body.splitlines()
    return [
        pytest.param(f"{hdr}\n{body}\n", "ok", 0, id="csv-valid"),
        pytest.param(f"\ufeff{hdr}\n{body}\n", "ok", 0, id="csv-bom"),
        pytest.param(f"{hdr.upper()}\n{body}\n", "ok", 0, id="csv-upper-header"),
        pytest.param(f"{hdr}\n{body}\n\n\n", "ok", 0, id="csv-trailing-blank-lines"),
        pytest.param(f"{hdr}\n", "error:no data rows", 1, id="csv-header-only"),
        pytest.param(f"{hdr.replace(',', ';')}\n{body.replace(',', ';')}\n", "error:missing CSV columns", 1, id="csv-semicolons"),
        pytest.param("t,gx,gy\n1,2,3\n", "error:missing CSV columns", 1, id="csv-missing-columns"),
        pytest.param(f"{hdr}\n" + "\n".join(lines[:50] + ["junk,1,2"] + lines[50:]), "error:unreadable CSV row", 1, id="csv-junk-row"),
        pytest.param(f"{hdr}\n" + "\n".join(lines[:50] + [lines[50] + ",7"] + lines[51:]), "error:unreadable CSV row", 1, id="csv-extra-field"),
        pytest.param(f"{hdr}\n" + body.replace("0,0,9.80665", "nan,0,9.80665", 1), "error:NaN or Inf", 1, id="csv-nan-acc"),
        pytest.param(f"{hdr}\n" + "\n".join(lines[::-1]), "error:not increasing", 1, id="csv-reversed"),
        pytest.param(f"{hdr}\n" + body.replace(",1,0,0,0", ",2,0,0,0"),
                     "warn:truth unusable: 200 of its 200 truth rows (qw,qx,qy,qz) are not unit quaternions (|q| 2)", 0,
                     id="csv-nonunit-quat"),
        pytest.param(f"{hdr}\n" + body.replace(",1,0,0,0", ",nan,nan,nan,nan"), "warn:no truth: its truth rows (qw,qx,qy,qz) hold no orientation", 0,
                     id="csv-truth-all-nan"),
        pytest.param(b"\x00\xff\xfe" * 100, "error:missing CSV columns", 1, id="csv-binary"),
        pytest.param(f"{hdr}\n" + body.replace("9.80665", "9,80665"), "error:", 1, id="csv-decimal-comma"),
        pytest.param(f"{hdr}\n1,0,0,0,0,0,9.8,1,0,0,0\n", "error:need at least 2 rows", 1, id="csv-one-row"),
        pytest.param(f"{hdr.replace('gy', 'gx')}\n{body}\n", "error:names column 'gx' more than once", 1, id="csv-duplicate-column"),
        pytest.param(f"{hdr},ax\n" + "\n".join(ln + ",0" for ln in lines), "error:names column 'ax' more than once", 1,
                     id="csv-duplicate-extra-column"),
        pytest.param(f"{hdr}\n" + body.replace("0,0,9.80665", "0,1e308,9.80665", 1), "error:reaches 1e+308 m/s^2", 1,
                     id="csv-acc-1e308"),
        pytest.param(f"{hdr}\n" + "\n".join(f"{r[0]:.6g},{r[1] + 200},0,0,0,0,9.80665,1,0,0,0" for r in rows),
                     "error:in deg/s? convert to rad/s", 1, id="csv-gyro-deg-s"),
        pytest.param(f"{hdr}\n" + "\n".join(f"{k},0,0,0,0,0,9.80665,1,0,0,0" for k in range(n)),
                     "error:look like sample numbers", 1, id="csv-sample-numbers"),
        pytest.param(f"{hdr}\n" + "\n".join(f"{10 * k},0,0,0,0,0,9.80665,1,0,0,0" for k in range(n)),
                     "error:milliseconds? divide by 1000", 1, id="csv-milliseconds"),
        pytest.param(f"{hdr}\n" + "\n".join(lines[:60] + [lines[59]] + lines[60:]), "warn:dropped 1", 0,
                     id="csv-duplicated-stamp-repaired"),
    ]


@pytest.mark.parametrize("fname, obj, vicon, expect, code", _corpus())
def test_corpus_file(root, fuzz_stats, fname, obj, vicon, expect, code):
    lab = fresh_dir(root)
    imu_path = write(lab / "imu" / fname, obj)
    paths = [imu_path]
    if vicon is not None:
        paths.append(write(lab / "vicon" / "viconRot1.p", vicon))
        judge(fuzz_stats, lambda: load_file(paths[1]), paths[1:])
    judge(fuzz_stats, lambda: load_file(imu_path), [imu_path], expect=expect)
    judge(fuzz_stats, lambda: datasets.load(str(imu_path), lab.parent), paths)
    out = code[4:] if isinstance(code, str) else None  # "out:<text>": exit 0, and the table says <text>
    run_cli(fuzz_stats, cli_args(imu_path), paths, expect_code=0 if out else code, expect_out=out)


@pytest.mark.parametrize("text, expect, code", _csv_corpus())
def test_corpus_csv(root, fuzz_stats, text, expect, code):
    path = write(fresh_dir(root) / "walk.csv", text)
    judge(fuzz_stats, lambda: generic_csv.load_csv(path), [path], expect=expect)
    run_cli(fuzz_stats, cli_args(path), [path], expect_code=code)


def test_missing_file_and_directory(root, fuzz_stats):
    lab = fresh_dir(root)
    (lab / "imu" / "imuRaw2.p").mkdir()
    for path in (lab / "imu" / "imuRaw1.p", lab / "imu" / "imuRaw2.p", lab / "x.csv"):
        judge(fuzz_stats, lambda: load_file(path), [path], expect="error:no such file")
    run_cli(fuzz_stats, cli_args(lab / "imu" / "imuRaw1.p"), [lab / "imu" / "imuRaw1.p"], expect_code=1)


def test_gap_marks_gyro_invalid_and_is_documented(root):
    t, c = good_counts(300)
    t[200:] += 1.0
    lab = fresh_dir(root)
    path = write(lab / "imu" / "imuRaw1.p", imu_276a(t, c))
    with pytest.warns(UserWarning, match="1 gaps in the time stamps"):
        rec = datasets.load(str(path), lab.parent)
    assert np.flatnonzero(~rec.imu.gyr_valid).tolist() == [199]  # the sample integrated over the gap
    assert "gaps" in loaders.__doc__ and "GAP_S" in loaders.__doc__


# --- generated cases ----------------------------------------------------------------------

JUNK_VALUES = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e308, -1e308, 5e-324, 1e6]
DTYPES = [np.float64, np.float32, np.float16, np.int8, np.int64, np.uint16, np.bool_, np.complex128, str, object]


def mutate(data, arr: np.ndarray) -> object:
    """A random broken version of a valid 2-D array (row 0 or `ts` holds the stamps)."""
    kind = data.draw(st.sampled_from([
        "none", "values", "stamps", "dtype", "shape", "slice", "wrap", "gap", "scale", "shuffle", "duplicate"]))
    arr = np.array(arr, copy=True)
    n = arr.shape[-1]
    if n < 2 and kind in ("gap", "duplicate", "values", "stamps", "shuffle"):
        kind = "dtype"
    if kind == "values":
        for _ in range(data.draw(st.integers(1, 5))):
            i, j = data.draw(st.integers(0, arr.shape[0] - 1)), data.draw(st.integers(0, n - 1))
            arr[i, j] = data.draw(st.sampled_from(JUNK_VALUES))
    elif kind == "stamps":
        idx = data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=n))
        arr[0, idx] = data.draw(st.sampled_from(JUNK_VALUES))
    elif kind == "dtype":
        with np.errstate(all="ignore"):  # inf -> int casts: the point is a broken file
            arr = arr.astype(data.draw(st.sampled_from(DTYPES)))
    elif kind == "shape":
        shape = data.draw(st.sampled_from([(-1,), (1, -1), (-1, 1), (n, -1), (2, -1, 1)]))
        try:
            arr = arr.reshape(shape)
        except ValueError:
            arr = arr.ravel()
    elif kind == "slice":
        lo = data.draw(st.integers(0, n))
        arr = arr[:, lo:lo + data.draw(st.integers(0, 3))] if data.draw(st.booleans()) else arr[: data.draw(st.integers(0, arr.shape[0]))]
    elif kind == "wrap":
        return data.draw(st.sampled_from([list, tuple, lambda x: {"data": x}, lambda x: [x, x], lambda x: x.tolist(), lambda x: None]))(arr)
    elif kind == "gap":
        k = data.draw(st.integers(1, n - 1))
        arr[0, k:] += data.draw(st.sampled_from([0.3, 0.6, 2.0, 30.0, 1e5]))
    elif kind == "scale":
        arr[0] = arr[0] * data.draw(st.sampled_from([1e-9, 1e-3, 1e3, -1.0, 0.0]))
    elif kind == "shuffle":
        lo = data.draw(st.integers(0, n - 1))
        hi = data.draw(st.integers(lo, n))
        arr[0, lo:hi] = data.draw(st.permutations(list(arr[0, lo:hi])))
    elif kind == "duplicate":
        k = data.draw(st.integers(1, n - 1))
        arr[0, k:k + data.draw(st.integers(1, 20))] = arr[0, k - 1]
    return arr


def mutate_bytes(data, raw: bytes) -> bytes:
    kind = data.draw(st.sampled_from(["truncate", "flip", "prefix", "suffix"]))
    if kind == "truncate":
        return raw[: data.draw(st.integers(0, len(raw)))]
    if kind == "flip":
        b = bytearray(raw)
        for _ in range(data.draw(st.integers(1, 8))):
            b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
        return bytes(b)
    if kind == "prefix":
        return data.draw(st.binary(max_size=20)) + raw
    return raw + data.draw(st.binary(min_size=1, max_size=20))


@settings(FUZZ, max_examples=500)
@given(blob=st.binary(max_size=400), suffix=st.sampled_from([".p", ".mat", ".csv", "vicon.p"]))
def test_random_bytes(root, fuzz_stats, blob, suffix):
    name = "viconRot1.p" if suffix == "vicon.p" else ("walk.csv" if suffix == ".csv" else f"imuRaw1{suffix}")
    path = write(fresh_dir(root) / name, blob)
    judge(fuzz_stats, lambda: load_file(path), [path])


@settings(FUZZ, max_examples=800)
@given(data=st.data(), n=st.integers(2, 200), layout=st.sampled_from(["276a", "2018", "mat"]),
       corrupt=st.sampled_from(["array", "ts", "bytes"]))
@pytest.mark.slow
def test_mutated_imu_files(root, fuzz_stats, data, n, layout, corrupt):
    t, c = good_counts(n)
    suffix = ".mat" if layout == "mat" else ".p"
    path = fresh_dir(root) / "imu" / f"imuRaw1{suffix}"
    if layout == "276a":
        obj = imu_276a(t, c)
        obj = mutate(data, obj) if corrupt != "bytes" else obj
    else:
        obj = imu_2018(t, c)
        if corrupt == "array":
            obj["vals"] = mutate(data, obj["vals"].astype(float))
        elif corrupt == "ts":
            obj["ts"] = mutate(data, obj["ts"])
    if layout == "mat":
        try:
            write(path, obj)
        except Exception:  # scipy cannot write this object (e.g. None): not a file, not a case
            return
    else:
        write(path, obj)
    if corrupt == "bytes":
        write(path, mutate_bytes(data, path.read_bytes()))
    judge(fuzz_stats, lambda: load_file(path), [path])


@settings(FUZZ, max_examples=400)
@given(data=st.data(), n=st.integers(2, 100), part=st.sampled_from(["rots", "ts", "bytes", "keys"]),
       mat=st.booleans())
@pytest.mark.slow
def test_mutated_vicon_files(root, fuzz_stats, data, n, part, mat):
    t, _ = good_counts(n)
    obj = vicon_dict(t)
    path = fresh_dir(root) / "vicon" / ("viconRot1.mat" if mat else "viconRot1.p")
    if part == "rots":
        rots = np.moveaxis(obj["rots"], 2, 0).reshape(n, 9).T  # 9 x K, mutate like an IMU array
        broken = mutate(data, np.vstack([t, rots]))
        obj["rots"] = np.moveaxis(broken[1:].T.reshape(-1, 3, 3), 0, 2) if isinstance(broken, np.ndarray) and broken.ndim == 2 \
            and broken.shape[0] == 10 and broken.dtype.kind in "fiub" else broken
    elif part == "ts":
        obj["ts"] = mutate(data, obj["ts"])
    elif part == "keys":
        obj = {data.draw(st.sampled_from(["rots", "ts", "Rots", 1, "__header__"])): v for v in obj.values()}
    try:
        write(path, obj)
    except Exception:  # scipy cannot write this object: not a file, not a case
        return
    if part == "bytes":
        write(path, mutate_bytes(data, path.read_bytes()))
    judge(fuzz_stats, lambda: load_file(path), [path])


CSV_TOKENS = ["0", "1", "-1", "0.01", "9.81", "nan", "inf", "-inf", "", " ", "abc", "1e999", "1e308", "0x3", "1,5", "\"2\"",
              "1e-320", "\t3", "１", "NaN", "1.0.0"]
HEADERS = ["t,gx,gy,gz,ax,ay,az", "t,gx,gy,gz,ax,ay,az,qw,qx,qy,qz", "\ufefft,gx,gy,gz,ax,ay,az", "t,gx,gy,gz,ax,ay",
           "T, GX, GY, GZ, AX, AY, AZ", "t;gx;gy;gz;ax;ay;az", "", "t,t,gx,gy,gz,ax,ay,az"]


@settings(FUZZ, max_examples=600)
@given(data=st.data(), header=st.sampled_from(HEADERS), n=st.integers(0, 40), junk=st.integers(0, 4),
       stamps=st.sampled_from(["increasing", "random", "gap", "ms"]))
def test_generated_csv(root, fuzz_stats, data, header, n, junk, stamps):
    ncol = max(1, len(header.split(",")))
    t = np.arange(n) * 0.01
    if stamps == "random":
        t = np.array(data.draw(st.lists(st.one_of(st.floats(-1, 1), st.just(np.nan)), min_size=n, max_size=n)), dtype=float)
    elif stamps == "gap" and n > 2:
        t[n // 2:] += data.draw(st.sampled_from([0.4, 3.0, 1e3]))
    elif stamps == "ms":
        t = t * 1000
    rows = []
    for k in range(n):
        vals = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 9.80665, 1.0, 0.0, 0.0, 0.0][: ncol]
        vals += [0.0] * (ncol - len(vals))
        vals[0] = t[k]
        rows.append([repr(float(x)) for x in vals])
    for _ in range(junk if n else 0):
        r, ci = data.draw(st.integers(0, n - 1)), data.draw(st.integers(0, ncol - 1))
        rows[r][ci] = data.draw(st.sampled_from(CSV_TOKENS))
    text = header + "\n" + "\n".join(",".join(r) for r in rows)
    path = write(fresh_dir(root) / "walk.csv", text.encode("utf-8", errors="surrogatepass"))
    judge(fuzz_stats, lambda: generic_csv.load_csv(path), [path])


@settings(FUZZ, max_examples=200)
@given(data=st.data(), n=st.integers(60, 250), imu_broken=st.booleans(), vicon_shift=st.sampled_from([0.0, 0.0, 2.5, -1e4, 1e4]))
def test_generated_recordings_through_load_and_cli(root, fuzz_stats, data, n, imu_broken, vicon_shift):
    """Whole recordings (IMU + VICON, one of them maybe broken) through `datasets.load` and `fusion compare`."""
    t, c = good_counts(n, seed=n)
    lab = fresh_dir(root)
    imu = imu_276a(t, c)
    vicon = vicon_dict(t + vicon_shift)
    if imu_broken:
        imu = mutate(data, imu)
    else:
        if data.draw(st.booleans()):
            rots = mutate(data, vicon["rots"].reshape(9, n))
            ok = isinstance(rots, np.ndarray) and rots.size % 9 == 0 and rots.size
            vicon["rots"] = rots.reshape(3, 3, -1) if ok else rots
        vicon["ts"] = mutate(data, vicon["ts"]) if data.draw(st.booleans()) else vicon["ts"]
    paths = [write(lab / "imu" / "imuRaw1.p", imu), write(lab / "vicon" / "viconRot1.p", vicon)]
    judge(fuzz_stats, lambda: datasets.load(str(paths[0]), lab.parent), paths)
    run_cli(fuzz_stats, cli_args(paths[0]), paths)


def test_valid_files_round_trip(root):
    """A clean file of each format loads back to the very counts it was written from."""
    t, c = good_counts(150)
    lab = fresh_dir(root)
    for path, obj in ((lab / "imu" / "imuRaw1.p", imu_276a(t, c)), (lab / "imu" / "imuRaw2.p", imu_2018(t, c)),
                      (lab / "imu" / "imuRaw3.mat", imu_2018(t, c))):
        raw = load_file(write(path, obj))
        np.testing.assert_array_equal(raw.counts, c)
        np.testing.assert_array_equal(raw.t, t)


# --- BROAD trials (fusion.broad: .mat through SciPy, .hdf5 through h5py) -----------------

def _broad_corpus():
    b = broad_trial(300)
    good = io.BytesIO()
    scipy.io.savemat(good, b)
    flags = bytearray(good.getvalue())
    flags[0x91] |= 0x08  # complex flag of the first array without an imaginary part (SciPy segfault)
    return [
        pytest.param(b, "ok", 0, id="broad-valid"),
        pytest.param(good.getvalue()[:400], "error:not a readable", 1, id="broad-truncated"),
        pytest.param(bytes(flags), "error:", 1, id="broad-complex-flag-segfault"),
        pytest.param({**b, "imu_gyr": b["imu_gyr"].astype(complex)}, "error:not an array of real numbers", 1, id="broad-complex"),
        pytest.param({**b, "imu_acc": np.array(["x"] * 3)}, "error:", 1, id="broad-string-acc"),
        pytest.param({**b, "sampling_rate": 0.0}, "error:sampling_rate", 1, id="broad-zero-rate"),
        pytest.param({**b, "sampling_rate": np.array(["fast"])}, "error:sampling_rate", 1, id="broad-string-rate"),
        pytest.param({**b, "opt_quat": b["opt_quat"] * np.nan}, "warn:no truth: its 'opt_quat' rows (w, x, y, z) hold no",
                     0, id="broad-no-truth"),
        pytest.param({k: v for k, v in b.items() if k != "imu_gyr"}, "error:no 'imu_gyr'", 1, id="broad-missing-gyr"),
        pytest.param({**b, "imu_gyr": b["imu_gyr"][:10]}, "error:", 1, id="broad-short-gyr"),
        pytest.param(huge_mat({"imu_gyr": (10_000_001, 3), "imu_acc": (3, 3), "opt_quat": (3, 4), "sampling_rate": (1, 1)}),
                     "error:'imu_gyr' declares shape (10000001, 3)", 1, id="broad-mat-declares-huge"),
        pytest.param({**b, "imu_acc": b["imu_acc"] * 1e6}, "error:beyond any accelerometer range", 1, id="broad-acc-x1e6"),
    ]


@pytest.mark.parametrize("rows, cols, expect", [
    (30_000_000, 3, "error:declares shape (30000000, 3)"),
    (10_000_001, 3, "error:declares shape (10000001, 3)"),
    (2_000, 3, "error:the median |a| is 0"),  # within the limits: read, then judged on its values (all zeros)
])
def test_corpus_broad_hdf5_declared_shapes(root, fuzz_stats, rows, cols, expect):
    """A ~2 KB .hdf5 declaring 30 million compressed (never written) rows is refused from its header."""
    h5py = require_module("h5py")
    path = fresh_dir(root) / "trial01.hdf5"
    with h5py.File(path, "w") as f:
        f.create_dataset("imu_gyr", shape=(rows, cols), dtype="f8", chunks=(min(rows, 50_000), cols), compression="gzip")
        f.create_dataset("imu_acc", shape=(rows, 3), dtype="f8", chunks=(min(rows, 50_000), 3), compression="gzip")
        f.create_dataset("opt_quat", shape=(rows, 4), dtype="f8", chunks=(min(rows, 50_000), 4), compression="gzip")
        f.attrs["sampling_rate"] = 286.0
    assert path.stat().st_size < 50_000
    judge(fuzz_stats, lambda: load_file(path), [path], expect=expect)
    run_cli(fuzz_stats, cli_args(path), [path], expect_code=1)


@pytest.mark.parametrize("obj, expect, code", _broad_corpus())
def test_corpus_broad(root, fuzz_stats, obj, expect, code):
    path = write(fresh_dir(root) / "trial01.mat", obj)
    judge(fuzz_stats, lambda: load_file(path), [path], expect=expect)
    run_cli(fuzz_stats, cli_args(path), [path], expect_code=code)


@settings(FUZZ, max_examples=250)
@given(data=st.data(), n=st.integers(2, 120), key=st.sampled_from(["imu_gyr", "imu_acc", "opt_quat", "movement", "sampling_rate", "bytes"]),
       hdf5=st.booleans())
@pytest.mark.slow
def test_mutated_broad_trials(root, fuzz_stats, data, n, key, hdf5):
    h5py = require_module("h5py") if hdf5 else None
    trial = broad_trial(n)
    if key != "bytes":
        value = np.atleast_2d(trial[key]).astype(float)
        trial[key] = mutate(data, value if value.shape[0] <= value.shape[-1] else value.T)
    path = fresh_dir(root) / ("trial01.hdf5" if hdf5 else "trial01.mat")
    try:
        if hdf5:
            with h5py.File(path, "w") as f:
                for k, v in trial.items():
                    f[k] = v
        else:
            write(path, trial)
    except Exception:  # the writer refuses this object: not a file, not a case
        return
    if key == "bytes":
        write(path, mutate_bytes(data, path.read_bytes()))
    judge(fuzz_stats, lambda: load_file(path), [path])


# --- EuRoC / TUM-VI folders (fusion.formats.asl) ------------------------------------------

ASL_IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                  "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
ASL_TRUTH_HEADER = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
T_BS_ROTATED = "T_BS:\n  cols: 4\n  rows: 4\n  data: [0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n"


def asl_tables(n: int, seed: int = 0) -> tuple[list[list[str]], list[list[str]]]:
    """Rows (as text fields) of a valid imu0/data.csv and truth data.csv: 200 Hz, ns stamps."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    ns = 1_403_636_579_758_555_392 + np.arange(n, dtype=np.int64) * 5_000_000
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0))
    gyr, acc = rng.normal(0, 0.2, (n, 3)), rot.inv().apply([0, 0, 9.81])
    imu = [[str(s), *(repr(float(x)) for x in (*g, *a))] for s, g, a in zip(ns, gyr, acc)]
    truth = [[str(s), "0", "0", "0", *(repr(float(x)) for x in q)] for s, q in zip(ns, rot.as_quat(scalar_first=True))]
    return imu, truth


def write_asl_folder(folder: Path, imu_rows, truth_rows=None, imu_header=ASL_IMU_HEADER, truth_header=ASL_TRUTH_HEADER,
                     truth_yaml: str | bytes | None = None, truth_folder: str = "state_groundtruth_estimate0") -> Path:
    mav0 = folder / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "imu0" / "data.csv").write_text(imu_header + "\n" + "\n".join(",".join(r) for r in imu_rows) + "\n")
    if truth_rows is not None:
        (mav0 / truth_folder).mkdir()
        (mav0 / truth_folder / "data.csv").write_text(truth_header + "\n" + "\n".join(",".join(r) for r in truth_rows) + "\n")
        if truth_yaml is not None:
            write(mav0 / truth_folder / "sensor.yaml", truth_yaml if isinstance(truth_yaml, bytes) else truth_yaml.encode())
    return folder


def _asl_corpus():
    imu, truth = asl_tables(300)

    def edit(rows, row, col, value):
        rows = [list(r) for r in rows]
        rows[row][col] = value
        return rows

    billion_laughs = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi")) + "T_BS:\n  data: *i\n"
    return [
        pytest.param(imu, truth, {}, "ok", 0, id="asl-valid"),
        pytest.param(imu, None, {}, "ok", 0, id="asl-no-truth"),
        pytest.param(imu, truth, {"truth_yaml": T_BS_ROTATED}, "ok", 0, id="asl-truth-t-bs"),
        pytest.param(imu, truth, {"truth_yaml": "%YAML:1.0\n" + T_BS_ROTATED}, "ok", 0, id="asl-opencv-yaml"),
        pytest.param(imu, truth, {"truth_folder": "mocap0"}, "ok", 0, id="asl-tumvi-mocap0"),
        pytest.param(imu, truth, {"imu_header": "t,gx,gy,gz,ax,ay,az"}, "error:missing ASL columns", 1, id="asl-generic-header"),
        pytest.param(imu[:1], truth, {}, "error:need at least 2 rows", 1, id="asl-one-row"),
        pytest.param([], truth, {}, "error:no data rows", 1, id="asl-header-only"),
        pytest.param([[str(k * 5), *r[1:]] for k, r in enumerate(imu)], None, {}, "error:integer nanoseconds", 1, id="asl-stamps-not-ns"),
        pytest.param(edit(imu, 10, 0, "1.4e18"), None, {}, "error:must hold integer nanoseconds", 1, id="asl-float-stamp"),
        pytest.param(edit(imu, 10, 0, "99999999999999999999"), None, {}, "error:integer nanoseconds", 1, id="asl-stamp-overflow"),
        pytest.param(edit(imu, 10, 2, "nan"), None, {}, "error:NaN or Inf", 1, id="asl-nan-gyro"),
        pytest.param(edit(imu, 10, 4, "1e6"), None, {}, "error:beyond any accelerometer range", 1, id="asl-acc-1e6"),
        pytest.param(edit(imu, 10, 3, "abc"), None, {}, "error:unreadable CSV row", 1, id="asl-junk-value"),
        pytest.param(edit(imu, 100, 0, imu[99][0]), truth, {}, "warn:dropped 1", 0, id="asl-duplicated-stamp"),
        pytest.param(imu[::-1], None, {}, "error:not increasing", 1, id="asl-reversed"),
        # the truth folder's problems cost the truth, not the recording: the table's footer says why
        pytest.param(imu, edit(truth, 5, 4, "2.0"), {}, "warn:1 of 300 q_RS_w, q_RS_x, q_RS_y, q_RS_z rows are not unit "
                     "quaternions (|q| 2", 0, id="asl-truth-not-unit"),
        pytest.param(imu, [[str(int(r[0]) + 10**13), *r[1:]] for r in truth], {}, "ok", "out:does not overlap",
                     id="asl-truth-no-overlap"),
        pytest.param(imu, truth, {"truth_header": "#timestamp,x,y,z"}, "ok", "out:missing ASL columns q_RS_w",
                     id="asl-truth-no-quat"),
        pytest.param(imu, truth, {"truth_yaml": "T_BS: [1, 2"}, "ok", "out:not a readable YAML file", id="asl-yaml-broken"),
        pytest.param(imu, truth, {"truth_yaml": "T_BS:\n  data: [1, 0, 0]\n"}, "ok", "out:T_BS must hold 16 numbers",
                     id="asl-t-bs-short"),
        pytest.param(imu, truth, {"truth_yaml": "T_BS:\n  data: [2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1]\n"},
                     "ok", "out:not a rotation matrix", id="asl-t-bs-not-rotation"),
        pytest.param(imu, truth, {"truth_yaml": "T_BS:\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, .nan, 0, 0, 0, 0, 1]\n"},
                     "ok", "out:T_BS holds NaN or Inf", id="asl-t-bs-nan"),
        pytest.param(imu, truth, {"truth_yaml": "!!python/object/apply:os.system ['echo pwned']\n"},
                     "ok", "out:not a readable YAML file", id="asl-yaml-python-tag"),
        pytest.param(imu, truth, {"truth_yaml": billion_laughs}, "ok", "out:T_BS must hold 16 numbers",
                     id="asl-yaml-billion-laughs"),
        pytest.param(imu, truth, {"truth_yaml": b"T_BS: " + b"[" * 2_000_000}, "ok", "out:not a sensor.yaml",
                     id="asl-yaml-huge"),
        pytest.param(imu, truth, {"truth_yaml": b"\xff\xfe\x00garbage: [\x00"}, "ok", "out:truth unusable: ",
                     id="asl-yaml-binary"),
    ]


@pytest.mark.parametrize("imu, truth, options, expect, code", _asl_corpus())
def test_corpus_asl(root, fuzz_stats, imu, truth, options, expect, code):
    folder = write_asl_folder(fresh_dir(root) / "V1_01", imu, truth, **options)
    judge(fuzz_stats, lambda: datasets.load(str(folder)), [folder], expect=expect)
    out = code[4:] if isinstance(code, str) else None  # "out:<text>": exit 0, and the table says <text>
    run_cli(fuzz_stats, ["compare", "--estimators", "dr", "--no-progress", "--dataset", str(folder)], [folder],
            expect_code=0 if out else code, expect_out=out)


@settings(FUZZ, max_examples=150)
@given(data=st.data(), n=st.integers(2, 80), which=st.sampled_from(["imu", "truth"]), junk=st.integers(1, 5))
def test_generated_asl_folders(root, fuzz_stats, data, n, which, junk):
    imu, truth = asl_tables(n, seed=n)
    rows = imu if which == "imu" else truth
    for _ in range(junk):
        r, c = data.draw(st.integers(0, n - 1)), data.draw(st.integers(0, len(rows[0]) - 1))
        rows[r][c] = data.draw(st.sampled_from(CSV_TOKENS + ["-1", "0", "9223372036854775807", rows[max(r - 1, 0)][c]]))
    folder = write_asl_folder(fresh_dir(root) / "V2_01", imu, truth)
    judge(fuzz_stats, lambda: datasets.load(str(folder)), [folder])


# --- ROS 1 and ROS 2 bags (fusion.formats.rosbag) -----------------------------------------

def good_bag(path: Path, version: int, storage: str = "sqlite3", n: int = 300, **kwargs) -> Path:
    from robotics_writers import write_bag

    t, c = good_counts(n)  # only for a recognisable motion; the bag holds physical units
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(n)
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0))
    tt = np.arange(n) / 200
    return write_bag(path, version, tt, rng.normal(0, 0.2, (n, 3)), rot.inv().apply([0, 0, 1.0]), tt,
                     rot.as_quat(scalar_first=True), storage=storage, **kwargs)


def _bag_file(path: Path) -> Path:
    """The file holding a bag's messages (the .bag, or a rosbag2 folder's .db3/.mcap)."""
    return path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))


def _raw_bag(path: Path, version: int, msgtype: str, raws: list[bytes], topic: str = "/imu0") -> Path:
    """A bag whose `topic` claims `msgtype` but holds the bytes `raws` (stamps 5 ms apart)."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    if version == 1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=9)
    with writer:
        conn = writer.add_connection(topic, msgtype, typestore=typestore)
        for k, raw in enumerate(raws):
            writer.write(conn, 1_400_000_000_000_000_000 + k * 5_000_000, raw)
    return path


def _imu_raws(version: int, n: int, edit=None) -> list[bytes]:
    from rosbags.typesys import Stores, get_typestore

    from robotics_writers import imu_message

    typestore = get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)
    out = []
    for k in range(n):
        ns = 1_400_000_000_000_000_000 + k * 5_000_000
        gyr, acc = np.array([0.1, -0.2, 0.05]), np.array([0.0, 0.0, 9.81])
        if edit is not None:
            ns, gyr, acc = edit(k, ns, gyr, acc)
        msg = imu_message(typestore, ns, gyr, acc)
        out.append(bytes(typestore.serialize_ros1(msg, "sensor_msgs/msg/Imu") if version == 1
                         else typestore.serialize_cdr(msg, "sensor_msgs/msg/Imu")))
    return out


def _bag_corpus():
    def nan_gyro(k, ns, g, a):
        return ns, (g * np.nan if k == 7 else g), a

    def backwards(k, ns, g, a):
        return (ns - 10**9 if k == 50 else ns), g, a

    def ms_apart(k, ns, g, a):
        return 1_400_000_000_000_000_000 + k * 5_000, g, a

    def far(k, ns, g, a):
        return ns + (10**9 * 1000 if k > 100 else 0), g, a

    cases = []
    for version in (1, 2):
        v = f"ros{version}"
        cases += [
            pytest.param(version, lambda p, v=version: good_bag(p, v), "ok", 0, id=f"{v}-valid"),
            pytest.param(version, lambda p, v=version: good_bag(p, v, extra_topics=(("/imu1", "sensor_msgs/msg/Imu"),)),
                         "error:2 topics of type sensor_msgs/msg/Imu: /imu0, /imu1; choose one with --imu-topic", 1,
                         id=f"{v}-two-imu-topics"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "geometry_msgs/msg/PoseStamped", [b"\0" * 64] * 3,
                                                                 topic="/pose"),
                         "error:no sensor_msgs/msg/Imu topic; topics: /pose (geometry_msgs/msg/PoseStamped)", 1, id=f"{v}-no-imu"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", [b"\0\1\0\0" + b"\1" * 40] * 300),
                         "error:", 1, id=f"{v}-wrong-bytes"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", _imu_raws(v, 300, nan_gyro)),
                         "error:NaN or Inf", 1, id=f"{v}-nan-gyro"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", _imu_raws(v, 300, backwards)),
                         "warn:dropped 1", 0, id=f"{v}-backwards-stamp"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", _imu_raws(v, 300, ms_apart)),
                         "error:median time step 5e-06 s", 1, id=f"{v}-stamps-too-close"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", _imu_raws(v, 300, far)),
                         "error:gaps cover more than half", 1, id=f"{v}-stamp-jump"),
            pytest.param(version, lambda p, v=version: _raw_bag(p, v, "sensor_msgs/msg/Imu", _imu_raws(v, 1)),
                         "error:1 samples; need at least 2", 1, id=f"{v}-one-message"),
        ]
    cases += [
        pytest.param(1, lambda p: write(p, b"#ROSBAG V2.0\n" + bytes(range(256)) * 8), "error:not a readable ROS bag", 1,
                     id="ros1-garbage"),
        pytest.param(1, lambda p: write(p, good_bag(p.with_name("x.bag"), 1).read_bytes()[:5000]), "error:not a readable ROS bag",
                     1, id="ros1-truncated"),
        pytest.param(2, lambda p: (good_bag(p, 2), (p / "metadata.yaml").write_text("rosbag2_bagfile_information: [")) and p,
                     "error:not a readable ROS bag", 1, id="ros2-broken-metadata"),
        pytest.param(2, lambda p: (good_bag(p, 2), write(_bag_file(p), _bag_file(p).read_bytes()[:3000])) and p,
                     "error:not a readable ROS bag", 1, id="ros2-truncated-db3"),
        pytest.param(2, lambda p: (good_bag(p, 2, storage="mcap"), write(_bag_file(p), _bag_file(p).read_bytes()[:3000])) and p,
                     "error:not a readable ROS bag", 1, id="ros2-truncated-mcap"),
    ]
    return cases


@pytest.mark.parametrize("version, make, expect, code", _bag_corpus())
def test_corpus_bags(root, fuzz_stats, version, make, expect, code):
    require_module("rosbags")
    path = make(fresh_dir(root) / ("run.bag" if version == 1 else "run"))
    judge(fuzz_stats, lambda: datasets.load(str(path)), [path], expect=expect)
    run_cli(fuzz_stats, ["compare", "--estimators", "dr", "--no-progress", "--dataset", str(path)], [path], expect_code=code)


@settings(FUZZ, max_examples=120)
@given(data=st.data(), kind=st.sampled_from(["ros1", "sqlite3", "mcap"]))
def test_mutated_bags(root, fuzz_stats, data, kind):
    """Valid bags of each storage with their bytes truncated, flipped or extended."""
    require_module("rosbags")
    lab = fresh_dir(root)
    path = good_bag(lab / ("run.bag" if kind == "ros1" else "run"), 1 if kind == "ros1" else 2,
                    storage="mcap" if kind == "mcap" else "sqlite3", n=60)
    target = _bag_file(path)
    write(target, mutate_bytes(data, target.read_bytes()))
    judge(fuzz_stats, lambda: datasets.load(str(path)), [path])
