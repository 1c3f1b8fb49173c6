"""What a recording really holds: sensor checks behind `fusion inspect` and the dropout mask.

Per recording (`check_recording`), for every format (raw counts or physical units):
- rest periods (every stationary run, `fusion.calibration.still_mask`, on the raw counts of
  recordings that have them, else on the calibrated samples), the calibrated |a| at each rest (a
  check of the accelerometer scale) and the gyro bias there (after the calibration, in deg/s; for
  raw counts also the zero-rate level in counts that the calibration removes); the bias drift
  between the first and the last rest;
- gyro freezes (`detect_freezes`): all three gyro channels flat while the accelerometer shows
  motion, judged against the gyro's own resolution and noise as measured on the recording, so
  for any IMU (the course recordings 1, 2, 4, 5, 8, 9 have one each);
- saturation: with raw counts the samples at the ADC rails, and samples beyond the gyros' nominal
  +-300 deg/s (reported only: on this board they are not clipped, the ADC reaches about
  +-490 deg/s and the values stay smooth); in physical units the flat tops at an axis' extreme
  (`FlatTopDetector`), gyro and accelerometer;
- time-stamp jitter and gaps of the IMU, and how often each sensor's value changes (a file whose
  rows repeat a sensor's last sample, as RepoIMU's pendulum holds its 50 Hz gyro over 163 Hz rows);
- VICON gaps (NaN rows) and the IMU-VICON clock offset (`clock_offset`), from the
  cross-correlation of the angular speed measured by the gyro and derived from VICON.

Times in reports are seconds after the first IMU sample (as in `../shared/data/README.md`).
`dropout_mask` turns freezes and saturated gyro samples into `ImuSamples.gyr_valid`; the loader
applies it (`fusion.datasets.LoadOptions` `dropouts`, the one switch).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import quaternion as quat
from .calibration import BoardModel, Calibration, RestCriteria, stationary_mask, still_mask
from .types import ImuSamples, RawImu, Recording, Trajectory

NOMINAL_GYRO_RANGE_DEG_S = 300.0  # LPR530AL / LY530ALH on the 4x outputs


@dataclass(frozen=True)
class FreezeDetector:
    """A window (`window_s`) is a freeze candidate when every gyro channel is flat in it while some
    accelerometer channel moves by more than `acc_p2p_g` (peak to peak, g). A channel is flat
    when its peak-to-peak stays within the larger of `gyro_p2p_steps` steps of its resolution
    (the smallest difference between two of its distinct values: one ADC count on the course
    board, 0.97 deg/s) and `noise_ratio` times its noise floor (the `noise_percentile`-th
    percentile of the peak-to-peak of its windows that are not within those steps: a real gyro is
    never that quiet for long), both measured on the recording itself. A gyro without noise (a
    simulation with exact rates: second differences of zero) is not judged.

    A freeze is a maximal run of gyro-flat windows that contains at least one such window
    and lasts at least `min_duration_s` (the run may extend into a rest: recording 8 freezes
    during a motion and stays frozen while the platform comes to rest).
    """

    window_s: float = 0.2
    gyro_p2p_steps: float = 2.0
    noise_ratio: float = 0.1
    noise_percentile: float = 10.0
    acc_p2p_g: float = 0.08  # about 8 counts on the course board; its rest noise stays within about 4
    min_duration_s: float = 0.2

    def __post_init__(self) -> None:
        for name in ("window_s", "gyro_p2p_steps", "noise_ratio", "noise_percentile", "acc_p2p_g", "min_duration_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"FreezeDetector.{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class Interval:
    """A run of samples `[first, stop)`; times in s after the first IMU sample."""

    start_s: float
    stop_s: float
    samples: int
    first: int
    stop: int

    @property
    def duration_s(self) -> float:
        return self.stop_s - self.start_s


@dataclass(frozen=True)
class RestPeriod:
    interval: Interval
    acc_norm_g: float  # |mean calibrated acceleration| over the rest
    gyro_bias_deg_s: tuple[float, float, float]  # mean calibrated gyro (raw counts: after the start bias is removed)
    gyro_mean_counts: tuple[float, float, float]  # the zero-rate level in counts (NaN in physical units)


@dataclass(frozen=True)
class Freeze:
    interval: Interval
    level_deg_s: tuple[float, float, float]  # mean calibrated gyro during the freeze
    level_counts: tuple[float, float, float]  # mean gyro counts during the freeze (NaN without raw counts)
    offset_from_bias_counts: tuple[float, float, float]  # level minus the start-rest bias (NaN without)
    acc_p2p_g: float  # largest accelerometer peak-to-peak inside (how much it moved)


@dataclass(frozen=True)
class RangeCheck:
    """Saturation, by `method`: "ADC rails" (raw counts: a channel within `rail_counts` of 0 or full
    scale) or "flat tops" (physical units: `FlatTopDetector`). The nominal range and the counts'
    extremes only with raw counts (None otherwise)."""

    saturated: list[Interval]  # some gyro channel saturated
    saturated_samples: int
    beyond_nominal_samples: tuple[int, int, int] | None  # per axis |rate| > nominal range
    beyond_nominal: list[Interval] | None
    max_abs_deg_s: tuple[float, float, float]
    count_min: tuple[float, float, float] | None
    count_max: tuple[float, float, float] | None
    acc_saturated_samples: int
    method: str = "ADC rails"
    acc_saturated: list[Interval] = field(default_factory=list)

    def gyro_beyond_range(self) -> list[Interval]:
        """The spans where the gyro read beyond its range: past the board's nominal range (raw
        counts), or on a flat top (physical units)."""
        return self.saturated if self.method == "flat tops" else list(self.beyond_nominal or [])


@dataclass(frozen=True)
class TimingCheck:
    rate_hz: float  # (N - 1) / span
    dt_median_s: float
    dt_std_s: float
    dt_min_s: float
    dt_max_s: float
    gaps: list[Interval]  # steps longer than `gap_factor` x median
    value_rates_hz: dict[str, float] = field(default_factory=dict)  # per sensor: its value changes per second


@dataclass(frozen=True)
class ClockOffset:
    """Truth time stamp minus IMU time stamp of the same instant (s): positive = VICON lags.

    Align the truth with `truth.t - offset_s`.
    """

    offset_s: float
    peak_correlation: float
    samples: int


@dataclass(frozen=True)
class ViconCheck:
    samples: int
    rate_hz: float
    gaps: list[Interval]  # NaN rows, times relative to the first IMU sample
    missing_samples: int
    start_s: float  # first VICON stamp relative to the first IMU sample
    stop_s: float
    stamp_jitter_std_s: float  # stamps minus the regular time base (`regular_stamps`)
    stamp_jitter_max_s: float
    near_duplicate_stamps: int  # steps shorter than a quarter of the median step
    clock: ClockOffset | None  # measured on the regular time base


@dataclass(frozen=True)
class MagnetometerCheck:
    """The magnetometer against the field it should see. The recording's median field stands for
    the local Earth field (its norm and dip; the toolkit does not know where the recording was
    made, so no model such as the IGRF is used); a sample is disturbed where its norm or dip
    departs from it by more than `MAG_NORM_TOLERANCE` or `MAG_DIP_TOLERANCE_DEG`, for at least
    `MAG_MIN_DISTURBANCE_S`. The dip (inclination of the field below the horizontal, positive
    downwards as in the northern hemisphere) is measured where the accelerometer reads 1 g (within
    `MAG_DIP_ACC_TOLERANCE_G`), which then points up."""

    samples: int  # valid magnetometer samples
    norm_median_ut: float
    norm_p5_ut: float
    norm_p95_ut: float
    dip_median_deg: float | None  # None: the accelerometer never read 1 g
    dip_std_deg: float | None
    disturbed: list[Interval]
    disturbed_fraction: float


MAG_NORM_TOLERANCE = 0.1  # relative
MAG_DIP_TOLERANCE_DEG = 5.0
MAG_MIN_DISTURBANCE_S = 0.2
MAG_DIP_ACC_TOLERANCE_G = 0.05
EARTH_FIELD_UT = (22.0, 67.0)  # the Earth's field at its surface (IGRF): outside, the sensor sees more than the Earth


@dataclass(frozen=True)
class RecordingCheck:
    id: str
    samples: int
    duration_s: float
    rests: list[RestPeriod]
    gyro_bias_drift_deg_s: tuple[float, float, float] | None  # last rest minus first rest
    freezes: list[Freeze]
    range: RangeCheck | None
    timing: TimingCheck
    vicon: ViconCheck | None
    notes: list[str] = field(default_factory=list)
    magnetometer: MagnetometerCheck | None = None

    def to_json(self) -> dict[str, Any]:
        return to_jsonable(self)


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, numpy scalars/arrays, tuples -> plain JSON types (NaN -> None)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        if isinstance(obj, Interval):
            out["duration_s"] = obj.duration_s
        return out
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


# ---------------------------------------------------------------------------- runs

def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of True in a 1-D bool array, as `(first, stop)` index pairs."""
    m = np.asarray(mask, bool)
    if m.size == 0:
        return []
    edges = np.diff(np.concatenate([[0], m.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _interval(t: np.ndarray, t0: float, first: int, stop: int) -> Interval:
    return Interval(float(t[first] - t0), float(t[stop - 1] - t0), stop - first, first, stop)


def _window(t: np.ndarray, seconds: float) -> int:
    return max(2, int(round(seconds / np.median(np.diff(t))))) if len(t) > 1 else 1


def _window_p2p(x: np.ndarray, w: int) -> np.ndarray:
    """(N - w + 1, C) the peak-to-peak of each column of (N, C) x over the windows x[i:i + w]: a
    running maximum and minimum (`scipy.ndimage`, O(N) whatever w), the window's centre at
    i + w // 2."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    x = np.asarray(x, dtype=float)
    valid = slice(w // 2, w // 2 + len(x) - w + 1)
    return maximum_filter1d(x, w, axis=0)[valid] - minimum_filter1d(x, w, axis=0)[valid]


def _windows_to_samples(flag: np.ndarray, n: int, w: int) -> np.ndarray:
    """(N - w + 1,) window flags -> (N,) samples covered by at least one flagged window."""
    cover = np.zeros(n + 1, int)
    idx = np.flatnonzero(flag)
    np.add.at(cover, idx, 1)
    np.add.at(cover, idx + w, -1)
    return np.cumsum(cover)[:n] > 0


# ------------------------------------------------------------------- detectors

def resolution(values: np.ndarray) -> np.ndarray:
    """(C,) the smallest difference between two distinct values of each column of (N, C)
    `values` (an ADC's step, in the values' unit); 0 for a constant column."""
    out = np.zeros(values.shape[1])
    for c in range(values.shape[1]):
        steps = np.diff(np.unique(values[:, c]))
        steps = steps[steps > 0]
        out[c] = steps.min() if steps.size else 0.0
    return out


def detect_freezes(imu: ImuSamples, detector: FreezeDetector = FreezeDetector(), raw: RawImu | None = None,
                   bias_counts: np.ndarray | None = None) -> list[Freeze]:
    """Gyro freezes: all three gyro channels flat while the accelerometer moves (see
    `FreezeDetector`), from the calibrated samples alone; raw: the counts they came from, for the
    freezes' levels in counts (and `bias_counts`, the start-rest bias, for their offsets)."""
    t, gyr = imu.t, np.asarray(imu.gyr_rad_s)
    n = len(t)
    w = _window(t, detector.window_s)
    if n < w:
        return []
    if not np.any(np.median(np.abs(np.diff(gyr, 2, axis=0)), axis=0) > 0):
        return []  # exact rates (a simulation): no noise to judge a freeze against
    gyr_p2p = _window_p2p(gyr, w)
    steps = detector.gyro_p2p_steps * resolution(gyr) * (1 + 1e-9)
    noise = np.array([np.percentile(p[p > s], detector.noise_percentile) if np.any(p > s) else 0.0
                      for p, s in zip(gyr_p2p.T, steps)])  # the noise floor of the windows that are not stuck
    tolerance = np.maximum(steps, detector.noise_ratio * noise)
    gyro_flat = np.all(gyr_p2p <= tolerance, axis=1)
    acc_p2p_g = _window_p2p(np.asarray(imu.acc_g), w).max(axis=1)
    moving = acc_p2p_g > detector.acc_p2p_g
    flat_samples = _windows_to_samples(gyro_flat, n, w)
    moving_flat = _windows_to_samples(gyro_flat & moving, n, w)
    out = []
    for first, stop in runs(flat_samples):
        if not moving_flat[first:stop].any() or t[stop - 1] - t[first] < detector.min_duration_s:
            continue
        level = raw.counts[first:stop, 3:].mean(axis=0) if raw is not None else np.full(3, np.nan)
        offset = level - bias_counts[3:] if bias_counts is not None else np.full(3, np.nan)
        win = slice(first, max(first + 1, stop - w + 1))
        out.append(Freeze(_interval(t, t[0], first, stop), tuple(np.degrees(gyr[first:stop].mean(axis=0))),
                          tuple(level), tuple(offset), float(acc_p2p_g[win].max())))
    return out


@dataclass(frozen=True)
class FlatTopDetector:
    """A sensor's saturation found from its values alone, for files in physical units (no ADC rails
    to compare with): a flat top at an axis' extreme. Per axis and sign, the band just below the
    extreme (`band_fraction` of it, or `band_steps` steps of the axis' resolution, whichever is
    wider) is a flat top when the signal piles up there: at least `min_samples` samples in runs of
    `min_run` or more, and `pile_ratio` times as many as in the next band down (`next_bands` band
    widths), and the extreme at least `tail_ratio` times the axis' median magnitude: a signal
    clipped at the sensor's range sits at it, where an unclipped peak spreads over both bands (and a
    long rest with gravity on the axis, whose noise stays in the band, is the axis' typical value,
    not its tail). Held values (a row repeating the sample
    before it, as RepoIMU's pendulum files hold them) count once. On the shared data it finds the
    T-stick's gyro clipped at +-7.2-7.4 rad/s (RepoIMU's TStick Test05 and Test10) and nothing on
    BROAD or the course (whose counts have rails of their own: `saturated_mask`)."""

    band_fraction: float = 0.005
    band_steps: float = 2.0
    min_run: int = 3
    min_samples: int = 10
    pile_ratio: float = 3.0
    next_bands: float = 5.0
    tail_ratio: float = 2.0

    def __post_init__(self) -> None:
        for name in ("band_fraction", "band_steps", "min_run", "min_samples", "pile_ratio", "next_bands", "tail_ratio"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"FlatTopDetector.{name} must be >= 0, got {getattr(self, name)}")

    def mask(self, values: np.ndarray, ignore: np.ndarray | None = None) -> np.ndarray:
        """(N, C) bool: the samples of (N, C) `values` on a flat top of their column; `ignore` (N,)
        bool: samples left out of the search (a frozen gyro's constant level is no flat top)."""
        values = np.asarray(values, dtype=float)
        use = np.ones(len(values), bool) if ignore is None else ~np.asarray(ignore, bool)
        out = np.zeros(values.shape, bool)
        if not use.any():
            return out
        step = resolution(values[use])
        for c in range(values.shape[1]):
            fresh = use & np.r_[True, np.diff(values[:, c]) != 0]  # a held value counts once
            for sign in (1.0, -1.0):
                v = sign * values[:, c]
                extreme = v[use].max()
                if not extreme > self.tail_ratio * np.median(np.abs(v[use])):
                    continue
                width = max(self.band_fraction * extreme, self.band_steps * step[c])
                band = use & (v >= extreme - width)
                below = fresh & (v < extreme - width) & (v >= extreme - (1 + self.next_bands) * width)
                plateau = np.zeros(len(v), bool)
                for first, stop in runs(band):
                    if fresh[first:stop].sum() >= self.min_run:
                        plateau[first:stop] = True
                piled = int((plateau & fresh).sum())
                if piled >= self.min_samples and piled >= self.pile_ratio * int(below.sum()):
                    out[:, c] |= plateau
        return out


def saturated_mask(raw: RawImu, board: BoardModel = BoardModel(), rail_counts: float = 2.0) -> np.ndarray:
    """(N,) bool: some gyro channel within `rail_counts` of 0 or of the ADC full scale (clipped)."""
    g = raw.counts[:, 3:]
    return np.any((g <= rail_counts) | (g >= board.adc_full_scale_counts - rail_counts), axis=1)


def dropout_mask(imu: ImuSamples, raw: RawImu | None = None, board: BoardModel = BoardModel(),
                 detector: FreezeDetector = FreezeDetector()) -> np.ndarray:
    """(N,) bool `gyr_valid`: `imu.gyr_valid`, and False inside detected freezes and (with raw
    counts) at samples on the ADC's rails.

    A flat top in physical units (`FlatTopDetector`) is reported (`fusion inspect`, the report's
    "gyro beyond range" events), not marked invalid: there the reading is the sensor's range, a
    lower bound of the true rate, and integrating it does far better than holding the orientation
    (RepoIMU's T-stick, clipped at +-7.3 rad/s for up to 8 s: 6-D inclination, `ekf`, Test10 trials
    5.4-5.9 deg integrated against 23-93 held; `docs/results.md`, "RepoIMU's clipped gyro")."""
    valid = np.array(imu.gyr_valid)
    if raw is not None:
        valid &= ~saturated_mask(raw, board)
    for freeze in detect_freezes(imu, detector):
        valid[freeze.interval.first:freeze.interval.stop] = False
    return valid


def check_range(raw: RawImu, imu: ImuSamples, board: BoardModel = BoardModel(), rail_counts: float = 2.0,
                nominal_deg_s: float = NOMINAL_GYRO_RANGE_DEG_S) -> RangeCheck:
    t0 = raw.t[0]
    sat = saturated_mask(raw, board, rail_counts)
    acc = raw.counts[:, :3]
    acc_sat = np.any((acc <= rail_counts) | (acc >= board.adc_full_scale_counts - rail_counts), axis=1)
    rate = np.abs(np.rad2deg(imu.gyr_rad_s))
    beyond = rate > nominal_deg_s
    return RangeCheck(
        saturated=[_interval(raw.t, t0, a, b) for a, b in runs(sat)],
        saturated_samples=int(sat.sum()),
        beyond_nominal_samples=tuple(int(v) for v in beyond.sum(axis=0)),
        beyond_nominal=[_interval(raw.t, t0, a, b) for a, b in runs(beyond.any(axis=1))],
        max_abs_deg_s=tuple(float(v) for v in rate.max(axis=0)),
        count_min=tuple(float(v) for v in raw.counts[:, 3:].min(axis=0)),
        count_max=tuple(float(v) for v in raw.counts[:, 3:].max(axis=0)),
        acc_saturated_samples=int(acc_sat.sum()),
    )


def check_timing(t: np.ndarray, gap_factor: float = 2.0, sensors: dict[str, np.ndarray] | None = None,
                 moving: np.ndarray | None = None) -> TimingCheck:
    """Sampling rate, jitter (std of the steps), gaps (steps > `gap_factor` x median) and, for each
    of `sensors` (name -> (N, 3) values on the stamps `t`), how often its value changes while the
    sensor moves (`value_rate_hz`; moving: (N,) bool, None for every sample)."""
    dt = np.diff(t)
    if len(dt) == 0:
        return TimingCheck(float("nan"), float("nan"), float("nan"), float("nan"), float("nan"), [])
    med = float(np.median(dt))
    gaps = [Interval(float(t[k] - t[0]), float(t[k + 1] - t[0]), 0, int(k), int(k + 1))
            for k in np.flatnonzero(dt > gap_factor * med)]
    rates = {name: value_rate_hz(t, values, moving) for name, values in (sensors or {}).items()}
    return TimingCheck(float((len(t) - 1) / (t[-1] - t[0])), med, float(dt.std()), float(dt.min()), float(dt.max()), gaps,
                       rates)


HELD_RATIO = 0.8  # a sensor whose value changes on fewer than this fraction of the rows holds its samples


def value_rate_hz(t: np.ndarray, values: np.ndarray, moving: np.ndarray | None = None) -> float:
    """How often (N, C) `values` on the stamps `t` (N,) change, per second: the steps between two
    moving rows (`moving` (N,) bool, None: all) where some channel differs, over those steps' time
    (rows without a sample, NaN, do not count). A sensor that delivers a new sample on every row
    changes at the rows' rate (at rest a quantised sensor repeats itself: rests are left out); one
    whose samples are held over rows (a slower sensor written at a faster clock) at its own."""
    values = np.asarray(values, dtype=float)
    step = np.all(np.isfinite(values[1:]), axis=1) & np.all(np.isfinite(values[:-1]), axis=1)
    if moving is not None:
        step &= moving[1:] & moving[:-1]
    span = float(np.diff(t)[step].sum())
    if not span > 0:
        return float("nan")
    return float((np.any(np.diff(values, axis=0) != 0, axis=1) & step).sum() / span)


def held_sensors(timing: TimingCheck) -> dict[str, float]:
    """The sensors of `timing.value_rates_hz` that hold their values over rows (their rate below
    `HELD_RATIO` of the rows')."""
    return {name: rate for name, rate in timing.value_rates_hz.items() if rate < HELD_RATIO * timing.rate_hz}


def imu_sensors(imu: ImuSamples) -> dict[str, np.ndarray]:
    """The sensors of a recording by name, for `check_timing`: gyro, accelerometer, magnetometer."""
    out = {"gyro": imu.gyr_rad_s, "accelerometer": imu.acc_g}
    if imu.mag_ut is not None:
        out["magnetometer"] = imu.mag_ut
    return out


def flat_top_range(imu: ImuSamples, detector: FlatTopDetector = FlatTopDetector(),
                   frozen: np.ndarray | None = None) -> RangeCheck:
    """The range check of a recording in physical units: the gyro and accelerometer samples on a flat
    top (`FlatTopDetector`; a frozen gyro, `frozen` (N,) bool, is not searched), and the largest rates."""
    t0 = imu.t[0]
    gyro = detector.mask(imu.gyr_rad_s, frozen).any(axis=1)
    acc = detector.mask(imu.acc_g).any(axis=1)
    return RangeCheck(
        saturated=[_interval(imu.t, t0, a, b) for a, b in runs(gyro)], saturated_samples=int(gyro.sum()),
        beyond_nominal_samples=None, beyond_nominal=None,
        max_abs_deg_s=tuple(float(v) for v in np.abs(np.rad2deg(imu.gyr_rad_s)).max(axis=0)),
        count_min=None, count_max=None, acc_saturated_samples=int(acc.sum()), method="flat tops",
        acc_saturated=[_interval(imu.t, t0, a, b) for a, b in runs(acc)])


def rest_periods(raw: RawImu | None, imu: ImuSamples, board: BoardModel = BoardModel(),
                 detector: RestCriteria = RestCriteria()) -> list[RestPeriod]:
    """Every stationary run of at least `detector.min_duration_s` (`check_recording` drops
    those inside a freeze: a frozen gyro looks still): judged on the raw counts where there are
    some (`stationary_mask`), else on the calibrated samples (`still_mask`)."""
    if raw is not None:
        still = stationary_mask(raw, board, detector)
    else:
        still = still_mask(imu.t, np.hstack([imu.acc_g, imu.gyr_rad_s]), detector)
    out = []
    for first, stop in runs(still):
        if imu.t[stop - 1] - imu.t[first] < detector.min_duration_s:
            continue
        acc = imu.acc_g[first:stop].mean(axis=0)
        gyr = np.rad2deg(imu.gyr_rad_s[first:stop].mean(axis=0))
        counts = raw.counts[first:stop, 3:].mean(axis=0) if raw is not None else np.full(3, np.nan)
        out.append(RestPeriod(_interval(imu.t, imu.t[0], first, stop), float(np.linalg.norm(acc)),
                              tuple(float(v) for v in gyr), tuple(float(v) for v in counts)))
    return out


# ----------------------------------------------------------------- VICON side

def regular_stamps(t: np.ndarray, max_residual_steps: float = 4.0) -> np.ndarray:
    """The least-squares line through the stamps against the row index: the time base of a
    regularly sampled stream whose stamps are arrival times.

    The real VICON stamps are late by up to about 23 ms on many rows (recordings 1-6: a late row
    is followed by one stamped some 14 us after it), while the rotations themselves are
    sampled regularly; differentiating over the raw stamps gives rates of 10^4 deg/s.
    Returns `t` unchanged when the residual exceeds `max_residual_steps` periods (rows missing
    rather than NaN: not a regular stream).
    """
    t = np.asarray(t, float)
    if len(t) < 3:
        return t
    k = np.arange(len(t), dtype=float)
    slope, icpt = np.polyfit(k, t, 1)
    fit = icpt + slope * k
    return fit if np.abs(t - fit).max() <= max_residual_steps * slope else t


def vicon_body_rate(truth: Trajectory, max_step_factor: float = 3.0, regular: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame angular rate from consecutive VICON rotations.

    Returns `(t_mid, omega)`: (K - 1,) midpoints of the steps (s, truth clock) and (K - 1, 3)
    rad/s, body frame, `rotvec(q_k^-1 q_{k+1}) / dt_k`; rows NaN where a neighbour is a gap
    or the step is longer than `max_step_factor` x the median step. With `regular`, the steps
    are taken on `regular_stamps(truth.t)` (see there why).
    """
    q = truth.quat_wxyz
    t = regular_stamps(truth.t) if regular else truth.t
    truth = Trajectory(t, q)
    dt = np.diff(t)
    omega = quat.relative_rotvec(q[:-1], q[1:]) / dt[:, None]
    bad = ~(truth.valid[:-1] & truth.valid[1:]) | (dt > max_step_factor * np.median(dt))
    omega[bad] = np.nan
    return 0.5 * (truth.t[:-1] + truth.t[1:]), omega


def _interp_valid(t_query: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of (K,) or (K, d) `values` (NaN = missing) at `t_query`; NaN where
    a neighbour is missing or outside the span."""
    values = np.asarray(values, float)
    flat = values.reshape(len(t), -1)
    ok = np.all(np.isfinite(flat), axis=1)
    right = np.clip(np.searchsorted(t, t_query, side="right"), 1, len(t) - 1)
    left = right - 1
    span = t[right] - t[left]
    frac = (t_query - t[left]) / span
    out = flat[left] + (flat[right] - flat[left]) * frac[:, None]
    bad = ~(ok[left] & ok[right]) | (t_query < t[0]) | (t_query > t[-1])
    out[bad] = np.nan
    return out.reshape((len(t_query),) + values.shape[1:])


def clock_offset(imu: ImuSamples, truth: Trajectory, max_lag_s: float = 0.2, grid_hz: float = 200.0,
                 smooth_s: float = 0.03) -> ClockOffset | None:
    """IMU-VICON clock offset from the cross-correlation of angular speeds.

    Both speeds (|gyro| of each IMU interval's reading, `ImuSamples.interval_rates`, at the
    interval's midpoint, invalid gyro samples excluded; |VICON rate| at the step midpoints,
    gaps excluded) are resampled on a common `grid_hz` grid over the overlap and
    smoothed alike (a moving average of `smooth_s`); the Pearson correlation is computed for
    every lag within +-`max_lag_s` over the samples valid in both, and the peak is refined by a
    parabola through the best lag and its neighbours (sub-sample resolution).
    Returns None without enough overlap.
    """
    t_mid, omega_v = vicon_body_rate(truth)
    speed_v = np.linalg.norm(omega_v, axis=1)
    rate, valid = imu.interval_rates()  # the mean rate over [t[k], t[k+1]], as the recording's gyr_timing says
    t_imu = 0.5 * (imu.t[1:] + imu.t[:-1])
    speed_i = np.linalg.norm(rate, axis=1).astype(float)
    speed_i[~valid] = np.nan
    h = 1.0 / grid_hz
    lo, hi = max(t_imu[0], t_mid[0]), min(t_imu[-1], t_mid[-1])
    if hi - lo < 4 * max_lag_s + 1.0:
        return None
    grid = np.arange(lo, hi, h)
    a = _interp_valid(grid, t_imu, speed_i)
    b = _interp_valid(grid, t_mid, speed_v)
    k = max(1, int(round(smooth_s / h)))
    a, b = _moving_average(a, k), _moving_average(b, k)
    max_lag = int(np.ceil(max_lag_s / h))
    lags = np.arange(-max_lag, max_lag + 1)
    corr = np.full(len(lags), np.nan)
    n = len(grid)
    counts = np.zeros(len(lags), int)
    for j, lag in enumerate(lags):  # a[i] (IMU at t) against b[i + lag] (VICON stamped t + lag h)
        x = a[max(0, -lag): n - max(0, lag)]
        y = b[max(0, lag): n - max(0, -lag)]
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 100:
            continue
        xs, ys = x[ok] - x[ok].mean(), y[ok] - y[ok].mean()
        denom = np.sqrt((xs @ xs) * (ys @ ys))
        corr[j] = (xs @ ys) / denom if denom > 0 else np.nan
        counts[j] = ok.sum()
    if not np.any(np.isfinite(corr)):
        return None
    j = int(np.nanargmax(corr))
    delta = 0.0
    if 0 < j < len(lags) - 1 and np.all(np.isfinite(corr[j - 1:j + 2])):
        c0, c1, c2 = corr[j - 1], corr[j], corr[j + 1]
        curv = c0 - 2 * c1 + c2
        delta = 0.5 * (c0 - c2) / curv if curv < 0 else 0.0  # vertex of the parabola through 3 points
    return ClockOffset(float((lags[j] + delta) * h), float(corr[j]), int(counts[j]))


def _moving_average(x: np.ndarray, k: int) -> np.ndarray:
    """Centred moving average over k samples; NaN where any sample in the window is NaN."""
    if k <= 1:
        return x
    finite = np.isfinite(x)
    filled = np.where(finite, x, 0.0)
    c = np.concatenate([[0.0], np.cumsum(filled)])
    cn = np.concatenate([[0], np.cumsum(~finite)])
    out = np.full(len(x), np.nan)
    half = k // 2
    first = np.clip(np.arange(len(x)) - half, 0, len(x))
    stop = np.clip(first + k, 0, len(x))
    full = (stop - first == k) & (cn[stop] - cn[first] == 0)
    out[full] = (c[stop] - c[first])[full] / k
    return out


def check_vicon(imu: ImuSamples, truth: Trajectory, t0: float) -> ViconCheck:
    bad = ~truth.valid
    dt = np.diff(truth.t)
    rate = float((len(truth.t) - 1) / (truth.t[-1] - truth.t[0])) if len(truth.t) > 1 else float("nan")
    return ViconCheck(
        samples=len(truth.t), rate_hz=rate,
        gaps=[_interval(truth.t, t0, a, b) for a, b in runs(bad)],
        missing_samples=int(bad.sum()),
        start_s=float(truth.t[0] - t0), stop_s=float(truth.t[-1] - t0),
        stamp_jitter_std_s=float(np.std(truth.t - regular_stamps(truth.t, np.inf))),
        stamp_jitter_max_s=float(np.abs(truth.t - regular_stamps(truth.t, np.inf)).max()),
        near_duplicate_stamps=int(np.sum(dt < 0.25 * np.median(dt))) if len(dt) else 0,
        clock=clock_offset(imu, truth) if len(dt) else None,
    )


# ------------------------------------------------------------------ the report

def check_magnetometer(imu: Any) -> MagnetometerCheck | None:
    """The magnetometer's norm and dip, and where it is disturbed (`MagnetometerCheck`); None
    without a magnetometer."""
    if not imu.has_mag:
        return None
    valid = imu.mag_valid
    mag = np.asarray(imu.mag_ut)
    norm = np.full(len(imu), np.nan)
    norm[valid] = np.linalg.norm(mag[valid], axis=1)
    median = float(np.nanmedian(norm))
    acc_norm = np.linalg.norm(imu.acc_g, axis=1)
    level = valid & (np.abs(acc_norm - 1.0) < MAG_DIP_ACC_TOLERANCE_G)
    dip = np.full(len(imu), np.nan)
    up = imu.acc_g[level] / acc_norm[level, None]
    dip[level] = np.degrees(np.arcsin(np.clip(-np.einsum("ij,ij->i", mag[level], up) / norm[level], -1.0, 1.0)))
    dip_median = float(np.nanmedian(dip)) if level.any() else None
    off = valid & (np.abs(norm - median) > MAG_NORM_TOLERANCE * median)
    if dip_median is not None:
        off |= level & (np.abs(dip - dip_median) > MAG_DIP_TOLERANCE_DEG)
    dt = float(np.median(np.diff(imu.t)))
    disturbed = [_interval(imu.t, imu.t[0], a, b) for a, b in runs(off) if (b - a) * dt >= MAG_MIN_DISTURBANCE_S]
    return MagnetometerCheck(int(valid.sum()), median, float(np.nanpercentile(norm, 5)), float(np.nanpercentile(norm, 95)),
                             dip_median, float(np.nanstd(dip)) if level.any() else None, disturbed,
                             sum(iv.samples for iv in disturbed) / max(int(valid.sum()), 1))


def check_recording(recording: Recording, freeze_detector: FreezeDetector = FreezeDetector()) -> RecordingCheck:
    """Every check on one recording (raw-count checks only when it has raw counts)."""
    imu, raw = recording.imu, recording.raw
    calib: Calibration | None = recording.calibration
    board = calib.board if calib is not None else BoardModel()
    t0 = imu.t[0]
    notes: list[str] = []
    rests: list[RestPeriod] = []
    freezes: list[Freeze] = []
    rng = None
    drift = None
    freezes = detect_freezes(imu, freeze_detector, raw, calib.bias_counts if calib is not None else None)
    detector = calib.detector if calib is not None else RestCriteria()
    rests = [r for r in rest_periods(raw, imu, board, detector)
             if not any(r.interval.first < f.interval.stop and f.interval.first < r.interval.stop for f in freezes)]
    if len(rests) >= 2:
        drift = tuple(float(b - a) for a, b in zip(rests[0].gyro_bias_deg_s, rests[-1].gyro_bias_deg_s))
    if raw is not None:
        rng = check_range(raw, imu, board)
    else:
        frozen = np.zeros(len(imu), bool)
        for f in freezes:
            frozen[f.interval.first:f.interval.stop] = True
        rng = flat_top_range(imu, frozen=frozen)
    if recording.truth is None:
        notes.append(f"{recording.truth_problem}; truth checks skipped" if recording.truth_problem
                     else "no ground truth: truth checks skipped")
    vicon = check_vicon(imu, recording.truth, t0) if recording.truth is not None else None
    mag = check_magnetometer(imu)
    if mag is not None and not EARTH_FIELD_UT[0] <= mag.norm_median_ut <= EARTH_FIELD_UT[1]:
        notes.append(f"magnetometer norm {mag.norm_median_ut:.1f} uT is outside the Earth's {EARTH_FIELD_UT[0]:.0f}-"
                     f"{EARTH_FIELD_UT[1]:.0f} uT: a hard-iron offset (iron or a magnet carried with the sensor), or an "
                     "uncalibrated magnetometer")
    moving = np.ones(len(imu), bool)
    for r in rests:
        moving[r.interval.first:r.interval.stop] = False
    return RecordingCheck(recording.id, len(imu), float(imu.t[-1] - t0), rests, drift, freezes, rng,
                          check_timing(imu.t, sensors=imu_sensors(imu), moving=moving), vicon, notes, mag)


def _fmt_intervals(intervals: list[Interval], limit: int = 4) -> str:
    if not intervals:
        return "-"
    text = ", ".join(f"{iv.start_s:.2f}-{iv.stop_s:.2f}" for iv in intervals[:limit])
    return text + (f" (+{len(intervals) - limit})" if len(intervals) > limit else "")


def _freeze_level(f: Freeze) -> str:
    if np.all(np.isfinite(f.level_counts)):
        return f"[{', '.join(f'{v:.0f}' for v in f.level_counts)}] counts"
    return f"[{', '.join(f'{v:+.2f}' for v in f.level_deg_s)}] deg/s"


def format_check(c: RecordingCheck) -> str:
    """A short human-readable table of one recording's checks."""
    lines = [f"{c.id}: {c.samples} samples, {c.duration_s:.1f} s"]

    def row(name: str, text: str) -> None:
        lines.append(f"  {name:<22} {text}")

    tm = c.timing
    row("IMU rate / jitter", f"{tm.rate_hz:.2f} Hz, dt median {tm.dt_median_s * 1e3:.2f} ms, std {tm.dt_std_s * 1e3:.2f} ms, "
        f"range {tm.dt_min_s * 1e3:.2f}-{tm.dt_max_s * 1e3:.2f} ms; gaps {_fmt_intervals(tm.gaps)}")
    held = held_sensors(tm)
    if held:
        row("held values", ", ".join(f"the {name} changes at {rate:.0f} Hz" for name, rate in held.items())
            + f" (of {tm.rate_hz:.0f} Hz rows: the rows between repeat its last sample)")
    if c.rests:
        row("rests (s)", ", ".join(f"{r.interval.start_s:.2f}-{r.interval.stop_s:.2f} |a|={r.acc_norm_g:.3f}g" for r in c.rests[:4])
            + (f" (+{len(c.rests) - 4})" if len(c.rests) > 4 else ""))
        last, first = c.rests[-1], c.rests[0]
        # The bias after calibration: the gyro's mean at the first rest, deg/s (raw counts: about 0 there, since the
        # calibration takes that rest's level as the bias; its level in counts is the zero-rate level, apart).
        row("gyro bias", "[" + ", ".join(f"{v:+.2f}" for v in first.gyro_bias_deg_s) + "] deg/s (mean at the first rest, "
            f"{first.interval.start_s:.1f}-{first.interval.stop_s:.1f} s, after calibration)")
        if np.all(np.isfinite(first.gyro_mean_counts)):
            row("zero-rate level", "[" + ", ".join(f"{v:.1f}" for v in first.gyro_mean_counts) + "] counts at the first "
                "rest (the level the calibration removes)")
        if c.gyro_bias_drift_deg_s is not None:
            row("gyro bias drift", "[" + ", ".join(f"{v:+.2f}" for v in c.gyro_bias_drift_deg_s)
                + f"] deg/s (last rest at {last.interval.start_s:.1f} s minus first)")
    else:
        row("rests", "none found")
    row("gyro freezes (s)", ", ".join(f"{f.interval.start_s:.2f}-{f.interval.stop_s:.2f} ({f.interval.duration_s:.2f} s at "
                                      + _freeze_level(f) + ")" for f in c.freezes) or "none")
    if c.range is not None and c.range.method == "ADC rails":
        r = c.range
        row("gyro range", f"|rate| max [{', '.join(f'{v:.0f}' for v in r.max_abs_deg_s)}] deg/s; "
            f"beyond +-{NOMINAL_GYRO_RANGE_DEG_S:.0f}: {sum(r.beyond_nominal_samples)} axis-samples; "
            f"saturated (ADC rail): {r.saturated_samples} samples {_fmt_intervals(r.saturated)}")
    elif c.range is not None:
        r = c.range
        row("gyro range", f"|rate| max [{', '.join(f'{v:.0f}' for v in r.max_abs_deg_s)}] deg/s; "
            f"saturated (flat tops): {r.saturated_samples} samples {_fmt_intervals(r.saturated)}")
        row("accelerometer range", f"saturated (flat tops): {r.acc_saturated_samples} samples "
            f"{_fmt_intervals(r.acc_saturated)}")
    v = c.vicon
    if v is not None:
        clock = f"truth lags by {v.clock.offset_s * 1e3:+.1f} ms (corr {v.clock.peak_correlation:.3f})" if v.clock else "offset: n/a"
        row("truth", f"{v.samples} samples {v.rate_hz:.2f} Hz, span {v.start_s:+.2f}..{v.stop_s:.2f} s; {clock}")
        row("truth stamps", f"jitter vs a regular {1e3 / v.rate_hz:.2f} ms base: std {v.stamp_jitter_std_s * 1e3:.2f} ms, "
            f"max {v.stamp_jitter_max_s * 1e3:.1f} ms; {v.near_duplicate_stamps} near-duplicate stamps")
        row("truth gaps (s)", f"{v.missing_samples} NaN rows: {_fmt_intervals(v.gaps)}")
    m = c.magnetometer
    if m is not None:
        dip = f"dip {m.dip_median_deg:+.1f} deg (std {m.dip_std_deg:.1f})" if m.dip_median_deg is not None else "dip n/a"
        row("magnetometer", f"|m| median {m.norm_median_ut:.1f} uT (5-95 %: {m.norm_p5_ut:.1f}-{m.norm_p95_ut:.1f}), "
            f"{dip}; disturbed {100 * m.disturbed_fraction:.1f} % of the samples: {_fmt_intervals(m.disturbed)}")
    for note in c.notes:
        row("note", note)
    return "\n".join(lines)
