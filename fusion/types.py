"""The data types that flow through the toolkit.

file -> loader -> `RawImu` -> calibration -> `ImuSamples` -> estimator -> `Trajectory`
-> scoring. A `Recording` bundles what one session provides.

Conventions: batch-first arrays, float64 seconds, SI units (the accelerometer
in g, said in the field name), scalar-first quaternions `R_world_body` with world z up.
Arrays are stored read-only: nothing downstream can modify what a loader produced.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


STANDARD_GRAVITY_M_S2 = 9.80665  # 1 g, the unit of `ImuSamples.acc_g`, in m/s^2 (CGPM 1901)

GyrTiming = Literal["end", "start"]
GYR_TIMINGS: tuple[str, ...] = ("end", "start")


def _check_timing(timing: str, what: str) -> None:
    if timing not in GYR_TIMINGS:
        raise ValueError(f"{what}: gyr_timing must be one of {', '.join(GYR_TIMINGS)}, got {timing!r}")


def _frozen(a: Any, dtype: type = float) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _check_time(t: np.ndarray, what: str) -> None:
    if t.ndim != 1 or len(t) == 0:
        raise ValueError(f"{what}: time stamps must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{what}: time stamps contain NaN or Inf")
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        raise ValueError(f"{what}: time stamps are not strictly increasing")


@dataclass(frozen=True, eq=False)
class RawImu:
    """Raw ADC counts as the board produced them, in one canonical layout.

    t: (N,) float64 s (unix time), strictly increasing.
    counts: (N, 6) native 10-bit counts in the order ax, ay, az, wx, wy, wz, *before* any
        sign flip (the x/y accelerometer inversion is part of the board model, applied in
        calibration). Loaders convert every file layout to this one.
    source: where it came from (a path, or "sim").
    gyr_timing: which interval a gyro sample covers, passed on to `ImuSamples` (see there).
    """

    t: np.ndarray
    counts: np.ndarray
    source: str = ""
    gyr_timing: GyrTiming = "end"

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _frozen(self.t))
        object.__setattr__(self, "counts", _frozen(self.counts))
        _check_time(self.t, self.source)
        _check_timing(self.gyr_timing, self.source)
        if self.counts.shape != (len(self.t), 6):
            raise ValueError(
                f"{self.source}: counts must be (N, 6) with N = {len(self.t)}, got {self.counts.shape}"
            )


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """Calibrated IMU samples, body frame.

    t: (N,) float64 s, strictly increasing. Use `dt` (the real steps), never a constant.
    gyr_rad_s: (N, 3) angular rate, rad/s, body frame.
    acc_g: (N, 3) specific force, in g, body frame; reads `R.inv().apply([0, 0, 1])` at rest.
    gyr_valid: (N,) bool, False where the gyro is known to be wrong (a dropout or
        saturation detected by `fusion.checks`). Estimators must not integrate those samples.
        All True unless a detector marked them.
    source: where the samples came from, for messages.
    mag_ut: (N, 3) magnetic field, uT, body frame, or None: the recording has no magnetometer (the
        course board), or it is not used (`--mag off`). NaN rows where there is no sample.
    mag_valid: (N,) bool, False where the magnetometer sample is missing (NaN) or known to be
        wrong; None without a magnetometer.
    gyr_timing: which interval gyro sample k stands for, a property of the recording set by
        its loader from evidence. "end" (the common convention, that of VQF, Madgwick,
        Mahony, Fusion, BROAD and the generic CSV): the rate over (t[k-1], t[k]], so the
        update at t[k] uses gyro k, then accelerometer k. "start": the rate over
        [t[k], t[k+1]), the course boards' pairing (gyro k, then accelerometer k + 1).
        Estimators read the rates through `interval_rates`, never by indexing `gyr_rad_s`.
    """

    t: np.ndarray
    gyr_rad_s: np.ndarray
    acc_g: np.ndarray
    gyr_valid: np.ndarray | None = None
    source: str = ""
    gyr_timing: GyrTiming = "end"
    mag_ut: np.ndarray | None = None
    mag_valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _frozen(self.t))
        object.__setattr__(self, "gyr_rad_s", _frozen(self.gyr_rad_s))
        object.__setattr__(self, "acc_g", _frozen(self.acc_g))
        valid = np.ones(len(self.t), bool) if self.gyr_valid is None else self.gyr_valid
        object.__setattr__(self, "gyr_valid", _frozen(valid, bool))
        _check_time(self.t, self.source)
        _check_timing(self.gyr_timing, self.source)
        n = len(self.t)
        for name in ("gyr_rad_s", "acc_g"):
            if getattr(self, name).shape != (n, 3):
                raise ValueError(f"{self.source}: {name} must be (N, 3) with N = {n}, got {getattr(self, name).shape}")
        if self.gyr_valid.shape != (n,):
            raise ValueError(f"{self.source}: gyr_valid must be (N,) with N = {n}, got {self.gyr_valid.shape}")
        if self.mag_ut is None:
            if self.mag_valid is not None:
                raise ValueError(f"{self.source}: mag_valid without mag_ut")
            return
        object.__setattr__(self, "mag_ut", _frozen(self.mag_ut))
        if self.mag_ut.shape != (n, 3):
            raise ValueError(f"{self.source}: mag_ut must be (N, 3) with N = {n}, got {self.mag_ut.shape}")
        finite = np.all(np.isfinite(self.mag_ut), axis=1)
        object.__setattr__(self, "mag_valid", _frozen(finite if self.mag_valid is None else self.mag_valid & finite, bool))
        if self.mag_valid.shape != (n,):
            raise ValueError(f"{self.source}: mag_valid must be (N,) with N = {n}, got {self.mag_valid.shape}")

    @property
    def has_mag(self) -> bool:
        """Whether there is a magnetometer to use (9-D estimation)."""
        return self.mag_ut is not None and bool(self.mag_valid.any())

    def __len__(self) -> int:
        return len(self.t)

    @property
    def dt(self) -> np.ndarray:
        """(N - 1,) time steps, s."""
        return np.diff(self.t)

    def interval_rates(self) -> tuple[np.ndarray, np.ndarray]:
        """The gyro reading for each interval between samples, as `gyr_timing` says.

        Returns `(rate, valid)`: rate (N - 1, 3) rad/s, body frame, row k the angular rate
        over [t[k], t[k+1]] (gyro sample k + 1 for "end", sample k for "start"); valid
        (N - 1,) bool, that sample's `gyr_valid`. A new array: callers may modify it.
        """
        first = 1 if self.gyr_timing == "end" else 0
        stop = first + len(self.t) - 1
        return np.array(self.gyr_rad_s[first:stop]), np.array(self.gyr_valid[first:stop])

    def window(self, start: int = 0, stop: int | None = None) -> "ImuSamples":
        """The samples `start:stop` (every per-sample array sliced alike; a new object)."""
        sl = slice(start, stop)
        return self.replace(t=self.t[sl], gyr_rad_s=self.gyr_rad_s[sl], acc_g=self.acc_g[sl],
                            gyr_valid=self.gyr_valid[sl], mag_ut=None if self.mag_ut is None else self.mag_ut[sl],
                            mag_valid=None if self.mag_valid is None else self.mag_valid[sl])

    def replace(self, **changes: Any) -> "ImuSamples":
        """A copy with some fields changed (the original is untouched)."""
        fields = dict(t=self.t, gyr_rad_s=self.gyr_rad_s, acc_g=self.acc_g, gyr_valid=self.gyr_valid,
                      source=self.source, gyr_timing=self.gyr_timing, mag_ut=self.mag_ut, mag_valid=self.mag_valid)
        fields.update(changes)
        if "mag_ut" in changes and "mag_valid" not in changes:
            fields["mag_valid"] = None  # recomputed from the new samples
        return ImuSamples(**fields)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Orientations over time.

    t: (N,) float64 s, strictly increasing.
    quat_wxyz: (N, 4) unit quaternions `R_world_body`. Rows may be NaN where the source has
        no orientation (VICON tracking gaps); `valid` tells which rows are usable.
    diagnostics: estimator-specific extras for reports, e.g. `{"loss": (K,) cost per iteration}`.
        An (N,) bool array is a per-sample flag (a filter's state switching on and off, e.g.
        `mag_used`, VQF's `rest_detected`): reports and `--rerun` show every one against the error.
    """

    t: np.ndarray
    quat_wxyz: np.ndarray
    diagnostics: Mapping[str, Any] = field(default_factory=dict)
    _last_interpolation: Any = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _frozen(self.t))
        object.__setattr__(self, "quat_wxyz", _frozen(self.quat_wxyz))
        _check_time(self.t, "trajectory")
        if self.quat_wxyz.shape != (len(self.t), 4):
            raise ValueError(f"trajectory: quat_wxyz must be (N, 4) with N = {len(self.t)}, got {self.quat_wxyz.shape}")

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def from_rotation(cls, t: np.ndarray, rotation: Rotation, **kwargs: Any) -> "Trajectory":
        return cls(t, rotation.as_quat(scalar_first=True), **kwargs)

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: rows holding a finite orientation."""
        return np.all(np.isfinite(self.quat_wxyz), axis=1)

    def rotation(self) -> Rotation:
        """All rows as one SciPy `Rotation` (raises if any row is invalid)."""
        return Rotation.from_quat(self.quat_wxyz, scalar_first=True)

    def interpolate(self, t: np.ndarray) -> tuple[Rotation | None, np.ndarray]:
        """Slerp the orientation at times `t` (N,).

        Returns `(rotation, mask)`: `mask` (N,) bool marks the query times inside the span
        whose two neighbouring rows are both valid (a query inside a NaN gap is *not*
        interpolated across the gap); `rotation` holds the slerped orientations at
        `t[mask]` (None if the mask is empty; `mask` is read-only). The last answer is kept for
        the same time stamps: every estimate of a recording lives on its IMU stamps, so the truth
        is slerped onto them once, not once per estimator.
        """
        t = np.asarray(t, dtype=float)
        last = self._last_interpolation
        if last is not None and len(last[0]) == len(t) and np.array_equal(last[0], t):
            return last[1], last[2]
        rotation, mask = self._interpolate(t)
        mask.setflags(write=False)
        object.__setattr__(self, "_last_interpolation", (_frozen(t), rotation, mask))
        return rotation, mask

    def _interpolate(self, t: np.ndarray) -> tuple[Rotation | None, np.ndarray]:
        valid = self.valid
        # The row at or before each query, and the one after it.
        right = np.searchsorted(self.t, t, side="right")
        inside = (t >= self.t[0]) & (t <= self.t[-1])
        left = np.clip(right - 1, 0, len(self.t) - 1)
        right = np.clip(right, 0, len(self.t) - 1)
        mask = inside & valid[left] & valid[right]
        if not np.any(mask):
            return None, mask
        good = np.flatnonzero(valid)
        if len(good) == 1:
            return Rotation.from_quat(np.repeat(self.quat_wxyz[good], mask.sum(), axis=0), scalar_first=True), mask
        slerp = Slerp(self.t[good], Rotation.from_quat(self.quat_wxyz[good], scalar_first=True))
        return slerp(t[mask]), mask


@dataclass(frozen=True, eq=False)
class Recording:
    """One session: calibrated IMU samples, optional ground truth and camera.

    id: the dataset id, e.g. "ece276a/3" or "sim".
    imu: calibrated samples (what estimators see).
    truth: VICON orientations on VICON's own clock (rows NaN in tracking gaps), or None.
    raw: the raw counts the samples were calibrated from (for checks), or None for
        recordings that come in physical units.
    calibration: the calibration applied (a `fusion.calibration.Calibration`), or None.
    camera: a camera source (see `fusion.camera`), or None.
    movement: (N,) bool over the IMU samples, the movement phases a benchmark scores
        (BROAD's `movement`, a CSV `movement` column), or None. A recording that has one is
        scored with the BROAD protocol by default (`fusion.evaluation.scoring.metrics.score`).
    truth_problem: why a recording whose file holds a truth was read without it, one line starting
        "no truth" (no row holds an orientation) or "truth unusable" (most rows are not
        orientations, or its span misses the IMU's: `fusion.format_checks.usable_truth`); None otherwise.
    truth_needs_alignment: the truth is given in frames of its own (a world whose vertical is not z,
        a marker body that is not the IMU's: RepoIMU's Vicon orientations), as its format says; it
        is scored through an alignment fitted per recording (`fusion.evaluation.scoring.align`) whether or
        not `--align` is given. False for truths already in our frames (VICON of the course, BROAD).
    """

    id: str
    imu: ImuSamples
    truth: Trajectory | None = None
    raw: RawImu | None = None
    calibration: Any = None
    camera: Any = None
    movement: np.ndarray | None = None
    truth_problem: str | None = None
    truth_needs_alignment: bool = False

    def __post_init__(self) -> None:
        if self.movement is not None:
            object.__setattr__(self, "movement", _frozen(self.movement, bool))
            if self.movement.shape != (len(self.imu),):
                raise ValueError(f"{self.id}: movement must be (N,) with N = {len(self.imu)}, got {self.movement.shape}")
