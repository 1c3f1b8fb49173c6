"""Your own estimator in the table, by reference, beside ours.

    fusion compare --estimators ./student.py:complementary,ekf --dataset ece276a/1
    fusion compare --estimators ./my_ukf.py:MyUKF:R=1e-3,Q=1e-4 --dataset all
    fusion compare --estimators mypackage.filters:MyFilter --dataset all

A spec names `FILE.py:NAME` (a file anywhere, run as `python FILE.py` would see it: its folder
first on `sys.path`) or `package.module:NAME` (importable), the way pytest, setuptools and
uvicorn name user code; installed packages can also register plain names in the entry-point
group `fusion.estimators` (`fusion list` shows them). NAME is one of two things:

- **a function** `f(t, gyro, acc, q0, **params) -> quat_wxyz` (`function_estimator`):
  t (T,) s; gyro (T, 3) rad/s, body frame, row k the rate over (t[k-1], t[k]] (the recording's
  timing convention is applied before the call, so the step is `q[k] = q[k-1] exp(gyro[k] dt/2)`
  with `dt = t[k] - t[k-1]`; row 0 is never needed: `q[0] = q0`), NaN rows where the toolkit
  knows the gyro is wrong (a freeze; `--dropouts off` passes the raw samples instead); acc
  (T, 3) m/s^2, body frame, reading +9.81 on z at rest with z up; q0 (4,) the orientation at
  t[0], scalar first `[w, x, y, z]`, `R_world_body` (body to world). It returns (T, 4) in the same
  convention. Its keyword parameters with defaults (`gain=0.02`) become parameters on the command
  line (`:gain=0.05`, `fusion ablate --param gain=...`), typed by their annotation or default.
  The arrays are fresh copies: the function may modify them.
- **a class** deriving from `fusion.estimators.Estimator` (parameters as a frozen dataclass
  `Params`, `estimate(imu, init_quat_wxyz) -> Trajectory`), which gets everything ours get.

What it returns is checked (`check_output`): shape, finiteness, unit norm (renormalised with a
warning beyond 1e-6), and, against the truth, the convention slips a first filter most often
makes (`convention_slip`: scalar-last quaternions, world-to-body instead of body-to-world). A
failure is a row of its own (`fusion.evaluation.run.job.run_job`): one line naming the estimator
and the recording, the other rows computed as usual.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import sys
import traceback
import typing
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fusion.types import STANDARD_GRAVITY_M_S2, ImuSamples, Trajectory

from ..base import Estimator

ENTRY_POINT_GROUP = "fusion.estimators"
NORM_TOLERANCE = 1e-6  # |q| further from 1 than this is renormalised, with a warning


def is_reference(name: str) -> bool:
    """Whether a spec's name refers to user code (`FILE.py:NAME`, `module:NAME`) rather than
    a registered name."""
    return ":" in name


@dataclasses.dataclass(frozen=True)
class Origin:
    """Where a user's estimator comes from: `kind` "file", "module", "entry point" or "trajectory"
    (a trajectory file or folder another program wrote: `fusion.estimators.adapters.trajectory_file`);
    `where` the file's absolute path, the module's name, or the entry point's `module:attr` and
    package; `sha256` of the file (None for modules and folders); `source` the file's bytes (sent
    to Dask workers, which need not see the file)."""

    kind: str
    where: str
    attribute: str
    sha256: str | None = None
    source: bytes | None = dataclasses.field(default=None, repr=False)

    def describe(self) -> dict[str, Any]:
        out = {"kind": self.kind, "where": self.where, "attribute": self.attribute}
        if self.sha256:
            out["sha256"] = self.sha256
        return out


def load_reference(name: str, file: tuple[str, bytes] | None = None) -> tuple[Any, Origin]:
    """The object `FILE.py:NAME` or `module:NAME` names, and its `Origin`; ValueError (one line)
    when the file, module or attribute cannot be had. file: the file's (absolute path, contents)
    when they were read elsewhere (by the process that resolved the spec first)."""
    target, _, attribute = name.rpartition(":")
    if not target or not attribute.isidentifier():
        raise ValueError(f"estimator {name!r}: expected FILE.py:NAME or package.module:NAME")
    if file is not None or target.endswith(".py") or "/" in target or "\\" in target:
        if file is not None:
            path, source = Path(file[0]), file[1]
        else:
            path = Path(target).expanduser().resolve()
            if not path.is_file():
                raise FileNotFoundError(f"{target}: no such file (estimator {name!r})")
            source = path.read_bytes()
        module = load_source(path, source)
        origin = Origin("file", str(path), attribute, hashlib.sha256(source).hexdigest(), source)
    else:
        try:
            module = importlib.import_module(target)
        except ImportError as exc:
            raise ValueError(f"estimator {name!r}: cannot import {target!r} ({exc}); give a file as "
                             f"./{target.replace('.', '/')}.py:{attribute}, or install the package") from None
        origin = Origin("module", target, attribute)
    return _attribute(module, attribute, name), origin


def load_source(path: Path, source: bytes) -> Any:
    """A user's file as a module (once per file and content: its name carries their sha256, so that
    the same code in two folders is two modules, each reporting its own file), with its folder
    first on `sys.path`, as `python FILE.py` would have it, so it can import files beside it."""
    digest = hashlib.sha256(str(path).encode() + b"\0" + source).hexdigest()[:16]
    module_name = f"fusion_user_{_identifier(path.stem)}_{digest}"
    if module_name in sys.modules:
        return sys.modules[module_name]
    folder = str(path.parent)
    if folder not in sys.path:
        sys.path.insert(0, folder)
    spec = importlib.util.spec_from_loader(module_name, loader=None, origin=str(path))
    module = importlib.util.module_from_spec(spec)
    module.__file__ = str(path)
    sys.modules[module_name] = module  # before running it: dataclasses and pickling look it up
    try:
        exec(compile(source, str(path), "exec"), module.__dict__)
    except BaseException as exc:
        del sys.modules[module_name]
        if isinstance(exc, KeyboardInterrupt):  # Ctrl-C while the file ran: the user stops the command
            raise
        if isinstance(exc, SystemExit):  # a script's own `sys.exit(main())`, run on import
            raise ValueError(f"{path}: running it called sys.exit({exc.code!r}); put the script's own code under "
                             "`if __name__ == \"__main__\":` so that importing it only defines the estimator") from None
        raise ValueError(f"{path}: running it raised {type(exc).__name__}: {' '.join(str(exc).split())[:300]}") from None
    return module


def failure_site(exc: BaseException, origin: Origin | None) -> tuple[str | None, str | None]:
    """Where a user's code raised `exc`: (`"my.py:12 in estimate"`, the innermost frame of the
    user's code, or None when none of its frames is the user's), and the traceback of the
    user's frames only, innermost last, with the exception's own line (None without).

    The user's frames: for a file, the file itself (loaded as a `fusion_user_*` module) and files
    beside it that it imports (not installed packages, not this toolkit); for a module or an
    entry point, the modules of its top-level package."""
    if origin is None or origin.kind not in ("file", "module", "entry point"):
        return None, None
    frames = [traceback.FrameSummary(frame.f_code.co_filename, lineno, frame.f_code.co_name)
              for frame, lineno in traceback.walk_tb(exc.__traceback__) if _users(frame, origin)]
    if not frames:
        return None, None
    last = frames[-1]
    text = ("Traceback (the estimator's own code, innermost last):\n" + "".join(traceback.format_list(frames))
            + "".join(traceback.format_exception_only(type(exc), exc)))
    return f"{_shown_path(last.filename)}:{last.lineno} in {last.name}", text.rstrip("\n")


def _users(frame: Any, origin: Origin) -> bool:
    """Whether a frame runs the user's code (`failure_site`)."""
    module = str(frame.f_globals.get("__name__", ""))
    if origin.kind != "file":  # a module or an entry point: its top-level package's modules
        top = origin.where.split(":")[0].split()[0].split(".")[0]
        return module == top or module.startswith(top + ".")
    if module.startswith("fusion_user_"):
        return True
    top = module.split(".")[0]
    if top in ("fusion", "numpy", "scipy") or top in sys.stdlib_module_names:
        return False
    path = Path(frame.f_code.co_filename)
    if any(part in ("site-packages", "dist-packages") for part in path.parts):
        return False
    return path.parent == Path(origin.where).parent or Path(origin.where).parent in path.parents


def _shown_path(filename: str) -> str:
    """A path as the user typed it: relative to the working folder when inside it."""
    try:
        return str(Path(filename).resolve().relative_to(Path.cwd()))
    except (ValueError, OSError):
        return filename


def _identifier(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text) or "file"


def _attribute(module: Any, attribute: str, name: str) -> Any:
    try:
        return getattr(module, attribute)
    except AttributeError:
        public = sorted(k for k, v in vars(module).items() if not k.startswith("_") and callable(v)
                        and getattr(v, "__module__", None) == module.__name__)
        raise ValueError(f"estimator {name!r}: {getattr(module, '__file__', module.__name__)} has no {attribute!r} "
                         f"(it defines: {', '.join(public) or 'no functions or classes'})") from None


def entry_points() -> dict[str, importlib.metadata.EntryPoint]:
    """The estimators installed packages register in the entry-point group `fusion.estimators`."""
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def load_entry_point(ep: importlib.metadata.EntryPoint) -> tuple[Any, Origin]:
    try:
        obj = ep.load()
    except Exception as exc:  # an installed package's import error: one line naming it
        raise ValueError(f"estimator {ep.name!r} (entry point {ep.value} of {_package(ep)}): cannot load it "
                         f"({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") from None
    return obj, Origin("entry point", f"{ep.value} ({_package(ep)})", ep.attr or "")


def _package(ep: importlib.metadata.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return f"{dist.name} {dist.version}" if dist is not None else "an installed package"


def estimator_class(obj: Any, name: str) -> type[Estimator]:
    """The `Estimator` class for what a reference names: the class itself, or a function wrapped
    by `function_estimator`."""
    if isinstance(obj, type) and issubclass(obj, Estimator):
        if inspect.isabstract(obj):
            raise ValueError(f"estimator {name!r}: {obj.__name__} does not implement estimate(imu, init_quat_wxyz)")
        return obj
    if isinstance(obj, type):
        raise ValueError(f"estimator {name!r}: the class {obj.__name__} does not derive from "
                         "fusion.estimators.Estimator; give a function f(t, gyro, acc, q0) instead, or derive from it")
    if callable(obj):
        return function_estimator(obj, name)
    raise ValueError(f"estimator {name!r}: {type(obj).__name__} is neither a function f(t, gyro, acc, q0) nor an "
                     "Estimator class")


# --------------------------------------------------------------------------- the function contract

_TEXT_TYPES = (bool, int, float, str)


class FunctionEstimator(Estimator):
    """A user's function `f(t, gyro, acc, q0, **params)` behind the `Estimator` interface (module
    docstring). Subclasses made by `function_estimator` set `function` and `Params`."""

    function: Callable[..., Any]

    def estimate(self, imu: ImuSamples, init_quat_wxyz: np.ndarray) -> Trajectory:
        t, gyro, acc, q0 = function_inputs(imu, init_quat_wxyz)
        params = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        nan_gyro = ~np.all(np.isfinite(gyro), axis=1)  # before the call: the function may modify its arrays
        out = type(self).function(t, gyro, acc, q0, **params)
        return Trajectory(imu.t, check_output(out, len(imu), nan_gyro_rows=nan_gyro))


def function_inputs(imu: ImuSamples, init_quat_wxyz: np.ndarray) -> tuple[np.ndarray, ...]:
    """(t, gyro, acc, q0) as the function contract gives them (module docstring): fresh arrays."""
    rates, valid = imu.interval_rates()
    gyro = np.empty((len(imu), 3))
    gyro[1:] = np.where(valid[:, None], rates, np.nan)
    first_valid = imu.gyr_valid[0] if imu.gyr_timing == "end" else (valid[0] if len(valid) else True)
    first = imu.gyr_rad_s[0] if imu.gyr_timing == "end" else (rates[0] if len(rates) else imu.gyr_rad_s[0])
    gyro[0] = first if first_valid else np.nan
    return (np.array(imu.t), gyro, np.asarray(imu.acc_g) * STANDARD_GRAVITY_M_S2,
            np.array(init_quat_wxyz, dtype=float))


def function_estimator(fn: Callable[..., Any], name: str) -> type[FunctionEstimator]:
    """An `Estimator` class for `fn(t, gyro, acc, q0, **params)`: its parameters after the first
    four, each with a default, become the fields of its `Params` dataclass (`params_dataclass`)."""
    params = params_dataclass(fn, ("t", "gyro", "acc", "q0"), name)
    title = params.__name__.removesuffix("Params")
    return type(title, (FunctionEstimator,), {"Params": params, "function": staticmethod(fn),
                                              "__module__": getattr(fn, "__module__", __name__),
                                              "__doc__": fn.__doc__})


def params_dataclass(fn: Callable[..., Any], leading: tuple[str, ...], name: str) -> type:
    """A frozen dataclass of `fn`'s parameters after the `leading` positional ones: each needs a
    default, and is typed by its annotation (bool, int, float or str) or else its default's type,
    so that `fusion.estimators.params.make_params` sets it from command-line text."""
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        raise ValueError(f"estimator {name!r}: cannot read the signature of {fn!r}") from None
    parameters = list(signature.parameters.values())
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(positional) < len(leading) and not any(p.kind is p.VAR_POSITIONAL for p in parameters):
        raise ValueError(f"estimator {name!r}: {getattr(fn, '__name__', fn)}{signature} must take "
                         f"({', '.join(leading)}) first")
    try:
        hints = typing.get_type_hints(fn)
    except Exception:  # unresolvable annotations: fall back to the defaults' types
        hints = {}
    fields = []
    for p in parameters[len(leading):]:
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        if p.default is p.empty:
            raise ValueError(f"estimator {name!r}: parameter {p.name!r} needs a default value (parameters after "
                             f"({', '.join(leading)}) are set from the command line, e.g. :{p.name}=...)")
        kind = hints.get(p.name, type(p.default))
        if kind not in _TEXT_TYPES:
            kind = type(p.default) if type(p.default) in _TEXT_TYPES else Any
        fields.append((p.name, kind, dataclasses.field(default=p.default)))
    title = _identifier(getattr(fn, "__name__", "function")).title().replace("_", "")
    params = dataclasses.make_dataclass(f"{title}Params", fields, frozen=True)
    params.__module__ = getattr(fn, "__module__", __name__)
    return params


def check_output(out: Any, n: int, nan_gyro_rows: np.ndarray | None = None) -> np.ndarray:
    """A user's (n, 4) scalar-first quaternions as a float64 array, renormalised (with a warning)
    where a norm is further than `NORM_TOLERANCE` from 1; ValueError for anything else, saying
    what was returned and what was expected (the caller names the estimator and the recording).
    nan_gyro_rows: (n,) bool, the gyro rows passed as NaN (samples the toolkit marked invalid), or
        None. Non-finite output whose first bad row is one of them (the NaN went into the
        filter) gets a hint to skip them; non-finite output that starts elsewhere does not."""
    try:
        quat = np.asarray(out, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"returned {type(out).__name__}, not an (N, 4) array of quaternions") from None
    if quat.shape != (n, 4):
        hint = ("transposed? return (N, 4), one row per sample" if quat.shape == (4, n) else
                "one row short: row 0 is q0" if quat.shape == (n - 1, 4) else
                "return (N, 4) scalar-first quaternions, one row per sample")
        raise ValueError(f"returned shape {quat.shape} for {n} samples ({hint})")
    finite = np.all(np.isfinite(quat), axis=1)
    if not finite.all():
        first = int(np.argmin(finite))
        nan_gyro = np.zeros(n, bool) if nan_gyro_rows is None else np.asarray(nan_gyro_rows, bool)
        # the NaN went in there: that row's gyro, or the one before it (a filter that lags a sample)
        fed = nan_gyro.shape == (n,) and bool(nan_gyro[max(first - 1, 0):first + 1].any())
        hint = (f"; the gyro there is NaN, one of {int(nan_gyro.sum())} samples the toolkit marked invalid (a "
                "freeze): skip them in your filter, or pass the raw samples with --dropouts off" if fed else "")
        raise ValueError(f"returned {int((~finite).sum())} non-finite rows (the first at row "
                         f"{first}){hint}")
    norm = np.linalg.norm(quat, axis=1)
    if np.min(norm) < 1e-6:
        raise ValueError(f"returned a zero quaternion at row {int(np.argmin(norm))}")
    worst = float(np.max(np.abs(norm - 1.0)))
    if worst > NORM_TOLERANCE:
        warnings.warn(f"quaternion norms differ from 1 by up to {worst:.2g}; renormalised",
                      stacklevel=2)
        quat = quat / norm[:, None]
    return quat


# Convention slips: what the returned quaternions would be if the estimator meant them otherwise.
SLIPS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "scalar-last [x, y, z, w]": lambda q: q[:, [3, 0, 1, 2]],
    "world-to-body (the inverse)": lambda q: q * np.array([1.0, -1.0, -1.0, -1.0]),
    "scalar-last and world-to-body": lambda q: q[:, [3, 0, 1, 2]] * np.array([1.0, -1.0, -1.0, -1.0]),
}
SLIP_MIN_ERROR_DEG = 20.0  # only an estimate this far off is checked for a slip
SLIP_RATIO = 0.3  # a slip's reading must be at least this much better, and by SLIP_MIN_GAIN_DEG
SLIP_MIN_GAIN_DEG = 15.0


def convention_slip(rmse_total_deg: float, rescore: Callable[[np.ndarray], float], quat_wxyz: np.ndarray) -> str | None:
    """The convention slip that explains a poor estimate, or None: when the estimate is off by
    more than `SLIP_MIN_ERROR_DEG` (RMSE, total) and reading its quaternions another way
    (`SLIPS`) scores far better (below `SLIP_RATIO` of it and at least `SLIP_MIN_GAIN_DEG`
    better). rescore: the total RMSE, deg, of other quaternions on the same recording."""
    if not rmse_total_deg > SLIP_MIN_ERROR_DEG:
        return None
    scores = {slip: rescore(read(quat_wxyz)) for slip, read in SLIPS.items()}
    slip, best = min(scores.items(), key=lambda item: item[1])
    if best < SLIP_RATIO * rmse_total_deg and best < rmse_total_deg - SLIP_MIN_GAIN_DEG:
        return (f"its orientations score {rmse_total_deg:.1f} deg RMSE as returned but {best:.1f} deg read as {slip}: "
                "return scalar-first [w, x, y, z] quaternions of R_world_body (body to world)")
    return None
