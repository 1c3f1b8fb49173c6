"""Raw ADC counts to physical units: `value = sign * (raw - bias) * scale`.

The board (see `../shared/data/README.md`): a 10-bit ADC at Vref = 3.3 V reads an ADXL335
accelerometer and LPR530AL / LY530ALH rate gyros (4x amplified outputs).

- Accelerometer scale: the ADXL335 is ratiometric, its sensitivity scales with the supply:
  300 mV/g at 3.0 V (datasheet) is about 330 mV/g at 3.3 V, i.e. 1023 * 330 / 3300 = 102.3
  counts per g.
- Gyro scale: 3.33 mV/(deg/s), i.e. 0.969 deg/s per count (datasheet; the real sensitivities
  differ by a few percent, see `fusion calibrate`, which fills `BoardModel.gyro_scale_factor`).
- The device's x and y accelerometer axes point the other way from the body axes: sign -1.
- Biases come from the stationary period at the start, detected from the data
  (`detect_rest`); the accelerometer's z bias keeps 1 g, because at rest z reads +1 g.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .types import ImuSamples, RawImu


@dataclass(frozen=True)
class BoardModel:
    """Nominal sensor model of the board; every number in the unit its name says."""

    vref_mv: float = 3300.0
    adc_full_scale_counts: float = 1023.0
    acc_sensitivity_mv_per_g: float = 330.0
    gyro_sensitivity_mv_per_deg_s: float = 3.33
    acc_sign: tuple[float, float, float] = (-1.0, -1.0, 1.0)
    gyro_sign: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # Multiplies the nominal gyro scale per axis (1 = datasheet); fitted by `fusion calibrate`.
    gyro_scale_factor: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def acc_g_per_count(self) -> float:
        return self.vref_mv / self.adc_full_scale_counts / self.acc_sensitivity_mv_per_g

    @property
    def gyro_rad_s_per_count(self) -> float:
        return np.deg2rad(self.vref_mv / self.adc_full_scale_counts / self.gyro_sensitivity_mv_per_deg_s)

    @property
    def scale(self) -> np.ndarray:
        """(6,) signed scale per channel ax ay az wx wy wz: g or rad/s per count."""
        acc = np.asarray(self.acc_sign) * self.acc_g_per_count
        gyr = np.asarray(self.gyro_sign) * np.asarray(self.gyro_scale_factor) * self.gyro_rad_s_per_count
        return np.concatenate([acc, gyr])


@dataclass(frozen=True)
class RestCriteria:
    """When raw samples count as rest for the calibration: a sample is at rest when, over a window
    around it, every channel's standard deviation stays below a threshold (in physical units,
    converted with the board's nominal scales). Not the filters' online rest detection
    (`fusion.estimators`' `rest_gyr_rad_s`, `rest_acc_g`, `rest_time_s` parameters)."""

    window_s: float = 0.3
    gyro_std_rad_s: float = 0.025  # about 1.4 deg/s, 1.5 counts
    acc_std_g: float = 0.025  # 2.5 counts
    min_duration_s: float = 0.25


@dataclass(frozen=True)
class Calibration:
    """What was applied to the raw counts of one recording.

    bias_counts: (6,) per channel ax ay az wx wy wz, native counts.
    rest_start, rest_end: (first, stop) sample indices of the stationary periods at the start
        and the end (`rest_end` None when the recording does not end at rest).
    """

    board: BoardModel
    bias_counts: np.ndarray
    rest_start: tuple[int, int]
    rest_end: tuple[int, int] | None = None
    detector: RestCriteria = field(default_factory=RestCriteria)

    def apply(self, raw: RawImu) -> ImuSamples:
        values = (raw.counts - self.bias_counts) * self.board.scale
        return ImuSamples(raw.t, values[:, 3:], values[:, :3], source=raw.source, gyr_timing=raw.gyr_timing)


_STD_CHUNK = 4096  # windows per chunk in `stationary_mask`


def stationary_mask(raw: RawImu, board: BoardModel, detector: RestCriteria) -> np.ndarray:
    """(N,) bool: samples inside a window whose every channel is still (raw counts, judged in
    physical units through the board's nominal scales)."""
    return still_mask(raw.t, raw.counts, detector, np.abs(board.scale))


def still_mask(t: np.ndarray, values: np.ndarray, detector: RestCriteria,
               scale: np.ndarray = np.ones(6)) -> np.ndarray:
    """(N,) bool: samples inside a window whose every channel is still. t: (N,) s; values: (N, 6)
    accelerometer then gyro channels, in g and rad/s once multiplied by `scale` (6,) (counts and a
    board's scales, or calibrated samples as they are)."""
    n = len(t)
    window = max(3, int(round(detector.window_s / np.median(np.diff(t))))) if n > 1 else 1
    if n < window:
        return np.zeros(n, bool)
    # Per-window standard deviations, (N-w+1, 6). The window view costs nothing, but `.std` on
    # all of it at once makes (N-w+1, 6, w) temporaries (1 GB for an hour at 100 Hz): go by
    # chunks of windows (same numbers, bit for bit; memory bounded).
    view = sliding_window_view(values, window, axis=0)
    std = np.empty((len(view), 6))
    with np.errstate(over="ignore", invalid="ignore"):  # an absurd count (1e308) gives inf/NaN: not still
        for lo in range(0, len(view), _STD_CHUNK):
            std[lo:lo + _STD_CHUNK] = view[lo:lo + _STD_CHUNK].std(axis=-1)
    std *= scale
    still_window = (std[:, :3].max(axis=1) < detector.acc_std_g) & (std[:, 3:].max(axis=1) < detector.gyro_std_rad_s)
    # A sample is still only if every window containing it is still (conservative at the
    # edges of a rest, so the first samples of a motion never count as rest).
    moving = np.concatenate([[0], np.cumsum(~still_window)])  # moving windows among the first j
    first = np.clip(np.arange(n) - window + 1, 0, len(still_window))
    last = np.clip(np.arange(n) + 1, 0, len(still_window))
    return moving[last] - moving[first] == 0


def detect_rest(raw: RawImu, board: BoardModel = BoardModel(), detector: RestCriteria = RestCriteria()
                ) -> tuple[tuple[int, int] | None, tuple[int, int] | None]:
    """The stationary periods at the start and at the end, as (first, stop) index pairs.

    Each is None when the recording does not start (end) with at least
    `detector.min_duration_s` of rest.
    """
    still = stationary_mask(raw, board, detector)
    t = raw.t

    def run_from(mask: np.ndarray) -> int:
        return len(mask) if mask.all() else int(np.argmin(mask))

    stop = run_from(still)
    start = (0, stop) if stop > 0 and t[stop - 1] - t[0] >= detector.min_duration_s else None
    first = len(t) - run_from(still[::-1])
    end = (first, len(t)) if first < len(t) and t[-1] - t[first] >= detector.min_duration_s else None
    return start, end


def calibrate(raw: RawImu, board: BoardModel = BoardModel(), detector: RestCriteria = RestCriteria()) -> Calibration:
    """Biases from the stationary start (z keeps 1 g). Raises if the recording has no rest at its start."""
    start, end = detect_rest(raw, board, detector)
    if start is None:
        raise ValueError(
            f"{raw.source}: no stationary period of {detector.min_duration_s} s at the start; "
            "the biases need the sensor at rest first"
        )
    bias = raw.counts[start[0]:start[1]].mean(axis=0)
    bias[2] -= 1.0 / board.scale[2]  # at rest z reads +1 g: that much of the mean is signal, not bias
    return Calibration(board, bias, start, end, detector)


def rest_gravity_norms(imu: ImuSamples, calibration: Calibration) -> dict[str, float]:
    """Mean |a| in g over the start and end rest windows (a check of the scale factors)."""
    out = {}
    for name, window in (("start", calibration.rest_start), ("end", calibration.rest_end)):
        if window is not None:
            out[name] = float(np.linalg.norm(imu.acc_g[window[0]:window[1]].mean(axis=0)))
    return out


def __getattr__(name: str):
    """`RestDetector`, this class's former name (the filters' online rest detection has that
    name): still importable, with a warning, for one release."""
    if name == "RestDetector":
        warnings.warn("fusion.calibration.RestDetector is now RestCriteria; the old name goes in the next release",
                      FutureWarning, stacklevel=2)
        return RestCriteria
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
