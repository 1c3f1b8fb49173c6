"""Parameters shared by the recursive attitude filters (`ukf`, `ukf-bias`, `ekf`).

`FilterParams` holds the fields every filter has (noise densities, initial variance,
accelerometer disturbance model, gating, invalid-gyro noise, heading_free);
`BiasFilterParams` adds the gyro bias, scale-factor and rest-detection fields of the
bias-estimating filters. Each filter's class derives from one of them, adds only its own
fields and, where its defaults differ, redeclares the field with `param_as` (the same alias,
unit, meaning, reference and range; `fusion.estimators.params`). Each field is documented where
it is declared (`param`): its unit, meaning, reference and valid range, which `fusion list NAME`
prints.

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
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from ..params import FormerSpellings, param
from ..search import Tunable
from .steps._error_state import axes_mask
from .steps._rest import REST_ACC_G, REST_GYR_RAD_S, REST_TILT_RAD, REST_TIME_S

Gate = Literal["off", "skip", "inflate"]

# The references the fields cite (each field's "reference" metadata, `fusion list NAME`).
SOLA_NOISE = ('Sola 2017, "Quaternion kinematics for the error-state Kalman filter", Sec. 5.4 (continuous-time '
              'noise over a step)')
VQF = 'Laidig & Seel 2023, "VQF: Highly accurate IMU orientation estimation", Information Fusion 91'
SUH_ADAPTIVE = "Suh 2010, IEEE TIM 59(12) (R adapted to the external acceleration)"
WALD = 'Wald 1945, "Sequential tests of statistical hypotheses", Ann. Math. Stat. 16(2), Sec. 3'
BAR_SHALOM_GATE = ('Bar-Shalom, Li & Kirubarajan 2001, "Estimation with Applications to Tracking and Navigation", '
                   'Sec. 5.4.2 (the innovation gate)')
HARD_IRON_FIT = ('Vasconcelos et al. 2011, "Geometric approach to strapdown magnetometer calibration in sensor '
                 'frame", IEEE TAES 47(2), eqs. 4-6 (hard iron only)')


def check_nonneg(owner: str, **values: float) -> None:
    """ValueError unless every value is a finite number >= 0."""
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0):
            raise ValueError(f"{owner}: {name} must be a finite number >= 0, got {value!r}")


def _text(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


@dataclass(frozen=True)
class FilterParams(FormerSpellings):
    """Fields of every recursive attitude filter; each field's unit, meaning, reference and valid
    range are at the field (`fusion list ukf` prints them).

    Noise is given as continuous-time densities, so one set means the same at 100 Hz and at
    286 Hz (Sola 2017, "Quaternion kinematics for the error-state Kalman filter", Sec. 5.4:
    a density sigma^2 over a step dt gives the variance sigma^2 dt for a rate noise
    integrated into an angle, and sigma^2 / dt for a white measurement noise sampled once
    per step; a per-sample variance R_k at rate f is the density R_k / f). Every noise and prior
    parameter is a variance (a variance density for continuous-time noise), here and in the
    smoothers; a datasheet's noise density n, given as a standard deviation density in
    rad/s/sqrt(Hz), is Q = n^2 rad^2/s. The former
    standard-deviation spellings (`Qbad`, `invalid_gyr_std_rad_s`) are accepted for one release,
    squared, with a warning (`fusion.estimators.params.FORMERLY_STD`).
    """

    owner: ClassVar[str] = "filter"  # the registry name in error messages
    former_std: ClassVar[tuple[str, ...]] = ("invalid_gyr_std_rad_s", "Qbad")  # `AcceptsFormerSpellings`

    # Search ranges (`fusion.estimators.search`): the noise densities two decades either side of the
    # default; the grids (Q x R x tauc, 27 settings) are benchmarks/cross_validate.py's, a factor of
    # about 3 either side of the defaults, which that script checks by leave-one-recording-out.
    process_noise_rad2_s: float = param(
        3e-4, alias="Q", unit="rad^2/s", valid=">= 0, finite", reference=SOLA_NOISE,
        meaning="Gyro (attitude process) noise density: each step adds the variance Q dt per axis to the attitude.",
        search=Tunable(3e-6, 3e-2, grid=(1e-4, 3e-4, 1e-3)))
    acc_noise_g2_s: float = param(
        3e-5, alias="R", unit="g^2 s", valid="> 0 when the accelerometer is used (>= 0 without it), finite",
        reference=SOLA_NOISE,
        meaning="Accelerometer noise density: a sample has the variance R / dt per axis, and without disturbance "
                "the attitude correction has the time constant sqrt(R / Q), at any sampling rate.",
        search=Tunable(3e-7, 3e-3, grid=(1e-5, 3e-5, 1e-4)))
    init_var_rad2: float = param(1e-4, alias="P0", unit="rad^2", valid=">= 0, finite",
                                 meaning="Initial attitude variance per axis.")
    # a decade either side of the default (0: no adaptation, outside a log range)
    disturbance_corr_s: float = param(
        0.1, alias="tauc", unit="s", valid=">= 0, finite; 0: no adaptation", reference=SUH_ADAPTIVE,
        meaning="Correlation time of the external acceleration, from which the accelerometer's noise is raised "
                "while the board accelerates (the adaptive R of `_accel.AccDisturbance`); 0 turns the adaptation off.",
        search=Tunable(0.01, 1.0, grid=(0.03, 0.1, 0.3)))
    disturbance_window_s: float = param(
        0.5, alias="tauw", unit="s", valid="> 0, finite", reference=SUH_ADAPTIVE,
        meaning="Time constant of the running variance of the external acceleration that the adaptive "
                "accelerometer noise is taken from.")
    # cross_validate.py's span, 0.3-10 s, around VQF's 3 s (Laidig & Seel 2023, Sec. 3.2, tauAcc)
    acc_lowpass_s: float = param(
        1.0, alias="taulp", unit="s", valid=">= 0, finite; 0: raw samples only", reference=VQF + ", Sec. 3.2, eq. 7",
        meaning="Time constant of the accelerometer low-passed in the strapdown frame: each update uses the "
                "low-passed or the raw sample, whichever has the smaller noise density, and 0 uses the raw samples "
                "only (the low-pass needs disturbance_corr_s > 0).",
        search=Tunable(0.3, 10.0))
    acc_lowpass_window_s: float = param(
        3.0, alias="taulpw", unit="s", valid="> 0, finite",
        meaning="Time constant of the running variance of the low-passed accelerometer, from which its noise "
                "density is measured.")
    use_acc: bool = param(True, alias="acc", unit="", valid="true | false",
                          meaning="Use the accelerometer update; false runs dead reckoning, with the covariance "
                                  "propagated.")
    gate: Gate = param(
        "off", unit="", valid="off | skip | inflate", reference="Sabatini 2006, IEEE Trans. Biomed. Eng. 53(7) "
        "(the |a| - g norm test)",
        meaning="Fixed accelerometer gating on the deviation of the sample's norm from 1 g (`_accel."
                "acc_variance_scale`): skip drops a sample beyond gate_g, inflate scales R by 1 + (deviation / "
                "gate_g)^2, off (the default, the adaptive R replacing it) uses every sample.")
    gate_g: float = param(0.2, unit="g", valid="> 0, finite; applies only with gate=skip or inflate",
                          meaning="The deviation of the accelerometer's norm from 1 g that gate acts on.")
    heading_free: bool = param(
        True, alias="hf", unit="", valid="true | false",
        meaning="The accelerometer correction does not turn the estimate about the predicted vertical (its gain is "
                "projected off it), so that the accelerometer never moves the heading.")
    invalid_gyr_var_rad2_s2: float = param(
        4.0, alias="Qinvalid", unit="rad^2/s^2", valid=">= 0, finite",
        meaning="Rate variance assumed on the gyro samples marked invalid (4: a standard deviation of 2 rad/s).")
    stuck_gyro_check: bool = param(
        True, alias="stuck", unit="", valid="true | false",
        meaning="Treat a gyro reading found stuck online (all channels flat within their resolution while the "
                "accelerometer moves, the causal form of `fusion.checks.detect_freezes`) as invalid, so that a freeze "
                "nobody flagged does not hold the attitude still while the board turns.")

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
    """`FilterParams` plus gyro bias, scale factors, rest detection and the magnetometer (ukf-bias,
    ekf); each field's unit, meaning, reference and valid range are at the field (`fusion list ekf`).

    The magnetometer fields (mag_*) apply to recordings with a magnetometer (9-D; the heading-only
    update of `_magnetometer.heading_update`); `--mag off` or a recording without one runs the 6-D
    filter, unchanged.
    """

    # Search ranges, no grid (the grid stays at Q x R x tauc): two decades either side of the default
    # (benchmarks/cross_validate.py tries 1e-9-1e-7).
    bias_walk_rad2_s3: float = param(
        1e-8, alias="Qb", unit="rad^2/s^3", valid=">= 0, finite", reference=SOLA_NOISE,
        meaning="Gyro-bias random-walk density: each step adds the variance Qb dt per axis to the bias.",
        search=Tunable(1e-10, 1e-6))
    init_bias_var_rad2_s2: float = param(
        1e-5, alias="Pb0", unit="rad^2/s^2", valid=">= 0, finite",
        meaning="Initial gyro-bias variance per axis, around a zero initial bias (the calibration removed the bias "
                "of the initial rest).")
    bias_max_rad_s: float = param(
        0.035, alias="bmax", unit="rad/s", valid="> 0",
        meaning="The bias estimate is clipped to this per axis (the calibration removed the rest bias, so a larger "
                "one means a wrong update).")
    estimate_scale: bool = param(
        True, alias="scale", unit="", valid="true | false",
        meaning="Estimate gyro scale-factor corrections in the state; the scale fields (init_scale_var, "
                "scale_walk_1_s, scale_max, scale_test_error, calibrated_scale_var, scale_axes) apply only with it.")
    # standard deviations of 1 % to 20 % (scale_max's bound; cross_validate.py tries 3-17 %)
    init_scale_var: float = param(
        1e-2, alias="Ps0", unit="1", valid=">= 0, finite",
        meaning="Initial scale-factor variance per axis (1e-2: a 10 % standard deviation, the tolerance of a "
                "low-cost MEMS gyro read with its datasheet sensitivity).",
        search=Tunable(1e-4, 4e-2))
    scale_walk_1_s: float = param(
        1e-8, alias="Qsw", unit="1/s", valid=">= 0, finite", reference=SOLA_NOISE,
        meaning="Scale-factor random-walk density: each step adds the variance Qsw dt per axis to the scale factor.")
    scale_max: float = param(0.2, alias="smax", unit="1", valid="(0, 1)",
                             meaning="The scale-factor correction is clipped to this per axis.")
    # error probabilities of 1-30 % (Wald's test needs < 50 %; cross_validate.py tries 5-20 %, and 0: no test)
    scale_test_error: float = param(
        0.1, alias="sprt", unit="1", valid="[0, 0.5); 0: no test", reference=WALD,
        meaning="Error probability (alpha = beta) of the sequential test that decides, in 6-D, whether the gyro "
                "has a scale error or is calibrated (`_scale_test.ScaleTest`); 0 runs no test and keeps the prior "
                "init_scale_var throughout.",
        search=Tunable(0.01, 0.3))
    # standard deviations of 0.3 % to 3 % (cross_validate.py tries 0.5-1.7 %)
    calibrated_scale_var: float = param(
        1e-4, alias="Psc", unit="1", valid="> 0, finite", reference=WALD,
        meaning="Scale-factor variance per axis of a calibrated gyro, the scale test's null hypothesis (1e-4: 1 %); "
                "with init_scale_var at or below it there is nothing to test.",
        search=Tunable(1e-5, 1e-3))
    scale_axes: str = param(
        "xy", alias="saxes", unit="", valid="distinct letters from xyz, or none",
        meaning="The body axes whose scale factor is estimated, the others staying at their calibration: z is left "
                "out by default because with the body z axis near vertical, as a hand-held or worn IMU mostly is, "
                "its scale acts on heading alone, which a gyro and an accelerometer cannot observe.")
    rest_gyr_rad_s: float = param(
        REST_GYR_RAD_S, unit="rad/s", valid=">= 0, finite", reference=VQF + ", Sec. 3.4",
        meaning="Rest detection: a sample counts as still while the gyro reading's norm is below this.")
    rest_acc_g: float = param(
        REST_ACC_G, unit="g", valid=">= 0, finite", reference=VQF + ", Sec. 3.4",
        meaning="Rest detection: a sample counts as still while the accelerometer is within this of its low-pass "
                "and of 1 g.")
    rest_time_s: float = param(
        REST_TIME_S, unit="s", valid="> 0; inf: no rest detection", reference=VQF + ", Sec. 3.4",
        meaning="Rest detection: the recording is at rest, and the zero-rate bias update runs, once samples have "
                "been still this long without interruption.")
    rest_tilt_rad: float = param(
        REST_TILT_RAD, alias="rtilt", unit="rad", valid="(0, pi/2); inf: no tilt test",
        meaning="The rest detector's tilt test (`_rest.RestDetector`): a still stretch ends where the low-passed "
                "accelerometer has turned by more than this since it began, so that a turn slower than the gyro "
                "threshold is not read as bias.")
    rest_noise_rad2_s: float = param(
        1e-6, alias="Rrest", unit="rad^2/s", valid="> 0 while rest detection is on (>= 0 otherwise), finite",
        reference=VQF + ", Sec. 3.4",
        meaning="Density of the gyro reading at rest in the zero-rate bias update: a sample has the variance "
                "Rrest / dt.")
    # two decades either side of the default (benchmarks/broad_9d.py --leave-one-out tries 0.03-1);
    # the unit is rad^2 s, not the rad^2/s its suffix reads as elsewhere (a measurement's density)
    mag_heading_noise_rad2_s: float = param(
        0.3, alias="Rm", unit="rad^2 s", valid="> 0, finite", reference=VQF + ", Sec. 3.3 (heading-only correction)",
        meaning="Density of the magnetometer's heading measurement: a sample has the variance Rm / dt, and with "
                "the gyro noise Q it sets the heading correction's time constant, about sqrt(Rm / Q) (30 s by "
                "default).",
        search=Tunable(3e-3, 30.0, magnetometer=True))
    mag_norm_gate_frac: float = param(
        0.1, alias="mnorm", unit="fraction", valid="> 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="A magnetometer sample passes the norm gate while its norm is within this fraction of the learned "
                "reference norm (`_magnetometer.MagReference`).")
    mag_dip_gate_rad: float = param(
        math.radians(10.0), alias="mdip", unit="rad", valid="> 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="A magnetometer sample passes the dip gate while its dip is within this of the learned reference "
                "dip.")
    mag_min_undisturbed_s: float = param(
        3.0, alias="mtime", unit="s", valid=">= 0, finite", reference=VQF + ", Sec. 3.3",
        meaning="The norm and dip gates must have held this long without interruption before a sample corrects "
                "the heading.")
    mag_ref_s: float = param(20.0, alias="mref", unit="s", valid="> 0, finite",
                             meaning="Time constant of the learned reference norm and dip.")
    mag_rate_rad_s: float = param(
        2.0, alias="mrate", unit="rad/s", valid="> 0; inf: a constant variance",
        meaning="The heading measurement's variance is Rm / dt (1 + (w / mrate)^2), w the rate about the vertical, "
                "because a magnetometer sample that lags the gyro (its own sampling and low-pass) errs in heading "
                "by the angle turned over the lag.")
    mag_heading_gate_rad: float = param(
        math.radians(2.0), alias="mhg", unit="rad", valid="> 0; inf: no heading gate", reference=BAR_SHALOM_GATE,
        meaning="The heading gate's tolerated slow deviation of the field's direction: a sample that passed the "
                "norm and dip gates corrects the heading while its low-passed heading innovation psi satisfies "
                "psi^2 < 10.83 (H P H^T + mhg^2), the chi-square bound of one degree of freedom at 99.9 % "
                "(`_magnetometer.MagReference.heading_gate_update`).")
    mag_heading_gate_s: float = param(
        1.0, alias="mhgs", unit="s", valid="> 0, finite",
        meaning="Time constant of the low-pass on the heading innovation that the heading gate tests.")
    mag_heading_gate_max_s: float = param(
        30.0, alias="mhgmax", unit="s", valid="> 0; inf: no limit",
        meaning="After this long rejected by the heading gate without interruption, the field is believed again "
                "until the innovation is back inside the gate (the heading, turned by a gyro bias, may be what is "
                "wrong).")
    mag_hard_iron: bool = param(
        True, alias="mhi", unit="", valid="true | false", reference=HARD_IRON_FIT,
        meaning="Estimate a magnet carried with the sensor (a constant body-frame offset) by a sphere fit "
                "(`_magnetometer.HardIron`) and, while the fit is trusted and its radius is the reference norm, use "
                "the samples with the offset removed; the mag_hard_iron_* fields apply only with it.")
    mag_hard_iron_window_s: float = param(
        10.0, alias="mhiw", unit="s", valid="> 0, finite", reference=HARD_IRON_FIT,
        meaning="Time constant of the sphere fit's exponential window.")
    mag_hard_iron_residual_ut: float = param(
        2.0, alias="mhires", unit="uT", valid="> 0, finite",
        meaning="The sphere fit is trusted while its RMS residual is below this and its offset is above it.")
    mag_hard_iron_coverage: float = param(
        0.3, alias="mhicov", unit="1", valid="> 0, finite",
        meaning="The sphere fit is trusted only while the samples' spread, the geometric mean of the standard "
                "deviations along their principal axes, is at least this fraction of its radius.")

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
