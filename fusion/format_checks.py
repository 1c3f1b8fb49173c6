"""What every file format shares: safe readers, resource bounds, time-stamp repairs and
plausibility checks. The formats themselves are in `fusion.formats` (one module each); each one
reads its layout with the functions here, so that every file goes through the same checks.

Every problem raises `ValueError` (or `FileNotFoundError`) naming the file, in one line
(exception texts from pickle/SciPy/HDF5/rosbags are folded onto that line, `one_line`).
`tests/test_fuzz_loaders.py` feeds thousands of broken files of every format through the
loaders and the CLI to keep it so.

Resource bounds (`MAX_SAMPLES`, `MAX_VALUES`, `MAX_BYTES`, `MAX_NESTING`) are checked on what a
file *declares* before anything is allocated: array shapes in HDF5/MATLAB headers
(`check_declared`), the structure of unpickled containers (`check_structure`), the row count of
a text table (`read_table`), the message counts of a ROS bag's index.

Time stamps (`repair_time` then `check_sampling`, applied by every loader):
- not strictly increasing (NaN/Inf, duplicated, backwards): the offending samples are
  dropped, with a warning saying how many, as long as at least half the samples survive;
  otherwise the file is rejected.
- implausible sampling: a median time step outside [10 us, 1 s] (100 kHz .. 1 Hz) is
  rejected; stamps in milliseconds or sample numbers instead of seconds end up here.
- gaps: a step longer than `GAP_S` (0.5 s, some 50 missing samples at 100 Hz) and than ten
  median steps is *kept*, with a warning giving their count and the longest. `fusion.datasets` then marks the gyro
  sample before each gap invalid (`ImuSamples.gyr_valid`), so estimators hold the orientation
  across the gap instead of integrating a stale rate over it (see `invalidate_gaps`). If the
  gaps cover more than half of the recording's span, the file is rejected (broken stamps).

Values: NaN or Inf IMU values are rejected; complex, string, object or structured arrays are
rejected; values in physical units must be physically plausible (`check_physical`,
`physical_samples`).

Truth, row by row (`truth_quaternions`, `truth_matrices`, `overlap_problem`): rows without an
orientation (NaN, all zero) are tracking gaps; rows that are not an orientation (a quaternion far
from unit norm, a matrix far from a rotation) become gaps too, with a warning counting them. A
recording whose truth is unusable as a whole (no row usable, most rows not orientations, no
overlap with the IMU) is read without it, and `Recording.truth_problem` says why: its IMU still
runs every estimator; the run lists it as not scored, with that reason.
MATLAB and HDF5 files are read in a forked child process (`read_isolated`): a corrupt file can
crash SciPy's or HDF5's C reader, and a crash must stay an error.

The gyro timing of each format (`ImuSamples.gyr_timing`) is said, with its evidence, in its
module: `fusion.formats.course` for the course boards ("start"), the others "end".
"""
from __future__ import annotations

import faulthandler
import io
import mmap
import os
import pickle
import struct
import sys
import warnings
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterable

import numpy as np

from .types import STANDARD_GRAVITY_M_S2, ImuSamples, Trajectory

ADC_LIMIT_COUNTS = 65535  # raw IMU values are ADC counts (10-bit here; any 16-bit ADC fits)
GAP_S = 0.5  # a time step longer than this is a gap (warned about; see the module docstring)
MIN_STEP_S, MAX_STEP_S = 1e-5, 1.0  # plausible median time step (100 kHz .. 1 Hz)

# Resource bounds, checked on what a file *declares* (array shapes in the HDF5/MATLAB headers,
# the structure of unpickled containers) before anything is allocated. A real recording is far
# below them: the course files hold ~5,000-10,000 samples, BROAD trials ~50,000-100,000.
MAX_SAMPLES = 10_000_000  # per array, its longest axis: 27 h at 100 Hz, 2.8 h at 1 kHz
MAX_VALUES = 16 * MAX_SAMPLES  # per array, all values (16 channels of MAX_SAMPLES)
MAX_BYTES = 2 * 1024**3  # all arrays of one file together, as float64 (what loading makes of them)
MAX_NESTING = 8  # nested lists/tuples/dicts in a pickle (a 3 x 3 x K list in a dict is 4)

# Physical plausibility of files in physical units (CSV, BROAD, ASL, ROS bags): see `check_physical`.
GYRO_LIMIT_RAD_S = 70.0  # 4000 deg/s: the widest range of common MEMS gyros
GYRO_MEDIAN_WARN_RAD_S = 10.0  # median |rate| over a recording (hand-held ~0.3-1 rad/s; BROAD up to 5.3)
# median |a| over a recording, m/s^2: near gravity's 9.81 (BROAD's fourteen trials 9.84-9.95, the course's 9.79-9.81,
# even in fast translation); a free fall or a spin would need most of the recording to leave it
ACC_MEDIAN_M_S2 = (4.0, 30.0)
# `gyro_tilt_ratio` above this: the gyro reads ~57x too much (deg/s). The shared recordings give 0.27-1.07 (BROAD's
# fast translation lowest), and 16-61 with their gyro converted to deg/s
GYRO_TILT_RATIO_WARN = 10.0
ACC_LIMIT_M_S2 = 200 * STANDARD_GRAVITY_M_S2  # 200 g: high-g MEMS accelerometers (ADXL375); BROAD's tapping peaks at 16 g


class _RestrictedUnpickler(pickle.Unpickler):
    """Builds numpy arrays, dtypes and plain containers; refuses every other global."""

    _ALLOWED = {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("builtins", "dict"),
        ("builtins", "list"),
        ("builtins", "tuple"),
        ("collections", "OrderedDict"),
        ("_codecs", "encode"),
    }

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays and plain containers)")


def one_line(exc: BaseException, limit: int = 200) -> str:
    """`Type: message` of an exception on one line, shortened (SciPy messages can hold matrices)."""
    text = " ".join(str(exc).split())
    text = text if len(text) <= limit else text[: limit - 3] + "..."
    return f"{type(exc).__name__}: {text}"


def read_pickle(path: Path, kind: str = "pickle", max_values: int = MAX_VALUES) -> Any:
    """The object of a pickle file, built by the restricted unpickler (numpy arrays and plain
    containers only: a pickle cannot run code here) and checked by `check_structure` with
    `max_values`. Any failure is one ValueError naming the file; `kind` names the format."""
    check_file(path)
    try:
        with open(path, "rb") as f:  # streamed: a camera pickle is hundreds of MB
            obj = _RestrictedUnpickler(f, encoding="latin1").load()
    except Exception as exc:  # pickle raises many types for corrupt input; report them all in one line
        raise ValueError(f"{path}: not a readable {kind} ({one_line(exc)})") from None
    check_structure(obj, path, max_values)
    return obj


_CONTAINERS = (list, tuple, dict)


def check_structure(obj: Any, path: Path | str, max_values: int = MAX_VALUES) -> None:
    """Refuse nested containers whose arrays would be unboundedly large, by structure alone.

    A 663-byte pickle of lists sharing references (`l = [l] * 10`, 30 times) holds 10**30
    values once `np.asarray` materialises it. Here each container's nesting depth and total
    value count (an ndarray counts its `size`, anything else 1) are computed once per object
    (memo on `id`, so shared references cost nothing, and are counted as often as they are
    referenced, as materialising would), iteratively (no recursion limit), and a container
    holding itself is refused. Limits: `MAX_NESTING` levels, `max_values` values.
    """
    if not isinstance(obj, _CONTAINERS):
        return
    memo: dict[int, int] = {}  # id -> total values
    active: set[int] = set()  # the containers on the current path (a repeat is a cycle)
    stack: list[tuple[Any, int, bool]] = [(obj, 1, False)]
    while stack:
        node, level, done = stack.pop()
        children = list(node.values()) if isinstance(node, dict) else node
        key = id(node)
        if done:
            total = 0
            for child in children:
                total += memo[id(child)] if isinstance(child, _CONTAINERS) else (child.size if isinstance(child, np.ndarray) else 1)
            if total > max_values:
                raise ValueError(f"{path}: nested containers hold {total:.3g} values, more than any recording "
                                 f"(limit {max_values:.3g})")
            memo[key] = total
            active.discard(key)
            continue
        if key in memo:
            continue
        if key in active:
            raise ValueError(f"{path}: a container holds itself (a reference cycle); not a recording")
        if level > MAX_NESTING:
            raise ValueError(f"{path}: containers nested more than {MAX_NESTING} deep; not a recording")
        active.add(key)
        stack.append((node, level, True))
        for child in children:
            if isinstance(child, _CONTAINERS) and id(child) not in memo:
                stack.append((child, level + 1, False))


def check_declared(path: Path | str, arrays: Iterable[tuple[str, tuple[int, ...]]], max_values: int = MAX_VALUES,
                   max_bytes: int = MAX_BYTES) -> None:
    """Refuse a file whose arrays, as its header declares them (`(name, shape)` pairs), exceed
    `MAX_SAMPLES` along an axis, `max_values` in one array or `max_bytes` (as float64) in all;
    called before any array is read."""
    total = 0
    for name, shape in arrays:
        shape = tuple(int(n) for n in shape)
        values = int(np.prod(shape, dtype=object)) if shape else 1
        if any(n > MAX_SAMPLES for n in shape) or values > max_values:
            raise ValueError(f"{path}: {name!r} declares shape {shape} ({values:.3g} values); the limit is "
                             f"{MAX_SAMPLES:.3g} samples along an axis and {max_values:.3g} values per array")
        total += 8 * values
        if total > max_bytes:
            raise ValueError(f"{path}: the arrays declare {total / 1024**3:.3g} GiB, more than the {max_bytes / 1024**3:.3g} "
                             "GiB limit of one file")


def read_mat(path: Path, kind: str = "MATLAB", variable_names: list[str] | None = None,
             v73: Callable[[Path], dict[str, Any]] | None = None, max_values: int = MAX_VALUES,
             max_bytes: int = MAX_BYTES) -> dict[str, np.ndarray]:
    """The numeric variables of a MATLAB file (all, or `variable_names`), read in a child
    process (`read_isolated`) after `check_declared` with `max_values` and `max_bytes`. A MATLAB
    v7.3 file (HDF5 inside, which SciPy does not read) goes to `v73` if given. Any failure is
    one ValueError naming the file; `kind` names the format."""
    import scipy.io  # noqa: F401  (imported here, so the child never imports: no import lock held across fork)

    check_file(path)
    return read_isolated(path, partial(_loadmat, kind=kind, variable_names=variable_names, v73=v73,
                                       max_values=max_values, max_bytes=max_bytes), kind)


def read_isolated(path: Path, reader: Callable[[Path], dict[str, Any]], kind: str) -> dict[str, np.ndarray]:
    """`reader(path)`'s arrays: numeric ones as they are, anything else as an empty object
    array (which `numeric_array` rejects). `reader` raises `ValueError` (or `ImportError`) for files
    it cannot read; `kind` names the format in messages.

    SciPy's MATLAB reader (and h5py's HDF5 library) are C code that a corrupt file can crash
    outright: with SciPy 1.17 a single flipped bit (the "complex" flag of a uint16 array
    without an imaginary part) is a segmentation fault, which no `except` can catch. So on
    Linux `reader` runs in a forked child (a few ms; the libraries are already imported) that
    sends the arrays back (`_send`, `_receive`: a protocol-5 pickle through a pipe, the arrays'
    data out of band in a shared-memory file that the parent maps, so it is copied once, in
    the child; the restricted unpickler rebuilds them); a crashed child becomes a one-line
    `ValueError`. Elsewhere (no safe fork) it runs in-process, unprotected.
    """
    if not sys.platform.startswith("linux"):
        return _plain_arrays(reader(path))
    read_fd, write_fd = os.pipe()
    store_fd = os.memfd_create("fusion-read", os.MFD_CLOEXEC)  # the arrays' bytes, shared with the child
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # Python >= 3.12: fork with threads
        pid = os.fork()
    if pid == 0:  # the child: read, send, exit without running any parent cleanup
        code = 0
        try:
            faulthandler.disable()  # an expected crash here is reported by the parent, in one line
            os.close(read_fd)
            try:
                message = ("ok", _plain_arrays(reader(path)))
            except ValueError as exc:
                message = ("error", str(exc))
            except ImportError as exc:
                message = ("import", str(exc))
            with os.fdopen(write_fd, "wb") as pipe, os.fdopen(store_fd, "wb", closefd=False) as store:
                _send(pipe, store, message)
        except BaseException:  # the child must never return into the parent's code
            code = 1
        finally:
            os._exit(code)
    os.close(write_fd)
    try:
        with os.fdopen(read_fd, "rb") as pipe:  # the child writes the pipe last: at its end, the store is complete
            message = _receive(pipe, store_fd)
    finally:
        os.close(store_fd)  # a mapping made from it stays valid
        _, status = os.waitpid(pid, 0)
    if message is None or status != 0:
        how = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit status {os.waitstatus_to_exitcode(status)}"
        raise ValueError(f"{path}: not a readable {kind} file (the reader crashed on it: {how})")
    result, value = message
    if result == "error":
        raise ValueError(" ".join(value.split()))
    if result == "import":
        raise ImportError(value)
    return value


_NUMBER = struct.Struct("<Q")
_ALIGN = 64  # each array starts on a cache line, as numpy's own allocations are aligned


def _send(pipe: BinaryIO, store: BinaryIO, message: Any) -> None:
    """Write `message` as a protocol-5 pickle whose contiguous arrays travel out of band: their
    bytes into `store` (a shared-memory file), each at an offset aligned to `_ALIGN`; into `pipe`
    the pickle's length and bytes, the number of arrays and each one's offset and length."""
    buffers: list[pickle.PickleBuffer] = []
    header = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    spans, end = [], 0
    for buffer in buffers:
        raw = buffer.raw()  # the array's own memory, not a copy
        start = -(-end // _ALIGN) * _ALIGN
        store.write(bytes(start - end))
        store.write(raw)
        spans += [start, raw.nbytes]
        end = start + raw.nbytes
    store.flush()
    pipe.write(_NUMBER.pack(len(header)) + header + _NUMBER.pack(len(buffers)) + b"".join(map(_NUMBER.pack, spans)))


def _receive(pipe: BinaryIO, store_fd: int) -> Any:
    """What `_send` wrote, rebuilt by the restricted unpickler, its arrays viewing the shared
    memory of `store_fd` (mapped, not copied); None if the pipe ends early (the child died)."""
    data = pipe.read()
    if len(data) < _NUMBER.size:
        return None
    size = _NUMBER.unpack_from(data)[0]
    header, at = data[_NUMBER.size:_NUMBER.size + size], _NUMBER.size + size
    if len(data) < at + _NUMBER.size:
        return None
    count, at = _NUMBER.unpack_from(data, at)[0], at + _NUMBER.size
    if len(data) != at + 2 * count * _NUMBER.size:
        return None
    numbers = [n for (n,) in _NUMBER.iter_unpack(data[at:])]
    spans = list(zip(numbers[0::2], numbers[1::2]))
    end = max((start + length for start, length in spans), default=0)
    if end != os.fstat(store_fd).st_size:
        return None
    # copy-on-write: the child's pages are read in place, and a write (here, or in a process forked
    # later) changes only the writer's copy
    store = memoryview(mmap.mmap(store_fd, end, access=mmap.ACCESS_COPY) if end else bytearray(0))
    buffers = [store[start:start + length] for start, length in spans]
    return _RestrictedUnpickler(io.BytesIO(header), buffers=buffers).load()


def _plain_arrays(variables: dict[str, Any]) -> dict[str, np.ndarray]:
    out = {}
    for key, value in variables.items():
        if isinstance(value, np.ndarray) and (np.issubdtype(value.dtype, np.number) or value.dtype == bool):
            out[str(key)] = value
        elif not str(key).startswith("__"):
            out[str(key)] = np.empty(0, dtype=object)  # structs, cells, strings, sparse: not numeric
    return out


def _loadmat(path: Path, kind: str, variable_names: list[str] | None, v73: Callable[[Path], dict[str, Any]] | None,
             max_values: int, max_bytes: int) -> dict[str, Any]:
    import scipy.io

    try:
        declared = scipy.io.whosmat(str(path))
        wanted = [(name, shape) for name, shape, _ in declared if variable_names is None or name in variable_names]
        check_declared(path, wanted, max_values, max_bytes)
        return scipy.io.loadmat(str(path), variable_names=variable_names)
    except NotImplementedError:  # MATLAB v7.3: an HDF5 file
        if v73 is None:
            raise ValueError(f"{path}: a MATLAB v7.3 file, which this {kind} reader does not read") from None
        return v73(path)
    except ValueError as exc:
        if str(exc).startswith(f"{path}:"):
            raise
        raise ValueError(f"{path}: not a readable {kind} file ({one_line(exc)})") from None
    except Exception as exc:  # scipy raises ValueError, TypeError, OSError... for broken files
        raise ValueError(f"{path}: not a readable {kind} file ({one_line(exc)})") from None


def check_file(path: Path) -> None:
    """A clear error for a missing or empty file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: file is empty")


def read_bytes(path: Path) -> bytes:
    """The bytes of a file (`check_file` first)."""
    check_file(path)
    return path.read_bytes()


def text_lines(path: Path, max_bytes: int = MAX_BYTES) -> list[str]:
    """The lines of a text file (UTF-8, a byte-order mark dropped, undecodable bytes replaced),
    refused when larger than `max_bytes` (before reading) or longer than `MAX_SAMPLES` rows
    after its header line."""
    check_file(path)
    size = path.stat().st_size
    if size > max_bytes:
        raise ValueError(f"{path}: {size / 1024**3:.3g} GiB, more than the {max_bytes / 1024**3:.3g} GiB limit of one file")
    lines = path.read_bytes().decode("utf-8-sig", errors="replace").splitlines()  # -sig: drop a BOM
    if len(lines) - 1 > MAX_SAMPLES:
        raise ValueError(f"{path}: {len(lines) - 1} rows, more than the {MAX_SAMPLES:.3g} samples of any recording")
    return lines


def parse_rows(path: Path, rows: list[str], delimiter: str = ",") -> np.ndarray:
    """(R, C) float table of comma-separated numeric rows (blank lines skipped); one line naming
    the file for a row that is not numbers."""
    if not any(line.strip() for line in rows):
        raise ValueError(f"{path}: no data rows after the header")
    try:
        return np.loadtxt(rows, delimiter=delimiter, ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: unreadable CSV row ({exc})") from None


def field_array(obj: Any, key: str, path: Path) -> np.ndarray:
    """`obj[key]` as a float array (`numeric_array`); `obj` must be a dict holding `key`."""
    if not isinstance(obj, dict) or key not in obj:
        have = (sorted((k for k in obj if not str(k).startswith("__")), key=str) if isinstance(obj, dict)
                else type(obj).__name__)  # key=str: keys of mixed types do not compare
        raise ValueError(f"{path}: expected a field {key!r}, found {have}")
    return numeric_array(obj[key], path, key)


def numeric_array(value: Any, path: Path, what: str) -> np.ndarray:
    """`value` as a float array; refused when ragged, not numeric (strings, objects,
    structured) or complex; `what` names it in messages."""
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise ValueError(f"{path}: {what} is not a numeric array ({one_line(exc)})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{path}: {what} is not numeric (dtype {arr.dtype})")
    if np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{path}: {what} is complex (dtype {arr.dtype}); expected real numbers")
    return arr.astype(float)


def time_row(ts: np.ndarray, n: int, path: Path) -> np.ndarray:
    """(n,) time stamps from a `1 x n` (or any shape of n values) array."""
    t = np.ravel(ts)
    if len(t) != n:
        raise ValueError(f"{path}: {len(t)} time stamps for {n} samples")
    return t


def repair_time(t: np.ndarray, path: Path | str, *arrays: np.ndarray, sampling: bool = True) -> tuple[np.ndarray, ...]:
    """Keep the samples whose stamp is finite and later than every earlier kept stamp.

    Returns `(t, *arrays)` restricted to those samples; warns with the count it dropped.
    Raises if fewer than half the samples (or fewer than 2) survive. sampling: also check that
    the steps are those of a sensor (`check_sampling`); False for a trajectory, which may be
    sparse (keyframes) or have gaps.
    """
    t = np.asarray(t, dtype=float)
    if len(t) < 2:
        raise ValueError(f"{path}: {len(t)} samples; need at least 2")
    finite = np.isfinite(t)
    running_max = np.maximum.accumulate(np.where(finite, t, -np.inf))
    keep = finite.copy()
    keep[1:] &= t[1:] > running_max[:-1]
    dropped = int(len(t) - keep.sum())
    if keep.sum() < max(2, len(t) // 2):
        raise ValueError(f"{path}: time stamps are not increasing ({dropped} of {len(t)} samples out of order or not finite)")
    if dropped:
        warnings.warn(f"{path}: dropped {dropped} samples with non-finite, duplicate or backwards time stamps", stacklevel=2)
    t = t[keep]
    if sampling:
        check_sampling(t, path)
    return (t, *(a[keep] for a in arrays))


def check_sampling(t: np.ndarray, path: Path | str) -> None:
    """Reject implausible time steps, warn about gaps (see the module docstring).

    t: (N,) strictly increasing time stamps, s, N >= 2.
    """
    with np.errstate(over="ignore"):  # 1e308 - (-1e308) is inf, and so is the median of two 1e308 steps: rejected below
        dt = np.diff(t)
        span = t[-1] - t[0]
        step = float(np.median(dt))
    if not (MIN_STEP_S <= step <= MAX_STEP_S):
        hint = " (milliseconds? divide by 1000)" if 1e-3 <= step <= 1e3 else ""
        raise ValueError(f"{path}: median time step {step:.3g} s is outside [{MIN_STEP_S:g}, {MAX_STEP_S:g}] s; "
                         f"time stamps must be in seconds{hint}")
    if step == 1.0 and np.all(t == np.round(t)):
        raise ValueError(f"{path}: time stamps {t[0]:g}, {t[1]:g}, {t[2] if len(t) > 2 else t[1] + 1:g} ... look like "
                         "sample numbers (an IMU at exactly 1 Hz is implausible); time stamps must be in seconds")
    gaps = _gaps(dt)
    if np.any(gaps):
        with np.errstate(over="ignore"):  # steps of 1e308 sum to inf: rejected with the span
            covered = float(dt[gaps].sum())
        if not np.isfinite(span) or covered > 0.5 * span:
            raise ValueError(f"{path}: time stamps jump by up to {dt.max():.3g} s; gaps cover more than half "
                             f"of the {span:.3g} s span (broken time stamps?)")
        k = int(np.argmax(dt))
        warnings.warn(f"{path}: {int(gaps.sum())} gaps in the time stamps longer than {max(GAP_S, 10 * step):.3g} s "
                      f"(longest {dt[k]:.3g} s, {t[k] - t[0]:.1f} s after the start)", stacklevel=3)


def gyro_tilt_ratio(t: np.ndarray, gyr_rad_s: np.ndarray, acc_m_s2: np.ndarray, block_s: float = 0.1,
                    min_tilt_rad: float = 1.0) -> float | None:
    """How far the gyro turns the gravity direction against how far the accelerometer sees it turn.

    t: (N,) s; gyr_rad_s: (N, 3) rad/s; acc_m_s2: (N, 3), body frame (any unit: only its direction
    is used). The accelerometer, averaged over blocks of `block_s`, gives the gravity direction g_j
    per block; the gyro's rotation over a block, theta_j = sum w dt, turns it by about
    |theta_j x g_j| (the body-frame gravity obeys dg/dt = -w x g, Titterton & Weston 2004, Ch. 3),
    its component about gravity leaving it unchanged. The ratio of the two sums over the
    recording is near 1 for a gyro in rad/s (below 1 where linear acceleration and noise move
    the measured direction) and near 180/pi = 57 for a gyro in deg/s. None when the accelerometer
    sees less than `min_tilt_rad` of tilt change in all (too little motion to judge) or the time
    stamps give no step.
    """
    t = np.asarray(t, dtype=float)
    if len(t) < 2 or not np.all(np.isfinite(t)):
        return None  # the time checks that follow say what is wrong
    step = float(np.median(np.diff(t)))
    if not step > 0.0:
        return None
    m = max(1, int(round(block_s / step)))
    blocks = len(t) // m
    if blocks < 3:
        return None
    acc = np.asarray(acc_m_s2, dtype=float)[: blocks * m].reshape(blocks, m, 3).mean(axis=1)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    g = np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)
    measured = np.arccos(np.clip(np.sum(g[1:] * g[:-1], axis=1), -1.0, 1.0))  # between block means
    # the gyro's rotation between the two block centres: the second half of block j, the first of j + 1
    theta = (np.asarray(gyr_rad_s, dtype=float)[: blocks * m] * step).reshape(blocks, m, 3)
    half = m // 2
    between = theta[:-1, half:].sum(axis=1) + theta[1:, :half].sum(axis=1)
    predicted = np.linalg.norm(np.cross(between, g[:-1]), axis=1)
    if measured.sum() < min_tilt_rad:
        return None
    return float(predicted.sum() / measured.sum())


def check_physical(path: Path | str, gyr_rad_s: np.ndarray, acc_m_s2: np.ndarray, gyr_names: tuple[str, ...],
                   acc_names: tuple[str, ...]) -> None:
    """Plausibility of IMU values in physical units (finite (N, 3) arrays; names for messages).

    Errors: a gyro value beyond `GYRO_LIMIT_RAD_S` (4000 deg/s; deg/s or scaled values, e.g.
    x1e6, end up here), an accelerometer value beyond `ACC_LIMIT_M_S2` (200 g; 1e308 too), or an
    accelerometer whose median |a| is not near 1 g in m/s^2 (`ACC_MEDIAN_M_S2`: a recording of
    anything that moves by hand, on a vehicle or a robot spends most of its time near 9.81; 1
    is g, 1000 mg, and the message says so).
    Warning: a median |rate| above `GYRO_MEDIAN_WARN_RAD_S` (likely deg/s of a slow motion; for
    any motion, see `check_gyro_turns_gravity`).
    """
    for values, names, limit, unit, fix in (
        (gyr_rad_s, gyr_names, GYRO_LIMIT_RAD_S, "rad/s", "beyond any MEMS gyro (4000 deg/s); "
         "in deg/s? convert to rad/s (multiply by pi/180)"),
        (acc_m_s2, acc_names, ACC_LIMIT_M_S2, "m/s^2", "beyond any accelerometer range (200 g); "
         "the column must be in m/s^2"),
    ):
        peak = np.abs(values).max(axis=0)
        worst = int(np.argmax(peak))
        if peak[worst] > limit:
            raise ValueError(f"{path}: column {names[worst]!r} reaches {peak[worst]:.3g} {unit}, {fix}")
    acc_median = float(np.median(np.sqrt(np.sum(acc_m_s2**2, axis=1))))
    if not ACC_MEDIAN_M_S2[0] <= acc_median <= ACC_MEDIAN_M_S2[1]:
        hint = ("in g? multiply by 9.80665" if 0.3 <= acc_median <= 3.0 else
                "in mg? multiply by 0.00980665" if 300.0 <= acc_median <= 3000.0 else "the columns must be in m/s^2")
        raise ValueError(f"{path}: columns {','.join(acc_names)}: the median |a| is {acc_median:.3g}, where gravity "
                         f"alone reads 9.81 m/s^2: {hint}")
    median = float(np.median(np.sqrt(np.sum(gyr_rad_s**2, axis=1))))
    if median > GYRO_MEDIAN_WARN_RAD_S:
        warnings.warn(f"{path}: columns {','.join(gyr_names)}: the median angular rate is {median:.3g} rad/s "
                      f"({np.degrees(median):.0f} deg/s) over the whole recording, implausible for hand-held motion; "
                      "if they are in deg/s, convert them to rad/s (multiply by pi/180)", stacklevel=3)


def check_gyro_turns_gravity(path: Path | str, t: np.ndarray, gyr_rad_s: np.ndarray, acc_m_s2: np.ndarray,
                             gyr_names: tuple[str, ...], acc_names: tuple[str, ...]) -> None:
    """Warn when the gyro turns the gravity direction more than `GYRO_TILT_RATIO_WARN` times as
    far as the accelerometer sees it turn (`gyro_tilt_ratio`: a gyro in deg/s, at any speed), unless
    `check_physical`'s median-rate warning has said so already. After the time checks: t (N,)
    increasing, s; gyr_rad_s, acc_m_s2 (N, 3) finite."""
    median = float(np.median(np.sqrt(np.sum(gyr_rad_s**2, axis=1))))
    ratio = gyro_tilt_ratio(t, gyr_rad_s, acc_m_s2)
    if ratio is not None and ratio > GYRO_TILT_RATIO_WARN and median <= GYRO_MEDIAN_WARN_RAD_S:
        warnings.warn(f"{path}: columns {','.join(gyr_names)}: the gyro turns the gravity direction {ratio:.0f} times "
                      f"as far as the accelerometer ({','.join(acc_names)}) sees it turn; if they are in deg/s, "
                      "convert them to rad/s (multiply by pi/180)", stacklevel=4)


def _gaps(dt: np.ndarray) -> np.ndarray:
    """(N-1,) bool: steps longer than `GAP_S` and than ten median steps."""
    return dt > max(GAP_S, 10.0 * float(np.median(dt))) if len(dt) else np.zeros(0, bool)


def invalidate_gaps(imu: ImuSamples) -> ImuSamples:
    """`imu` with `gyr_valid` False for the gyro sample standing for each gap's interval
    (the sample before the gap for `gyr_timing` "start", after it for "end"; see `check_sampling`).

    Step k integrates the reading for [t[k], t[k+1]] over `dt[k]`; across a gap that would
    extrapolate one stale rate over seconds. Marked invalid, estimators hold the orientation
    instead. Returns `imu` itself when there is no gap (nothing is copied or modified).
    """
    gap = np.zeros(len(imu), bool)
    if imu.gyr_timing == "start":
        gap[:-1] = _gaps(imu.dt)
    else:
        gap[1:] = _gaps(imu.dt)
    if not np.any(gap & imu.gyr_valid):
        return imu
    return imu.replace(gyr_valid=imu.gyr_valid & ~gap)


def matrices_to_quat(matrices: np.ndarray, path: Path | str) -> np.ndarray:
    """(K, 3, 3) rotation matrices -> (K, 4) wxyz, every one a proper rotation (a sensor's
    mounting, `T_BS`); a truth's matrices go through `truth_matrices`, row by row."""
    from scipy.spatial.transform import Rotation

    matrices = np.asarray(matrices, dtype=float)
    if not np.all(np.isfinite(matrices)):
        raise ValueError(f"{path}: a rotation matrix holds NaN or Inf")
    with np.errstate(over="ignore", invalid="ignore"):
        error = np.abs(np.einsum("kij,kil->kjl", matrices, matrices) - np.eye(3)).max()
    if not error <= MATRIX_TOLERANCE:
        raise ValueError(f"{path}: not a rotation matrix (R^T R differs from I)")
    if np.any(np.linalg.det(matrices) < 0):
        raise ValueError(f"{path}: a reflection (determinant -1), not a rotation matrix")
    return Rotation.from_matrix(matrices).as_quat(scalar_first=True)


# A truth is read row by row (a motion-capture system loses markers and glitches): rows that hold no
# orientation are gaps, and rows that are not one (a quaternion far from unit norm, a matrix far from a
# rotation) become gaps too, counted in a warning. Only when most rows that hold something are not an
# orientation is the whole truth refused (a wrong layout or unit, not glitches), and then the recording
# is read without it, saying why (`Recording.truth_problem`): its IMU is still worth running.
TRUTH_BAD_FRACTION = 0.5  # more than this fraction of a truth's rows not orientations: the truth is unusable
MATRIX_TOLERANCE = 1e-2  # |R^T R - I| of a rotation matrix as files print them


def truth_quaternions(path: Path | str, quat_wxyz: np.ndarray, what: str,
                      tolerance: float) -> tuple[np.ndarray | None, str | None]:
    """A truth's (N, 4) quaternions, row by row: `(quat, None)` with rows normalised, and NaN where a
    row holds no orientation (not finite, or all zero: markers not seen) or is not one (its norm more
    than `tolerance` from 1: counted in a warning naming the file); `(None, why)` when no row is
    usable (`usable_truth`). what: the rows, for messages ("Vicon orientation rows (w, x, y, z)")."""
    quat = np.array(quat_wxyz, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.linalg.norm(quat, axis=1)
    held = np.isfinite(norm) & (norm > 0.0)
    unit = held & (np.abs(norm - 1.0) <= tolerance)
    off = norm[held & ~unit]
    low, high = (f"{off.min():.3g}", f"{off.max():.3g}") if len(off) else ("", "")
    detail = f"not unit quaternions (|q| {low if low == high else f'from {low} to {high}'})"
    problem = usable_truth(path, what, held, unit, detail)
    if problem is not None:
        return None, problem
    quat[unit] /= norm[unit, None]
    quat[~unit] = np.nan
    return quat, None


def truth_matrices(path: Path | str, matrices: np.ndarray, what: str) -> tuple[np.ndarray | None, str | None]:
    """A truth's (K, 3, 3) rotation matrices as (K, 4) wxyz quaternions, row by row as
    `truth_quaternions`: NaN where a matrix is not finite, or is not a proper rotation (|R^T R - I|
    beyond `MATRIX_TOLERANCE`, or a reflection: counted in a warning); `(None, why)` when none is usable."""
    from scipy.spatial.transform import Rotation

    matrices = np.asarray(matrices, dtype=float)
    held = np.all(np.isfinite(matrices), axis=(1, 2))
    rotation = held.copy()
    m = matrices[held]
    with np.errstate(over="ignore", invalid="ignore"):  # a matrix of 1e200s: not a rotation (inf error)
        error = np.nan_to_num(np.abs(np.einsum("kij,kil->kjl", m, m) - np.eye(3)).max(axis=(1, 2)), nan=np.inf)
        reflection = np.linalg.det(m) < 0
    rotation[held] = (error <= MATRIX_TOLERANCE) & ~reflection
    parts = []
    if np.any(error > MATRIX_TOLERANCE):
        parts.append(f"not rotation matrices (|R^T R - I| up to {error.max():.3g})")
    if np.any(reflection & (error <= MATRIX_TOLERANCE)):
        parts.append("reflections (determinant -1)")
    problem = usable_truth(path, what, held, rotation, " or ".join(parts))
    if problem is not None:
        return None, problem
    quat = np.full((len(matrices), 4), np.nan)
    quat[rotation] = Rotation.from_matrix(matrices[rotation]).as_quat(scalar_first=True)
    return quat, None


def usable_truth(path: Path | str, what: str, held: np.ndarray, good: np.ndarray, detail: str) -> str | None:
    """Whether a truth can be used, from its rows: `held` (N,) bool, the rows holding something;
    `good`, those that are orientations (`detail` says what the others are). None when it can (the bad
    rows, if any, are counted in a warning naming the file: they become gaps); else why not, one line
    starting "no truth" (no row holds anything) or "truth unusable" (most rows that do are not
    orientations, more than `TRUTH_BAD_FRACTION`: a wrong layout or unit)."""
    n_held, n_bad = int(held.sum()), int((held & ~good).sum())
    if n_held == 0:
        return f"no truth: its {what} hold no orientation (every row empty, zero or not finite)"
    if n_bad > TRUTH_BAD_FRACTION * n_held:
        return f"truth unusable: {n_bad} of its {n_held} {what} are {detail} (a wrong layout or unit?)"
    if n_bad:
        warnings.warn(f"{path}: {n_bad} of {n_held} {what} are {detail}; read as truth gaps", stacklevel=3)
    return None


def unit_quaternions(path: Path | str, quat_wxyz: np.ndarray, what: str, tolerance: float) -> np.ndarray | None:
    """(N, 4) quaternions of an estimate (a trajectory file: `fusion.trajectory_files`), rows
    normalised, rows that are not finite NaN; None when no row is finite. Refused when a finite
    row's norm is more than `tolerance` from 1 (a wrong layout or unit); `what` names them in the
    message. (A truth is read row by row instead: `truth_quaternions`.)"""
    with np.errstate(over="ignore"):  # a 1e308 row has an infinite norm: not finite
        norm = np.linalg.norm(quat_wxyz, axis=1)
    ok = np.isfinite(norm)
    if not np.any(ok):
        return None
    if np.any(np.abs(norm[ok] - 1.0) > tolerance):
        raise ValueError(f"{path}: {what} are not unit quaternions")
    out = np.array(quat_wxyz, dtype=float)
    out[ok] /= norm[ok, None]
    out[~ok] = np.nan
    return out


def physical_samples(path: Path | str, t: np.ndarray, gyr_rad_s: np.ndarray, acc_m_s2: np.ndarray,
                     names: tuple[str, ...], gyr_timing: str, *arrays: np.ndarray,
                     mag: tuple[np.ndarray, str] | None = None) -> tuple[Any, ...]:
    """`ImuSamples` from values in physical units, through the shared checks: finite values,
    `check_physical` (`names`: the six gyro and accelerometer columns, for messages),
    `magnetometer_in_ut`, then `repair_time`, which drops the same rows of `arrays` (per-sample
    extras: truth, a mask) and of the magnetometer.

    t: (N,) s; gyr_rad_s: (N, 3) rad/s; acc_m_s2: (N, 3) m/s^2 (returned in g), body frame;
    mag: the magnetometer, `(mag_ut, name)`: (N, 3) uT, body frame, NaN rows where there is no
    sample, and the name of its columns in messages; or None. Returns `(imu, *arrays)`.
    """
    if len(t) < 2:
        raise ValueError(f"{path}: {len(t)} samples; need at least 2")
    if not (np.all(np.isfinite(gyr_rad_s)) and np.all(np.isfinite(acc_m_s2))):
        raise ValueError(f"{path}: the gyro or accelerometer values contain NaN or Inf")
    check_physical(path, gyr_rad_s, acc_m_s2, names[:3], names[3:])
    mag_ut = None
    if mag is not None:
        mag_ut = magnetometer_in_ut(path, *mag)
        t, gyr_rad_s, acc_m_s2, mag_ut, *arrays = repair_time(t, path, gyr_rad_s, acc_m_s2, mag_ut, *arrays)
    else:
        t, gyr_rad_s, acc_m_s2, *arrays = repair_time(t, path, gyr_rad_s, acc_m_s2, *arrays)
    check_gyro_turns_gravity(path, t, gyr_rad_s, acc_m_s2, names[:3], names[3:])
    imu = ImuSamples(t, gyr_rad_s, acc_m_s2 / STANDARD_GRAVITY_M_S2, source=str(path), gyr_timing=gyr_timing,
                     mag_ut=mag_ut)
    return (imu, *arrays)


# The Earth's field is 22-67 uT at the surface (IGRF); a sensor beside iron or a magnet reads more.
MAG_NORM_UT = (5.0, 2000.0)  # plausible median norm of a magnetometer's samples, uT


def magnetometer_in_ut(path: Path | str, mag: np.ndarray, name: str) -> np.ndarray | None:
    """(N, 3) magnetometer samples in uT, infinite rows made NaN (no sample); refused, naming the
    file and the columns, when their median norm says they are in another unit (gauss: 1 G =
    100 uT; tesla; nanotesla) or nothing like a magnetic field. None when no row is finite."""
    mag = np.array(mag, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        norm = np.linalg.norm(mag, axis=1)
    finite = np.isfinite(norm)
    mag[~finite] = np.nan
    if not finite.any():
        return None
    median = float(np.median(norm[finite]))
    if not MAG_NORM_UT[0] <= median <= MAG_NORM_UT[1]:
        hint = ("; in gauss? (1 G = 100 uT)" if 0.05 <= median < MAG_NORM_UT[0] else
                "; in tesla? (1 T = 1e6 uT)" if 1e-7 <= median < 1e-3 else
                "; in nanotesla? (1 uT = 1000 nT)" if 1e4 <= median <= 1e6 else "")
        raise ValueError(f"{path}: the {name} reads {median:.3g} (median norm); it must be in uT (the Earth's field is "
                         f"22-67 uT){hint}")
    return mag


def overlap_problem(truth: Trajectory | None, imu_t: np.ndarray, what: str) -> str | None:
    """Why a truth cannot be scored against the IMU: its time span does not overlap the IMU's
    (`what` says whose, e.g. "the VICON file's"), as a `Recording.truth_problem`; None when it does
    (or there is no truth)."""
    if truth is not None and not (truth.t[0] < imu_t[-1] and imu_t[0] < truth.t[-1]):
        return f"truth unusable: {what} time span ({truth.t[0]:.6g}..{truth.t[-1]:.6g} s) does not overlap the IMU's"
    return None


def seconds_since(sec: np.ndarray, nsec: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
    """Integer time stamps (seconds and nanoseconds, as ROS and nanosecond clocks give them) as
    float64 seconds since `origin` (sec, nsec), subtracted in integers first: converting a unix
    time in ns to float64 seconds would round every stamp to 0.24 us."""
    sec, nsec = np.asarray(sec, np.int64), np.asarray(nsec, np.int64)
    return (sec - origin[0]).astype(float) + (nsec - origin[1]).astype(float) * 1e-9
