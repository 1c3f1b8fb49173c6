"""Gyro scale factors (and clock offsets) fitted against VICON: the library behind `fusion calibrate`.

Model, per axis i (body frame; the IMU axes coincide with VICON's, see the data README):

    omega_vicon_i(t) = s_i * omega_nominal_i(t) + b_i

`omega_nominal` is the gyro calibrated with the board's current scale factors (the nominal
datasheet scale unless a calibration is already applied), `omega_vicon` the body rate from
consecutive VICON rotations (`fusion.checks.vicon_body_rate`, on the regular VICON time base),
moved onto the IMU clock by the recording's measured clock offset and interpolated to the
midpoints of the IMU intervals (each gyro reading is the rate over one interval,
`ImuSamples.interval_rates`). Both are smoothed alike (a short moving average) so that the VICON differentiation noise
and the 10 ms difference quotient see the same bandwidth. Samples used: gyro valid (no freeze,
no saturation), VICON valid on both sides. The fit pools all samples of the given recordings
(ordinary least squares with an intercept per axis, which absorbs a residual bias); the fitted
factor is `s_i` times the current factor. A full 3 x 3 matrix is fitted as well and reported
(its off-diagonal terms measure the axis misalignment), not applied: `BoardModel` has
per-axis factors only.

The calibration file (JSON, `FORMAT`, version 1) is documented in the README.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .calibration import BoardModel, Calibration
from .checks import _interp_valid, _moving_average, clock_offset, to_jsonable, vicon_body_rate
from .types import Recording

FORMAT = "fusion-gyro-calibration"
VERSION = 1


@dataclass(frozen=True)
class FitData:
    """One recording's paired samples: (M, 3) gyro rate at the current scale and VICON rate, rad/s."""

    id: str
    gyro_rad_s: np.ndarray
    vicon_rad_s: np.ndarray
    current_factor: tuple[float, float, float]
    clock_offset_s: float


@dataclass(frozen=True)
class GyroFit:
    gyro_scale_factor: tuple[float, float, float]  # multiplies the nominal rad/s per count
    gyro_bias_rad_s: tuple[float, float, float]  # intercept of the fit (residual bias)
    gyro_matrix: list[list[float]]  # full 3 x 3 fit (reported, not applied)
    misalignment_deg: tuple[float, float, float]  # antisymmetric part of the normalised matrix
    residual_rms_deg_s: float
    samples: int
    fitted_on: list[str]
    clock_offset_s: dict[str, float] = field(default_factory=dict)

    @property
    def sensitivity_ratio(self) -> tuple[float, float, float]:
        """True / nominal gyro sensitivity (on the course board about +9 %, +4-6 %, -3-4 %)."""
        return tuple(1.0 / s for s in self.gyro_scale_factor)


def fit_data(recording: Recording, smooth_s: float = 0.03, offset_s: float | None = None) -> FitData:
    """The paired samples of one recording (needs ground truth)."""
    if recording.truth is None:
        raise ValueError(f"{recording.id}: calibration against VICON needs ground truth, and this recording has none")
    imu = recording.imu
    if offset_s is None:
        clock = clock_offset(imu, recording.truth)
        if clock is None:
            raise ValueError(f"{recording.id}: IMU and VICON overlap too little to measure the clock offset")
        offset_s = clock.offset_s
    t_mid, omega_v = vicon_body_rate(recording.truth)
    gyr, valid = imu.interval_rates()  # each interval's reading, paired with VICON at the interval's midpoint
    vic = _interp_valid(0.5 * (imu.t[1:] + imu.t[:-1]), t_mid - offset_s, omega_v)  # onto the IMU clock
    gyr[~valid] = np.nan
    k = max(1, int(round(smooth_s / np.median(imu.dt))))
    gyr = np.column_stack([_moving_average(gyr[:, i], k) for i in range(3)])
    vic = np.column_stack([_moving_average(vic[:, i], k) for i in range(3)])
    ok = np.all(np.isfinite(gyr), axis=1) & np.all(np.isfinite(vic), axis=1)
    board = recording.calibration.board if recording.calibration is not None else BoardModel()
    return FitData(recording.id, gyr[ok], vic[ok], tuple(board.gyro_scale_factor), float(offset_s))


def fit(data: Iterable[FitData]) -> GyroFit:
    """Pooled least squares over the recordings' paired samples (see the module docstring)."""
    data = list(data)
    if not data:
        raise ValueError("no recording with ground truth to fit the gyro scales on")
    factors = {d.current_factor for d in data}
    if len(factors) > 1:
        raise ValueError(f"recordings calibrated with different gyro scale factors {sorted(factors)}: fit them separately")
    g = np.concatenate([d.gyro_rad_s for d in data])
    v = np.concatenate([d.vicon_rad_s for d in data])
    if len(g) < 100:
        raise ValueError(f"only {len(g)} usable samples to fit the gyro scales on")
    scale, bias = np.empty(3), np.empty(3)
    resid = np.empty_like(v)
    for i in range(3):  # per axis: v_i = s_i g_i + b_i
        a = np.column_stack([g[:, i], np.ones(len(g))])
        (scale[i], bias[i]), *_ = np.linalg.lstsq(a, v[:, i], rcond=None)
        resid[:, i] = v[:, i] - a @ np.array([scale[i], bias[i]])
    a = np.column_stack([g, np.ones(len(g))])
    full, *_ = np.linalg.lstsq(a, v, rcond=None)  # v = g M^T + b
    matrix = full[:3].T
    normalised = matrix / np.diag(matrix)[None, :]  # columns scaled to unit diagonal
    skew = 0.5 * (normalised - normalised.T)
    current = np.asarray(data[0].current_factor)
    return GyroFit(
        gyro_scale_factor=tuple(float(x) for x in scale * current),
        gyro_bias_rad_s=tuple(float(x) for x in bias),
        gyro_matrix=(matrix * current[None, :]).tolist(),
        misalignment_deg=tuple(float(x) for x in np.rad2deg([skew[2, 1], skew[0, 2], skew[1, 0]])),
        residual_rms_deg_s=float(np.rad2deg(np.sqrt(np.mean(resid**2)))),
        samples=int(len(g)),
        fitted_on=[d.id for d in data],
        clock_offset_s={d.id: d.clock_offset_s for d in data},
    )


def fit_recordings(recordings: Iterable[Recording]) -> GyroFit:
    """`fit` over the recordings that have ground truth (the others are skipped)."""
    return fit(fit_data(r) for r in recordings if r.truth is not None)


def leave_one_out(recordings: list[Recording]) -> list[tuple[str, GyroFit]]:
    """For each recording with truth, the fit on all the *other* recordings with truth."""
    data = {r.id: fit_data(r) for r in recordings if r.truth is not None}
    if len(data) < 2:
        raise ValueError("leave-one-out needs at least two recordings with ground truth")
    return [(held, fit(d for rid, d in data.items() if rid != held)) for held in data]


def with_gyro_scale(recording: Recording, factor: Iterable[float], truth_offset_s: float = 0.0) -> Recording:
    """The recording re-calibrated from its raw counts with new gyro scale factors (same biases,
    same `gyr_valid`); the truth moved by `-truth_offset_s`."""
    from .datasets import _shift

    calib = recording.calibration
    if recording.raw is None or calib is None:
        raise ValueError(f"{recording.id}: no raw counts, so gyro scale factors cannot be applied")
    board = replace(calib.board, gyro_scale_factor=tuple(float(x) for x in factor))
    new_calib = Calibration(board, calib.bias_counts, calib.rest_start, calib.rest_end, calib.detector)
    imu = new_calib.apply(recording.raw).replace(gyr_valid=recording.imu.gyr_valid)
    return replace(recording, imu=imu, calibration=new_calib, truth=_shift(recording.truth, truth_offset_s))


# ------------------------------------------------------------------ the file

@dataclass(frozen=True)
class CalibrationFile:
    gyro_scale_factor: tuple[float, float, float] = (1.0, 1.0, 1.0)
    clock_offset_s: dict[str, float] = field(default_factory=dict)  # per recording id; empty unless fitted
    info: dict[str, Any] = field(default_factory=dict)

    def board(self, base: BoardModel = BoardModel()) -> BoardModel:
        return replace(base, gyro_scale_factor=tuple(self.gyro_scale_factor))

    def offset_for(self, recording_id: str) -> float:
        return float(self.clock_offset_s.get(recording_id, 0.0))


def to_document(result: GyroFit, with_clock_offset: bool, command: str = "") -> dict[str, Any]:
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "gyro_scale_factor": list(result.gyro_scale_factor),
        "clock_offset_s": dict(result.clock_offset_s) if with_clock_offset else {},
        "info": {
            "gyro_sensitivity_ratio": list(result.sensitivity_ratio),
            "gyro_bias_rad_s": list(result.gyro_bias_rad_s),
            "gyro_matrix": result.gyro_matrix,
            "misalignment_deg": list(result.misalignment_deg),
            "residual_rms_deg_s": result.residual_rms_deg_s,
            "samples": result.samples,
            "fitted_on": result.fitted_on,
            "measured_clock_offset_s": dict(result.clock_offset_s),
            "command": command,
        },
    }
    return to_jsonable(doc)


def to_json_text(result: GyroFit, with_clock_offset: bool = False, command: str = "") -> str:
    """The calibration file's text (what `write` writes)."""
    return json.dumps(to_document(result, with_clock_offset, command), indent=2) + "\n"


def write(path: str | Path, result: GyroFit, with_clock_offset: bool = False, command: str = "") -> None:
    Path(path).write_text(to_json_text(result, with_clock_offset, command))


def read(path: str | Path) -> CalibrationFile:
    """Read and validate a calibration file (raises `ValueError` naming the file and the problem)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such calibration file")
    if path.stat().st_size > 10 * 1024**2:  # ours are ~2 KB
        raise ValueError(f"{path}: {path.stat().st_size} bytes, far larger than a calibration file")
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a calibration file (not UTF-8 text: byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: not a calibration file (JSON nested too deeply)") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} file (missing or wrong 'format')")
    if doc.get("version") != VERSION or isinstance(doc.get("version"), bool):
        raise ValueError(f"{path}: calibration file version {_short(doc.get('version'))}, this fusion reads version {VERSION}")
    scale = doc.get("gyro_scale_factor")
    if not (isinstance(scale, list) and len(scale) == 3 and all(_is_number(x) for x in scale)):
        raise ValueError(f"{path}: 'gyro_scale_factor' must be a list of 3 numbers (not booleans), got {_short(scale)}")
    if not all(0.5 <= x <= 2.0 for x in scale):
        raise ValueError(f"{path}: 'gyro_scale_factor' {scale} outside the plausible 0.5-2")
    offsets = doc.get("clock_offset_s", {}) or {}
    if not isinstance(offsets, dict) or not all(_is_number(v) and abs(v) < 1.0 for v in offsets.values()):
        raise ValueError(f"{path}: 'clock_offset_s' must map recording ids to offsets in s (numbers, |offset| < 1)")
    info = doc.get("info", {})
    return CalibrationFile(tuple(float(x) for x in scale), {str(k): float(v) for k, v in offsets.items()},
                           info if isinstance(info, dict) else {})


def _is_number(x: Any) -> bool:
    """A finite int or float; JSON's true/false are Python bools, which are ints: refused."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and bool(np.isfinite(x))


def _short(value: Any) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= 80 else text[:77] + "..."


def warn_not_applied(path: str | Path, sources: Iterable[Any]) -> None:
    """Warn, per recording, that a calibration file's gyro scale factors are not applied to it.

    The factors multiply the nominal counts-to-rad/s scale of the course board (`BoardModel`);
    recordings in physical units (CSV, BROAD, EuRoC, ROS bags: `fusion.formats.Holds.raw_counts`
    False) are already in rad/s, calibrated by whoever wrote them, so the factors are not applied
    there (their clock offsets, if the file has one for the recording, are). Applying a scale
    fitted on another sensor would be a silent wrong answer.
    """
    from .formats import FORMATS

    for source in sources:
        kind = getattr(source, "kind", None)
        if kind in FORMATS and not FORMATS[kind].holds(source).raw_counts:
            warnings.warn(f"{source.id}: --calibration {path}: gyro scale factors not applied ({kind} recordings "
                          "are already in rad/s; the factors are for the course board's raw counts)", stacklevel=2)
