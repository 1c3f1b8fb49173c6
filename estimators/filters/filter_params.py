"""Parameters shared by the recursive attitude filters (`ukf`, `ukf-bias`, `ekf`).

`FilterParams` holds the fields every filter has (noise densities, initial variance,
accelerometer disturbance model, gating, invalid-gyro noise, heading_free);
`BiasFilterParams` adds the gyro bias, scale-factor and rest-detection fields of the
bias-estimating filters. Each filter's class derives from one of them, adds only its own
fields and, where its defaults differ, redeclares the field with the same alias.

Validation lives here once: `_check` (extended by subclasses through `super()`) checks
values, `_only_with` names the parameters that one option ignores. A parameter set away
from its default while the option it needs is off is an error (`ukf:alpha=0.1` with the
default `sigma=kraft` would otherwise be silently ignored).

Field order: dataclass inheritance puts base fields first; params are built by keyword
(`estimators.params.make_params`), so the order changes nothing but the listing order.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from ..params import FormerSpellings
from ..search import Tunable
from .steps._error_state import axes_mask
from .steps._rest import REST_ACC_G, REST_GYR_RAD_S, REST_TILT_RAD, REST_TIME_S

Gate = Literal["off", "skip", "inflate"]


def check_nonneg(owner: str, **values: float) -> None:
    """ValueError unless every value is a finite number >= 0."""
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0):
            raise ValueError(f"{owner}: {name} must be a finite number >= 0, got {value!r}")


def _text(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


@dataclass(frozen=True)
class FilterParams(FormerSpellings):
    """Fields of every recursive attitude filter (units in the names; aliases in brackets).

    Noise is given as continuous-time densities, so one set means the same at 100 Hz and at
    286 Hz (Sola 2017, "Quaternion kinematics for the error-state Kalman filter", Sec. 5.4:
    a density sigma^2 over a step dt gives the variance sigma^2 dt for a rate noise
    integrated into an angle, and sigma^2 / dt for a white measurement noise sampled once
    per step):

    process_noise_rad2_s (Q): gyro (attitude process) noise density, rad^2/s; step
        variance `Q dt` per axis.
    acc_noise_g2_s (R): accelerometer noise density, g^2 s; step variance `R / dt` per axis
        (a per-sample variance R_k at rate f is the density R_k / f). Without disturbance
        the attitude correction has the time constant `sqrt(R / Q)`, independent of the rate.
    init_var_rad2 (P0): initial attitude variance per axis, rad^2.
    disturbance_corr_s (tauc): correlation time of the external acceleration, s (adaptive R,
        see `_accel.AccDisturbance`); 0 turns the adaptation off.
    disturbance_window_s (tauw): time constant of its running variance, s.
    acc_lowpass_s (taulp): time constant of the accelerometer low-passed in the strapdown
        frame, s (see `_accel.AccDisturbance`); each update uses the low-passed or the raw
        sample, whichever has the smaller noise density. 0 turns it off (raw samples only);
        it needs the disturbance model (disturbance_corr_s > 0).
    acc_lowpass_window_s (taulpw): time constant of the running variance of the low-passed
        signal, s, from which its noise density is measured.
    use_acc (acc): False turns the accelerometer update off (dead reckoning + covariance).
    gate, gate_g: fixed accelerometer gating (see `_accel.acc_variance_scale`), off by
        default (the adaptive R replaces it); gate_g applies only with gate=skip or inflate.
    heading_free (hf): the accelerometer correction does not turn the estimate about the
        predicted vertical (see the `ukf` and `ekf` module docstrings).
    invalid_gyr_var_rad2_s2 (Qinvalid): assumed rate variance on invalid gyro samples,
        (rad/s)^2 (4: a 2 rad/s standard deviation).
    stuck_gyro_check (stuck): a gyro reading found stuck online (`_stuck.stuck_gyro_update`:
        all channels flat within their resolution while the accelerometer moves, the causal
        form of `fusion.checks.detect_freezes`) is treated as invalid, so that a freeze that
        nobody flagged (`--dropouts off`, or an IMU whose freezes the loader does not know)
        does not hold the attitude still while the board turns.

    Every noise and prior parameter is a variance (a variance density for continuous-time
    noise), here and in the smoothers; a datasheet's noise density n, given as a standard
    deviation density in rad/s/sqrt(Hz), is Q = n^2 rad^2/s. The former standard-deviation
    spellings (`Qbad`, `invalid_gyr_std_rad_s`) are accepted for one release, squared, with a
    warning (`fusion.estimators.params.FORMERLY_STD`).
    """

    owner: ClassVar[str] = "filter"  # the registry name in error messages
    former_std: ClassVar[tuple[str, ...]] = ("invalid_gyr_std_rad_s", "Qbad")  # `AcceptsFormerSpellings`

    # Search ranges (`fusion.estimators.search`): the noise densities two decades either side of the
    # default; the grids (Q x R x tauc, 27 settings) are benchmarks/cross_validate.py's, a factor of
    # about 3 either side of the defaults, which that script checks by leave-one-recording-out.
    process_noise_rad2_s: float = field(default=3e-4, metadata={
        "alias": "Q", "search": Tunable(3e-6, 3e-2, grid=(1e-4, 3e-4, 1e-3))})
    acc_noise_g2_s: float = field(default=3e-5, metadata={
        "alias": "R", "search": Tunable(3e-7, 3e-3, grid=(1e-5, 3e-5, 1e-4))})
    init_var_rad2: float = field(default=1e-4, metadata={"alias": "P0"})
    # a decade either side of the default (0: no adaptation, outside a log range)
    disturbance_corr_s: float = field(default=0.1, metadata={
        "alias": "tauc", "search": Tunable(0.01, 1.0, grid=(0.03, 0.1, 0.3))})
    disturbance_window_s: float = field(default=0.5, metadata={"alias": "tauw"})
    # cross_validate.py's span, 0.3-10 s, around VQF's 3 s (Laidig & Seel 2023, Sec. 3.2, tauAcc)
    acc_lowpass_s: float = field(default=1.0, metadata={"alias": "taulp", "search": Tunable(0.3, 10.0)})
    acc_lowpass_window_s: float = field(default=3.0, metadata={"alias": "taulpw"})
    use_acc: bool = field(default=True, metadata={"alias": "acc"})
    gate: Gate = "off"
    gate_g: float = 0.2
    heading_free: bool = field(default=True, metadata={"alias": "hf"})
    invalid_gyr_var_rad2_s2: float = field(default=4.0, metadata={"alias": "Qinvalid"})
    stuck_gyro_check: bool = field(default=True, metadata={"alias": "stuck"})

    def __post_init__(self) -> None:
        self._check()
        self._check_applicable()

    def _check(self) -> None:
        """Value checks; subclasses extend them through `super()._check()`."""
        owner = self.owner
        check_nonneg(
            owner,
            process_noise_rad2_s=self.process_noise_rad2_s,
            acc_noise_g2_s=self.acc_noise_g2_s,
            init_var_rad2=self.init_var_rad2,
            invalid_gyr_var_rad2_s2=self.invalid_gyr_var_rad2_s2,
        )
        if self.use_acc and self.acc_noise_g2_s <= 0.0:
            raise ValueError(f"{owner}: acc_noise_g2_s (R) must be > 0 when the accelerometer is used, got {self.acc_noise_g2_s}")
        check_nonneg(owner, disturbance_corr_s=self.disturbance_corr_s)
        if not (math.isfinite(self.disturbance_window_s) and self.disturbance_window_s > 0.0):
            raise ValueError(f"{owner}: disturbance_window_s must be > 0 s, got {self.disturbance_window_s!r}")
        check_nonneg(owner, acc_lowpass_s=self.acc_lowpass_s)
        if not (math.isfinite(self.acc_lowpass_window_s) and self.acc_lowpass_window_s > 0.0):
            raise ValueError(f"{owner}: acc_lowpass_window_s must be > 0 s, got {self.acc_lowpass_window_s!r}")
        if self.gate not in ("off", "skip", "inflate"):
            raise ValueError(f"{owner}: gate must be off, skip or inflate, got {self.gate!r}")
        if not (math.isfinite(self.gate_g) and self.gate_g > 0.0):
            raise ValueError(f"{owner}: gate_g must be > 0 g, got {self.gate_g!r}")

    def _only_with(self) -> dict[str, tuple[str, tuple[Any, ...]]]:
        """Parameter -> (the option it needs, the option values it applies with)."""
        return {"gate_g": ("gate", ("skip", "inflate"))}

    def _check_applicable(self) -> None:
        """A parameter away from its default is an error where its option ignores it."""
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        for name, (option, values) in self._only_with().items():
            current = getattr(self, option)
            if current not in values and getattr(self, name) != defaults[name]:
                raise ValueError(
                    f"{self.owner}: {name} applies only with {option}={' or '.join(map(_text, values))}; "
                    f"it is ignored with {option}={_text(current)}"
                )


@dataclass(frozen=True)
class BiasFilterParams(FilterParams):
    """`FilterParams` plus gyro bias, scale factors and rest detection (ukf-bias, ekf).

    bias_walk_rad2_s3 (Qb): gyro-bias random-walk density, rad^2/s^3 (step variance Qb dt).
    init_bias_var_rad2_s2 (Pb0): initial bias variance per axis, (rad/s)^2. The initial bias
        estimate is zero (calibration removed the bias of the initial rest).
    bias_max_rad_s (bmax): the bias estimate is clipped to this per axis, rad/s (the
        calibration removed the rest bias; a larger one means a wrong update).
    estimate_scale (scale): gyro scale-factor corrections `s` in the state; the six scale
        fields below apply only with it.
    init_scale_var (Ps0): initial scale-factor variance per axis, dimensionless (1e-2: a
        10 % standard deviation, the tolerance of a low-cost MEMS gyro read with its
        datasheet sensitivity).
    scale_walk_1_s (Qsw): scale-factor random-walk density, 1/s (step variance Qsw dt).
    scale_max (smax): the scale correction is clipped to this per axis.
    scale_test_error (sprt): the error probabilities (alpha = beta) of the sequential test that
        decides, in 6-D, whether the gyro has a scale error or is calibrated
        (`_scale_test.ScaleTest`; "Scale test" in `fusion.estimators.filters.ekf`; 0: no test, the prior
        `init_scale_var` throughout).
    calibrated_scale_var (Psc): the scale-factor variance per axis of a calibrated gyro, the
        test's H0 (1e-4: 1 %); with `init_scale_var` at or below it there is nothing to test.
    scale_axes (saxes): the body axes whose scale factor is estimated ("xy" by default; the
        others stay at their calibration). With the body z axis near vertical, as a hand-held
        or worn IMU mostly is, z's scale acts on heading alone, which a gyro and an
        accelerometer cannot observe; estimating it lets the accelerometer's corrections after a
        long gyro outage drive a wrong z scale and with it the heading.
    rest_gyr_rad_s, rest_acc_g, rest_time_s: rest detection (gyro norm, accelerometer
        deviation, minimum duration) for the zero-rate bias update; rest_time_s = inf
        turns it off.
    rest_tilt_rad (rtilt): the rest detector's tilt test (`_rest.RestDetector`): a still stretch
        ends where the low-passed accelerometer has turned by more than this since it began, rad,
        so that a turn slower than the gyro threshold is not read as bias; inf: no test.
    rest_noise_rad2_s (Rrest): density of the gyro reading at rest, rad^2/s (step variance
        Rrest / dt).
    mag_heading_noise_rad2_s (Rm): density of the magnetometer's heading measurement, rad^2 s
        (step variance Rm / dt); with the gyro noise Q it sets the heading correction's time
        constant, about sqrt(Rm / Q) (30 s by default). The magnetometer fields (mag_*) apply to
        recordings with a magnetometer (9-D; `ekf` and `ukf-bias`, the heading-only update of
        `_magnetometer.heading_update`); `--mag off` or a recording without one runs the 6-D filter,
        unchanged.
    mag_norm_gate_frac (mnorm): a magnetometer sample is in the gates while its norm is within
        this fraction of the learned reference norm (`_magnetometer.MagReference`).
    mag_dip_gate_rad (mdip): ... and its dip within this of the learned reference dip, rad.
    mag_min_undisturbed_s (mtime): the gates must have held this long, s, before a sample
        corrects the heading.
    mag_ref_s (mref): time constant of the learned reference norm and dip, s.
    mag_rate_rad_s (mrate): the heading measurement's variance is Rm / dt (1 + (w / mrate)^2),
        w the rate about the vertical, rad/s: a magnetometer sample that lags the gyro (its own
        sampling and low-pass) errs in heading by the angle turned over the lag; inf: constant.
    mag_heading_gate_rad (mhg): the heading gate (`_magnetometer.MagReference.heading_gate_update`):
        a sample that passed the norm and dip gates corrects the heading while its low-passed
        heading innovation psi satisfies psi^2 < 10.83 (H P H^T + mhg^2) (chi-square, one degree
        of freedom, 99.9 %), mhg the field direction's tolerated slow deviation, rad; inf: no gate.
    mag_heading_gate_s (mhgs): the innovation's low-pass time constant, s.
    mag_heading_gate_max_s (mhgmax): after this long rejected without interruption, s, the field
        is believed again until the innovation is back inside the bound (the heading, turned by a
        gyro bias, may be what is wrong).
    mag_hard_iron (mhi): estimate a magnet carried with the sensor (a constant body-frame
        offset) by a sphere fit (`_magnetometer.HardIron`); while the fit is trusted and its radius
        is the reference norm, samples are used with the offset removed. The three fields below
        apply only with it.
    mag_hard_iron_window_s (mhiw): time constant of the sphere fit's exponential window, s.
    mag_hard_iron_residual_ut (mhires): the fit is trusted while its RMS residual is below this,
        uT, and its offset above it.
    mag_hard_iron_coverage (mhicov): ... and the samples' spread, the geometric mean of the
        standard deviations along the principal axes, at least this fraction of the radius.
    """

    # Search ranges, no grid (the grid stays at Q x R x tauc): two decades either side of the default
    # (benchmarks/cross_validate.py tries 1e-9-1e-7).
    bias_walk_rad2_s3: float = field(default=1e-8, metadata={"alias": "Qb", "search": Tunable(1e-10, 1e-6)})
    init_bias_var_rad2_s2: float = field(default=1e-5, metadata={"alias": "Pb0"})
    bias_max_rad_s: float = field(default=0.035, metadata={"alias": "bmax"})
    estimate_scale: bool = field(default=True, metadata={"alias": "scale"})
    # standard deviations of 1 % to 20 % (scale_max's bound; cross_validate.py tries 3-17 %)
    init_scale_var: float = field(default=1e-2, metadata={"alias": "Ps0", "search": Tunable(1e-4, 4e-2)})
    scale_walk_1_s: float = field(default=1e-8, metadata={"alias": "Qsw"})
    scale_max: float = field(default=0.2, metadata={"alias": "smax"})
    # error probabilities of 1-30 % (Wald's test needs < 50 %; cross_validate.py tries 5-20 %, and 0: no test)
    scale_test_error: float = field(default=0.1, metadata={"alias": "sprt", "search": Tunable(0.01, 0.3)})
    # standard deviations of 0.3 % to 3 % (cross_validate.py tries 0.5-1.7 %)
    calibrated_scale_var: float = field(default=1e-4, metadata={"alias": "Psc", "search": Tunable(1e-5, 1e-3)})
    scale_axes: str = field(default="xy", metadata={"alias": "saxes"})
    rest_gyr_rad_s: float = REST_GYR_RAD_S
    rest_acc_g: float = REST_ACC_G
    rest_time_s: float = REST_TIME_S
    rest_tilt_rad: float = field(default=REST_TILT_RAD, metadata={"alias": "rtilt"})
    rest_noise_rad2_s: float = field(default=1e-6, metadata={"alias": "Rrest"})
    # two decades either side of the default (benchmarks/broad_9d.py --leave-one-out tries 0.03-1);
    # the unit is rad^2 s, not the rad^2/s its suffix reads as elsewhere (a measurement's density)
    mag_heading_noise_rad2_s: float = field(default=0.3, metadata={
        "alias": "Rm", "unit": "rad^2 s", "search": Tunable(3e-3, 30.0, magnetometer=True)})
    mag_norm_gate_frac: float = field(default=0.1, metadata={"alias": "mnorm"})
    mag_dip_gate_rad: float = field(default=math.radians(10.0), metadata={"alias": "mdip"})
    mag_min_undisturbed_s: float = field(default=3.0, metadata={"alias": "mtime"})
    mag_ref_s: float = field(default=20.0, metadata={"alias": "mref"})
    mag_rate_rad_s: float = field(default=2.0, metadata={"alias": "mrate"})
    mag_heading_gate_rad: float = field(default=math.radians(2.0), metadata={"alias": "mhg"})
    mag_heading_gate_s: float = field(default=1.0, metadata={"alias": "mhgs"})
    mag_heading_gate_max_s: float = field(default=30.0, metadata={"alias": "mhgmax"})
    mag_hard_iron: bool = field(default=True, metadata={"alias": "mhi"})
    mag_hard_iron_window_s: float = field(default=10.0, metadata={"alias": "mhiw"})
    mag_hard_iron_residual_ut: float = field(default=2.0, metadata={"alias": "mhires"})
    mag_hard_iron_coverage: float = field(default=0.3, metadata={"alias": "mhicov"})

    def _check(self) -> None:
        owner = self.owner
        check_nonneg(owner, bias_walk_rad2_s3=self.bias_walk_rad2_s3, init_bias_var_rad2_s2=self.init_bias_var_rad2_s2)
        super()._check()
        check_nonneg(owner, rest_gyr_rad_s=self.rest_gyr_rad_s, rest_acc_g=self.rest_acc_g,
                     rest_noise_rad2_s=self.rest_noise_rad2_s)
        if not 0.0 < self.rest_tilt_rad < math.pi / 2 and self.rest_tilt_rad != math.inf:
            raise ValueError(f"{owner}: rest_tilt_rad must be in (0, pi/2) rad (inf: no tilt test), "
                             f"got {self.rest_tilt_rad!r}")
        if not (self.bias_max_rad_s > 0.0):
            raise ValueError(f"{owner}: bias_max_rad_s must be > 0 rad/s, got {self.bias_max_rad_s!r}")
        if not (self.rest_time_s > 0.0):
            raise ValueError(f"{owner}: rest_time_s must be > 0 s (inf: no rest detection), got {self.rest_time_s!r}")
        if self.rest_noise_rad2_s <= 0.0 and math.isfinite(self.rest_time_s):
            raise ValueError(f"{owner}: rest_noise_rad2_s must be > 0 when rest detection is on")
        check_nonneg(owner, init_scale_var=self.init_scale_var, scale_walk_1_s=self.scale_walk_1_s)
        if not (self.scale_max > 0.0 and self.scale_max < 1.0):
            raise ValueError(f"{owner}: scale_max must be in (0, 1), got {self.scale_max!r}")
        if not 0.0 <= self.scale_test_error < 0.5:
            raise ValueError(f"{owner}: scale_test_error must be in [0, 0.5) (0: no test), "
                             f"got {self.scale_test_error!r}")
        if not (self.calibrated_scale_var > 0.0 and math.isfinite(self.calibrated_scale_var)):
            raise ValueError(f"{owner}: calibrated_scale_var must be a finite number > 0, "
                             f"got {self.calibrated_scale_var!r}")
        try:
            axes_mask(self.scale_axes)
        except ValueError as exc:
            raise ValueError(f"{owner}: {exc}") from None
        if not self.mag_rate_rad_s > 0.0:
            raise ValueError(f"{owner}: mag_rate_rad_s must be > 0 (inf: no rate term), got {self.mag_rate_rad_s!r}")
        for name in ("mag_heading_gate_rad", "mag_heading_gate_max_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0.0):
                raise ValueError(f"{owner}: {name} must be a number > 0 (inf: none), got {value!r}")
        for name in ("mag_heading_noise_rad2_s", "mag_norm_gate_frac", "mag_dip_gate_rad", "mag_ref_s",
                     "mag_heading_gate_s", "mag_hard_iron_window_s", "mag_hard_iron_residual_ut", "mag_hard_iron_coverage"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{owner}: {name} must be a finite number > 0, got {value!r}")
        check_nonneg(owner, mag_min_undisturbed_s=self.mag_min_undisturbed_s)

    def _only_with(self) -> dict[str, tuple[str, tuple[Any, ...]]]:
        scale = ("estimate_scale", (True,))
        hard_iron = ("mag_hard_iron", (True,))
        return {**super()._only_with(), "init_scale_var": scale, "scale_walk_1_s": scale, "scale_max": scale,
                "scale_axes": scale, "scale_test_error": scale, "calibrated_scale_var": scale,
                "mag_hard_iron_window_s": hard_iron, "mag_hard_iron_residual_ut": hard_iron,
                "mag_hard_iron_coverage": hard_iron}
