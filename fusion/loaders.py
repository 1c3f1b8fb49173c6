"""Readers for every file format of the course recordings, and a generic CSV.

Each loader turns one file layout into the canonical types of `fusion.types` and nothing
else: IMU files become `RawImu` (native ADC counts, order ax ay az wx wy wz, no sign flip)
or, for files in physical units, `ImuSamples`; VICON files become a `Trajectory`. Raw layouts
(`7 x T`, `6 x T`, `3 x 3 x K`) are converted here and nowhere else.

Formats (see `../shared/data/README.md`):
- ECE276A `imuRawN.p`: float 7 x T; row 0 unix time, rows 1-6 ax ay az wx wy wz, with ax and
  ay already negated by the course (`-raw`); undone here so all formats give the same counts.
- ECE276A-2018 `imuRawN.p`: dict `vals` uint16 6 x T (ax ay az wz wx wy, not negated), `ts` 1 x T.
- ESE650 `imuRawN.mat`: `vals` 6 x T (ax ay az wz wx wy, not negated), `ts` 1 x T.
- VICON `viconRotN.p` / `.mat`: `rots` 3 x 3 x K (world <- body), `ts` 1 x K.
- Generic CSV (`load_csv`): a header line and columns `t` (s), `gx gy gz` (rad/s),
  `ax ay az` (m/s^2), optionally `qw qx qy qz` (ground truth `R_world_body`). Gyro timing
  "end": the gyro values on row k are the rate over (t[k-1], t[k]], as VQF, Madgwick, Mahony,
  Fusion and BROAD take them.

Gyro timing of the course files (`ImuSamples.gyr_timing`): "start", gyro sample k is the rate
over [t[k], t[k+1]) (gyro k, then accelerometer k + 1). Evidence on ece276a 1-9
(`python benchmarks/timing_evidence.py`), ambiguous at the level of the scores:
- Gyro against accelerometer on the IMU's own clock (gravity in the body frame turns as
  `-w x a`): gyro sample k matches the accelerometer's turn rate at t[k] + 9.2 ms (pooled;
  +2 to +14 ms, all nine positive). A mean over [t[k], t[k+1]] predicts +5 ms, over
  (t[k-1], t[k]] -5 ms (the method gives +5.6 / -4.4 ms on `fusion.sim`): "start" fits.
- Against VICON the pairing is not identifiable by itself: a one-sample gyro shift equals a
  VICON clock shift. With each pairing's own measured clock offset (VICON lags by -5..+21 ms
  with "start", +5..+31 ms with "end"), mean RMSEs differ by at most 0.16 deg: dr 11.68 vs
  11.67 total, gn inclination 1.47 vs 1.49, ekf 1.91 vs 1.86, vqf 4.41 vs 4.34 ("start" vs
  "end"). The filters lean slightly to "end", by less than their recording-to-recording spread.

Pickles can run code when loaded: only open pickle files you trust. As a guard, pickles are
read with a restricted unpickler that only builds numpy arrays and plain containers and
refuses any other class.

Every problem raises `ValueError` (or `FileNotFoundError`) naming the file, in one line
(exception texts from pickle/SciPy are folded onto that line). `tests/test_fuzz_loaders.py`
feeds thousands of broken files through every loader and the CLI to keep it so.

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

Values: NaN or Inf IMU values are rejected (VICON NaN matrices are tracking gaps and kept);
complex, string, object or structured arrays are rejected; VICON matrices must be proper
rotations (orthonormal, determinant +1). MATLAB files are read in a forked child process
(`read_isolated`): a corrupt file can crash SciPy's C reader, and a crash must stay an error.
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

from .types import STANDARD_GRAVITY_M_S2, ImuSamples, RawImu, Trajectory

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

# Physical plausibility of files in physical units (CSV, BROAD): see `check_physical`.
GYRO_LIMIT_RAD_S = 70.0  # 4000 deg/s: the widest range of common MEMS gyros
GYRO_MEDIAN_WARN_RAD_S = 10.0  # median |rate| over a recording (hand-held ~0.3-1 rad/s; BROAD up to 5.3)
ACC_LIMIT_M_S2 = 200 * STANDARD_GRAVITY_M_S2  # 200 g: high-g MEMS accelerometers (ADXL375); BROAD's tapping peaks at 16 g

# Canonical channel order ax ay az wx wy wz from the (ax ay az wz wx wy) layout of the
# .mat and 2018 files.
_FROM_AZ_WZ_WX_WY = [0, 1, 2, 4, 5, 3]


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


def _one_line(exc: BaseException, limit: int = 200) -> str:
    """`Type: message` of an exception on one line, shortened (SciPy messages can hold matrices)."""
    text = " ".join(str(exc).split())
    text = text if len(text) <= limit else text[: limit - 3] + "..."
    return f"{type(exc).__name__}: {text}"


def read_pickle(path: Path, kind: str = "pickle", max_values: int = MAX_VALUES) -> Any:
    """The object of a pickle file, built by the restricted unpickler (numpy arrays and plain
    containers only: a pickle cannot run code here) and checked by `check_structure` with
    `max_values`. Any failure is one ValueError naming the file; `kind` names the format."""
    _check_file(path)
    try:
        with open(path, "rb") as f:  # streamed: a camera pickle is hundreds of MB
            obj = _RestrictedUnpickler(f, encoding="latin1").load()
    except Exception as exc:  # pickle raises many types for corrupt input; report them all in one line
        raise ValueError(f"{path}: not a readable {kind} ({_one_line(exc)})") from None
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

    _check_file(path)
    return read_isolated(path, partial(_loadmat, kind=kind, variable_names=variable_names, v73=v73,
                                       max_values=max_values, max_bytes=max_bytes), kind)


def read_isolated(path: Path, reader: Callable[[Path], dict[str, Any]], kind: str) -> dict[str, np.ndarray]:
    """`reader(path)`'s arrays: numeric ones as they are, anything else as an empty object
    array (which `_numeric` rejects). `reader` raises `ValueError` (or `ImportError`) for files
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
        raise ValueError(f"{path}: not a readable {kind} file ({_one_line(exc)})") from None
    except Exception as exc:  # scipy raises ValueError, TypeError, OSError... for broken files
        raise ValueError(f"{path}: not a readable {kind} file ({_one_line(exc)})") from None


def _check_file(path: Path) -> None:
    """A clear error for a missing or empty file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: file is empty")


def _read_bytes(path: Path) -> bytes:
    _check_file(path)
    return path.read_bytes()


def _field(obj: Any, key: str, path: Path) -> np.ndarray:
    if not isinstance(obj, dict) or key not in obj:
        have = (sorted((k for k in obj if not str(k).startswith("__")), key=str) if isinstance(obj, dict)
                else type(obj).__name__)  # key=str: keys of mixed types do not compare
        raise ValueError(f"{path}: expected a field {key!r}, found {have}")
    return _numeric(obj[key], path, key)


def _numeric(value: Any, path: Path, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise ValueError(f"{path}: {what} is not a numeric array ({_one_line(exc)})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ValueError(f"{path}: {what} is not numeric (dtype {arr.dtype})")
    if np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{path}: {what} is complex (dtype {arr.dtype}); expected real numbers")
    return arr.astype(float)


def _time_row(ts: np.ndarray, n: int, path: Path) -> np.ndarray:
    t = np.ravel(ts)
    if len(t) != n:
        raise ValueError(f"{path}: {len(t)} time stamps for {n} samples")
    return t


def repair_time(t: np.ndarray, path: Path | str, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Keep the samples whose stamp is finite and later than every earlier kept stamp.

    Returns `(t, *arrays)` restricted to those samples; warns with the count it dropped.
    Raises if fewer than half the samples (or fewer than 2) survive.
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


def check_physical(path: Path | str, gyr_rad_s: np.ndarray, acc_m_s2: np.ndarray, gyr_names: tuple[str, ...],
                   acc_names: tuple[str, ...]) -> None:
    """Plausibility of IMU values in physical units (finite (N, 3) arrays; names for messages).

    Errors: a gyro value beyond `GYRO_LIMIT_RAD_S` (4000 deg/s; deg/s or scaled values, e.g.
    x1e6, end up here) or an accelerometer value beyond `ACC_LIMIT_M_S2` (200 g; 1e308 too).
    Warning: a median |rate| above `GYRO_MEDIAN_WARN_RAD_S` (likely deg/s of a slow motion).
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
    median = float(np.median(np.sqrt(np.sum(gyr_rad_s**2, axis=1))))
    if median > GYRO_MEDIAN_WARN_RAD_S:
        warnings.warn(f"{path}: columns {','.join(gyr_names)}: the median angular rate is {median:.3g} rad/s "
                      f"({np.degrees(median):.0f} deg/s) over the whole recording, implausible for hand-held motion; "
                      "if they are in deg/s, convert them to rad/s (multiply by pi/180)", stacklevel=3)


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


def _raw_imu(t: np.ndarray, counts: np.ndarray, path: Path) -> RawImu:
    if counts.ndim != 2 or counts.shape[1] != 6:
        raise ValueError(f"{path}: IMU values must be a 6 x T array, got shape {counts.shape[::-1]}")
    if counts.shape[0] < 2:
        raise ValueError(f"{path}: {counts.shape[0]} IMU samples; need at least 2")
    if not np.all(np.isfinite(counts)):
        raise ValueError(f"{path}: IMU values contain NaN or Inf")
    if np.abs(counts).max() > ADC_LIMIT_COUNTS:
        raise ValueError(f"{path}: IMU values up to {np.abs(counts).max():.3g} are not ADC counts (|value| <= {ADC_LIMIT_COUNTS})")
    t, counts = repair_time(t, path, counts)
    return RawImu(t, counts, source=str(path), gyr_timing="start")  # the evidence: see the module docstring


def load_imu_pickle(path: str | Path) -> RawImu:
    """ECE276A `imuRawN.p`, either release (7 x T array, or the 2018 dict `vals`/`ts`)."""
    path = Path(path)
    obj = read_pickle(path)
    if isinstance(obj, dict):  # 2018 release: same layout as the .mat files
        vals = _field(obj, "vals", path)
        if vals.ndim != 2 or vals.shape[0] != 6:
            raise ValueError(f"{path}: 'vals' must be 6 x T, got shape {vals.shape}")
        return _raw_imu(_time_row(_field(obj, "ts", path), vals.shape[1], path), vals[_FROM_AZ_WZ_WX_WY].T, path)
    if not isinstance(obj, np.ndarray):
        raise ValueError(f"{path}: expected a 7 x T array or a dict with 'vals' and 'ts', found {type(obj).__name__}")
    arr = _numeric(obj, path, "the array")
    if arr.ndim != 2 or arr.shape[0] != 7:
        raise ValueError(f"{path}: expected a 7 x T array (time + 6 channels), got shape {arr.shape}")
    counts = arr[1:].T.copy()
    counts[:, :2] *= -1.0  # this release negated ax and ay; back to native counts
    return _raw_imu(arr[0], counts, path)


def load_imu_mat(path: str | Path) -> RawImu:
    """ESE650 `imuRawN.mat`: `vals` 6 x T (ax ay az wz wx wy), `ts` 1 x T."""
    path = Path(path)
    mat = read_mat(path)
    vals = _field(mat, "vals", path)
    if vals.ndim != 2 or vals.shape[0] != 6:
        raise ValueError(f"{path}: 'vals' must be 6 x T, got shape {vals.shape}")
    return _raw_imu(_time_row(_field(mat, "ts", path), vals.shape[1], path), vals[_FROM_AZ_WZ_WX_WY].T, path)


def load_vicon(path: str | Path) -> Trajectory:
    """VICON `viconRotN.p` or `.mat`: `rots` 3 x 3 x K (world <- body), `ts` 1 x K.

    Rows with NaN matrices (tracking gaps) stay NaN in the trajectory; scoring skips them.
    """
    path = Path(path)
    obj = read_mat(path) if path.suffix == ".mat" else read_pickle(path)
    rots = _field(obj, "rots", path)
    if rots.ndim != 3 or rots.shape[:2] != (3, 3):
        raise ValueError(f"{path}: 'rots' must be 3 x 3 x K, got shape {rots.shape}")
    t = _time_row(_field(obj, "ts", path), rots.shape[2], path)
    matrices = np.moveaxis(rots, 2, 0)  # (K, 3, 3)
    t, matrices = repair_time(t, path, matrices)
    return Trajectory(t, matrices_to_quat(matrices, path))


def matrices_to_quat(matrices: np.ndarray, path: Path | str) -> np.ndarray:
    """(K, 3, 3) rotation matrices -> (K, 4) wxyz; non-finite rows stay NaN.

    Rejects matrices that are far from orthonormal (a wrong layout would be).
    """
    from scipy.spatial.transform import Rotation

    quat = np.full((len(matrices), 4), np.nan)
    good = np.all(np.isfinite(matrices), axis=(1, 2))
    if not np.any(good):
        raise ValueError(f"{path}: no finite rotation matrix")
    m = matrices[good]
    err = np.abs(np.einsum("kij,kil->kjl", m, m) - np.eye(3)).max()
    if err > 1e-2:
        raise ValueError(f"{path}: 'rots' are not rotation matrices (|R^T R - I| up to {err:.3g})")
    if np.any(np.linalg.det(m) < 0):
        raise ValueError(f"{path}: 'rots' hold reflections (determinant -1), not rotation matrices")
    quat[good] = Rotation.from_matrix(m).as_quat(scalar_first=True)
    return quat


CSV_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")
CSV_TRUTH = ("qw", "qx", "qy", "qz")


def load_csv(path: str | Path, with_movement: bool = False):
    """Generic CSV in physical units: header `t,gx,gy,gz,ax,ay,az[,qw,qx,qy,qz][,movement]`.

    t in s, gyro in rad/s, accelerometer in m/s^2 (converted to g), all body frame; gyro
    row k is the angular rate over (t[k-1], t[k]] (`ImuSamples.gyr_timing` "end", the common
    convention of IMU drivers and of VQF, Madgwick, Mahony and Fusion; a file whose gyro
    rows cover [t[k], t[k+1]) instead can be loaded and then declared with
    `imu.replace(gyr_timing="start")`); the
    optional quaternion is the ground truth `R_world_body`, scalar first (NaN rows = no truth);
    the optional `movement` column (0/1) marks the samples a BROAD-style score uses.
    Returns `(imu, truth)`, or `(imu, truth, movement)` with `with_movement` (movement None
    without the column).
    """
    path = Path(path)
    text = _read_bytes(path).decode("utf-8-sig", errors="replace").splitlines()  # -sig: drop a BOM
    header = [h.strip().strip("\"'").strip().lower() for h in text[0].split(",")]
    repeated = sorted({h for h in header if header.count(h) > 1 and h})
    if repeated:
        raise ValueError(f"{path}: the header names column {', '.join(repr(h) for h in repeated)} more than once")
    if len(text) - 1 > MAX_SAMPLES:
        raise ValueError(f"{path}: {len(text) - 1} rows, more than the {MAX_SAMPLES:.3g} samples of any recording")
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"{path}: missing CSV columns {', '.join(missing)} (need {','.join(CSV_COLUMNS)}[,{','.join(CSV_TRUTH)}])")
    if not any(line.strip() for line in text[1:]):
        raise ValueError(f"{path}: no data rows after the header")
    try:
        table = np.loadtxt(text[1:], delimiter=",", ndmin=2)
    except ValueError as exc:
        raise ValueError(f"{path}: unreadable CSV row ({exc})") from None
    if table.shape[0] < 2 or table.shape[1] != len(header):
        raise ValueError(f"{path}: need at least 2 rows of {len(header)} columns, got shape {table.shape}")
    col = {name: table[:, i] for i, name in enumerate(header)}
    gyr = np.column_stack([col[c] for c in ("gx", "gy", "gz")])
    acc = np.column_stack([col[c] for c in ("ax", "ay", "az")])
    if not (np.all(np.isfinite(gyr)) and np.all(np.isfinite(acc))):
        raise ValueError(f"{path}: gyro or accelerometer columns contain NaN or Inf")
    check_physical(path, gyr, acc, ("gx", "gy", "gz"), ("ax", "ay", "az"))
    acc = acc / STANDARD_GRAVITY_M_S2  # CSV files are in m/s^2
    has_truth = all(c in header for c in CSV_TRUTH)
    quat = np.column_stack([col[c] for c in CSV_TRUTH]) if has_truth else np.zeros((len(gyr), 4))
    movement = col["movement"] != 0 if "movement" in col else np.ones(len(gyr), bool)
    t, gyr, acc, quat, movement = repair_time(col["t"], path, gyr, acc, quat, movement)
    imu = ImuSamples(t, gyr, acc, source=str(path), gyr_timing="end")  # the common convention
    extra = (movement if "movement" in col else None,) if with_movement else ()
    if not has_truth:
        return (imu, None, *extra)
    with np.errstate(over="ignore"):  # a 1e308 row has an infinite norm: not finite, so not truth
        norm = np.linalg.norm(quat, axis=1)
    ok = np.isfinite(norm)
    if not np.any(ok):
        warnings.warn(f"{path}: the truth columns hold no finite quaternion; loaded without ground truth", stacklevel=2)
        return (imu, None, *extra)
    if np.any(np.abs(norm[ok] - 1.0) > 1e-3):
        raise ValueError(f"{path}: truth quaternions (qw,qx,qy,qz) are not unit quaternions")
    quat[ok] /= norm[ok, None]
    return (imu, Trajectory(t, quat), *extra)
